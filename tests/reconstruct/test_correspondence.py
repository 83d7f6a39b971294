"""Spatial correspondence on simulated object-mode detections with spurious blobs."""
import numpy as np
import pytest

from hw_sim.observe import observe
from hw_sim.rig import make_rig
from hw_sim.scenes import static_markers
from reconstruct.correspondence import (CorrespondenceConfig, epipolar_geometry,
                                        match_frame)
from reconstruct.triangulation import rig_arrays
from tests.reconstruct.simdata import (MAX_SPURIOUS, MIN_FOUND, NOISE_PX, match_points,
                                       reconstructable)

SPURIOUS_PER_CAMERA_FRAME = 0.4   # ~1% of the blobs of 40 markers
MATCH_TOL_M = 0.005               # a point within this of a true marker is that marker
POINT_ERR_M = 0.001               # largest 3D error of a correct point at 0.05 px noise
                                  # (0.44-0.76 mm measured with 3, 8 and 12 cameras)

DIST = (-0.06, 0.01, 0.0, 0.0, 0.0)


def _frames(rig, obs):
    det = obs.detections
    out = []
    for f, s in det.frame_slices().items():
        cam, xy = det.camera[s], det.xy[s]
        mid = np.where(obs.merged_row[s], -2, obs.marker_id[s])  # -2: images of several markers
        blobs = [rig[c].pixel_to_normalized(xy[cam == c]) for c in range(len(rig))]
        ids = [mid[cam == c] for c in range(len(rig))]
        out.append((f, blobs, ids))
    return out


@pytest.mark.parametrize("n_cameras", [3, 8, 12])
def test_markers_found_no_spurious_blobs_used_once(n_cameras):
    rig = make_rig(n_cameras, dist=DIST, rng=n_cameras)
    scene = static_markers(40, 30, rng=1, min_separation_m=0.05)
    obs = observe(rig, scene, rng=2, noise_px=NOISE_PX,
                  spurious_per_frame=SPURIOUS_PER_CAMERA_FRAME)
    epi = epipolar_geometry(rig_arrays(rig))
    need = reconstructable(obs)
    n_need = n_found = n_pts = n_spur = 0
    for f, blobs, ids in _frames(rig, obs):
        pc = match_frame(blobs, epi, frame=f)
        assert pc.frame == f and pc.points.shape == (len(pc), 3)
        truth = obs.positions[f]
        m = match_points(pc.points, truth, MATCH_TOL_M)
        n_pts += len(pc)
        n_spur += int(np.sum(m < 0))
        n_need += int(need[f].sum())
        n_found += int(np.sum(need[f][np.unique(m[m >= 0])]))
        ok = m >= 0
        assert np.linalg.norm(pc.points[ok] - truth[m[ok]], axis=1).max() < POINT_ERR_M
        # every contributing blob is an image of the point's marker; each blob used once
        for c in range(n_cameras):
            used = pc.obs[:, c][pc.cameras[:, c]]
            assert len(np.unique(used)) == len(used)
            sel = ok & pc.cameras[:, c]
            blob_ids = ids[c][pc.obs[sel, c]]
            single = blob_ids != -2
            assert np.array_equal(blob_ids[single], m[sel][single])
        assert np.all(pc.cameras.sum(axis=1) >= 2)
    assert n_found / n_need >= MIN_FOUND, (n_found, n_need)
    assert n_spur / max(n_pts, 1) <= MAX_SPURIOUS, (n_spur, n_pts)


def test_ghost_pairs_of_two_markers_are_not_reconstructed():
    """Two markers on a common epipolar plane of cameras 0 and 1 give two true and two ghost
    intersections with those cameras alone; the third camera decides."""
    rig = make_rig(3, rng=None)
    c0, c1 = rig[0].center, rig[1].center
    mid = np.array([0.0, 0.0, 1.2])
    n = np.cross(c1 - c0, mid - c0)
    n /= np.linalg.norm(n)
    u = np.cross(n, c1 - c0)
    u /= np.linalg.norm(u)
    X = np.array([mid + 0.3 * u, mid - 0.25 * u + 0.2 * (c1 - c0) / np.linalg.norm(c1 - c0)])
    xy = rig.project(X)
    blobs = [rig[c].pixel_to_normalized(xy[c]) for c in range(3)]
    pc = match_frame(blobs, epipolar_geometry(rig_arrays(rig)))
    assert len(pc) == 2
    order = np.argsort(match_points(pc.points, X, 1e-6))
    assert np.abs(pc.points[order] - X).max() < 1e-9
    assert pc.cameras.all()


def test_points_outside_bounds_dropped_and_empty_frames():
    rig = make_rig(4)
    X = np.array([[0.0, 0.0, 1.0], [0.0, 0.5, -0.3]])  # second one under the floor
    xy = rig.project(X)
    blobs = [rig[c].pixel_to_normalized(xy[c]) for c in range(4)]
    epi = epipolar_geometry(rig_arrays(rig))
    cfg = CorrespondenceConfig(bounds=((-2, -2, 0), (2, 2, 2.5)))
    pc = match_frame(blobs, epi, cfg)
    assert len(pc) == 1 and np.abs(pc.points[0] - X[0]).max() < 1e-9
    empty = match_frame([np.zeros((0, 2))] * 4, epi, cfg, frame=3)
    assert len(empty) == 0 and empty.cameras.shape == (0, 4)


def test_bad_input():
    rig = make_rig(3)
    epi = epipolar_geometry(rig_arrays(rig))
    with pytest.raises(ValueError, match="3-camera"):
        match_frame([np.zeros((0, 2))] * 2, epi)
    with pytest.raises(ValueError, match="gate_px"):
        CorrespondenceConfig(gate_px=0)
    with pytest.raises(ValueError, match=r"blobs_norm\[1\]"):
        match_frame([np.zeros((1, 2)), np.zeros((1, 3)), np.zeros((1, 2))], epi)


def test_marker_losing_a_merged_blob_keeps_its_other_views():
    """Two markers whose images coincide in camera 0 (one merged blob): one point takes the
    blob, the other is reconstructed once from its remaining views (not split in two)."""
    rig = make_rig(6)
    A = np.array([0.1, -0.2, 1.1])
    cam0 = rig[0]
    ray = (A - cam0.center) / np.linalg.norm(A - cam0.center)
    side = np.cross(ray, [0, 0, 1.0])
    side /= np.linalg.norm(side)
    depth = cam0.depth(A[None])[0]
    B = A + 0.25 * ray + 0.8 * depth / cam0.K[0, 0] * side   # ~0.8 px apart in camera 0
    X = np.stack([A, B])
    xy = rig.project(X)
    blobs = [rig[c].pixel_to_normalized(xy[c]) for c in range(6)]
    blobs[0] = rig[0].pixel_to_normalized(xy[0].mean(axis=0, keepdims=True))   # merged
    # one round: the loser must be re-queued within the round, not left to a second round
    pc = match_frame(blobs, epipolar_geometry(rig_arrays(rig)), CorrespondenceConfig(rounds=1))
    assert len(pc) == 2
    m = match_points(pc.points, X, 0.002)
    assert sorted(m.tolist()) == [0, 1]
    assert pc.cameras[:, 0].sum() == 1 and pc.cameras[:, 1:].all()


def test_result_does_not_depend_on_blob_order():
    rig = make_rig(8, dist=DIST, rng=3)
    scene = static_markers(30, 1, rng=4, min_separation_m=0.05)
    obs = observe(rig, scene, rng=5, noise_px=NOISE_PX, spurious_per_frame=0.5)
    epi = epipolar_geometry(rig_arrays(rig))
    _, blobs, _ = _frames(rig, obs)[0]
    ref = match_frame(blobs, epi)
    g = np.random.default_rng(6)
    for _ in range(3):
        perms = [g.permutation(len(b)) for b in blobs]
        pc = match_frame([b[p] for b, p in zip(blobs, perms)], epi)
        assert len(pc) == len(ref)
        a, b = np.lexsort(ref.points.T), np.lexsort(pc.points.T)
        assert np.abs(ref.points[a] - pc.points[b]).max() < 1e-9
        for c in range(8):   # obs indexes the permuted list: same blobs
            used = pc.cameras[b, c]
            assert np.array_equal(perms[c][pc.obs[b, c][used]], ref.obs[a, c][ref.cameras[a, c]])


def test_merged_blob_ray_is_dropped_when_areas_are_given():
    """Marker 0's blob in camera 0 is merged with a neighbour's (centroid 0.5 px off, below
    the bad-ray threshold; twice the area): with areas its ray is dropped and the point is
    exact; without areas it is used and biases the point. A marker whose only views are
    merged blobs gives no point."""
    rig = make_rig(8)
    scene = static_markers(20, 1, rng=3, min_separation_m=0.2)
    obs = observe(rig, scene, rng=4, noise_px=0.0, occlusion=False, merge_blobs=False)
    X = scene.positions[0]
    det = obs.detections
    cam, mid, xy, area = det.camera, obs.marker_id, det.xy.copy(), det.area_px.copy()
    row = np.flatnonzero((cam == 0) & (mid == 0))[0]
    xy[row] += [0.5, 0.0]
    area[row] *= 2.0
    blobs = [rig[c].pixel_to_normalized(xy[cam == c]) for c in range(len(rig))]
    areas = [area[cam == c] for c in range(len(rig))]
    ids = [mid[cam == c] for c in range(len(rig))]
    epi = epipolar_geometry(rig_arrays(rig))
    cfg = CorrespondenceConfig()

    def point_of_marker0(pc):
        for k in range(len(pc)):
            c = np.flatnonzero(pc.cameras[k])[0]
            if ids[c][pc.obs[k, c]] == 0:
                return k
        raise AssertionError("marker 0 not reconstructed")

    with_a = match_frame(blobs, epi, cfg, areas=areas)
    k = point_of_marker0(with_a)
    assert with_a.obs[k, 0] == -1
    assert np.linalg.norm(with_a.points[k] - X[0]) < 1e-6
    without = match_frame(blobs, epi, cfg)
    k = point_of_marker0(without)
    assert without.obs[k, 0] >= 0
    assert np.linalg.norm(without.points[k] - X[0]) > 1e-4
    # every view of marker 0 merged: no point for it
    area2 = area.copy()
    area2[mid == 0] *= 2.0
    only = match_frame(blobs, epi, cfg, areas=[area2[cam == c] for c in range(len(rig))])
    assert all(ids[c][only.obs[k, c]] != 0 for k in range(len(only))
               for c in np.flatnonzero(only.cameras[k]))
    assert len(only) == len(with_a) - 1
    with pytest.raises(ValueError, match="merged_size_ratio"):
        CorrespondenceConfig(merged_size_ratio=1.0)

"""hw_sim.observe: object-mode detections with truth, visibility and occlusion."""
import numpy as np
import pytest

from calibration.camera import Camera, Rig, look_at
from hw_sim.observe import observe, segment_distance, visibility
from hw_sim.rig import make_rig
from hw_sim.scenes import MarkerScene, static_markers, wand

EXACT_PX = 1e-9
BRUTE_FORCE_M = 2e-3   # distance on a 1/400 grid of each segment (unit-size segments)
NOISE_REL = 0.05       # sample std within 5% of the injected noise (>= 4000 samples)


def test_segment_distance_matches_brute_force():
    g = np.random.default_rng(0)
    P = g.normal(size=(300, 4, 3))
    P[:20, 1] = P[:20, 0]          # degenerate first segment
    P[20:40, 3] = P[20:40, 2]      # degenerate second segment
    P[40:60, 3] = P[40:60, 2] + (P[40:60, 1] - P[40:60, 0]) * 0.7  # parallel
    d = segment_distance(P[:, 0], P[:, 1], P[:, 2], P[:, 3])
    s = np.linspace(0, 1, 401)
    bf = []
    for p in P:  # |p0 + s d1 - q0 - t d2|^2 on a 401 x 401 grid of (s, t)
        d1, d2, r = p[1] - p[0], p[3] - p[2], p[0] - p[2]
        sq = (r @ r + (s ** 2 * (d1 @ d1) + 2 * s * (d1 @ r))[:, None]
              + (s ** 2 * (d2 @ d2) - 2 * s * (d2 @ r))[None]
              - 2 * np.outer(s, s) * (d1 @ d2))
        bf.append(np.sqrt(max(sq.min(), 0.0)))
    bf = np.array(bf)
    assert np.all(d <= bf + 1e-12)
    assert np.max(bf - d) < BRUTE_FORCE_M


def test_noise_free_detections_are_the_camera_projections():
    rig = make_rig(8, dist=(-0.05, 0.01, 0.0005, -0.0003, 0.0), rng=1)
    scene = static_markers(15, 4, rng=2, min_separation_m=0.4)
    obs = observe(rig, scene, rng=3, noise_px=0.0, merge_blobs=False)
    det = obs.detections
    assert det.camera_names == tuple(rig.names) and det.rate_hz == scene.rate_hz
    assert np.all(obs.marker_id >= 0)
    expect = np.array([rig[c].project(scene.positions[f, m][None])[0]
                       for f, c, m in zip(det.frame, det.camera, obs.marker_id)])
    assert np.abs(det.xy - expect).max() < EXACT_PX
    assert np.array_equal(det.xy, obs.true_xy)
    depth = np.array([rig[c].depth(scene.positions[f, m][None])[0]
                      for f, c, m in zip(det.frame, det.camera, obs.marker_id)])
    assert np.allclose(det.area_px, np.pi / 4 * (0.014 * rig[0].K[0, 0] / depth) ** 2,
                       rtol=1e-12)
    # every visible (frame, camera, marker) appears exactly once
    assert len(det) == obs.visible.sum()
    L = obs.labelled_xy()
    assert np.array_equal(np.isfinite(L[..., 0]), obs.visible)


def test_noise_level_and_shuffled_order():
    rig = make_rig(8)
    scene = static_markers(20, 40, rng=5, min_separation_m=0.4)
    obs = observe(rig, scene, rng=6, noise_px=0.2, merge_blobs=False)
    err = obs.detections.xy - obs.true_xy
    assert err.size > 4000
    assert abs(err.std() / 0.2 - 1) < NOISE_REL
    assert abs(err.mean()) < 4 * 0.2 / np.sqrt(err.size)
    # cameras do not know marker ids: order within (frame, camera) is not the id order
    d = obs.detections
    sl = (d.frame == 0) & (d.camera == 0)
    ids = obs.marker_id[sl]
    assert len(ids) > 5 and not np.all(np.diff(ids) > 0)


def test_deterministic_with_seed():
    rig = make_rig(4)
    scene = wand(50, rng=1)
    a = observe(rig, scene, rng=7, spurious_per_frame=1.0)
    b = observe(rig, scene, rng=7, spurious_per_frame=1.0)
    c = observe(rig, scene, rng=8, spurious_per_frame=1.0)
    assert np.array_equal(a.detections.xy, b.detections.xy)
    assert np.array_equal(a.marker_id, b.marker_id)
    assert not np.array_equal(a.detections.xy, c.detections.xy)


def test_spurious_blobs_are_marked_and_inside():
    rig = make_rig(4)
    scene = static_markers(5, 200, rng=1)
    obs = observe(rig, scene, rng=2, spurious_per_frame=2.0)
    sp = obs.marker_id == -1
    n = sp.sum()
    expect = 2.0 * 200 * 4
    assert abs(n - expect) < 5 * np.sqrt(expect)
    cams = obs.detections.camera[sp]
    assert all(rig[int(c)].in_image(obs.detections.xy[sp][cams == c]).all() for c in range(4))


def _two_camera_rig():
    cams = []
    for name, eye in (("front", (0.0, -4.0, 1.0)), ("back", (0.0, 4.0, 1.0))):
        R, t = look_at(eye, (0.0, 0.0, 1.0))
        cams.append(Camera.from_params(name=name, size=(640, 480), fx=600, R=R, t=t))
    return Rig(cameras=tuple(cams))


def test_capsule_hides_markers_behind_it():
    rig = _two_camera_rig()
    radius = 0.15
    # vertical capsule (a "torso") on the z axis between the cameras
    segs = np.array([[[[0.0, 0.0, 0.5], [0.0, 0.0, 1.5]]]])
    markers = np.array([[[0.0, radius + 0.008, 1.0],    # back surface: hidden from front
                         [0.0, -radius - 0.008, 1.1],   # front surface: hidden from back
                         [1.0, 0.0, 1.0],               # to the side: seen by both
                         [0.0, 0.5, 1.0]]])             # behind, far: hidden from front
    scene = MarkerScene(positions=markers, marker_diameter_m=[0.014] * 4, rate_hz=100,
                        labels="abcd", occluder_segments=segs, occluder_radii_m=[radius])
    obs = observe(rig, scene, rng=0, noise_px=0.0, merge_blobs=False)
    expect_visible = np.array([[False, True, True, False],   # front camera
                               [True, False, True, True]])   # back camera
    assert np.array_equal(obs.visible[0], expect_visible)
    assert np.array_equal(obs.occluded[0], ~expect_visible)
    no_occ = observe(rig, scene, rng=0, noise_px=0.0, occlusion=False, merge_blobs=False)
    assert no_occ.visible.all()
    # visibility() on the raw arrays agrees
    v = visibility(rig, markers, 0.014, occluder_segments=segs, occluder_radii_m=[radius])
    assert np.array_equal(v.visible, obs.visible)


def test_close_markers_merge_into_one_blob():
    rig = _two_camera_rig()
    # two markers 5 mm apart along x: ~0.75 px apart in each camera, blobs ~2 px wide
    P = np.array([[[0.0, 0.0, 1.0], [0.005, 0.0, 1.0], [0.5, 0.0, 1.0]]])
    scene = MarkerScene(positions=P, marker_diameter_m=[0.014] * 3, rate_hz=100, labels="abc")
    obs = observe(rig, scene, rng=0, noise_px=0.0)
    assert np.array_equal(obs.merged[0], [[True, True, False]] * 2)
    assert len(obs.detections) == 4 and obs.merged_row.sum() == 2
    mid = rig.project(P[0, :2].mean(0)[None])[:, 0]
    rows = obs.merged_row
    assert np.abs(obs.true_xy[rows] - mid[obs.detections.camera[rows]]).max() < 0.01
    single = obs.detections.area_px[~rows]  # the lone marker, same depth
    assert np.allclose(obs.detections.area_px[rows], 2 * single, rtol=1e-2)
    far = observe(rig, scene, rng=0, noise_px=0.0, merge_blobs=False)
    assert len(far.detections) == 6 and not far.merged.any()


def test_min_blob_px_drops_far_markers():
    rig = _two_camera_rig()
    P = np.array([[[0.0, 0.0, 1.0]]])  # 4 m from both cameras: 0.014*600/4 = 2.1 px
    scene = MarkerScene(positions=P, marker_diameter_m=[0.014], rate_hz=100, labels="a")
    assert observe(rig, scene, min_blob_px=2.0).visible.all()
    assert not observe(rig, scene, min_blob_px=2.2).visible.any()


def test_bad_input():
    rig = make_rig(2)
    with pytest.raises(TypeError, match="MarkerScene"):
        observe(rig, np.zeros((2, 3, 3)))
    with pytest.raises(ValueError, match="noise_px"):
        observe(rig, static_markers(2, 2, rng=0), noise_px=-1)
    with pytest.raises(ValueError, match="positions.shape"):
        visibility(rig, np.zeros((2, 3, 2)), 0.01)

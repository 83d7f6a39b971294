"""End to end: simulated 8-camera detections -> clouds -> trajectories, scored against truth."""
import numpy as np
import pytest

from capture.detections import Detections2D
from hw_sim.observe import observe
from hw_sim.rig import make_rig
from reconstruct.pipeline import ReconstructionConfig, reconstruct_sequence
from reconstruct.tracking import TrackingConfig
from tests.reconstruct.simdata import (MAX_SPURIOUS, MIN_FOUND, NOISE_PX, RMS_3D_M,
                                       figure_scene, match_points, score_clouds,
                                       score_tracks)

RATE_HZ = 120.0
SPURIOUS_PER_CAMERA_FRAME = 0.35   # ~1% of the blobs
MAX_GAP = 5
DIST = (-0.05, 0.01, 0.0, 0.0, 0.0)


@pytest.fixture(scope="module")
def session():
    rig = make_rig(8, dist=DIST, rng=11)
    scene = figure_scene(240, RATE_HZ, rng=12)
    obs = observe(rig, scene, rng=13, noise_px=NOISE_PX,
                  spurious_per_frame=SPURIOUS_PER_CAMERA_FRAME)
    calls = []
    cfg = ReconstructionConfig(tracking=TrackingConfig(max_gap_frames=MAX_GAP), chunk_frames=60)
    clouds, traj = reconstruct_sequence(obs.detections, rig, cfg, workers=2,
                                        progress=lambda d, n: calls.append((d, n)))
    return rig, obs, clouds, traj, calls, cfg


def test_acceptance_correspondence_and_accuracy(session):
    rig, obs, clouds, traj, calls, _ = session
    assert obs.occluded.any()                      # occlusion is really on
    s = score_clouds(clouds, obs)
    assert s["found"] / s["need"] >= MIN_FOUND, s
    assert s["spurious"] / s["points"] <= MAX_SPURIOUS, s
    assert np.sqrt(np.mean(s["errors"] ** 2)) < RMS_3D_M
    assert len(clouds) == obs.positions.shape[0]
    assert calls[-1] == (240, 240) and len(calls) == 4
    assert [d for d, _ in calls] == sorted(d for d, _ in calls)


def test_acceptance_tracking(session):
    _, obs, _, traj, _, _ = session
    st = score_tracks(traj, obs, MAX_GAP)
    assert st["swaps"] == 0
    # trajectories broken only where the marker could not be reconstructed for > MAX_GAP
    assert np.array_equal(st["actual"], st["expected"]), (st["actual"], st["expected"])
    assert traj.rate_hz == RATE_HZ and traj.positions.shape[0] == 240


def test_in_process_matches_parallel_and_camera_order(session):
    rig, obs, clouds, _, _, cfg = session
    det = obs.detections
    sel = det.frame < 30
    # the table names cameras in another order: the rig's order must win
    perm = np.arange(len(rig))[::-1]
    det2 = Detections2D(frame=det.frame[sel], camera=perm[det.camera[sel]], xy=det.xy[sel],
                        camera_names=tuple(np.array(rig.names)[np.argsort(perm)]),
                        rate_hz=RATE_HZ, area_px=det.area_px[sel])
    c2, _ = reconstruct_sequence(det2, rig, cfg, workers=1)
    for a, b in zip(c2.clouds, clouds.clouds[:30]):
        assert len(a) == len(b)
        oa, ob = np.lexsort(a.points.T), np.lexsort(b.points.T)
        assert np.allclose(a.points[oa], b.points[ob], atol=1e-12)


def test_fill_and_filter_options(session):
    """Every camera loses frames 20-22 (a 3-frame gap, within MAX_GAP): the filled samples
    are there, where the markers truly were, and the low-pass changes the rest."""
    rig, obs, _, _, _, _ = session
    det = obs.detections
    sel = (det.frame < 60) & ~((det.frame >= 20) & (det.frame <= 22))
    d = Detections2D(frame=det.frame[sel], camera=det.camera[sel], xy=det.xy[sel],
                     camera_names=det.camera_names, rate_hz=RATE_HZ)
    cfg = ReconstructionConfig(fill_max_gap=MAX_GAP, filter_cutoff_hz=10.0)
    _, traj = reconstruct_sequence(d, rig, cfg, workers=1)
    _, raw = reconstruct_sequence(d, rig, ReconstructionConfig(), workers=1)
    assert traj.present().sum() == raw.present().sum() + traj.filled.sum()
    assert not np.array_equal(traj.positions[raw.present()], raw.positions[raw.present()])
    across = raw.present()[19 - raw.first_frame] & raw.present()[23 - raw.first_frame]
    rows = np.arange(20, 23) - traj.first_frame
    assert across.sum() >= 10 and traj.filled[rows][:, across].all()
    for t in range(20, 23):
        pts = traj.positions[t - traj.first_frame, traj.filled[t - traj.first_frame]]
        m = match_points(pts, obs.positions[t], 0.005)
        assert (m >= 0).all()
        assert np.linalg.norm(pts - obs.positions[t][m], axis=1).max() < 1e-3


def test_camera_mismatch_raises(session):
    rig, obs, *_ = session
    det = Detections2D(frame=[0], camera=[0], xy=[[1.0, 2.0]], camera_names=("nope",),
                       rate_hz=RATE_HZ)
    with pytest.raises(ValueError, match="nope"):
        reconstruct_sequence(det, rig)

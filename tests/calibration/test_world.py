"""World alignment recovers a known rigid transform; floor fit puts floor markers at z = 0."""
import numpy as np
import pytest

from calibration.camera import rotation_from_rodrigues
from calibration.world import (align_to_reference, floor_from_points, kabsch, match_reference,
                               transform_rig)
from hw_sim.rig import make_rig

EXACT_M = 1e-12
L_FRAME = np.array([[0, 0, 0], [0.5, 0, 0], [0.25, 0, 0], [0, 0.3, 0.0]])


def test_align_l_frame_recovers_world():
    rig = make_rig(4, rng=1)
    Rm = rotation_from_rodrigues([0.3, -0.2, 1.1])
    tm = np.array([0.4, -1.0, 2.0])
    moved = transform_rig(rig, Rm, tm)           # rig expressed in some other frame
    measured = L_FRAME @ Rm.T + tm               # the L-frame seen in that frame
    back, rms = align_to_reference(moved, measured, L_FRAME)
    assert rms < EXACT_M
    for a, b in zip(back, rig):
        assert np.linalg.norm(a.center - b.center) < 1e-9
        assert np.abs(a.R - b.R).max() < 1e-12


def test_floor_fit_and_errors():
    rig = make_rig(4, rng=2)
    g = np.random.default_rng(0)
    floor = np.c_[g.uniform(-2, 2, (10, 2)), np.zeros(10)]
    Rm = rotation_from_rodrigues([0.1, 0.4, -0.3])
    tm = np.array([1.0, 2.0, 0.5])
    moved = transform_rig(rig, Rm, tm)
    R, t = floor_from_points(moved, floor @ Rm.T + tm)
    z = (floor @ Rm.T + tm) @ R.T + t
    assert np.abs(z[:, 2]).max() < 1e-12
    assert all(c.center[2] > 0 for c in transform_rig(moved, R, t))
    with pytest.raises(ValueError, match="collinear"):
        kabsch(L_FRAME[:3], L_FRAME[:3])
    # a collinear reference is named as the reference, not blamed on the measured points
    line = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.3, 0, 0]])
    with pytest.raises(ValueError, match="the reference points are collinear"):
        match_reference(g.uniform(-1, 1, (4, 3)), line)


# --- from observed markers: hw_sim rig in the camera-0 gauge (as wand calibration leaves it) --
from calibration.static_markers import static_points  # noqa: E402
from calibration.world import align_floor, align_world, l_frame_reference  # noqa: E402
from hw_sim.observe import observe  # noqa: E402
from hw_sim.scenes import MarkerScene  # noqa: E402

L_TRUE = l_frame_reference(600.0, 400.0, 250.0)
# 0.05 px blob noise averaged over 100 frames (0.005 px): markers to ~0.02 mm (measured
# 0.01-0.03 mm), so the 0.25-0.6 m arms fix the axes to sigma ~ 0.02 * sqrt(2) / 400 ~ 7e-5 rad
# (0.004 deg); 3 sigma is 0.012 deg, which moves cameras ~6.5 m away by ~1.4 mm. Measured over
# 4 noise seeds: angle <= 0.0037 deg, centre <= 0.41 mm.
NOISY_CENTRE_M = 1.5e-3
NOISY_ANGLE_DEG = 0.012


def _scene(points, n_frames=20):
    P = np.broadcast_to(np.asarray(points), (n_frames, len(points), 3)).copy()
    return MarkerScene(positions=P, marker_diameter_m=np.full(len(points), 0.014), rate_hz=100.0,
                       labels=tuple(f"m{i}" for i in range(len(points))))


def _gauge0(rig):
    return transform_rig(rig, rig[0].R, rig[0].t)     # camera 0 at the identity pose


def _angle_deg(Ra, Rb):
    return np.degrees(np.arccos(np.clip((np.trace(Ra @ Rb.T) - 1) / 2, -1, 1)))


@pytest.mark.parametrize("noise", [0.0, 0.05])
def test_l_frame_observed_sets_world_axes(noise):
    truth = make_rig(8, rng=4)
    # the L-frame placed somewhere on the floor, turned about z: the world is where it lies
    Rz = rotation_from_rodrigues([0, 0, 0.7])
    placed = L_TRUE @ Rz.T + np.array([0.3, -0.2, 0.0])
    ob = observe(truth, _scene(placed, 100), rng=1, noise_px=noise, spurious_per_frame=0.5)
    sp = static_points(ob.detections, _gauge0(truth))
    assert len(sp.points) == 4
    res = align_world(_gauge0(truth), sp.points, L_TRUE)
    assert res.ok, res.reason
    # expected world: truth re-expressed in the L-frame's coordinates
    expect = transform_rig(truth, Rz.T, -Rz.T @ np.array([0.3, -0.2, 0.0]))
    tol_c, tol_a = (1e-6, 1e-5) if noise == 0 else (NOISY_CENTRE_M, NOISY_ANGLE_DEG)
    for a, b in zip(res.rig, expect):
        assert np.linalg.norm(a.center - b.center) < tol_c
        assert _angle_deg(a.R, b.R) < tol_a
        assert a.center[2] > 2.0                         # z up: cameras ~3 m above the floor
    # right-handed: world x cross world y is world z
    assert np.linalg.det(res.R) > 0


def test_mirrored_or_symmetric_reference_is_refused():
    truth = make_rig(6, rng=5)
    ob = observe(truth, _scene(L_TRUE), rng=2, noise_px=0.0)
    sp = static_points(ob.detections, _gauge0(truth))
    mirrored = L_TRUE * np.array([1, 1, 1.0])
    mirrored[:, [0, 1]] = mirrored[:, [1, 0]]               # x and y arms swapped: left-handed
    res = align_world(_gauge0(truth), sp.points, mirrored)
    assert not res.ok and "mirrored" in res.reason
    square = np.array([[0, 0, 0], [0.5, 0, 0], [0.5, 0.5, 0], [0, 0.5, 0.0]])
    ob2 = observe(truth, _scene(square + [0.1, 0.1, 0]), rng=2, noise_px=0.0)
    sp2 = static_points(ob2.detections, _gauge0(truth))
    res2 = align_world(_gauge0(truth), sp2.points, square)
    assert not res2.ok and "symmetric" in res2.reason


def test_floor_markers_observed_give_z_up_floor():
    truth = make_rig(8, rng=6)
    g = np.random.default_rng(3)
    floor = np.c_[g.uniform(-1.5, 1.5, (6, 2)), np.zeros(6)]
    ob = observe(truth, _scene(floor), rng=3, noise_px=0.0)
    sp = static_points(ob.detections, _gauge0(truth))
    assert len(sp.points) == 6
    res = align_floor(_gauge0(truth), sp.points)
    assert res.ok and res.rms_m < 1e-9
    for a, b in zip(res.rig, truth):
        assert abs(a.center[2] - b.center[2]) < 1e-6          # heights above the floor
    assert not align_floor(_gauge0(truth), sp.points[:2]).ok

"""World alignment recovers a known rigid transform; floor fit puts floor markers at z = 0."""
import numpy as np
import pytest

from calibration.camera import rotation_from_rodrigues
from calibration.world import align_to_reference, floor_from_points, kabsch, transform_rig
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

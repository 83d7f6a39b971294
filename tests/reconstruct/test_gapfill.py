"""Gap filling: spline for short gaps, rigid-body fill from segment markers."""
import numpy as np
import pytest

from calibration.camera import rotation_from_rodrigues
from reconstruct.gapfill import fill_gaps_rigid, fill_gaps_spline, gap_runs, kabsch

EXACT_M = 1e-9
SMOOTH_FILL_M = 5e-5   # spline error on a 1 Hz, 0.2 m sinusoid at 120 Hz, 8-frame gap (2.4e-5)


def test_gap_runs():
    p = np.array([0, 1, 1, 0, 0, 1, 0, 1, 1, 0], bool)
    assert gap_runs(p) == [(3, 5), (6, 7)]
    assert gap_runs(np.zeros(4, bool)) == []


def test_spline_reproduces_a_cubic_exactly_and_leaves_long_gaps():
    t = np.arange(100, dtype=float)
    cubic = np.stack([1e-6 * t ** 3 - 1e-4 * t ** 2 + 0.01 * t, 0.002 * t, 1 + 0 * t], 1)
    P = np.stack([cubic, cubic + 0.1], axis=1)
    G = P.copy()
    G[20:25, 0] = np.nan        # short
    G[50:70, 1] = np.nan        # long
    G[:3, 1] = np.nan           # leading: not interior
    out, filled = fill_gaps_spline(G, max_gap=5)
    assert np.abs(out[20:25, 0] - P[20:25, 0]).max() < EXACT_M
    assert filled[20:25, 0].all() and filled.sum() == 5
    assert np.isnan(out[50:70, 1]).all() and np.isnan(out[:3, 1]).all()
    assert np.array_equal(out[~np.isnan(G)], G[~np.isnan(G)])


def test_spline_on_smooth_motion():
    t = np.arange(240) / 120.0
    P = 0.2 * np.sin(2 * np.pi * t)[:, None, None] * np.ones((1, 1, 3))
    G = P.copy()
    G[100:108] = np.nan
    out, _ = fill_gaps_spline(G, max_gap=8)
    assert np.abs(out - P).max() < SMOOTH_FILL_M


def test_kabsch_recovers_rotation_with_positive_determinant():
    g = np.random.default_rng(0)
    src = g.normal(size=(6, 3))
    R = rotation_from_rodrigues([0.3, -1.2, 2.0])
    t = np.array([0.1, -2.0, 0.5])
    Re, te = kabsch(src, src @ R.T + t)
    assert np.abs(Re - R).max() < EXACT_M and np.abs(te - t).max() < EXACT_M
    # a reflected target still gives a proper rotation
    Rr, _ = kabsch(src, src * np.array([1, 1, -1]))
    assert np.linalg.det(Rr) == pytest.approx(1.0)
    with pytest.raises(ValueError):
        kabsch(src[:2], src[:2])


def test_rigid_fill_is_exact_for_a_rigid_segment():
    g = np.random.default_rng(1)
    T = 50
    body = g.normal(0, 0.1, (5, 3))
    rv = np.cumsum(g.normal(0, 0.05, (T, 3)), axis=0)
    tr = np.cumsum(g.normal(0, 0.01, (T, 3)), axis=0)
    P = np.stack([body @ rotation_from_rodrigues(r).T + x for r, x in zip(rv, tr)])
    other = g.normal(size=(T, 1, 3))
    P = np.concatenate([P, other], axis=1)       # marker 5 is not in the segment
    G = P.copy()
    G[10:30, 2] = np.nan                          # long gap of one marker
    G[15:18, 0] = np.nan                          # overlapping gap of another (3 remain)
    G[40, 5] = np.nan
    out, filled = fill_gaps_rigid(G, [[0, 1, 2, 3, 4]])
    assert np.abs(out[:, :5] - P[:, :5]).max() < EXACT_M
    assert filled[10:30, 2].all() and filled[15:18, 0].all() and filled.sum() == 23
    assert np.isnan(out[40, 5]).all()
    with pytest.raises(ValueError, match="outside"):
        fill_gaps_rigid(G, [[0, 9]])

"""skeleton.star_lm: the compiled Levenberg-Marquardt of a star model, against SciPy."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from skeleton.star_lm import star_lm


def _star(seed, F=12, noise_mm=0.5):
    """A hub with 3 markers and one member with 2 markers on a ball joint (mm): the
    measured markers, the true state, and a start 5 deg / 5 mm off it."""
    g = np.random.default_rng(seed)
    Rh = Rotation.from_rotvec(g.normal(0, 0.6, (F, 3)))
    Rm = Rotation.from_rotvec(g.normal(0, 0.6, (F, 3)))
    t = g.normal(0, 100, (F, 3))
    y = g.normal(0, 60, (3, 3))
    j = g.normal(0, 80, 3)
    z = g.normal(0, 60, (2, 3))
    X = np.concatenate([np.stack([Rh.apply(yy) for yy in y], 1),
                        np.stack([Rm.apply(zz) + Rh.apply(j) for zz in z], 1)], 1)
    X = X + t[:, None] + g.normal(0, noise_mm, X.shape)
    off = Rotation.from_rotvec(g.normal(0, np.deg2rad(5), (F, 3)))
    R0 = np.stack([(off * Rh).as_matrix(), (off * Rm).as_matrix()])
    start = (np.ascontiguousarray(R0), t + g.normal(0, 5, t.shape), y + g.normal(0, 5, y.shape),
             (j + g.normal(0, 5, 3))[None].copy(), z + g.normal(0, 5, z.shape))
    return X, start


def _scipy_minimum(X, start):
    """The same model, per frame >= 1 absolute rotation vectors, the first frame's pose
    held at its start (the gauge), minimised by SciPy (finite differences)."""
    R0, t0, y0, j0, z0 = start
    F = X.shape[0]

    def unpack(p):
        fr = p[:9 * (F - 1)].reshape(F - 1, 9)
        Rh = np.concatenate([R0[0, :1], Rotation.from_rotvec(fr[:, :3]).as_matrix()])
        Rm = np.concatenate([R0[1, :1], Rotation.from_rotvec(fr[:, 6:]).as_matrix()])
        t = np.concatenate([t0[:1], fr[:, 3:6]])
        g = p[9 * (F - 1):]
        return Rh, Rm, t, g[:9].reshape(3, 3), g[9:12], g[12:].reshape(2, 3)

    def fun(p):
        Rh, Rm, t, y, j, z = unpack(p)
        hub = np.einsum("fij,nj->fni", Rh, y) + t[:, None]
        mem = np.einsum("fij,nj->fni", Rm, z) + (t + Rh @ j)[:, None]
        return (np.concatenate([hub, mem], 1) - X).ravel()

    p0 = np.concatenate([
        np.column_stack([Rotation.from_matrix(R0[0, 1:]).as_rotvec(), t0[1:],
                         Rotation.from_matrix(R0[1, 1:]).as_rotvec()]).ravel(),
        y0.ravel(), j0.ravel(), z0.ravel()])
    sol = least_squares(fun, p0, method="trf", x_scale="jac", xtol=1e-14, ftol=1e-14,
                        gtol=1e-14, max_nfev=20000)
    return 2 * sol.cost


@pytest.mark.parametrize("seed", [1, 2])
def test_reaches_the_minimum_scipy_finds(seed):
    X, start = _star(seed)
    ref = _scipy_minimum(X, start)
    R, t, y, js, z = (a.copy() for a in start)
    seg = np.array([0, 0, 0, 1, 1], np.int64)
    status, ssq, it = star_lm(X, seg, R, t, y, js, z, start[3].copy(), 1e9, 500, 0.0, 0.0)
    assert status in (0, 1)
    assert ssq == pytest.approx(ref, rel=1e-6)
    # the state returned is the one whose residuals were reported
    model = np.concatenate([np.einsum("fij,nj->fni", R[0], y) + t[:, None],
                            np.einsum("fij,nj->fni", R[1], z)
                            + (t + np.einsum("fij,j->fi", R[0], js[0]))[:, None]], 1)
    assert ((model - X) ** 2).sum() == pytest.approx(ssq, rel=1e-9)
    np.testing.assert_allclose(R[:, 0], start[0][:, 0])     # the gauge frame is held
    np.testing.assert_allclose(t[0], start[1][0])
    np.testing.assert_allclose(np.einsum("kfij,kfil->kfjl", R, R), np.broadcast_to(
        np.eye(3), R.shape), atol=1e-9)                     # rotations stay rotations


def test_the_pull_holds_a_joint_near_its_start():
    """A strong pull keeps the joint at its anchor (the data's fit gets worse, not the
    anchor's distance)."""
    X, start = _star(3)
    seg = np.array([0, 0, 0, 1, 1], np.int64)
    out = []
    for pull in (1e9, 1e-3):
        R, t, y, js, z = (a.copy() for a in start)
        _, ssq, _ = star_lm(X, seg, R, t, y, js, z, start[3].copy(), pull, 300, 0.0, 0.0)
        out.append((ssq, np.linalg.norm(js[0] - start[3][0])))
    (free_ssq, free_d), (held_ssq, held_d) = out
    assert held_d < 0.01 < free_d
    assert held_ssq > free_ssq

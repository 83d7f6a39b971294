"""Joint centre between two rigid segments: sphere fit in one segment's frame, refined.

``fit_joint(traj (T, M, 3), markers_a, markers_b) -> JointFit``. The segment with more
markers (>= 3) is the reference; the other segment's markers, expressed in the reference
frame (Kabsch per frame), stay at constant distances from the joint centre. An algebraic
(linear) sphere fit gives the start; ``scipy.optimize.least_squares`` minimises the
distance residuals ``|x_tm - c| - r_m`` with their analytic Jacobian (the variance-of-
distance cost). A hinge (rank-2 system, singular-value ratio below ``HINGE_RATIO``) has no
unique centre: it is placed on the axis at the foot of the child markers' centroid.
Conventions: docs/conventions.md [arrays], [errors].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from skeleton.rigid import kabsch

__all__ = ["JointFit", "fit_joint", "HINGE_RATIO"]

HINGE_RATIO = 0.05
MIN_FRAMES = 10


@dataclass(frozen=True, kw_only=True)
class JointFit:
    """ok/reason; ref (0: markers_a is the reference frame, 1: markers_b); centre_local (3,)
    in the reference frame (its markers' positions at ``ref_frame``); world (T, 3) m (NaN
    where the reference is not fully seen); residual_m (rms distance residual); hinge;
    axis_local (3,) or NaN; sv_ratio."""

    ok: bool
    reason: str
    ref: int
    centre_local: np.ndarray
    world: np.ndarray
    residual_m: float
    hinge: bool
    axis_local: np.ndarray
    sv_ratio: float


def _fail(T, reason):
    n = np.full(3, np.nan)
    return JointFit(ok=False, reason=reason, ref=0, centre_local=n, world=np.full((T, 3), np.nan),
                    residual_m=np.inf, hinge=False, axis_local=n, sv_ratio=np.nan)


def fit_joint(traj: np.ndarray, markers_a, markers_b, refine: bool = True) -> JointFit:
    traj = np.asarray(traj, np.float64)
    T = traj.shape[0]
    a, b = np.asarray(markers_a, int), np.asarray(markers_b, int)
    ref = 0 if a.size >= b.size else 1
    r_idx, c_idx = (a, b) if ref == 0 else (b, a)
    if r_idx.size < 3:
        return _fit_world(traj, np.concatenate([a, b]))
    full = ~np.isnan(traj[:, r_idx]).any(axis=(1, 2))
    if full.sum() < MIN_FRAMES:
        return _fail(T, f"only {int(full.sum())} frames see the reference segment")
    ref_pts = traj[np.flatnonzero(full)[0], r_idx]
    R, t = kabsch(traj[full][:, r_idx], ref_pts)
    child = np.einsum("tij,tmj->tmi", R, traj[full][:, c_idx]) + t[:, None]   # (F, Mc, 3)
    # algebraic fit: 2 (x - mean_m) . c = |x|^2 - mean_m |x|^2
    X, y, mk = [], [], []
    for m in range(c_idx.size):
        xm = child[:, m]
        ok = ~np.isnan(xm).any(1)
        if ok.sum() < MIN_FRAMES:
            continue
        xm = xm[ok]
        q = (xm**2).sum(1)
        X.append(2 * (xm - xm.mean(0)))
        y.append(q - q.mean())
        mk.append((m, xm))
    if not mk:
        return _fail(T, "child markers seen in too few frames")
    X, y = np.concatenate(X), np.concatenate(y)
    U, s, Vt = np.linalg.svd(X, full_matrices=False)
    ratio = float(s[-1] / s[0])
    hinge = ratio < HINGE_RATIO
    if hinge:
        c = Vt[:2].T @ ((U[:, :2].T @ y) / s[:2])
    else:
        c = np.linalg.lstsq(X, y, rcond=None)[0]
    pts = np.concatenate([x for _, x in mk])
    lab = np.concatenate([np.full(len(x), k) for k, (_, x) in enumerate(mk)])
    r0 = np.array([np.linalg.norm(x - c, axis=1).mean() for _, x in mk])

    def fun(p):
        d = np.linalg.norm(pts - p[:3], axis=1)
        return d - p[3:][lab]

    def jac(p):
        diff = pts - p[:3]
        d = np.linalg.norm(diff, axis=1, keepdims=True)
        J = np.zeros((len(pts), 3 + len(mk)))
        J[:, :3] = -diff / np.maximum(d, 1e-12)
        J[np.arange(len(pts)), 3 + lab] = -1.0
        return J

    p = np.concatenate([c, r0])
    if refine:
        p = least_squares(fun, p, jac=jac, method="trf" if hinge else "lm",
                          x_scale="jac").x
    c = p[:3]
    axis = np.full(3, np.nan)
    if hinge:
        axis = Vt[2] / np.linalg.norm(Vt[2])
        cen = pts.mean(0)
        c = c + axis * np.dot(cen - c, axis)
    res = float(np.sqrt(np.mean(fun(np.concatenate([c, p[3:]])) ** 2))) if not hinge else \
        float(np.sqrt(np.mean(fun(p) ** 2)))
    world = np.full((T, 3), np.nan)
    world[full] = np.einsum("tji,tj->ti", R, c[None] - t)
    return JointFit(ok=True, reason="", ref=ref, centre_local=c, world=world, residual_m=res,
                    hinge=hinge, axis_local=axis, sv_ratio=ratio)


WORLD_MAX_FRAMES = 60


def _fit_world(traj: np.ndarray, idx: np.ndarray) -> JointFit:
    """Two-marker segments: a per-frame centre ``c_t`` at constant distances ``r_m`` from
    every marker of both segments (the thesis' cost in world coordinates), sparse LSQ."""
    T = traj.shape[0]
    if idx.size < 4:
        return _fail(T, f"{idx.size} markers on the two segments, need 4")
    full = np.flatnonzero(~np.isnan(traj[:, idx]).any(axis=(1, 2)))
    if full.size < MIN_FRAMES:
        return _fail(T, f"only {full.size} frames see both segments")
    sel = full[np.linspace(0, full.size - 1, min(full.size, WORLD_MAX_FRAMES)).astype(int)]
    X = traj[sel][:, idx]                                   # (F, N, 3)
    F, N = X.shape[:2]
    c0 = X.mean(1) + 0.05 * np.cross(X[:, 1] - X[:, 0], X[:, -1] - X[:, 0])
    r0 = np.linalg.norm(X - c0[:, None], axis=2).mean(0)

    def fun(p):
        c = p[: 3 * F].reshape(F, 3)
        return (np.linalg.norm(X - c[:, None], axis=2) - p[3 * F:]).ravel()

    from scipy.sparse import lil_matrix
    sp = lil_matrix((F * N, 3 * F + N), dtype=int)
    for f in range(F):
        sp[f * N:(f + 1) * N, 3 * f:3 * f + 3] = 1
        sp[f * N:(f + 1) * N, 3 * F:] = np.eye(N, dtype=int)
    sol = least_squares(fun, np.concatenate([c0.ravel(), r0]), jac_sparsity=sp,
                        method="trf", x_scale="jac", max_nfev=200)
    res = float(np.sqrt(np.mean(sol.fun ** 2)))
    world = np.full((T, 3), np.nan)
    world[sel] = sol.x[: 3 * F].reshape(F, 3)
    n = np.full(3, np.nan)
    return JointFit(ok=True, reason="world-frame fit (two-marker segments)", ref=-1,
                    centre_local=n, world=world, residual_m=res, hinge=False, axis_local=n,
                    sv_ratio=np.nan)

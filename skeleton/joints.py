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
    axis_local (3,) or NaN; sv_ratio; cost_m (the noise-normalised topology cost: the
    residual weighted by its propagated noise factor, over its degrees of freedom; ~ the
    marker noise sd for a true joint)."""

    ok: bool
    reason: str
    ref: int
    centre_local: np.ndarray
    world: np.ndarray
    residual_m: float
    hinge: bool
    axis_local: np.ndarray
    sv_ratio: float
    cost_m: float = np.inf


def _fail(T, reason):
    n = np.full(3, np.nan)
    return JointFit(ok=False, reason=reason, ref=0, centre_local=n, world=np.full((T, 3), np.nan),
                    residual_m=np.inf, hinge=False, axis_local=n, sv_ratio=np.nan)


def fit_joint(traj: np.ndarray, markers_a, markers_b, refine: bool = True,
              ref: int | None = None) -> JointFit:
    """``ref`` forces the reference segment (0: a, 1: b); default: the one with more markers."""
    traj = np.asarray(traj, np.float64)
    T = traj.shape[0]
    a, b = np.asarray(markers_a, int), np.asarray(markers_b, int)
    if ref is None:
        ref = 0 if a.size >= b.size else 1
    elif ref not in (0, 1):
        raise ValueError(f"ref={ref!r}, expected 0, 1 or None")
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
    if hinge:   # truncated pseudo-inverse, then the foot of the child markers on the axis
        c = Vt[:2].T @ ((U[:, :2].T @ y) / s[:2])
        ax0 = Vt[2] / np.linalg.norm(Vt[2])
        cen0 = np.concatenate([x for _, x in mk]).mean(0)
        c = c + ax0 * np.dot(cen0 - c, ax0)
    else:
        c = np.linalg.lstsq(X, y, rcond=None)[0]
    pts = np.concatenate([x for _, x in mk])
    lab = np.concatenate([np.full(len(x), k) for k, (_, x) in enumerate(mk)])
    r0 = np.array([np.linalg.norm(x - c, axis=1).mean() for _, x in mk])
    # Noise propagation: a child marker seen in the reference frame carries its own noise
    # plus the reference pose's (Kabsch: rotation covariance sigma^2 P^-1, P the reference
    # markers' inertia about their centroid; translation sigma^2 / n). Its radial residual
    # thus has variance sigma^2 w, w = 1 + 1/n + (l x u)^T P^-1 (l x u) (l: lever from the
    # reference centroid, u: radial direction). Residuals are weighted by 1/sqrt(w), so the
    # normalised cost estimates sigma whatever the marker layout.
    q = ref_pts - ref_pts.mean(0)
    P = (q**2).sum() * np.eye(3) - q.T @ q
    Pinv = np.linalg.pinv(P)
    lever = pts - ref_pts.mean(0)
    u0 = pts - c
    u0 /= np.maximum(np.linalg.norm(u0, axis=1, keepdims=True), 1e-12)
    lu = np.cross(lever, u0)
    wsq = np.sqrt(1 + 1 / r_idx.size + np.einsum("ni,ij,nj->n", lu, Pinv, lu))

    def fun(p):
        d = np.linalg.norm(pts - p[:3], axis=1)
        return (d - p[3:][lab]) / wsq

    def jac(p):
        diff = pts - p[:3]
        d = np.linalg.norm(diff, axis=1, keepdims=True)
        J = np.zeros((len(pts), 3 + len(mk)))
        J[:, :3] = -diff / np.maximum(d, 1e-12)
        J[np.arange(len(pts)), 3 + lab] = -1.0
        return J / wsq[:, None]

    p = np.concatenate([c, r0])
    if refine:
        p = least_squares(fun, p, jac=jac, method="trf" if hinge else "lm",
                          x_scale="jac").x
    c = p[:3]
    axis = np.full(3, np.nan)
    dof = len(pts) - 3 - len(mk) + (1 if hinge else 0)
    cost = float(np.sqrt((fun(p) ** 2).sum() / dof)) if dof > 0 else np.inf
    res = float(np.sqrt(np.mean((fun(p) * wsq) ** 2)))
    if hinge:
        axis = Vt[2] / np.linalg.norm(Vt[2])
        cen = pts.mean(0)
        c = c + axis * np.dot(cen - c, axis)
        if not refine:
            res = float(np.sqrt(np.mean((fun(np.concatenate([c, p[3:]])) * wsq) ** 2)))
    world = np.full((T, 3), np.nan)
    world[full] = np.einsum("tji,tj->ti", R, c[None] - t)
    return JointFit(ok=True, reason="", ref=ref, centre_local=c, world=world, residual_m=res,
                    hinge=hinge, axis_local=axis, sv_ratio=ratio, cost_m=cost)


WORLD_MAX_FRAMES = 60


def _fit_world(traj: np.ndarray, idx: np.ndarray) -> JointFit:
    """Two-marker segments: a per-frame centre ``c_t`` at constant distances ``r_m`` from
    every marker of both segments (the thesis' cost in world coordinates), ``_world_solve``."""
    T = traj.shape[0]
    if idx.size < 4:
        return _fail(T, f"{idx.size} markers on the two segments, need 4")
    full = np.flatnonzero(~np.isnan(traj[:, idx]).any(axis=(1, 2)))
    if full.size < MIN_FRAMES:
        return _fail(T, f"only {full.size} frames see both segments")
    X = traj[full][:, idx]                                  # (F, N, 3)
    c, r, ssr = _world_solve(X, idx.size // 2)
    res = float(np.sqrt(ssr / X.shape[0] / X.shape[1]))
    world = np.full((T, 3), np.nan)
    world[full] = c
    n = np.full(3, np.nan)
    return JointFit(ok=True, reason="world-frame fit (two-marker segments)", ref=-1,
                    centre_local=n, world=world, residual_m=res, hinge=False, axis_local=n,
                    sv_ratio=np.nan)


# --- topology cost ----------------------------------------------------------------------
COST_FRAMES = 200        # frames sampled (evenly) for the joint cost of one segment pair
COST_ITERS = 60
SCREEN_FRAMES = 40
SCREEN_ITERS = 40
REFINE_STARTS = 2


def _world_lm(X: np.ndarray, c: np.ndarray, r: np.ndarray, iters: int = COST_ITERS):
    """Levenberg-Marquardt on the thesis' world-frame cost ``sum (|x_fn - c_f| - r_n)^2``
    over per-frame centres ``c`` (F, 3) and constant distances ``r`` (N,), with the analytic
    Jacobian and the per-frame 3x3 blocks eliminated (Schur complement on ``r``)."""
    F, N = X.shape[:2]

    def resid(c, r):
        D = X - c[:, None]
        d = np.linalg.norm(D, axis=2)
        return D, d, d - r

    D, d, e = resid(c, r)
    ssr = float((e**2).sum())
    lam = 1e-3
    eye = np.eye(3)
    for _ in range(iters):
        u = D / np.maximum(d, 1e-12)[..., None]                   # (F, N, 3); J_c = -u
        A = np.einsum("fni,fnj->fij", u, u)
        gc = -np.einsum("fni,fn->fi", u, e)                      # J_c^T e
        gr = -e.sum(0)                                           # J_r^T e
        Ad = A + lam * (A * eye).sum(2)[:, :, None] * eye + 1e-12 * eye
        Ainv = np.linalg.inv(Ad)
        AiB = np.einsum("fij,fnj->fin", Ainv, u)                 # (F, 3, N)
        Sm = (1 + lam) * F * np.eye(N) - np.einsum("fni,fim->nm", u, AiB)
        rhs = -gr + np.einsum("fni,fi->n", u, np.einsum("fij,fj->fi", Ainv, gc))
        dr = np.linalg.solve(Sm, rhs)
        dc = -np.einsum("fij,fj->fi", Ainv, gc) - np.einsum("fin,n->fi", AiB, dr)
        D2, d2, e2 = resid(c + dc, r + dr)
        ssr2 = float((e2**2).sum())
        if ssr2 < ssr:
            small = ssr - ssr2 < 1e-12 * ssr + 1e-30
            c, r, D, d, e, ssr = c + dc, r + dr, D2, d2, e2, ssr2
            lam = max(lam / 4, 1e-9)
            if small:
                break
        else:
            lam *= 8
            if lam > 1e8:
                break
    return c, r, ssr


def _four_marker_init(X: np.ndarray) -> np.ndarray | None:
    """Closed-form centres (F, 3) for a point at constant distances from 4 markers X (F, 4, 3).

    Per frame, differences of ``|c - m_j|^2 = r_j^2`` are linear: ``M_t c_t = y_t - k`` with
    rows ``2 (m_j - m_0)``, ``y_tj = |m_j|^2 - |m_0|^2`` and ``k_j = r_j^2 - r_0^2``
    constant. With ``Q_t = M_t^-1``, ``p_t = Q_t y_t - m_0t``, the remaining condition
    ``|p_t - Q_t k|^2 = r_0^2`` is linear in (k, r_0^2, k k^T) (lifted least squares)."""
    m0 = X[:, 0]
    M = 2 * (X[:, 1:4] - m0[:, None])                                   # (F, 3, 3)
    y = (X[:, 1:4] ** 2).sum(2) - (m0**2).sum(1)[:, None]
    cond = np.linalg.cond(M)
    ok = cond < 1e4
    if ok.sum() < 12:
        return None
    Q = np.linalg.inv(M[ok])
    p = np.einsum("fij,fj->fi", Q, y[ok]) - m0[ok]
    QQ = np.einsum("fki,fkj->fij", Q, Q)
    iu = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]
    A = np.column_stack([-2 * np.einsum("fki,fk->fi", Q, p), -np.ones(ok.sum())] +
                        [QQ[:, i, j] * (1 if i == j else 2) for i, j in iu])
    w = 1 / (1 + (Q**2).sum((1, 2)))                                    # tame near-singular
    b = -(p**2).sum(1) * w
    U, sv, Vt = np.linalg.svd(A * w[:, None], full_matrices=False)
    # The lifted system has an exact null vector (and near-null ones at small motion): solve
    # on the 7 largest singular values, then move in the 3 smallest directions until the
    # lifted unknowns are consistent (K = k k^T).
    th0 = Vt[:7].T @ ((U[:, :7].T @ b) / sv[:7])
    Nb = Vt[7:].T

    def incons(beta):
        th = th0 + Nb @ beta
        kk = np.outer(th[:3], th[:3])
        return np.array([th[4 + n] - kk[i, j] for n, (i, j) in enumerate(iu)])

    best, k = np.inf, th0[:3]
    scale = max(np.abs(th0).max(), 1e-9)
    for g in (0.0, -1.0, 1.0, -10.0, 10.0):
        sol = least_squares(incons, np.array([g * scale, 0.0, 0.0]), method="lm")
        if sol.cost < best:
            best, k = sol.cost, (th0 + Nb @ sol.x)[:3]
    Mi = np.linalg.pinv(M)
    return np.einsum("fij,fj->fi", Mi, y - k)


def _world_solve(X: np.ndarray, na: int):
    """World-frame joint fit for two 2-marker segments, X (F, 4, 3) with the first ``na`` = 2
    markers on one segment: (c (F, 3), r (4,), ssr)."""
    F = X.shape[0]
    # two 2-marker segments: the world-frame cost is very non-convex (local minima 10-20 cm
    # from the joint), so start along both marker lines, extended past the markers where
    # joints sit; screen the starts on a few frames, refine the best on all.
    lam = np.array([-1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0, 2.5])
    starts = [X[:, o][:, None] + lam[None, :, None] * (X[:, o + 1] - X[:, o])[:, None]
              for o in (0, na)]
    starts = np.concatenate(starts, axis=1).transpose(1, 0, 2)          # (K, F, 3)
    lin = _four_marker_init(X)
    if lin is not None:
        starts = np.concatenate([lin[None], starts])
    few = np.linspace(0, F - 1, min(F, SCREEN_FRAMES)).astype(int)
    screened = []
    for c0 in starts:
        r0 = np.linalg.norm(X[few] - c0[few][:, None], axis=2).mean(0)
        c, r, ssr = _world_lm(X[few], c0[few].copy(), r0, SCREEN_ITERS)
        # the screened centres, interpolated to every frame (smooth motion)
        call = np.stack([np.interp(np.arange(F), few, c[:, k]) for k in range(3)], 1)
        screened.append((ssr, call, r))
    screened.sort(key=lambda z: z[0])
    best = (None, None, np.inf)
    for _, c0, r in screened[:REFINE_STARTS]:
        sol = _world_lm(X, c0.copy(), r.copy())
        if sol[2] < best[2]:
            best = sol
    return best


def joint_cost(traj: np.ndarray, markers_a, markers_b, rng=None) -> float:
    """Topology cost of a candidate joint between two segments: the thesis' variance-of-
    distance cost in world coordinates (one centre per frame at constant distances from
    every marker of both segments), minimised, and normalised by its degrees of freedom:
    ``sqrt(SSR / (F N - 3 F - N))``. For a true joint it estimates the marker noise level
    whatever the marker layout (no lever-arm amplification as in a one-segment-frame fit,
    and the per-frame centres of 2+2-marker pairs cannot absorb it); a false pair adds its
    misfit. Initialised by the closed-form sphere fit (>= 3 markers on one side) and from
    the closest cross-segment marker pairs; the lowest minimum is kept. m; inf if unfit."""
    traj = np.asarray(traj, np.float64)
    a, b = np.asarray(markers_a, int), np.asarray(markers_b, int)
    idx = np.concatenate([a, b])
    full = np.flatnonzero(~np.isnan(traj[:, idx]).any(axis=(1, 2)))
    F = min(full.size, COST_FRAMES)
    N = idx.size
    dof = F * N - 3 * F - N
    if N < 4 or full.size < MIN_FRAMES or dof <= 0:
        return np.inf
    sel = full[np.linspace(0, full.size - 1, F).astype(int)]
    X = traj[sel][:, idx]
    if max(a.size, b.size) >= 3:
        refs = [k for k, m in enumerate((a, b)) if m.size >= 3]
        costs = [fit_joint(traj[sel], a, b, refine=True, ref=k).cost_m for k in refs]
        return float(np.mean(costs))
    _, _, ssr = _world_solve(X, a.size)
    return float(np.sqrt(ssr / dof))

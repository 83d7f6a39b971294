"""Joint centre between two rigid segments: sphere fit in one segment's frame, refined.

``fit_joint(traj (T, M, 3), markers_a, markers_b) -> JointFit``. The segment with more
markers (>= 3) is the reference; the other segment's markers, expressed in the reference
frame (Kabsch per frame), stay at constant distances from the joint centre. An algebraic
(linear) sphere fit gives the start; Levenberg-Marquardt (MINPACK, ``_minpack_lm``)
minimises the distance residuals ``|x_tm - c| - r_m`` with their analytic Jacobian (the
variance-of-distance cost; residuals and Jacobian compiled). A hinge (rank-2 system,
singular-value ratio below ``HINGE_RATIO``) has no unique centre: it is placed on the axis
at the foot of the child markers' centroid.
Residuals are weighted by their propagated noise (see ``fit_joint``), which makes
``JointFit.cost_m`` a layout-independent estimate of the marker noise for a true joint.
Two 2-marker segments have no frame: a per-frame centre at constant distances from all
four markers (the thesis' world-frame cost, ``_world_lm``: Levenberg-Marquardt with the
per-frame 3x3 blocks eliminated, batched), started in closed form (``_four_marker_init``).
``joint_cost`` is the topology cost of a candidate pair.
Conventions: docs/conventions.md [arrays], [errors].
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit
from scipy.optimize import leastsq

from skeleton.rigid import kabsch
from skeleton.world_lm import world_lm

__all__ = ["JointFit", "fit_joint", "HINGE_RATIO"]

HINGE_RATIO = 0.05
HINGE_Z = 2.0     # out-of-plane energy below 2x that of its propagated noise: a hinge
                  # (true hinges score 0.9-1.2 with 1 mm noise; a false pair 3.4)
MIN_FRAMES = 10
MAX_JOINT_RADIUS_M = 1.0   # a ball fit's centre farther than this from a child marker ran off
PLANE_WORSE = 1.5          # a hinge centre on the foot plane fitting this x worse (rms) than
                           # the free centre (when near the markers): the free centre is kept
PLANE_RMS_MIN_M = 1e-5     # ... the free rms taken as at least this (noise-free fits)



def _minpack_lm(fun, x0, jac, max_nfev: int | None = None):
    """``least_squares(fun, x0, jac=jac, method="lm", x_scale="jac")`` (SciPy >= 1.16's
    default scaling for "lm") by MINPACK's lmder through ``leastsq``: the same iterations
    without least_squares' wrappers, which took a quarter of the solver's time after the
    pair costs (176 fits in the largest case at 1 mm). Returns (x, cost = sum r^2 / 2)."""
    x0 = np.asarray(x0, np.float64)
    x, _, info, _, _ = leastsq(fun, x0, Dfun=jac, full_output=True, ftol=1e-8, xtol=1e-8,
                               gtol=1e-8, maxfev=max_nfev or 100 * x0.size, factor=100,
                               diag=None)
    f = info["fvec"]
    return np.atleast_1d(x), 0.5 * float(np.dot(f, f))


@dataclass(frozen=True, kw_only=True)
class JointFit:
    """ok/reason; ref (0: markers_a is the reference frame, 1: markers_b); centre_local (3,)
    in the reference frame (its markers' positions at ``ref_frame``); world (T, 3) m (NaN
    where the reference is not fully seen); residual_m (rms distance residual); hinge;
    axis_local (3,) or NaN; sv_ratio; cost_m (the noise-normalised topology cost: the
    residual weighted by its propagated noise factor, over its degrees of freedom; ~ the
    marker noise sd for a true joint); axis_world (T, 3) the hinge axis per frame (NaN where
    unknown; None when not a hinge)."""

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
    axis_world: np.ndarray | None = None


def _fail(T, reason):
    n = np.full(3, np.nan)
    return JointFit(ok=False, reason=reason, ref=0, centre_local=n, world=np.full((T, 3), np.nan),
                    residual_m=np.inf, hinge=False, axis_local=n, sv_ratio=np.nan)


def inertia(pts: np.ndarray) -> np.ndarray:
    """(3, 3) inertia of points (N, 3) about their centroid: a Kabsch pose from them has
    rotation covariance sigma^2 P^-1 (sigma: the points' noise)."""
    q = pts - pts.mean(0)
    return (q**2).sum() * np.eye(3) - q.T @ q


def frame_quality(traj: np.ndarray, idx) -> float:
    """How well a segment's markers define a frame (m^2): the middle eigenvalue of their
    scatter about the centroid (how far they are from a line; a plane is enough), median
    over up to 20 frames that see them all; 0 for fewer than 3 markers. Three markers of
    which two sit a few mm apart are nearly a line, and a rotation about it is lost in the
    noise (linear noise propagation no longer holds)."""
    idx = np.asarray(idx, int)
    if idx.size < 3:
        return 0.0
    X = traj[:, idx]
    full = np.flatnonzero(~np.isnan(X).any(axis=(1, 2)))
    if full.size == 0:
        return 0.0
    X = X[full[np.linspace(0, full.size - 1, min(full.size, 20)).astype(int)]]
    Q = X - X.mean(1, keepdims=True)
    return float(np.median(np.linalg.eigvalsh(np.einsum("fni,fnj->fij", Q, Q))[:, 1]))


def fit_joint(traj: np.ndarray, markers_a, markers_b, refine: bool = True,
              ref: int | None = None, noise_m: float | None = None,
              radii: np.ndarray | None = None, min_quality: float = 0.0) -> JointFit:
    """``ref`` forces the reference segment (0: a, 1: b); default: the better frame
    (``frame_quality``: a segment of >= 3 markers, the one least close to a line).
    ``noise_m`` (two 2-marker segments only): the cost a true joint scores on this data
    (``joint_cost``'s units); the closed-form start is kept when it scores within 1.2x that,
    else (or without it) the multi-start search runs. ``radii`` (two 2-marker segments
    only): marker-joint distances (4,) found by a search on similar data (``joint_cost``'s
    ``detail``), a further start; given, they replace the multi-start search."""
    traj = np.asarray(traj, np.float64)
    T = traj.shape[0]
    a, b = np.asarray(markers_a, int), np.asarray(markers_b, int)
    if ref is None:
        qa, qb = frame_quality(traj, a), frame_quality(traj, b)
        if max(qa, qb) <= min_quality:
            return _fit_world(traj, a.size, np.concatenate([a, b]), noise_m, radii)
        ref = 0 if qa >= qb else 1
    elif ref not in (0, 1):
        raise ValueError(f"ref={ref!r}, expected 0, 1 or None")
    r_idx, c_idx = (a, b) if ref == 0 else (b, a)
    if r_idx.size < 3:
        return _fit_world(traj, a.size, np.concatenate([a, b]), noise_m, radii)
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
    # truncated pseudo-inverse, then the foot of the child markers' centroid on the weakest
    # direction (a hinge's axis): the start of a hinge, and of a fit that runs off
    pts = np.concatenate([x for _, x in mk])
    ax0 = Vt[2] / np.linalg.norm(Vt[2])
    c_foot = Vt[:2].T @ ((U[:, :2].T @ y) / s[:2])
    c_foot = c_foot + ax0 * np.dot(pts.mean(0) - c_foot, ax0)
    c = c_foot if hinge else np.linalg.lstsq(X, y, rcond=None)[0]
    lab = np.concatenate([np.full(len(x), k) for k, (_, x) in enumerate(mk)])
    r0 = np.array([np.linalg.norm(x - c, axis=1).mean() for _, x in mk])
    # Noise propagation: a child marker seen in the reference frame carries its own noise
    # plus the reference pose's (Kabsch: rotation covariance sigma^2 P^-1, P the reference
    # markers' inertia about their centroid; translation sigma^2 / n). Its radial residual
    # thus has variance sigma^2 w, w = 1 + 1/n + (l x u)^T P^-1 (l x u) (l: lever from the
    # reference centroid, u: radial direction). Residuals are weighted by 1/sqrt(w), so the
    # normalised cost estimates sigma whatever the marker layout.
    Pinv = np.linalg.pinv(inertia(ref_pts))
    lever = pts - ref_pts.mean(0)
    u0 = pts - c
    u0 /= np.maximum(np.linalg.norm(u0, axis=1, keepdims=True), 1e-12)
    lu = np.cross(lever, u0)
    wsq = np.sqrt(1 + 1 / r_idx.size + np.einsum("ni,ij,nj->n", lu, Pinv, lu))

    n_r = len(mk)

    def fun(p):
        return _sphere_res(np.asarray(p, np.float64), pts, lab, wsq)

    def jac(p):
        return _sphere_jac(np.asarray(p, np.float64), pts, lab, wsq, n_r)

    p = np.concatenate([c, r0])
    if refine:
        p = _minpack_lm(fun, p, jac)[0]
    c = p[:3]
    axis = np.full(3, np.nan)
    if not hinge and len(pts) - 3 - len(mk) > 0:
        # Statistical hinge test: the motion out of the best plane (smallest singular value
        # of the algebraic system) against what the propagated noise alone would put there
        # (rows 2 (x - mean): variance 4 sigma^2 w_n^2, w_n as wsq for the plane normal;
        # sigma from the reference markers' own scatter about their rigid mean shape, not
        # from this fit, whose residual a false pair inflates). A small or cramped
        # reference frame can put far more noise out of the plane than HINGE_RATIO allows.
        aligned = np.einsum("tij,tmj->tmi", R, traj[full][:, r_idx]) + t[:, None]
        sigma = np.sqrt(((aligned - aligned.mean(0)) ** 2).sum()
                        / (aligned.shape[0] * (3 * r_idx.size - 6)))
        ln = np.cross(lever, Vt[2])
        wn2 = 1 + 1 / r_idx.size + np.einsum("ni,ij,nj->n", ln, Pinv, ln)
        hinge = bool(s[-1] ** 2 < HINGE_Z * 4 * sigma**2 * wn2.sum())
    dof = len(pts) - 3 - len(mk) + (1 if hinge else 0)
    cost = float(np.sqrt((fun(p) ** 2).sum() / dof)) if dof > 0 else np.inf
    res = float(np.sqrt(np.mean((fun(p) * wsq) ** 2)))
    def near(centre):       # within MAX_JOINT_RADIUS_M of every child marker point
        return bool(np.max(np.linalg.norm(pts - centre, axis=1)) <= MAX_JOINT_RADIUS_M)

    runaway = not hinge and not near(c)
    if hinge or runaway:
        # The centre is free (hinge) or nearly free (a sphere fit running off to fit noise
        # with a near-plane) along the weakest direction: it is refined on the plane
        # through the foot point perpendicular to it, so it stays near the markers. (Left
        # free, a near-hinge's centre ran off by up to 1e6 m, and the foot taken there on a
        # slightly wrong axis missed the joint by as much: seeds 3040, 8018, 10008 with 1 mm
        # noise.) The cost above is the free fit's (what the topology compares).
        axis = ax0
        p2 = np.concatenate([c_foot, [np.linalg.norm(x - c_foot, axis=1).mean()
                                      for _, x in mk]])
        if refine:
            B = _perp_basis(axis)
            q = _minpack_lm(lambda q: fun(np.concatenate([c_foot + B @ q[:2], q[2:]])),
                            np.concatenate([[0.0, 0.0], p2[3:]]),
                            lambda q: jac(np.concatenate([c_foot + B @ q[:2], q[2:]]))
                            @ _plane_jac(B, len(mk)))[0]
            if near(c_foot + B @ q[:2]):
                p2 = np.concatenate([c_foot + B @ q[:2], q[2:]])    # else: the foot point
            if (hinge and near(p[:3])
                    and np.sqrt(np.mean(fun(p2) ** 2))
                    > PLANE_WORSE * max(np.sqrt(np.mean(fun(p) ** 2)), PLANE_RMS_MIN_M)):
                # the plane holds no centre as good as the free one: the weakest direction
                # is no axis the centre is free along (a hinge called by the statistical
                # test on a noisy frame; seed 29014, 1 mm: 7.6 mm rms on the plane, 0.51 mm
                # free) - the free centre stays
                p2 = p
        c = p2[:3]
        res = float(np.sqrt(np.mean((fun(p2) * wsq) ** 2)))
        if not hinge:
            axis = np.full(3, np.nan)
    world = np.full((T, 3), np.nan)
    world[full] = np.einsum("tji,tj->ti", R, c[None] - t)
    axis_world = None
    if hinge:
        axis_world = np.full((T, 3), np.nan)
        axis_world[full] = np.einsum("tji,j->ti", R, axis)
    return JointFit(ok=True, reason="", ref=ref, centre_local=c, world=world, residual_m=res,
                    hinge=hinge, axis_local=axis, sv_ratio=ratio, cost_m=cost,
                    axis_world=axis_world)


@njit(cache=True, error_model="numpy")
def _sphere_res(p, pts, lab, wsq):
    """fit_joint's weighted distance residuals ``(|x_n - c| - r_lab(n)) / w_n``, p = (c, r).
    Compiled, as the Jacobian below: MINPACK calls them ~20 times per fit on up to ~6000
    points, and NumPy's call overhead was most of a fit's time."""
    n = pts.shape[0]
    out = np.empty(n)
    for i in range(n):
        dx = pts[i, 0] - p[0]
        dy = pts[i, 1] - p[1]
        dz = pts[i, 2] - p[2]
        out[i] = (np.sqrt(dx * dx + dy * dy + dz * dz) - p[3 + lab[i]]) / wsq[i]
    return out


@njit(cache=True, error_model="numpy")
def _sphere_jac(p, pts, lab, wsq, n_r):
    """d ``_sphere_res`` / d p, (n, 3 + n_r)."""
    n = pts.shape[0]
    J = np.zeros((n, 3 + n_r))
    for i in range(n):
        dx = pts[i, 0] - p[0]
        dy = pts[i, 1] - p[1]
        dz = pts[i, 2] - p[2]
        d = max(np.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
        J[i, 0] = -dx / d / wsq[i]
        J[i, 1] = -dy / d / wsq[i]
        J[i, 2] = -dz / d / wsq[i]
        J[i, 3 + lab[i]] = -1.0 / wsq[i]
    return J


def warm_up() -> None:
    """Compiles the sphere-fit kernels, or loads them from the cache, now."""
    pts = np.eye(3)
    p = np.array([0.0, 0.0, 0.0, 1.0])
    lab = np.zeros(3, np.int64)
    _sphere_res(p, pts, lab, np.ones(3))
    _sphere_jac(p, pts, lab, np.ones(3), 1)


def _perp_basis(n: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal columns perpendicular to the unit vector n."""
    u = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
    u /= np.linalg.norm(u)
    return np.column_stack([u, np.cross(n, u)])


def _plane_jac(B: np.ndarray, n_radii: int) -> np.ndarray:
    """(3 + n, 2 + n): d(centre, radii) / d(plane coordinates, radii)."""
    D = np.zeros((3 + n_radii, 2 + n_radii))
    D[:3, :2] = B
    D[3:, 2:] = np.eye(n_radii)
    return D


FRAME_ITERS = 8


def _fit_world(traj: np.ndarray, na: int, idx: np.ndarray, noise_m: float | None = None,
               radii: np.ndarray | None = None) -> JointFit:
    """Two-marker segments: a per-frame centre ``c_t`` at constant distances ``r_m`` from
    every marker of both segments (the thesis' cost in world coordinates), ``_world_solve``."""
    T = traj.shape[0]
    if idx.size < 4:
        return _fail(T, f"{idx.size} markers on the two segments, need 4")
    full = np.flatnonzero(~np.isnan(traj[:, idx]).any(axis=(1, 2)))
    if full.size < MIN_FRAMES:
        return _fail(T, f"only {full.size} frames see both segments")
    X = traj[full][:, idx]                                  # (F, N, 3)
    sub = np.linspace(0, full.size - 1, min(full.size, COST_FRAMES)).astype(int)
    Xs = X[sub]
    dof = Xs.shape[0] * (idx.size - 3) - idx.size
    cs, r, ssr = _world_solve(Xs, na, multistart=False, iters=WORLD_ITERS)
    if radii is not None:   # the centres at those distances (closed form), refined
        k = radii[1:4] ** 2 - radii[0] ** 2
        M = 2 * (Xs[:, 1:4] - Xs[:, :1])
        y = (Xs[:, 1:4] ** 2).sum(2) - (Xs[:, 0] ** 2).sum(1)[:, None]
        c0 = np.einsum("fij,fj->fi", np.linalg.pinv(M), y - k)
        cs2, r2, ssr2 = _world_lm(Xs, c0, np.array(radii, float), WORLD_ITERS)
        if _plausible(r2[None])[0] and (ssr2 < ssr or not _plausible(r[None])[0]):
            cs, r, ssr = cs2, r2, ssr2
    elif noise_m is None or dof <= 0 or not np.sqrt(ssr / dof) <= 1.2 * noise_m:
        cs2, r2, ssr2 = _world_solve(Xs, na)
        if ssr2 < ssr or not _plausible(r[None])[0]:
            cs, r = cs2, r2
    c = np.stack([np.interp(np.arange(full.size), sub, cs[:, k]) for k in range(3)], 1)
    def frame_ssr(c):
        return ((np.linalg.norm(X - c[:, None], axis=2) - r) ** 2).sum(1)

    ssr_f = frame_ssr(c)
    for _ in range(FRAME_ITERS):   # every frame's centre at the fitted distances r (Gauss-Newton)
        D = X - c[:, None]
        d = np.maximum(np.linalg.norm(D, axis=2), 1e-12)
        u = D / d[..., None]
        e = d - r
        A = np.swapaxes(u, 1, 2) @ u + 1e-9 * np.eye(3)
        c2 = c + np.linalg.solve(A, (np.swapaxes(u, 1, 2) @ e[..., None]))[..., 0]
        s2 = frame_ssr(c2)
        better = s2 < ssr_f                     # a step that does not help is not taken
        c[better], ssr_f[better] = c2[better], s2[better]
    res = float(np.sqrt(np.mean((np.linalg.norm(X - c[:, None], axis=2) - r) ** 2)))
    world = np.full((T, 3), np.nan)
    world[full] = c
    n = np.full(3, np.nan)
    return JointFit(ok=True, reason="world-frame fit (two-marker segments)", ref=-1,
                    centre_local=n, world=world, residual_m=res, hinge=False, axis_local=n,
                    sv_ratio=np.nan)


# --- topology cost ----------------------------------------------------------------------
REF_QUALITY = 0.25       # a reference frame this much worse than the other is not used
COST_FRAMES = 200        # frames sampled (evenly) for the joint cost of one segment pair
COST_ITERS = 60
SCREEN_FRAMES = 20
SCREEN_ITERS = 25
REFINE_STARTS = 3
# starts along each 2-marker line, in units of marker 0 -> marker 1
LINE_STARTS = (-1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0, 2.5)
WORLD_ITERS = 100
QUICK_ITERS = 30         # the closed-form start alone (noise-free: 1-2 iterations)
INIT_FRAMES = 60         # frames for the closed-form 2+2 start
MAX_JOINT_MARKER_M = 1.0   # a joint farther than this from a marker of its segments: rejected
JOINT_REACH_M = 0.5        # ... or farther than this from every marker of one of them: a joint
                           # lies near its segments (hw_sim's random trees, 23,322 joints of
                           # seeds 1000-2999: nearest child marker <= 409 mm, nearest parent
                           # marker <= 327 mm; a 2+2 world fit found no true pair of figures
                           # 1000-1099 farther, and 198 of 887 false pairs: /tmp script)
LM_RTOL = 1e-7           # stop: relative decrease of the sum of squares
LM_ATOL_M = 1e-10        # stop: rms residual


def _world_lm(X: np.ndarray, c: np.ndarray, r: np.ndarray, iters: int = COST_ITERS):
    """Levenberg-Marquardt on the thesis' world-frame cost ``sum (|x_fn - c_f| - r_n)^2``
    over per-frame centres ``c`` (F, 3) and constant distances ``r`` (N,), with the analytic
    Jacobian and the per-frame 3x3 blocks eliminated (Schur complement on ``r``); compiled
    (``skeleton.world_lm``). Batched: X (B, F, N, 3), c (B, F, 3), r (B, N) solve B problems
    at once."""
    return world_lm(X, c, r, iters, LM_RTOL, LM_ATOL_M)


def _four_marker_init(X: np.ndarray, extra_starts=()) -> np.ndarray | None:
    """Closed-form-started centres (F, 3) for a point at constant distances from 4 markers
    X (F, 4, 3).

    Per frame, differences of ``|c - m_j|^2 = r_j^2`` are linear: ``M_t c_t = y_t - k`` with
    rows ``2 (m_j - m_0)``, ``y_tj = |m_j|^2 - |m_0|^2`` and ``k_j = r_j^2 - r_0^2``
    constant. With ``Q_t = M_t^-1``, ``p_t = Q_t y_t - m_0t``, the remaining condition
    ``|p_t - Q_t k|^2 = r_0^2`` is linear in (k, r_0^2, k k^T) (lifted least squares; its
    exact null vector is fixed by K = k k^T). The 4 unknowns (k, r_0) are then refined on
    ``(|p_t - Q_t k| - r_0) / |Q_t|`` from that start and from ``extra_starts`` (centre
    trajectories (F, 3)); the best is returned."""
    m0 = X[:, 0]
    M = 2 * (X[:, 1:4] - m0[:, None])                                   # (F, 3, 3)
    y = (X[:, 1:4] ** 2).sum(2) - (m0**2).sum(1)[:, None]
    cond = np.linalg.cond(M)
    ok = cond < 1e3
    if ok.sum() > INIT_FRAMES:   # the 4 unknowns need few frames: keep an even subset
        keep = np.flatnonzero(ok)
        ok = np.zeros_like(ok)
        ok[keep[np.linspace(0, keep.size - 1, INIT_FRAMES).astype(int)]] = True
    if ok.sum() < 12:
        return None
    Q = np.linalg.inv(M[ok])
    p = np.einsum("fij,fj->fi", Q, y[ok]) - m0[ok]
    QQ = np.einsum("fki,fkj->fij", Q, Q)
    iu = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]
    A = np.column_stack([-2 * np.einsum("fki,fk->fi", Q, p), -np.ones(ok.sum())] +
                        [QQ[:, i, j] * (1 if i == j else 2) for i, j in iu])
    qn = np.sqrt((Q**2).sum((1, 2)))
    w = 1 / (1 + qn**2)                                                 # tame near-singular
    b = -(p**2).sum(1) * w
    U, sv, Vt = np.linalg.svd(A * w[:, None], full_matrices=False)
    th0 = Vt[:7].T @ ((U[:, :7].T @ b) / sv[:7])
    Nb = Vt[7:].T

    ii, jj = np.array(iu).T

    def incons(beta):
        th = th0 + Nb @ beta
        return th[4:] - th[ii] * th[jj]

    def incons_jac(beta):
        th = th0 + Nb @ beta
        return Nb[4:] - Nb[ii] * th[jj][:, None] - th[ii][:, None] * Nb[jj]

    cons = []
    scale = max(np.abs(th0).max(), 1e-9)
    for g in (0.0, -1.0, 1.0, -10.0, 10.0):
        x, cost = _minpack_lm(incons, np.array([g * scale, 0.0, 0.0]), incons_jac)
        th = th0 + Nb @ x
        cons.append((cost, np.concatenate([th[:3], [np.sqrt(max(th[3], 0.0))]])))
    cons.sort(key=lambda z: z[0])
    starts = [z for _, z in cons[:2]]
    for c0 in extra_starts:
        r = np.linalg.norm(X - c0[:, None], axis=2).mean(0)
        starts.append(np.concatenate([r[1:] ** 2 - r[0] ** 2, [r[0]]]))
    wq = 1 / qn

    def red(z):
        v = p - np.einsum("fij,j->fi", Q, z[:3])
        return (np.linalg.norm(v, axis=1) - z[3]) * wq

    def red_jac(z):
        v = p - np.einsum("fij,j->fi", Q, z[:3])
        n = np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        J = np.empty((len(v), 4))
        J[:, :3] = -np.einsum("fi,fij->fj", v / n, Q)
        J[:, 3] = -1
        return J * wq[:, None]

    best, k = np.inf, starts[0][:3]
    for z0 in starts:
        x, cost = _minpack_lm(red, z0, red_jac, max_nfev=100)
        if cost < best:
            best, k = cost, x[:3]
    Mi = np.linalg.pinv(M)
    return np.einsum("fij,fj->fi", Mi, y - k)


def _plausible(r: np.ndarray) -> np.ndarray:
    """(B, 4) marker-joint distances of two 2-marker segments -> (B,) whether a fit is a
    joint, not a far-away point (noisy 2+2 data also fits a point metres away at nearly
    constant distances): every marker within ``MAX_JOINT_MARKER_M``, and the nearest
    marker of each segment within ``JOINT_REACH_M``."""
    return ((r > 0).all(1) & (r < MAX_JOINT_MARKER_M).all(1)
            & (r[:, :2].min(1) < JOINT_REACH_M) & (r[:, 2:].min(1) < JOINT_REACH_M))


CIRCLE_AXIAL = (-0.5, 0.5, 1.5)      # along the 2-marker line, marker 0 -> 1 = 1
CIRCLE_RADII_M = (0.05, 0.10)        # off that line (markers sit on the skin)
CIRCLE_ANGLES_DEG = (0, 90, 180, -90)   # about it, from the other segment's markers


def _circle_starts(X: np.ndarray, na: int) -> np.ndarray:
    """(K, F, 3) start centres off the marker lines. A point at constant distances from a
    segment's two markers lies on a circle about their line (its angle about the line is
    the one thing two markers cannot tell); the joint sits off the line, inside the body.
    For each segment: circles at ``CIRCLE_AXIAL`` x ``CIRCLE_RADII_M``, the point on each
    at ``CIRCLE_ANGLES_DEG`` from the direction of the other segment's markers."""
    out = []
    for o, q in ((0, na), (na, 0)):
        a1, a2 = X[:, o], X[:, o + 1]
        L = np.maximum(np.linalg.norm(a2 - a1, axis=1, keepdims=True), 1e-12)
        u = (a2 - a1) / L
        other = X[:, q:q + 2].mean(1)
        for s in CIRCLE_AXIAL:
            base = a1 + s * L * u
            w = other - base
            w = w - (w * u).sum(1, keepdims=True) * u
            w /= np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-12)
            v = np.cross(u, w)
            for rho in CIRCLE_RADII_M:
                for ang in np.deg2rad(CIRCLE_ANGLES_DEG):
                    out.append(base + rho * (np.cos(ang) * w + np.sin(ang) * v))
    return np.stack(out)


def _world_solve(X: np.ndarray, na: int, multistart: bool = True, iters: int = QUICK_ITERS):
    """World-frame joint fit for two 2-marker segments, X (F, 4, 3) with the first ``na`` = 2
    markers on one segment: (c (F, 3), r (4,), ssr). ``multistart=False``: only the closed-
    form start (fast; may stop in a local minimum when the data is noisy), ``iters``
    Levenberg-Marquardt iterations from it."""
    F = X.shape[0]
    if not multistart:
        lin = _four_marker_init(X)
        if lin is not None:
            c, r, ssr = _world_lm(X, lin, np.linalg.norm(X - lin[:, None], axis=2).mean(0),
                                  iters)
            if _plausible(r[None])[0]:
                return c, r, ssr
    # two 2-marker segments: the world-frame cost is very non-convex (local minima 10-20 cm
    # from the joint), so start along both marker lines, extended past the markers where
    # joints sit; screen the starts on a few frames, refine the best on all.
    lam = np.array(LINE_STARTS)
    starts = [X[:, o][:, None] + lam[None, :, None] * (X[:, o + 1] - X[:, o])[:, None]
              for o in (0, na)]
    starts = np.concatenate(starts, axis=1).transpose(1, 0, 2)          # (K, F, 3)
    lin = _four_marker_init(X)
    sc = starts
    if multistart:   # not for a failed quick start: those pairs are many and mostly false
        sc = np.concatenate([starts, _circle_starts(X, na)])
    few = np.linspace(0, F - 1, min(F, SCREEN_FRAMES)).astype(int)
    Xf = np.broadcast_to(X[few], (len(sc),) + X[few].shape)
    r0 = np.linalg.norm(Xf - sc[:, few][:, :, None], axis=3).mean(1)
    c, r, ssr = _world_lm(Xf, sc[:, few], r0, SCREEN_ITERS)
    order = np.argsort(np.where(_plausible(r), ssr, np.inf + ssr))[:REFINE_STARTS]
    # the screened centres, interpolated to every frame (smooth motion)
    cands = [np.stack([np.interp(np.arange(F), few, c[o][:, k]) for k in range(3)], 1)
             for o in order]
    rads = [r[o] for o in order]
    if lin is not None:
        cands.insert(0, lin)
        rads.insert(0, np.linalg.norm(X - lin[:, None], axis=2).mean(0))
    # refine them on a third of the frames, then the best on all
    mid = np.arange(0, F, 3)
    cb, rb, sb = _world_lm(np.broadcast_to(X[mid], (len(cands),) + X[mid].shape),
                           np.array(cands)[:, mid], np.array(rads), SCREEN_ITERS)
    o = int(np.argmin(np.where(_plausible(rb), sb, np.inf + sb)))
    c0 = np.stack([np.interp(np.arange(F), mid, cb[o][:, k]) for k in range(3)], 1)
    c, r, ssr = _world_lm(X, c0, rb[o], WORLD_ITERS)
    return c, r, float(ssr)


class PairCost(NamedTuple):
    cost: float
    hinge: bool
    radii: np.ndarray | None


def joint_cost(traj: np.ndarray, markers_a, markers_b, multistart: bool = True,
               detail: bool = False, min_quality: float = 0.0):
    """Topology cost of a candidate joint between two segments, normalised so that a true
    joint scores the marker noise sd (m) whatever the marker layout; a false pair adds its
    misfit. inf if the pair cannot be fitted.

    - One segment with >= 3 markers: the sphere fit of ``fit_joint`` in that segment's frame
      (both ways, averaged, when both have >= 3 and neither frame's ``frame_quality`` is
      below ``REF_QUALITY`` x the other's), residuals weighted by their propagated
      noise (the reference pose's rotation noise grows with the lever arm), over the
      degrees of freedom (``JointFit.cost_m``). An unweighted residual made pairs whose
      reference markers are close together look bad, and false pairs win.
    - Two 2-marker segments: the thesis' world-frame cost (one centre per frame at constant
      distances from all 4 markers), ``sqrt(SSR / (F N - 3 F - N))``, started from the
      closed form of ``_four_marker_init``; ``multistart`` adds starts along both marker
      lines (screened on a few frames), for data where the closed form is too noisy. inf
      when the fit is no joint near the markers (``_plausible``).

    ``COST_FRAMES`` frames are used, evenly spaced over those seeing both segments.
    ``detail``: returns ``PairCost`` (cost, hinge: True when every reference frame's fit is
    a hinge (``fit_joint``; never for two 2-marker segments), radii: the 2+2 fit's marker-
    joint distances (4,) or None)."""
    traj = np.asarray(traj, np.float64)
    a, b = np.asarray(markers_a, int), np.asarray(markers_b, int)
    idx = np.concatenate([a, b])
    full = np.flatnonzero(~np.isnan(traj[:, idx]).any(axis=(1, 2)))
    F = min(full.size, COST_FRAMES)
    N = idx.size
    dof = F * N - 3 * F - N
    if N < 4 or full.size < MIN_FRAMES or dof <= 0:
        return PairCost(np.inf, False, None) if detail else np.inf
    sel = full[np.linspace(0, full.size - 1, F).astype(int)]
    X = traj[sel][:, idx]
    q = [frame_quality(traj[sel], m) for m in (a, b)]
    if max(q) > min_quality:
        refs = [k for k in (0, 1) if q[k] > min_quality and q[k] >= REF_QUALITY * max(q)]
        fits = [fit_joint(traj[sel], a, b, refine=True, ref=k) for k in refs]
        cost = float(np.mean([f.cost_m for f in fits]))
        return PairCost(cost, all(f.hinge for f in fits), None) if detail else cost
    _, r, ssr = _world_solve(X, a.size, multistart)
    # no fit near the markers (``_plausible``): no joint (seed 56046, 1 mm: a false pair fitted
    # a point 548-664 mm from all four markers at the true joint's cost, and the tree took it)
    cost = float(np.sqrt(ssr / dof)) if _plausible(r[None])[0] else np.inf
    return PairCost(cost, False, r) if detail else cost

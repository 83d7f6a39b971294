"""A junction's star model fitted to all its markers: which hub explains the data best.

``star_misfit(traj (T, M, 3), members, group, hub, centre (T, 3)) -> StarFit``.
Segments meeting at (nearly) one point can be linked by any of several trees, and the joint
costs of pairs compare fits over different markers with different frame noise, so they tell
sibling joints a few mm apart from their parent poorly. Here every candidate tree of a group
(the star around each candidate hub) is fitted as one articulated model to the *same*
markers: per frame the hub's pose (6) and each other member's rotation (3) about its ball
joint; over all frames the hub's marker offsets, each joint's position in the hub and each
member's marker offsets from its joint. Every star of a group has the same number of
parameters, so their residual sums of squares compare directly (a likelihood ratio under
Gaussian marker noise). A sibling hung from its sibling instead of their common parent
carries the parent's joint about the sibling's: its markers miss by about the joint gap times
the sibling's rotation in every frame, which the model cannot absorb (moving the sibling
moves its own markers with the lever arm), so siblings a fraction of a mm apart separate
at 1 mm marker noise over a few hundred frames, where the pairwise costs do not (see
``skeleton.junctions``). The solve is Levenberg-Marquardt with the analytic Jacobian, the
normal equations reduced to the global parameters by the Schur complement of the per-frame
blocks (bundle adjustment's structure), the gauge (each segment's local frame) fixed by
holding the first frame's pose parameters at their start, and each joint pulled weakly
towards its start (``JOINT_PULL_MM``: a hinge's centre is free along its axis, and without
the pull the fit crawls after the noise along it for hundreds of iterations, so stars were
compared part-converged; the sum of squares returned is the data's); compiled
(``skeleton.star_lm``). It starts in closed form: each segment's rotations by Kabsch of its
markers and its joint's start point (a frame even for two markers). Written by hand rather
than with SciPy's ``least_squares`` (finite-difference Jacobian with its sparsity, lsmr:
0.6-1.1 s per star on 3-segment groups); stop 22's vectorised NumPy loop took 0.04-0.2 s,
the compiled one 0.4x that (``benchmarks/bench_star_fit.py``), which is what lets the
solver test every tree triple (``skeleton.relink``).
Conventions: docs/conventions.md [arrays], [units], [rotations].
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from threadpoolctl import ThreadpoolController

from skeleton.star_lm import _residuals, star_lm

__all__ = ["StarFit", "star_misfit", "margin_unit", "residual_tau", "STAR_FRAMES",
           "VAR_FLOOR_M2", "TAU_REF"]

STAR_FRAMES = 150   # frames sampled (evenly) for the fit
VAR_FLOOR_M2 = 1e-10  # residual variance floor (10 um RMS) for margins in units of it: noise-
                      # free fits reach ~1e-20, and stars of exactly coincident joints are
                      # equivalent: a margin over that would count the solver's convergence
JOINT_PULL_MM = 20.0  # each joint is pulled towards its start: 20 mm off adds 1 mm^2 (the
                      # residual variance per residual is ~0.05 mm^2 at 1 mm noise). Without
                      # it a hinge's centre, free along its axis, runs off with the noise and
                      # the fit crawls after it for hundreds of iterations (seed 97022's true
                      # star: unconverged after 400; with it: 7-12)
TAU_REF = 4.0       # residuals more correlated from frame to frame than this (``residual_tau``)
                    # widen the margin's unit by the excess (``margin_unit``). The margins
                    # are sums of squares in units of one residual's variance, which assumes
                    # independent residuals; a sum over residuals that move together over tau
                    # frames varies ~tau times more. Low-passed 1 mm noise (the benchmark
                    # figures: 6 Hz at 120 Hz, 150 of 600 frames) gives tau 2.8-3.2 for the
                    # better star of every re-link comparison of seeds 1000-1049 (max 3.17);
                    # skin markers sliding on their bones (hw_sim's soft_tissue_m, 2 mm) give
                    # 16-26, and on those figures stars re-linked wrongly (acceptance set: 34
                    # of 50 exact with the star fits, 38 without).
MAX_ITER = 50       # Levenberg-Marquardt iterations ...
TOL = 1e-6          # ... until the sum of squares falls by less than this fraction, or by
STOP_VAR = 0.1      # less than this x the residual variance (hub margins are 200x that)


class StarFit(NamedTuple):
    """ok/reason; ssq_m2: residual sum of squares (m^2) over n_res residuals; n_par: the
    model's parameters (gauge freedoms included: the same for every hub of one group);
    n_iter: Levenberg-Marquardt iterations (``MAX_ITER``: stopped before converging);
    joints: member -> (T, 3) its fitted joint with the hub in world coordinates (m) on the
    fitted frames, NaN elsewhere (a start for another star of the same group)."""

    ok: bool
    reason: str
    ssq_m2: float
    n_res: int
    n_par: int
    n_iter: int = 0
    joints: dict | None = None
    tau: float = 1.0


def _frames(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, n, 3) points -> rotations (F, 3, 3) and centroids (F, 3) with
    P_f - cen_f ~ R_f (P_0 - cen_0) (Kabsch, det +1)."""
    cen = P.mean(1)
    Q = P - cen[:, None]
    H = np.einsum("ni,fnj->fij", Q[0], Q)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones((len(P), 3))
    D[:, 2] = d
    return np.einsum("fji,fj,fkj->fik", Vt, D, U), cen


_BLAS: ThreadpoolController | None = None


def star_misfit(traj: np.ndarray, members, group, hub: int, centre,
                n_frames: int = STAR_FRAMES) -> StarFit:
    """The star of ``group`` (segment indices) around ``hub`` fitted to the group's markers
    (``members[s]``: marker indices of segment s) on ``n_frames`` frames sampled evenly
    among those where every marker and start point is seen. ``centre``: the junction point
    (T, 3), the start of every joint; or a mapping member -> (T, 3), the start of that
    member's joint with the hub, for every member but the hub. Fewer than 10 such frames:
    a StarFit that is not ok and says so."""
    # small dense products: BLAS threads only contend (1.0 s -> 0.13 s for one fit on a
    # loaded 2-core machine); the controller is made once (finding the BLAS libraries took
    # 5 ms per fit)
    global _BLAS
    if _BLAS is None:
        _BLAS = ThreadpoolController()
    with _BLAS.limit(limits=1, user_api="blas"):
        return _star_misfit(traj, members, group, hub, centre, n_frames)


def _star_misfit(traj, members, group, hub, centre, n_frames) -> StarFit:
    traj = np.asarray(traj, np.float64)
    others = [int(s) for s in sorted(group) if s != hub]
    if int(hub) not in set(int(s) for s in group) or not others:
        raise ValueError(f"hub={hub!r}, group={sorted(group)!r}: the hub must be a member of "
                         "a group of >= 2 segments")
    if isinstance(centre, dict):
        missing = [s for s in others if s not in centre]
        if missing:
            raise ValueError(f"centre has no start for members {missing} (hub {hub})")
        starts = [np.asarray(centre[s], np.float64) for s in others]
    else:
        starts = [np.asarray(centre, np.float64)] * len(others)
    if any(c.shape != (traj.shape[0], 3) for c in starts):
        raise ValueError(f"centre shapes {[c.shape for c in starts]}, expected "
                         f"({traj.shape[0]}, 3)")
    segs = [int(hub)] + others
    idx = [np.asarray(members[s], int) for s in segs]
    allm = np.concatenate(idx)
    seen = ~np.isnan(traj[:, allm]).any((1, 2))
    for c in starts:
        seen &= ~np.isnan(c).any(1)
    ok_t = np.flatnonzero(seen)
    if ok_t.size < 10:
        return StarFit(False, f"{ok_t.size} frames with every marker seen", np.inf, 0, 0)
    sel = ok_t[np.linspace(0, ok_t.size - 1, min(ok_t.size, n_frames)).astype(int)]
    F = sel.size
    X = traj[sel] * 1e3                      # mm: residuals near 1, well scaled
    cs = [c[sel] * 1e3 for c in starts]
    pts = [np.mean(cs, axis=0)] + cs         # a point beside each segment's markers
    # closed-form start: rotations of each segment from its markers and its joint's start
    R0, cen = [], []
    for ix, c in zip(idx, pts):
        R, ce = _frames(np.concatenate([X[:, ix], c[:, None]], axis=1))
        R0.append(R)
        cen.append(ce)
    Rh, th = R0[0], cen[0]
    y0 = np.einsum("fji,fnj->fni", Rh, X[:, idx[0]] - th[:, None]).mean(0)     # hub local
    j0 = np.stack([np.einsum("fji,fj->fi", Rh, c - th).mean(0) for c in cs])   # (K, 3)
    J0 = [th + np.einsum("fij,j->fi", Rh, j) for j in j0]
    zl = [np.einsum("fji,fnj->fni", R0[k + 1], X[:, idx[k + 1]] - J0[k][:, None]).mean(0)
          for k in range(len(others))]
    K = len(others)
    n = [ix.size for ix in idx]
    N = int(sum(n))
    # parameters: per frame the hub's rotation and translation and each member's rotation;
    # over all frames the hub's marker offsets, the joints in the hub, the members' marker
    # offsets from their joints (gauge freedoms included: the same count for every hub)
    n_par = F * (6 + 3 * K) + 3 * N + 3 * K
    Xs = np.concatenate([X[:, ix] for ix in idx], axis=1)     # (F, N, 3) in model order
    seg = np.concatenate([np.full(m, k) for k, m in enumerate(n)]).astype(np.int64)
    R = np.ascontiguousarray(np.stack(R0))   # (K + 1, F, 3, 3): hub, then the members
    z = np.ascontiguousarray(np.concatenate(zl))   # K >= 1 (checked above)
    j0 = np.ascontiguousarray(j0)
    t_fit, js_fit, y_fit = th.copy(), j0.copy(), y0.copy()
    Xs = np.ascontiguousarray(Xs)
    status, ssq, it = star_lm(Xs, seg, R, t_fit, y_fit,
                              js_fit, z, j0, JOINT_PULL_MM, MAX_ITER, TOL, STOP_VAR)
    if status == 2:
        return StarFit(False, "normal equations not positive definite or not finite", np.inf,
                       3 * N * F, n_par)
    joints = {}
    for k, s in enumerate(others):      # world joint of member s with the hub, fitted frames
        w = np.full((traj.shape[0], 3), np.nan)
        w[sel] = (t_fit + np.einsum("fij,j->fi", R[0], js_fit[k])) * 1e-3
        joints[s] = w
    r = np.empty_like(Xs)
    _residuals(Xs, seg, R, t_fit, y_fit, js_fit, z, r)
    # the data's sum of squares (the pull only guides the search along near-free directions)
    return StarFit(True, "", float(ssq) * 1e-6, 3 * N * F, n_par, int(it), joints,
                   residual_tau(r))


def margin_unit(best: StarFit) -> float:
    """The unit of a star comparison's margin (m^2): the better fit's residual variance
    (floored at ``VAR_FLOOR_M2``), times its residuals' correlation time over ``TAU_REF``
    where that is > 1."""
    return (max(best.ssq_m2 / best.n_res, VAR_FLOOR_M2)
            * max(1.0, best.tau / TAU_REF))


def residual_tau(r: np.ndarray) -> float:
    """Integrated autocorrelation time of residuals ``r`` (F, ...) over their F frames, pooled
    over every channel: 1 + 2 sum_k rho_k, summed while rho_k > 0 (the initial positive
    sequence) and k < F / 4. 1 for residuals independent from frame to frame; the number of
    consecutive frames whose residuals move together in general."""
    r = np.asarray(r, np.float64).reshape(r.shape[0], -1)
    r = r - r.mean(0)
    den = float((r * r).sum())
    if not den > 0:
        return 1.0
    tau = 1.0
    for k in range(1, max(r.shape[0] // 4, 1)):
        rho = float((r[k:] * r[:-k]).sum()) / den
        if rho <= 0:
            break
        tau += 2 * rho
    return tau

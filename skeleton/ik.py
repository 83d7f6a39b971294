"""Whole-skeleton inverse kinematics per frame: batched Gauss-Newton from the closed form.

``refine_fit(trajectories (T, M, 3), rigid, fit: SkeletonFit, iterations=5) -> SkeletonFit``.
The thesis' hierarchical closed-form fit (``skeleton.fit``) poses one segment at a time,
so a parent's rotation error moves every joint below it. This step minimises, in every
frame where the whole tree is fitted and connected, the sum of squared distances between
all visible markers and the skeleton's markers over the root translation and every
segment's rotation at once (the rigid skeleton's offsets fixed):

    x_m = t_root + sum_{a on the chain to s} R_parent(a) o_a + R_s q_m

with world-frame rotation increments ``R <- exp([w]x) R``. The per-frame normal equations
(3 + 3S unknowns) are solved for all frames at once (``numpy.linalg.solve`` on a stack),
with a small Levenberg damping; a step is kept per frame only when it lowers that frame's
cost. The closed form starts it, so noise-free data stays exact.
Conventions: docs/conventions.md [rotations], [arrays].
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from skeleton.fit import FIT_MARKERS, FIT_NONE, SkeletonFit
from skeleton.rigid_skeleton import RigidSkeleton

__all__ = ["refine_fit"]

DAMPING = 1e-9


def _skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def _forward(rigid: RigidSkeleton, R: np.ndarray, t_root: np.ndarray):
    """Segment origins (F, S, 3) and markers (F, M, 3) for rotations (F, S, 3, 3)."""
    F, S = R.shape[:2]
    org = np.empty((F, S, 3))
    for s in rigid.order:
        p = rigid.parents[s]
        org[:, s] = t_root if p < 0 else org[:, p] + R[:, p] @ rigid.joint_offsets[s]
    ms = rigid.marker_segment
    mk = org[:, ms] + np.einsum("fmij,mj->fmi", R[:, ms], rigid.marker_offsets)
    return org, mk


def refine_fit(trajectories, rigid: RigidSkeleton, fit: SkeletonFit,
               iterations: int = 5) -> SkeletonFit:
    X = np.asarray(trajectories, np.float64)
    T, M = X.shape[:2]
    S = rigid.n_segments
    if X.shape != (T, rigid.n_markers, 3) or fit.world_from_segment_R.shape[:2] != (T, S):
        raise ValueError(f"trajectories.shape={X.shape}, fit for "
                         f"{fit.world_from_segment_R.shape[:2]} frames/segments, "
                         f"rigid skeleton with {rigid.n_markers} markers")
    st = fit.status
    connected = (st != FIT_NONE).all(1) & ((st != FIT_MARKERS) |
                                           (np.arange(S) == rigid.root)).all(1)
    fr = np.flatnonzero(connected)
    Rw = np.array(fit.world_from_segment_R)
    tw = np.array(fit.world_from_segment_t)
    if fr.size:
        R = Rw[fr].copy()
        t = tw[fr, rigid.root].copy()
        x = X[fr]
        vis = ~np.isnan(x).any(2)                                   # (F, M)
        x0 = np.where(vis[..., None], x, 0.0)
        ms = rigid.marker_segment
        # chains: for marker m, the segments whose rotation moves it and the vector each one
        # rotates (a joint offset for an ancestor's child on the path, q_m for its own)
        paths = []
        for s in range(S):
            c, a = [], s
            while rigid.parents[a] >= 0:
                c.append(a)
                a = int(rigid.parents[a])
            paths.append(c[::-1])
        F = fr.size
        n = 3 + 3 * S

        def cost(R, t):
            _, mk = _forward(rigid, R, t)
            r = np.where(vis[..., None], x0 - mk, 0.0)
            return r, (r ** 2).sum((1, 2))

        r, c0 = cost(R, t)
        for _ in range(iterations):
            J = np.zeros((F, M, 3, n))
            J[:, :, :, :3] = np.eye(3)
            for m in range(M):
                s = int(ms[m])
                for a in paths[s]:
                    p = int(rigid.parents[a])
                    v = R[:, p] @ rigid.joint_offsets[a]
                    J[:, m, :, 3 + 3 * p:6 + 3 * p] -= _skew(v)
                J[:, m, :, 3 + 3 * s:6 + 3 * s] -= _skew(R[:, s] @ rigid.marker_offsets[m])
            J *= vis[:, :, None, None]
            J = J.reshape(F, 3 * M, n)
            A = np.einsum("fki,fkj->fij", J, J)
            A += (DAMPING + 1e-12 * np.trace(A, axis1=1, axis2=2))[:, None, None] * np.eye(n)
            b = np.einsum("fki,fk->fi", J, r.reshape(F, 3 * M))
            d = np.linalg.solve(A, b[..., None])[..., 0]
            Rn = Rotation.from_rotvec(d[:, 3:].reshape(-1, 3)).as_matrix().reshape(F, S, 3, 3)
            Rn = Rn @ R
            tn = t + d[:, :3]
            rn, c1 = cost(Rn, tn)
            better = c1 < c0
            R[better], t[better], r[better], c0[better] = Rn[better], tn[better], rn[better], \
                c1[better]
            if not better.any():
                break
        org, _ = _forward(rigid, R, t)
        Rw[fr], tw[fr] = R, org
    ms = rigid.marker_segment
    fitted = tw[:, ms] + np.einsum("tmij,mj->tmi", Rw[:, ms], rigid.marker_offsets)
    return SkeletonFit(world_from_segment_R=Rw, world_from_segment_t=tw, joint_centres=tw.copy(),
                       fitted_markers=fitted, status=fit.status, rate_hz=fit.rate_hz)

"""Per-frame fit of a rigid skeleton back to marker data: hierarchical and closed form.

``fit_skeleton(trajectories (T, M, 3), rigid: RigidSkeleton, rate_hz=1.0,
child_joints=True) -> SkeletonFit``. The thesis'
fit back (000, section 3.8.2), segment by segment from the root outwards, each step a
closed-form Horn/Kabsch rotation:

- the root (or a segment whose parent could not be fitted) with >= 3 visible markers:
  rotation and translation from its markers (``FIT_MARKERS``);
- any other segment whose parent is fitted: its origin is its joint, placed by the parent's
  pose; it only rotates about it (the segments stay connected, 3.8.2 step 3). The joint
  centre is the extra fixed point of the rotation-point thesis (001, 5.5.1): 2 or more
  visible points suffice (``FIT_JOINT``); with 1 visible marker a hinge's axis (known in
  the parent's frame) is the third constraint (001, case 3, ``FIT_HINGE``);
- with ``child_joints`` (default) a segment's points also include its children's joints as
  located by the children's own markers (Horn/Kabsch, >= 3 visible): the rotation is then
  fitted out to the far joint instead of extrapolated from markers near the near one, which
  keeps a parent's rotation noise from swinging the whole subtree;
- otherwise (a ball joint with one visible marker, nothing visible, markers collinear with
  the joint) the segment and its subtree stay NaN in that frame (``FIT_NONE``).

Conventions: docs/conventions.md [frames] (``world_from_segment``), [arrays], [rotations].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skeleton.rigid_skeleton import RigidSkeleton

__all__ = ["SkeletonFit", "fit_skeleton", "FIT_NONE", "FIT_MARKERS", "FIT_JOINT",
           "FIT_HINGE", "DEGENERATE_RATIO"]

FIT_NONE, FIT_MARKERS, FIT_JOINT, FIT_HINGE = 0, 1, 2, 3
DEGENERATE_RATIO = 1e-3    # second/first singular value of the point spread below: degenerate


@dataclass(frozen=True, kw_only=True)
class SkeletonFit:
    """Per-frame skeleton poses (NaN where a segment could not be fitted).

    Attributes:
        world_from_segment_R: (T, S, 3, 3).
        world_from_segment_t: (T, S, 3) m, segment origins: the proximal joint (root: the
            origin of the rigid skeleton's root frame).
        joint_centres: (T, S, 3) m, segment s's proximal joint (= world_from_segment_t; for
            the root its origin), as ``hw_sim.articulated.Motion.joint_centres``.
        fitted_markers: (T, M, 3) m, the rigid skeleton's markers at the fitted poses.
        status: (T, S) int8, FIT_NONE / FIT_MARKERS / FIT_JOINT / FIT_HINGE.
        rate_hz: frame rate.
    """

    world_from_segment_R: np.ndarray
    world_from_segment_t: np.ndarray
    joint_centres: np.ndarray
    fitted_markers: np.ndarray
    status: np.ndarray
    rate_hz: float

    def __post_init__(self):
        R = np.asarray(self.world_from_segment_R)
        if R.ndim != 4 or R.shape[2:] != (3, 3):
            raise ValueError(f"world_from_segment_R.shape={R.shape}, expected (T, S, 3, 3)")
        T, S = R.shape[:2]
        M = np.asarray(self.fitted_markers).shape[1]
        for name, shape in (("world_from_segment_t", (T, S, 3)), ("joint_centres", (T, S, 3)),
                            ("fitted_markers", (T, M, 3)), ("status", (T, S))):
            if np.asarray(getattr(self, name)).shape != shape:
                raise ValueError(f"{name}.shape={np.asarray(getattr(self, name)).shape}, "
                                 f"expected {shape}")
        if not self.rate_hz > 0:
            raise ValueError(f"rate_hz={self.rate_hz!r}, expected > 0")
        for name in ("world_from_segment_R", "world_from_segment_t", "joint_centres",
                     "fitted_markers", "status"):
            a = np.array(getattr(self, name))
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    def marker_deviation(self, trajectories) -> np.ndarray:
        """(T, M) m distance between measured and fitted markers (NaN where either is)."""
        return np.linalg.norm(np.asarray(trajectories, np.float64) - self.fitted_markers, axis=2)


def _rotation_about(p: np.ndarray, q: np.ndarray, w: np.ndarray | None = None):
    """Rotations R (F, 3, 3) minimising sum_i w_i |R p_i - q_i|^2 (no translation) for
    p, q (F, N, 3) with NaN rows ignored; returns (R, ok (F,))."""
    valid = ~(np.isnan(p).any(2) | np.isnan(q).any(2))
    ww = valid.astype(float) if w is None else np.where(valid, w, 0.0)
    H = np.einsum("fn,fni,fnj->fij", ww, np.nan_to_num(q), np.nan_to_num(p))
    U, s, Vt = np.linalg.svd(H)
    ok = s[:, 1] > DEGENERATE_RATIO * np.maximum(s[:, 0], 1e-300)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.zeros_like(H)
    D[:, 0, 0] = D[:, 1, 1] = 1
    D[:, 2, 2] = d
    return U @ D @ Vt, ok


def _free_origins(traj: np.ndarray, rigid: RigidSkeleton) -> np.ndarray:
    """(T, S, 3) each segment's origin (its proximal joint) from its own markers alone
    (Horn/Kabsch, >= 3 visible markers), NaN elsewhere."""
    T = traj.shape[0]
    out = np.full((T, rigid.n_segments, 3), np.nan)
    for s in range(rigid.n_segments):
        idx = np.flatnonzero(rigid.marker_segment == s)
        if idx.size < 3:
            continue
        X = traj[:, idx]
        vis = ~np.isnan(X).any(2)
        f3 = np.flatnonzero(vis.sum(1) >= 3)
        for k in np.unique(vis[f3], axis=0) if f3.size else []:
            fk = f3[(vis[f3] == k).all(1)]
            src = np.broadcast_to(rigid.marker_offsets[idx[k]], (fk.size, int(k.sum()), 3))
            _, t, ok = _kabsch_to(src, X[fk][:, k])
            out[fk[ok], s] = t[ok]
    return out


def fit_skeleton(trajectories, rigid: RigidSkeleton, rate_hz: float = 1.0,
                 child_joints: bool = True) -> SkeletonFit:
    traj = np.asarray(trajectories, np.float64)
    if traj.ndim != 3 or traj.shape[2] != 3 or traj.shape[1] != rigid.n_markers:
        raise ValueError(f"trajectories.shape={traj.shape}, expected (T, {rigid.n_markers}, 3)")
    T, M = traj.shape[:2]
    S = rigid.n_segments
    Rw = np.full((T, S, 3, 3), np.nan)
    tw = np.full((T, S, 3), np.nan)
    status = np.zeros((T, S), np.int8)
    seg = rigid.marker_segment
    kids = rigid.children
    free_origin = _free_origins(traj, rigid) if child_joints else None
    for s in rigid.order:
        idx = np.flatnonzero(seg == s)
        P = rigid.marker_offsets[idx]                              # (n, 3) in s's frame
        X = traj[:, idx]                                           # (T, n, 3)
        if child_joints and kids[s]:
            # the children's joints, located by the children's own markers, as extra points
            P = np.concatenate([P, rigid.joint_offsets[list(kids[s])]])
            X = np.concatenate([X, free_origin[:, list(kids[s])]], 1)
            idx = np.concatenate([idx, np.full(len(kids[s]), -1)])
        vis = ~np.isnan(X).any(2)                                  # (T, n)
        nvis = vis.sum(1)
        p = rigid.parents[s]
        if p >= 0:
            par_ok = status[:, p] > 0
            c = tw[:, p] + np.einsum("tij,j->ti", Rw[:, p], rigid.joint_offsets[s])
        else:
            par_ok = np.zeros(T, bool)
            c = np.full((T, 3), np.nan)
        # 1) rotation about the joint placed by the parent (>= 2 markers)
        f2 = np.flatnonzero(par_ok & (nvis >= 2))
        if f2.size:
            R, ok = _rotation_about(np.broadcast_to(P, (f2.size,) + P.shape),
                                    np.where(vis[f2][..., None], X[f2] - c[f2, None], np.nan))
            f = f2[ok]
            Rw[f, s], tw[f, s], status[f, s] = R[ok], c[f], FIT_JOINT
        # 2) hinge with one marker: marker + axis (001, case 3)
        if rigid.hinge[s] and p >= 0:
            f1 = np.flatnonzero(par_ok & (nvis == 1))
            if f1.size:
                a_c = rigid.hinge_axes_child[s]
                a_w = np.einsum("tij,j->ti", Rw[f1, p], rigid.hinge_axes_parent[s])
                w_ax = max(float(np.mean(np.sum(P ** 2, 1))), 1e-6)
                pp = np.concatenate([np.broadcast_to(P, (f1.size,) + P.shape),
                                     np.broadcast_to(a_c, (f1.size, 1, 3))], 1)
                qq = np.concatenate([np.where(vis[f1][..., None], X[f1] - c[f1, None], np.nan),
                                     a_w[:, None]], 1)
                w = np.concatenate([np.ones((f1.size, len(idx))),
                                    np.full((f1.size, 1), w_ax)], 1)
                R, ok = _rotation_about(pp, qq, w)
                f = f1[ok]
                Rw[f, s], tw[f, s], status[f, s] = R[ok], c[f], FIT_HINGE
        # 3) root, or parent missing: free Horn/Kabsch from >= 3 markers
        f3 = np.flatnonzero(~par_ok & (nvis >= 3))
        for k in np.unique(vis[f3], axis=0) if f3.size else []:
            fk = f3[(vis[f3] == k).all(1)]
            src = np.broadcast_to(P[k], (fk.size, int(k.sum()), 3))
            # world_from_segment: X ~ R P + t  <=>  kabsch(P -> X) per frame
            Rk, tk, ok = _kabsch_to(src, X[fk][:, k])
            f = fk[ok]
            Rw[f, s], tw[f, s], status[f, s] = Rk[ok], tk[ok], FIT_MARKERS
    fitted = np.full((T, M, 3), np.nan)
    fitted[:] = tw[:, seg] + np.einsum("tmij,mj->tmi", Rw[:, seg], rigid.marker_offsets)
    return SkeletonFit(world_from_segment_R=Rw, world_from_segment_t=tw, joint_centres=tw.copy(),
                       fitted_markers=fitted, status=status, rate_hz=float(rate_hz))


def _kabsch_to(src: np.ndarray, dst: np.ndarray):
    """Per frame (R, t, ok) with dst[f] ~ R src[f] + t for src, dst (F, N, 3)."""
    cs, cd = src.mean(1), dst.mean(1)
    R, ok = _rotation_about(src - cs[:, None], dst - cd[:, None])
    t = cd - np.einsum("fij,fj->fi", R, cs)
    return R, t, ok

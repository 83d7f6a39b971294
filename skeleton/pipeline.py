"""Marker trajectories -> skeleton: segments, topology, joint centres.

``solve_skeleton(trajectories (T, M, 3), rate_hz, n_segments=None, rng=None, progress=None)
-> SkeletonResult``. Stages: ``skeleton.segments`` (spectral clustering of distance
variance), ``skeleton.joints`` (joint fit of every segment pair; its residual is the edge
cost), ``skeleton.topology`` (MST, root = tree centre), then a refined joint fit per edge.
Conventions: docs/conventions.md [arrays], [units].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skeleton.joints import JointFit, fit_joint
from skeleton.segments import segment_markers
from skeleton.topology import skeleton_tree

__all__ = ["SkeletonResult", "solve_skeleton"]


@dataclass(frozen=True, kw_only=True)
class SkeletonResult:
    """labels (M,) segment per marker; n_segments; eigengap_k; root; parents (S,);
    cost (S, S) joint-fit residuals m; joints: tuple of JointFit per segment (None for the
    root: the joint with its parent); joint_centres (T, S, 3) m (the root's: NaN); rate_hz."""

    labels: np.ndarray
    n_segments: int
    eigengap_k: int
    root: int
    parents: np.ndarray
    cost: np.ndarray
    joints: tuple
    joint_centres: np.ndarray
    rate_hz: float


def solve_skeleton(trajectories, rate_hz: float, n_segments: int | None = None, rng=None,
                   progress=None) -> SkeletonResult:
    traj = np.asarray(trajectories, np.float64)
    if traj.ndim != 3 or traj.shape[2] != 3:
        raise ValueError(f"trajectories.shape={traj.shape}, expected (T, M, 3)")
    say = progress or (lambda msg: None)
    seg = segment_markers(traj, n_segments, rng)
    S = seg.n_segments
    say(f"segments: {S} (eigengap choice {seg.eigengap_k})")
    members = [np.flatnonzero(seg.labels == s) for s in range(S)]
    cost = np.full((S, S), np.inf)
    for i in range(S):
        for j in range(i + 1, S):
            f = fit_joint(traj, members[i], members[j], refine=False)
            cost[i, j] = cost[j, i] = f.residual_m if f.ok else np.inf
    say(f"joint costs: {S * (S - 1) // 2} pairs")
    top = skeleton_tree(cost)
    say(f"topology: root segment {top.root}")
    T = traj.shape[0]
    jc = np.full((T, S, 3), np.nan)
    joints: list[JointFit | None] = [None] * S
    for s in range(S):
        p = top.parents[s]
        if p < 0:
            continue
        f = fit_joint(traj, members[p], members[s])
        joints[s] = f
        jc[:, s] = f.world
    return SkeletonResult(labels=seg.labels, n_segments=S, eigengap_k=seg.eigengap_k,
                          root=top.root, parents=top.parents, cost=cost, joints=tuple(joints),
                          joint_centres=jc, rate_hz=float(rate_hz))

"""Marker trajectories -> skeleton: segments, topology, joint centres.

``solve_skeleton(trajectories (T, M, 3), rate_hz, n_segments=None, rng=None, progress=None)
-> SkeletonResult``. Stages: ``skeleton.segments`` (spectral clustering of distance
variance, K by eigengap unless given), ``skeleton.joints.joint_cost`` for every segment pair
(noise-normalised joint-fit residual; on 6 Hz low-passed data when the data is noisy),
``skeleton.topology`` (MST; pairs whose fit is a hinge within the noise are taken first),
``skeleton.junctions`` (segments meeting at one point re-linked around their hub), root =
tree centre, then a refined joint fit per tree edge. Two-marker pairs are fitted in world
coordinates from a closed-form start, re-searched from many starts where the tree could take
them.
Conventions: docs/conventions.md [arrays], [units].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scipy.signal import butter, sosfiltfilt

from skeleton.joints import JointFit, fit_joint, joint_cost
from skeleton.segments import segment_markers
from skeleton.junctions import resolve_junctions
from skeleton.topology import skeleton_tree, tree_from_edges

__all__ = ["SkeletonResult", "solve_skeleton", "lowpass", "COST_CUTOFF_HZ"]

COST_CUTOFF_HZ = 6.0   # low-pass for the topology costs (biomechanics' usual 6 Hz)
RECHECK = 10.0         # 2+2 pairs re-searched when their quick cost is below RECHECK x ...
RECHECK_MIN_M = 5e-3   # ... the median tree-edge cost (noise-free data: below this)
BROKEN_M = 0.02        # ... or above this (no fit: the closed-form start failed; measured on
                       # 30 held-out figures: 2 of 45 true 2+2 pairs scored 139 and 507 mm,
                       # 48 of 267 false ones > 20 mm)
PRUNE = 0.9            # ... and the tree path between them has an edge above this x it
CLEAN_NOISE_M = 1e-4   # within-segment distance sd below which the data is not filtered
HINGE_SURE = 1.5       # hinge pairs costing at most this x the median tree-edge cost: sure
JUNCTION_K = 25.0      # tree joints closer than this x the within-segment distance sd: one
JUNCTION_COST = 1.5    # junction (skeleton.junctions), re-linked with edges costing at most
                       # this x the largest tree-edge cost. Sibling joints a few cm apart are
                       # still told apart better by the hub prior + star cost than by the
                       # MST's pairwise costs: exact topology over seed sets 1000/2000/3000
                       # (1 mm noise; benchmarks/bench_skeleton.py) with K = 4: 47/44/43,
                       # 8: 47/44/47, 12: 48/46/48, 20: 49/47/48, 30: 49/47/48; on a fresh
                       # set 4000, looked at once per value: K = 4 37/50, K = 25 43/50.


def lowpass(traj: np.ndarray, rate_hz: float, cutoff_hz: float = COST_CUTOFF_HZ,
            trim: bool = False) -> np.ndarray:
    """Zero-phase 4th-order Butterworth low-pass of (T, M, 3) trajectories along time, run by
    run between NaN gaps (runs too short to filter are kept as they are). The input is
    returned unchanged when ``cutoff_hz`` is not below the Nyquist frequency / 2. ``trim``
    sets the first and last ``1.5 / cutoff_hz`` s of every filtered run to NaN (the
    filter's start-up transient), keeping at least half of the run."""
    traj = np.asarray(traj, np.float64)
    if not rate_hz > 0 or not cutoff_hz > 0:
        raise ValueError(f"rate_hz={rate_hz!r}, cutoff_hz={cutoff_hz!r}, expected > 0")
    if cutoff_hz >= rate_hz / 4:
        return traj.copy()
    sos = butter(2, cutoff_hz, fs=rate_hz, output="sos")
    out = traj.copy()
    pad = 3 * (2 * len(sos) + 1)
    for m in range(traj.shape[1]):
        ok = ~np.isnan(traj[:, m]).any(1)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(int), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            if b - a > pad:
                out[a:b, m] = sosfiltfilt(sos, traj[a:b, m], axis=0)
                e = min(int(1.5 * rate_hz / cutoff_hz), (b - a) // 4)
                if trim and e > 0:
                    out[a:a + e, m] = out[b - e:b, m] = np.nan
    return out


def _path_max(top, cost: np.ndarray, i: int, j: int) -> float:
    """The largest cost among the edges of tree ``top`` on the path between i and j."""
    worst = 0.0
    up = {int(i): 0.0}             # worst edge from i up to each ancestor
    a = int(i)
    while top.parents[a] >= 0:
        p = int(top.parents[a])
        up[p] = max(up[a], cost[a, p])
        a = p
    b = int(j)
    while b not in up:
        p = int(top.parents[b])
        worst = max(worst, cost[b, p])
        b = p
    return max(worst, up[b])


@dataclass(frozen=True, kw_only=True)
class SkeletonResult:
    """labels (M,) segment per marker; n_segments; eigengap_k; root; parents (S,);
    cost (S, S) topology costs m (noise-normalised joint-fit residuals,
    ``skeleton.joints.joint_cost``; on 6 Hz low-passed data when the data is noisy);
    joints: tuple of JointFit per segment (None for the root: the joint with its parent;
    fitted on the low-passed data when noisy); joint_centres (T, S, 3) m (the root's: NaN);
    rate_hz."""

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
    # Topology cost of every pair on low-passed data: a false joint's misfit follows the
    # (slow) motion, the marker noise is broadband, so filtering separates them.
    # (Not when the data is already clean: the filter's own error, ~0.05 mm at 6 Hz, would
    # then be the largest term. Noise level: within-segment distance sd.)
    same = (seg.labels[:, None] == seg.labels[None]) & ~np.eye(seg.labels.size, dtype=bool)
    noise_m = float(np.median(seg.distance_sd[same])) if same.any() else 0.0
    noisy = noise_m > CLEAN_NOISE_M
    smooth = lowpass(traj, rate_hz, trim=True) if noisy else traj
    cost = np.full((S, S), np.inf)
    hinge = np.zeros((S, S), bool)
    radii = {}      # 2+2 pairs: the fit's marker-joint distances (a start for the final fit)
    for i in range(S):
        for j in range(i + 1, S):
            pc = joint_cost(smooth, members[i], members[j], multistart=False, detail=True)
            cost[i, j] = cost[j, i] = pc.cost
            hinge[i, j] = hinge[j, i] = pc.hinge
            radii[i, j] = pc.radii
    # 2+2-marker pairs got only their closed-form start (an upper bound on their cost). Pairs
    # that could still matter (below RECHECK x the median tree-edge cost, but above the
    # noise floor; or no fit at all) get the multi-start search - unless the tree could not
    # take them: by the cycle property, a pair enters the minimum spanning tree only by
    # replacing the costliest edge on the tree path between its segments, and a true pair
    # costs no less than the noise floor.
    mst = skeleton_tree(cost)
    floor = float(np.median(cost[tuple(mst.edges.T)]))
    two = np.array([m.size == 2 for m in members])
    for i, j in zip(*np.triu_indices(S, 1)):
        upper = RECHECK * floor if noisy else RECHECK_MIN_M
        if (two[i] and two[j] and 1.2 * floor < cost[i, j]
                and (cost[i, j] < upper or cost[i, j] > BROKEN_M)
                and _path_max(mst, cost, i, j) > PRUNE * floor):
            pc = joint_cost(smooth, members[i], members[j], detail=True)
            if pc.cost < cost[i, j]:
                cost[i, j] = cost[j, i] = pc.cost
                radii[i, j] = pc.radii
                mst = skeleton_tree(cost)
    say(f"joint costs: {S * (S - 1) // 2} pairs")
    # A pair whose relative motion is a rotation about one axis, fitting within the noise,
    # is a true joint: between segments that are not neighbours the relative motion
    # composes two or more joints' rotations, which is one-axis only for hinges about one
    # common axis. Such pairs enter the tree first (the tree of the rest of the pairs).
    floor = float(np.median(cost[tuple(skeleton_tree(cost).edges.T)]))
    sure = hinge & (cost <= HINGE_SURE * floor)
    top = skeleton_tree(cost, first=sure)
    T = traj.shape[0]
    # joint centres from the low-passed data too (all frames, untrimmed) when it is noisy
    fit_data = lowpass(traj, rate_hz) if noisy else traj
    fits: dict[tuple, JointFit] = {}

    def fit(p, s):
        if (p, s) not in fits:
            r = radii.get((min(p, s), max(p, s)))
            if r is not None and p > s:     # radii follow the markers' order: a's, then b's
                r = np.concatenate([r[members[s].size:], r[:members[s].size]])
            fits[p, s] = fit_joint(fit_data, members[p], members[s], noise_m=floor, radii=r)
        return fits[p, s]

    # Segments meeting at one point (sibling joints within the joint-centre uncertainty):
    # the MST's choice among them is arbitrary; re-link each such group around its hub.
    if S > 2:
        centres = {frozenset((int(a), int(b))): fit(int(a), int(b)).world for a, b in top.edges}
        axes = {frozenset((int(a), int(b))): fit(int(a), int(b)).axis_world
                for a, b in top.edges}
        tree_cost = cost[tuple(top.edges.T)]
        edges = resolve_junctions(fit_data, members, top.edges, centres, cost,
                                  tol_m=JUNCTION_K * noise_m,
                                  max_cost=JUNCTION_COST * float(np.max(tree_cost)), axes=axes,
                                  recost=lambda a, b: joint_cost(smooth, members[a], members[b]),
                                  is_hinge=lambda a, b: fit(a, b).hinge)
        top = tree_from_edges(S, edges)
    say(f"topology: root segment {top.root}")
    jc = np.full((T, S, 3), np.nan)
    joints: list[JointFit | None] = [None] * S
    for s in range(S):
        p = top.parents[s]
        if p < 0:
            continue
        f = fit(p, s)
        joints[s] = f
        jc[:, s] = f.world
    return SkeletonResult(labels=seg.labels, n_segments=S, eigengap_k=seg.eigengap_k,
                          root=top.root, parents=top.parents, cost=cost, joints=tuple(joints),
                          joint_centres=jc, rate_hz=float(rate_hz))

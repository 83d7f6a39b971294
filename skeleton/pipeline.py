"""Marker trajectories -> skeleton: segments, topology, joint centres.

``solve_skeleton(trajectories (T, M, 3), rate_hz, n_segments=None, rng=None, progress=None,
workers=None) -> SkeletonResult``. Stages: ``skeleton.segments`` (spectral clustering of
distance variance, K by eigengap unless given), ``skeleton.joints.joint_cost`` for every
segment pair (noise-normalised joint-fit residual; the closed-form costs in one worker
process per CPU) - both on 6 Hz low-passed data when the data is noisy,
``skeleton.topology`` (MST; pairs whose fit is a hinge within the noise are taken first),
``skeleton.junctions`` (segments meeting at one point re-linked around their hub, sure hinge
pairs kept; found on the tree's joints as the final fit makes them), ``skeleton.relink``
(two tree edges sharing a segment: the triple's three stars fitted to its markers as one
articulated model each, re-linked where a neighbour's fits decisively better), root = tree centre,
then a refined joint fit per tree edge (``_completed_fits``: a joint between two frameless
segments fitted in one's frame completed by a neighbour's joint; ``_world_centre``: a centre
its reference frame carries too noisily placed by the world-frame fit). Segments without
a usable frame (two markers, or markers within the noise of a line) are fitted in world
coordinates from a closed-form start, re-searched from many starts where the tree could
take them; their cheap pairs are then re-tested with an anchor joint completing their frame
(``_Completed``; a completed segment lends its frame on down a chain of 2-marker segments),
or - without anchors - raised where a framed segment fits both at distinct points
(``_raise_split_siblings``).
Conventions: docs/conventions.md [arrays], [units].
"""
from __future__ import annotations

import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace

import numpy as np

from scipy.signal import butter, sosfiltfilt
from threadpoolctl import threadpool_limits

from skeleton import joints as _joints, rigid as _rigid, star_lm as _star_lm
from skeleton import world_lm as _world_lm
from skeleton.joints import JointFit, fit_joint, frame_quality, inertia, joint_cost
from skeleton.rigid import kabsch
from skeleton.segments import distance_sd, noise_sd, segment_markers
from skeleton.junctions import (STAR_MARGIN, Junction, joint_gap, joint_spread,
                                resolve_junctions)
from skeleton.relink import relink_by_stars
from skeleton.topology import skeleton_tree, tree_from_edges

__all__ = ["SkeletonResult", "solve_skeleton", "lowpass", "warm_up", "COST_CUTOFF_HZ"]

COST_CUTOFF_HZ = 6.0   # low-pass for the topology costs (biomechanics' usual 6 Hz)
FIT_TRIM = True        # the joint fits, junction and star decisions also run on the trimmed
                       # low-pass (it was untrimmed: with 30 frames trimmed it lost too much;
                       # with 5 the filter's start-up error at every gap is the larger harm):
                       # occluded bench sets 1000, 2000, 4000-7000 (1 mm) 343 -> 345/350
                       # (2004, 2021), unoccluded 1000-6000 298/300 both, median joint errors
                       # within +-0.03 mm; real recordings' trees identical, mean marker
                       # deviations +0.00 to +0.05 mm
TRIM_PERIODS = 0.25    # lowpass(trim=True): run ends cut, in periods of the cut-off
                       # (5 frames at 6 Hz and 120 Hz). The filter's start-up error lies
                       # within ~8 frames of a run end (1 mm noise, 60 deg, 20 occluded
                       # figures: rms 2.0 mm at 0-2 frames, 1.5 at 3-7, 1.0 beyond). It was
                       # 1.5 (30 frames): every occlusion then cost its marker 60 frames
                       # more, a pair of many-marker segments kept few frames in common, and
                       # with 1-3 gaps of 3-40 frames per marker (400 frames, ids kept) the
                       # topology was exact on 4 of figures 0-79; 77 at 0.25 (0.5: 73, 0:
                       # 76), and 149 -> 150 of 150 on unoccluded sets 1000-3000
RECHECK_MIN_M = 5e-3   # noise-free data: pairs of frameless segments costing below this
                       # are re-tested in completed frames
PRUNE = 0.9            # 2+2 pairs searched when the tree path between them has an edge
                       # above this x the noise floor
POOR_FRAME = 3.0       # markers within this x the noise (distance sd) of a line: no frame
ANCHOR = 1.5           # frameless segments' anchor joints: cost <= this x the noise floor
ANCHOR_GAIN = 2.5      # ... and centre noise <= this x the marker noise
FALSIFY_BELOW = 3.0    # pairs of a frameless segment costing below this x the floor are
FALSIFY = 2.5          # re-tested with anchors; raised when the completed fit costs > this x
                       # the floor. Measured on the 10 failing figures of seed sets 1000-4000
                       # (1 mm noise): the false pairs the tree took, at 1.0-1.1x the floor,
                       # complete to 12-58x; true pairs stay <= 1.5x when the anchor's gain
                       # is <= 2.5 (gains of 3-7 inflated them to 3-16x). Exact topology
                       # over six seed sets, before the junction split: FALSIFY 2.5 and 3.5
                       # both 290/300, POOR_FRAME 5 289/300; with the split 291/300; before
                       # these rules 284/300. With hw_sim's 20 mm marker spacing (70ca108):
                       # 293/300, with anchors chained through completed segments 294/300;
                       # with 400 draws per marker (90200a6, 14 figures re-rolled) 293/300;
                       # anchors only from the cheapest neighbour with a frame 294/300
PARALLEL_PAIRS = 28     # pair costs computed in forked processes from this many pairs (8
                       # segments): the pool's start-up, ~0.015 s, against ~0.01 s per pair
                       # (largest benchmark case, 78 pairs: 0.77 -> 0.43 s on 2 cores)
CLEAN_NOISE_M = 1e-4   # within-segment distance sd below which the data is not filtered
WORLD_GAIN = 8.0       # a joint centre carried by its reference frame with more noise than
                       # this x the marker noise is placed by the world-frame fit
                       # (_world_centre). True joints of seed sets 1000-3000 (1 mm), frame
                       # fit / world fit error: gain >= 8, 8 joints, world better in all 8
                       # (frame up to 31.9 mm, world <= 6.2); gain 5-8, 23 joints, mixed
                       # (world up to 49 mm)
WORLD_RES = 1.5        # ... unless the world fit is no joint within the noise (RMS residual
WORLD_SHIFT = 20.0     # above WORLD_RES x the floor) and its centre lies more than WORLD_SHIFT x
                       # the frame's carried noise (gain x floor) from the frame fit's: another
                       # solution (held-out 136015, 1 mm: a 2-marker root's joint with a
                       # 3-marker child, world residual 2.2x, shift 57.7x, 143.7 mm off the
                       # truth; the frame fit 3.7 mm). The 29 world placements of 1000-8000
                       # and 105000-112000 (800 figures): residuals 0.57-0.81x except 107017's
                       # 2.03x (shift 2.4x; world 1.7 mm off, frame 3.7), shifts of the ball
                       # fits 0.3-7.5x; 76033's (a hinge the fit did not call one): shift 22x,
                       # residual 0.7x, world 2.7 mm off, frame 46.8 mm. None is changed
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
    sets the first and last frames of every filtered run to NaN (the
    filter's start-up transient, ``TRIM_PERIODS`` / ``cutoff_hz`` s), keeping at least half
    of the run."""
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
                e = min(int(TRIM_PERIODS * rate_hz / cutoff_hz), (b - a) // 4)
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


def _tree_floor(cost: np.ndarray) -> float:
    """The median cost of the minimum spanning tree's edges (what a true joint scores); NaN
    for one segment (no edge)."""
    if cost.shape[0] < 2:
        return float("nan")
    return float(np.median(cost[tuple(skeleton_tree(cost).edges.T)]))


def _point_noise_gain(ref_pts: np.ndarray, point: np.ndarray) -> float:
    """RMS noise (per axis, in units of the marker noise) of a point fixed in the frame of
    the reference markers ``ref_pts`` (N, 3) and carried by their pose (Kabsch: translation
    variance 1/N, rotation covariance P^-1 with P the markers' inertia about their centroid,
    times the lever arm)."""
    lx = np.cross(np.eye(3), point - ref_pts.mean(0))
    C = np.eye(3) / ref_pts.shape[0] + lx @ np.linalg.pinv(inertia(ref_pts)) @ lx.T
    return float(np.sqrt(np.trace(C) / 3))


def _world_centre(data, members, p: int, s: int, f: JointFit, noise_m: float) -> JointFit:
    """The joint (p, s) ``f``, fitted in one segment's frame, with its centre placed by the
    world-frame fit (``fit_joint`` of both segments' markers without a frame) where that
    frame carries the centre with more than WORLD_GAIN x the marker noise
    (``_point_noise_gain``). Such a frame's rotation noise moves the other segment's markers
    by its lever arm, which biases the sphere fit, not only blurs it. The world fit's
    per-frame centres are kept where it has all markers. Elsewhere the centre is their
    mean in the reference frame, carried by that frame. A world fit that fits no joint
    within the noise (RMS residual > WORLD_RES x ``noise_m``) and whose centre lies more
    than WORLD_SHIFT x the frame's carried noise from the frame fit's is another solution:
    the frame fit stays. Cost, hinge and axis stay the frame fit's."""
    if not f.ok or f.ref not in (0, 1):
        return f
    ref = members[p] if f.ref == 0 else members[s]
    full = np.flatnonzero(~np.isnan(data[:, ref]).any(axis=(1, 2)))
    if full.size == 0:
        return f
    gain = _point_noise_gain(data[full[0], ref], f.world[full[0]])
    if gain <= WORLD_GAIN:
        return f
    w = fit_joint(data, members[p], members[s], noise_m=noise_m, min_quality=np.inf)
    both = full[~np.isnan(w.world[full]).any(1)] if w.ok else full[:0]
    if both.size < 10:
        return f
    R, t = kabsch(data[full][:, ref], data[full[0], ref])
    k = np.searchsorted(full, both)
    local = (np.einsum("tij,tj->ti", R[k], w.world[both]) + t[k]).mean(0)
    if (w.residual_m > WORLD_RES * noise_m
            and np.linalg.norm(local - f.centre_local) > WORLD_SHIFT * gain * noise_m):
        return f        # no joint within the noise, far off the frame's: another solution
    world = np.full_like(f.world, np.nan)
    world[full] = np.einsum("tji,tj->ti", R, local[None] - t)
    world[both] = w.world[both]
    return replace(f, centre_local=local, world=world)


def _anchor_points(data, members, cost, floor, frameless, min_quality: float = 0.0
                   ) -> tuple[dict, np.ndarray, dict]:
    """For each frameless segment a: (p, J (T, 3)) - the joint with the cheapest segment p
    that has a frame, costing at most ANCHOR x ``floor``, whose centre the pose of p
    carries with noise at most ANCHOR_GAIN x the marker noise. J is a point fixed in a
    (a joint within the noise): a third point for a's frame. In rounds: a segment completed
    by its anchor lends its completed frame (markers + anchor) to its frameless neighbours
    in the next round (a chain of 2-marker segments hanging from a framed one). When the
    cheapest neighbour with a frame carries the centre too noisily, a gets no anchor in that
    round: a costlier neighbour is likelier a false sibling (seed 3022: its true parent's
    gain was 3.3, and the next one, completed later, was a sibling 31 mm away). (Tried:
    waiting for a cheaper frameless neighbour to be completed first - it anchored the
    largest benchmark case's segment 7 on its false sibling 4.) A completed neighbour is
    ranked by a's cost in its completed frame, not by the pair's world fit (two frameless
    segments: four marker distances per frame leave that fit near the floor for false
    siblings, and its closed-form start can be broken for true ones - seed 24010, 1 mm: the
    true parent's world cost 1.2 m, 1.08x the floor in its completed frame; seed 25033: a
    false sibling 21 mm away at 0.96x the floor, 1.98x in its completed frame). A completed
    neighbour in whose frame a costs more than FALSIFY x the floor (the level at which
    ``_Completed.raise_false`` calls a pair false) is no candidate, however cheap the world
    fit (held-out seed 187015, 1 mm: 2-marker segment 14 anchored in the second round on
    2, completed in the first, at 14.55x in 2's frame - its world fit 1.37x - before its
    true parent 0, a chain of 2-marker segments away, was completed; through that anchor
    the true pair 0-14 (0.81x) was raised to 11.3x. Now 14 waits for 0: 1.04x in 0's
    completed frame).
    Returns the anchors, the data with the anchor points appended as extra markers, and
    each completed segment's column in it."""
    anchors, cols, ext = {}, {}, data
    has_frame = ~np.asarray(frameless, bool)
    too_noisy = set()       # (a, p) whose fit failed or was too noisy: same in later rounds
    framed: dict[tuple, float] = {}     # (a, p): a's cost in p's completed frame

    def frame_cost(a, p):
        """a's cost against p: the matrix's, or - p completed - its fit in p's completed
        frame (p's own cost with a, a world fit of two frameless segments, may be broken)"""
        if p not in cols:
            return cost[a, p]
        if (a, p) not in framed:
            framed[a, p] = joint_cost(ext, np.append(members[p], cols[p]), members[a],
                                      min_quality=min_quality)
        return framed[a, p]

    while True:
        new = {}
        for a in np.flatnonzero(~has_frame):
            cand = [(frame_cost(a, p), int(p)) for p in np.flatnonzero(has_frame)
                    if min(cost[a, p], frame_cost(a, p)) <= ANCHOR * floor
                    and frame_cost(a, p) <= FALSIFY * max(floor, CLEAN_NOISE_M)]
            if not cand:
                continue
            _, p = min(cand)                # the cheapest neighbour with a frame, or none
            if (a, p) in too_noisy:
                continue
            ref = members[p] if p not in cols else np.append(members[p], cols[p])
            f = fit_joint(ext, ref, members[a], ref=0)
            seen = np.flatnonzero(~np.isnan(f.world).any(1))
            if f.ok and seen.size and _point_noise_gain(
                    ext[seen[0], ref], f.world[seen[0]]) <= ANCHOR_GAIN:
                new[int(a)] = (int(p), f.world)
            else:
                too_noisy.add((a, p))
        if not new:
            return anchors, ext, cols
        for a in sorted(new):
            cols[a] = ext.shape[1]
            ext = np.concatenate([ext, new[a][1][:, None]], 1)
            has_frame[a] = True
        anchors.update(new)


class _Completed:
    """Pairs of frameless segments re-fitted with the segments' anchor points
    (``_anchor_points``) added as extra markers: a true joint is still fixed in the
    segment's completed frame, a false one - free to turn about a 2-marker segment's line -
    no longer fits. A pair whose completed fit costs more than FALSIFY x the floor takes
    that cost (``raise_false``; costs are only ever raised: the anchor point's own noise
    adds to a true pair's cost, so completed costs are not compared otherwise)."""

    def __init__(self, data, members, cost, floor, frameless, min_quality):
        self.anchors, self.ext, self.col = _anchor_points(data, members, cost, floor,
                                                          frameless, min_quality)
        self.members, self.min_quality, self.raised = members, min_quality, 0
        self.costs: dict[tuple, float] = {}

    def applies(self, i, j) -> bool:
        """Whether a completed frame can test the pair: one of them has an anchor, and
        neither is the other's anchor."""
        return (i in self.anchors or j in self.anchors) and not self.anchored(i, j)

    def anchored(self, i, j) -> bool:
        """Whether one of the pair is the other's anchor segment (``_anchor_points``: the
        anchored one fits a joint in the anchor's completed frame within ANCHOR x the
        floor)."""
        an = self.anchors
        return an.get(i, (-1,))[0] == j or an.get(j, (-1,))[0] == i

    def raise_false(self, cost, i, j, floor) -> bool:
        """Whether the pair's completed fit costs > FALSIFY x ``floor`` (x CLEAN_NOISE_M
        at least: clean data is treated as noisy at that level); then ``cost`` (in place)
        takes it (when higher)."""
        if (i, j) not in self.costs:
            # each completed frame on its own, against the other's bare markers: a true
            # joint is fixed in each, a false one fails in at least one (seed 25033, 1 mm:
            # false siblings 21 mm apart cost 1.98x and 4.57x the floor so, 1.75x with both
            # frames completed at once)
            mi, mj = self.members[i], self.members[j]
            self.costs[i, j] = max(
                joint_cost(self.ext, np.append(mi, self.col[i]), mj,
                           min_quality=self.min_quality) if i in self.anchors else 0.0,
                joint_cost(self.ext, mi, np.append(mj, self.col[j]),
                           min_quality=self.min_quality) if j in self.anchors else 0.0)
        c2 = self.costs[i, j]
        if not c2 > FALSIFY * max(floor, CLEAN_NOISE_M):
            return False
        if c2 > cost[i, j]:
            cost[i, j] = cost[j, i] = c2
            self.raised += 1
        return True


def _raise_split_siblings(data, members, cost, floor, frameless, upper, tol_m, log=None,
                          anchored=None):
    """Cheap pairs (below ``upper``) of two frameless segments a, b with a framed segment p
    that fits a joint within the noise with each (cost <= ANCHOR x ``floor``), at centres
    that lie apart in p (median distance > ``tol_m``; to a hinge's axis line): their cost is
    raised to FALSIFY x the floor (x CLEAN_NOISE_M at least; in place, never lowered). Of
    the three pairs of such a triangle a tree takes two, and all three are joints only where
    the two joints on p coincide (a junction). p's fits are framed (a centre fixed in p,
    constant distances to the other's markers); the world fit of a, b only has four marker
    distances per frame to place a point, which false siblings can meet (seed 63031, 1 mm:
    siblings 41 mm apart under 3-marker segment 1 at 1.00x the floor, their true joints on
    1 at 0.97x and 1.01x; the tree took the false one). This is the anchor test
    (``_Completed``) where no anchor exists: p's frame carries both joints too noisily
    (gains 3.5 and 2.7). ``anchored(a, b)``, when given: whether one of the pair is the
    other's anchor (``_Completed.anchored``); such a pair is not raised. Its joint already
    fitted within the noise in the anchor's completed frame, and then the cheap pair on p
    is the likelier false one of the triangle (seed 119044, 1 mm: 2-marker hinge child 1 of
    2-marker root 0, anchored on it; the false sibling pair 1-2 at 1.31x the floor, 2-0 at
    1.03x, their centres 103 mm apart on 3-marker segment 2; the true edge 0-1, at 0.84x,
    was raised and the tree took 1-2). ``log``, when given, gets (a, b, p, median distance
    m, cost / floor) per raised pair. Returns the raised pairs (frozensets)."""
    fits: dict = {}

    def fit(p, a):
        if (p, a) not in fits:
            fits[p, a] = fit_joint(data, members[p], members[a], ref=0)
        return fits[p, a]

    out: set = set()
    for a, b in zip(*np.triu_indices(len(members), 1)):
        if not (frameless[a] and frameless[b] and cost[a, b] < upper):
            continue
        if anchored is not None and anchored(a, b):
            continue
        for p in np.flatnonzero(~np.asarray(frameless, bool)):
            if max(cost[p, a], cost[p, b]) > ANCHOR * floor:
                continue
            fa, fb = fit(p, a), fit(p, b)
            if not (fa.ok and fb.ok):
                continue
            gap = joint_gap(fa.world, fa.axis_world, fb.world, fb.axis_world)
            if np.isfinite(gap).any() and np.nanmedian(gap) > tol_m:
                if log is not None:
                    log.append((int(a), int(b), int(p), float(np.nanmedian(gap)),
                                float(cost[a, b] / floor)))
                cost[a, b] = cost[b, a] = max(cost[a, b], FALSIFY * max(floor, CLEAN_NOISE_M))
                out.add(frozenset((int(a), int(b))))
                break
    return out


def _completed_fits(data, members, parents, fits: dict, min_q: float, memo: dict | None = None
                    ) -> dict:
    """Joints of a tree between two frameless segments (world-frame fits,
    ``JointFit.ref`` -1), re-fitted in the frame of one of them completed by a joint it has
    with a segment that has a frame (``_anchor_points``' idea on a tree): that joint
    is fixed in it, a third point. Its frame's roll about the marker line is then known, and
    the other segment's markers get a sphere fit in it, where the world fit only has four
    marker distances to place a centre each frame. Where both segments can be completed, the
    joint is fitted in both frames and the lower (noise-normalised) cost kept: an anchor
    near its two markers' line leaves the frame's roll to the noise. A completed segment
    passes its new joint on down a chain of frameless segments (used on the tree the
    junctions are found in, and on the final one). ``fits``: child -> JointFit of the tree
    (parents[s], s). Returns the re-fitted ones (child -> JointFit, ``ref`` 0 or 1 naming
    the completed side; ``hinge`` only where that frame's first full frame is its markers')."""
    world = {s for s, f in fits.items() if f.ok and f.ref == -1}
    if not world:
        return {}
    anchor: dict[int, tuple[float, np.ndarray]] = {}      # segment -> (noise gain, point)

    def offer(seg, point, ref_pts):
        seen = np.flatnonzero(~np.isnan(point).any(1))
        if seen.size == 0 or frame_quality(data, members[seg]) > min_q and members[seg].size > 2:
            return
        gain = _point_noise_gain(ref_pts(seen[0]), point[seen[0]])
        if np.isfinite(gain) and (seg not in anchor or gain < anchor[seg][0]):
            anchor[seg] = (gain, point)

    for s, f in fits.items():
        if f.ok and f.ref in (0, 1):
            p = int(parents[s])
            ref_seg, other = (p, s) if f.ref == 0 else (s, p)
            offer(other, f.world, lambda t, r=ref_seg: data[t, members[r]])

    def fit_in(s, p, side):
        """the joint (p, s) fitted in the frame of side (0: p, 1: s) completed by its anchor:
        (JointFit or None where the completed frame is poor, side, data with the anchor
        column, the reference columns)"""
        done = (p, s)[side]
        ext = np.concatenate([data, anchor[done][1][:, None]], 1)
        col = np.array([data.shape[1]])
        idx_p = np.concatenate([members[p], col]) if side == 0 else members[p]
        idx_s = np.concatenate([members[s], col]) if side == 1 else members[s]
        ref_idx = idx_p if side == 0 else idx_s
        f = None
        key = (s, p, side, id(anchor[done][1]))
        if memo is not None and key in memo:
            f = memo[key][1]
        elif frame_quality(ext, ref_idx) > min_q:
            f = fit_joint(ext, idx_p, idx_s, ref=side)
            if memo is not None:        # the anchor kept alive: its id stays its own
                memo[key] = (anchor[done][1], f)
        return f, side, ext, ref_idx

    out = {}
    while True:
        todo = [s for s in sorted(world - set(out)) if s in anchor or int(parents[s]) in anchor]
        if not todo:
            return out
        for s in todo:
            p = int(parents[s])
            tried = [fit_in(s, p, side) for side in (0, 1) if (p, s)[side] in anchor]
            tried = [t for t in tried if t[0] is not None and t[0].ok]
            if not tried:
                out[s] = fits[s]            # no usable completed frame: the world fit stays
                continue
            # both segments completed: the frame the joint fits better in (seed 37036, 1 mm:
            # one side's anchor lay 8 mm off its two markers' line, 175 mm apart - the
            # frame's roll was lost in the noise and the fit, at 2.3x the floor, put the
            # hinge 120 mm off its axis)
            f, side, ext, ref_idx = min(tried, key=lambda t: t[0].cost_m)
            done = (p, s)[side]
            if f.hinge:
                full = np.flatnonzero(~np.isnan(ext[:, ref_idx]).any(axis=(1, 2)))
                own = np.flatnonzero(~np.isnan(data[:, members[done]]).any(axis=(1, 2)))
                if full[0] != own[0]:
                    f = replace(f, hinge=False, axis_local=np.full(3, np.nan), axis_world=None)
            out[s] = f
            nxt = s if side == 0 else p
            offer(nxt, f.world, lambda t, e=ext, r=ref_idx: e[t, r])


@dataclass(frozen=True, kw_only=True)
class SkeletonResult:
    """labels (M,) segment per marker; n_segments; eigengap_k; root; parents (S,);
    cost (S, S) topology costs m (noise-normalised joint-fit residuals,
    ``skeleton.joints.joint_cost``; on 6 Hz low-passed data when the data is noisy);
    joints: tuple of JointFit per segment (None for the root: the joint with its parent;
    fitted on the low-passed data when noisy); joint_centres (T, S, 3) m (the root's: NaN);
    rate_hz; junctions: a ``skeleton.junctions.Junction`` per group of segments found
    meeting at one point and re-linked around a hub: there the parent-child choice rests on
    a prior as much as on the fit (coincident joints make the alternatives kinematically
    equivalent)."""

    labels: np.ndarray
    n_segments: int
    eigengap_k: int
    root: int
    parents: np.ndarray
    cost: np.ndarray
    joints: tuple
    joint_centres: np.ndarray
    rate_hz: float
    junctions: tuple[Junction, ...] = ()


_JOB: tuple = ()     # a pair-cost worker's (data, members, min_q), set by _init_worker


def _init_worker(data, members, min_q):
    global _JOB
    _JOB = (data, members, min_q)
    # one BLAS thread per worker: the pool is the parallelism (no oversubscription)
    threadpool_limits(limits=1, user_api="blas")


def _pair_cost(data, members, min_q, ij):
    """joint_cost's closed-form cost (``detail``) of the pair ij"""
    return joint_cost(data, members[ij[0]], members[ij[1]], multistart=False, detail=True,
                      min_quality=min_q)


def _one_pair_cost(ij):
    return _pair_cost(*_JOB, ij)


def warm_up() -> None:
    """Loads the solver's compiled kernels now (compiles them on the first run in a checkout,
    ~30 s): the 2+2 world fit, Kabsch, the sphere fit's residuals and the star fit."""
    _world_lm.warm_up()
    _rigid.warm_up()
    _joints.warm_up()
    _star_lm.warm_up()


def _pair_costs(data, members, pairs, min_q, workers: int | None, progress=None) -> list:
    """joint_cost's closed-form cost (``detail``) of every pair, in order, in ``workers``
    forked processes (None: the CPUs this process may run on) when there are at least
    PARALLEL_PAIRS pairs and the platform can fork; each pair's fit is independent of the
    others, so the results are the serial loop's up to the last digits, which vary with
    memory layout alone (the serial loop's cost of one pair moved by 1e-10 relative when
    another module was imported first). Falls back to the serial loop when a pool cannot be
    started. ``progress(msg)`` hears of every quarter of the pairs done."""
    step = max(1, -(-len(pairs) // 4))

    def counted(costs):
        out = []
        for k, c in enumerate(costs, 1):
            out.append(c)
            if progress is not None and (k % step == 0 or k == len(pairs)):
                progress(f"joint costs: {k}/{len(pairs)} segment pairs")
        return out

    if workers is None:
        workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
            os.cpu_count() or 1)
    if workers > 1 and len(pairs) >= PARALLEL_PAIRS and "fork" in mp.get_all_start_methods():
        warm_up()   # compiled fits loaded once, here, not in every worker
        try:
            # fork: the workers inherit the data (no pickling); each gets its share in
            # chunks small enough to balance 2+2 pairs (slower) against the rest
            with ProcessPoolExecutor(workers, mp_context=mp.get_context("fork"),
                                     initializer=_init_worker,
                                     initargs=(data, members, min_q)) as ex:
                return counted(ex.map(_one_pair_cost, pairs,
                                      chunksize=max(1, len(pairs) // (4 * workers))))
        except (OSError, BrokenProcessPool):
            pass
    return counted(_pair_cost(data, members, min_q, ij) for ij in pairs)


def solve_skeleton(trajectories, rate_hz: float, n_segments: int | None = None, rng=None,
                   progress=None, workers: int | None = None,
                   star_margin: float = STAR_MARGIN) -> SkeletonResult:
    """``workers``: processes for the pair costs (``_pair_costs``; None: every CPU this
    process may run on, 1: none forked). ``star_margin``: how much better (x the residual
    variance) a star of segments must fit their markers to decide a junction's hub or
    re-link a tree triple (``skeleton.star_fit``); inf turns both off (the solver as it was
    before them: the benchmarks' baseline)."""
    if not star_margin > 0:
        raise ValueError(f"star_margin={star_margin!r}, expected > 0 (inf: off)")
    traj = np.asarray(trajectories, np.float64)
    if traj.ndim != 3 or traj.shape[2] != 3:
        raise ValueError(f"trajectories.shape={traj.shape}, expected (T, M, 3)")
    if workers is not None and (not isinstance(workers, (int, np.integer)) or workers < 1):
        raise ValueError(f"workers={workers!r}, expected an int >= 1 or None")
    say = progress or (lambda msg: None)
    # Segments from 6 Hz low-passed data when it is noisy: the distance changes across a
    # joint follow the (slow) motion, white marker noise is broadband (skeleton/segments.py:
    # right K and partition on seed sets 1000-3000 and 7000-9000, raw -> low-passed: 1 mm
    # 298 -> 300/300, 2 mm 277 -> 298, 3 mm 230 -> 296; the real arm recording's distance
    # sd is slow soft-tissue motion, which the filter keeps: its ratios do not change).
    # The noise level below stays the raw data's.
    raw_sd = distance_sd(traj)
    lp = lowpass(traj, rate_hz, trim=True) if noise_sd(raw_sd) > CLEAN_NOISE_M else None
    seg = segment_markers(traj if lp is None else lp, n_segments, rng)
    S = seg.n_segments
    say(f"segments: {S} (eigengap choice {seg.eigengap_k})")
    members = [np.flatnonzero(seg.labels == s) for s in range(S)]
    # Topology cost of every pair on low-passed data: a false joint's misfit follows the
    # (slow) motion, the marker noise is broadband, so filtering separates them.
    # (Not when the data is already clean: the filter's own error, ~0.05 mm at 6 Hz, would
    # then be the largest term. Noise level: within-segment distance sd.)
    same = (seg.labels[:, None] == seg.labels[None]) & ~np.eye(seg.labels.size, dtype=bool)
    noise_m = float(np.median(raw_sd[same])) if same.any() else 0.0
    noisy = noise_m > CLEAN_NOISE_M
    smooth = (lowpass(traj, rate_hz, trim=True) if lp is None else lp) if noisy else traj
    min_q = (POOR_FRAME * noise_m) ** 2 if noisy else 0.0
    cost = np.full((S, S), np.inf)
    hinge = np.zeros((S, S), bool)
    radii = {}      # 2+2 pairs: the fit's marker-joint distances (a start for the final fit)
    pairs = list(zip(*np.triu_indices(S, 1)))
    for (i, j), pc in zip(pairs, _pair_costs(smooth, members, pairs, min_q, workers,
                                             progress=progress)):
        cost[i, j] = cost[j, i] = pc.cost
        hinge[i, j] = hinge[j, i] = pc.hinge
        radii[i, j] = pc.radii
    first_cost = cost.copy()    # before any completed frame raises a pair (see the re-link)
    # 2+2-marker pairs got only their closed-form start (an upper bound on their cost). Every
    # pair that could still matter gets the multi-start search - unless the tree could not
    # take it: by the cycle property, a pair enters the minimum spanning tree only by
    # replacing the costliest edge on the tree path between its segments, and a true pair
    # costs no less than the noise floor. However high the closed-form start: held-out seed
    # 178047 (1 mm), true 2+2 pair 1-3 started at 11.5x the floor and searched costs 1.25x;
    # left unsearched above 10x the floor, the tree hung 3 from its sibling (2.88x), whose
    # joint with their parent lies 134.5 mm off 3's (seeds 1000-20000 and 160000-179000: the
    # same failures otherwise, 10 % more time per figure).
    mst = skeleton_tree(cost)
    floor = _tree_floor(cost)
    frameless = np.array([frame_quality(smooth, m) <= min_q for m in members])
    completed = _Completed(smooth, members, cost, floor, frameless, min_q)
    for i, j in zip(*np.triu_indices(S, 1)):
        if (frameless[i] and frameless[j] and 1.2 * floor < cost[i, j]
                and _path_max(mst, cost, i, j) > PRUNE * floor):
            # a pair its completed frame rejects needs no search (the search only lowers
            # costs). On noise-free data the floor is ~1e-7 m: rejecting above FALSIFY x
            # that rejected true pairs (exact topology 49, 47, 49 of 50 on seed sets
            # 2000/3000/6000), so clean data is rejected above FALSIFY x CLEAN_NOISE_M.
            if completed.applies(i, j) and completed.raise_false(cost, i, j, floor):
                mst = skeleton_tree(cost)
                continue
            pc = joint_cost(smooth, members[i], members[j], detail=True, min_quality=min_q)
            if pc.cost < cost[i, j]:
                cost[i, j] = cost[j, i] = pc.cost
                radii[i, j] = pc.radii
                mst = skeleton_tree(cost)
    # the cheap pairs of frameless segments, re-tested with their completed frames
    floor = _tree_floor(cost)
    upper = FALSIFY_BELOW * floor if noisy else RECHECK_MIN_M
    for i, j in zip(*np.triu_indices(S, 1)):
        if cost[i, j] < upper and completed.applies(i, j):
            completed.raise_false(cost, i, j, floor)
    # pairs of frameless segments that a framed segment fits apart (no anchor needed)
    _raise_split_siblings(smooth, members, cost, floor, frameless, upper,
                          JUNCTION_K * max(noise_m, CLEAN_NOISE_M), anchored=completed.anchored)
    raised = completed.raised
    say(f"joint costs: {S * (S - 1) // 2} pairs ({raised} raised by completed frames)")
    # A pair whose relative motion is a rotation about one axis, fitting within the noise,
    # is a true joint: between segments that are not neighbours the relative motion
    # composes two or more joints' rotations, which is one-axis only for hinges about one
    # common axis. Such pairs enter the tree first (the tree of the rest of the pairs).
    floor = _tree_floor(cost)
    sure = hinge & (cost <= HINGE_SURE * floor)
    top = skeleton_tree(cost, first=sure)
    T = traj.shape[0]
    # joint centres from the low-passed data too (trimmed, FIT_TRIM: the costs' own
    # ``smooth``) when it is noisy
    fit_data = smooth if FIT_TRIM else lowpass(traj, rate_hz) if noisy else traj
    fits: dict[tuple, JointFit] = {}
    memo: dict = {}     # _completed_fits' fits, shared by tree_joints' two calls

    def fit(p, s):
        if (p, s) not in fits:
            r = radii.get((min(p, s), max(p, s)))
            if r is not None and p > s:     # radii follow the markers' order: a's, then b's
                r = np.concatenate([r[members[s].size:], r[:members[s].size]])
            fits[p, s] = fit_joint(fit_data, members[p], members[s], noise_m=floor, radii=r,
                                   min_quality=min_q)
        return fits[p, s]

    placed: dict[tuple, JointFit] = {}      # tree edges' fits, centres by _world_centre

    def tree_joint(p, s):
        if (p, s) not in placed:
            placed[p, s] = _world_centre(fit_data, members, p, s, fit(p, s), floor)
        return placed[p, s]

    def tree_joints(parents) -> dict:
        """child -> JointFit of every tree edge (``_world_centre``), world fits between two
        frameless segments re-fitted in completed frames (``_completed_fits``)"""
        out = {int(s): tree_joint(int(parents[s]), int(s)) for s in range(S) if parents[s] >= 0}
        out.update(_completed_fits(fit_data, members, parents, out, min_q, memo))
        return out

    # Segments meeting at one point (sibling joints within the joint-centre uncertainty):
    # the MST's choice among them is arbitrary; re-link each such group around its hub.
    junctions: list[Junction] = []
    if S > 2:
        # the tree's joints as the final ones will be: world fits between two frameless
        # segments re-fitted in completed frames (their centres can lie far off the point
        # the segments share)
        world = [frame_quality(fit_data, m) <= min_q for m in members]   # as fit_joint's
        pre = tree_joints(top.parents)
        centres = {frozenset((int(top.parents[s]), s)): f.world for s, f in pre.items()}
        axes = {frozenset((int(top.parents[s]), s)): f.axis_world for s, f in pre.items()}
        tree_cost = cost[tuple(top.edges.T)]

        def is_hinge(a, b) -> bool:
            """the pair's fit is a hinge; two frameless segments' world fit never is, so
            for them: the tree edge's fit in a completed frame (``_completed_fits``), where
            the tree has the pair (seed 85038, 1 mm: sibling hinges 35.6 mm apart on a
            2-marker parent; the true 2+2 link, a hinge in its completed frame, counted as
            none, and the sibling whose star had two hinge fits took the group)"""
            if not (world[a] and world[b]):
                return fit(a, b).hinge
            c = b if top.parents[b] == a else a if top.parents[a] == b else None
            return c is not None and pre[c].hinge
        edges = resolve_junctions(fit_data, members, top.edges, centres, cost,
                                  tol_m=JUNCTION_K * noise_m,
                                  max_cost=JUNCTION_COST * float(np.max(tree_cost)), axes=axes,
                                  recost=lambda a, b: joint_cost(smooth, members[a], members[b],
                                                                 min_quality=min_q),
                                  is_hinge=is_hinge, record=junctions,
                                  keep=sure, floor_m=floor, star_margin=star_margin)
        top = tree_from_edges(S, edges)
    # Two tree edges sharing a segment: the triple's three stars fitted to its markers; a
    # neighbour's star that fits decisively better re-links it (skeleton.relink). Which
    # alternatives are plausible enough to fit is judged on the pair costs before the
    # completed frames raised any: a raise is a test through an anchor that may itself be a
    # false joint, the star fit is the stronger test (held-out seed 144001, 1 mm: true 2+2
    # pair 5-7 at 0.96x the floor, raised to 21.2x through 7's anchor on its grandparent 1,
    # a false joint at 0.63x; the tree hung 7 from 1, and the star around 5 fits 8451x
    # better; 130009: the true 2+2 pair raised to 6.94x through a hinge not called one,
    # 20165x)
    if S > 2:
        parents, moves = relink_by_stars(
            fit_data, members, top.parents,
            lambda par: {s: f.world for s, f in tree_joints(par).items()},
            np.minimum(cost, first_cost), floor,
            margin=star_margin, log=say)
        if moves:
            top = tree_from_edges(S, [(s, int(parents[s])) for s in range(S) if parents[s] >= 0])
            # a junction keeps the members still linked to its hub
            linked = [tuple(m for m in jn.segments if m == jn.hub or top.parents[m] == jn.hub
                            or top.parents[jn.hub] == m) for jn in junctions]
            junctions = [jn._replace(segments=k) for jn, k in zip(junctions, linked)
                         if len(k) >= 3]
    final = tree_joints(top.parents)
    # each junction's spread over its final joints (a centre the group was found around may
    # lie off the junction: skeleton.junctions' fixed-point test; a world fit is re-fitted
    # by _completed_fits)
    for k, jn in enumerate(junctions):
        fj = {frozenset((int(top.parents[c]), int(c))): final[int(c)]
              for c in jn.segments if top.parents[c] in jn.segments}
        junctions[k] = jn._replace(spread_m=joint_spread(
            fj, {e: f.world for e, f in fj.items()}, {e: f.axis_world for e, f in fj.items()}))
        say(f"junction: segments {', '.join(map(str, jn.segments))}, joints within "
            f"{junctions[k].spread_m * 1e3:.1f} mm; hub {jn.hub} (relative rotation + joint "
            f"costs)")
    say(f"topology: root segment {top.root}")
    jc = np.full((T, S, 3), np.nan)
    joints: list[JointFit | None] = [None] * S
    for s, f in final.items():
        joints[s] = f
        jc[:, s] = f.world
    return SkeletonResult(labels=seg.labels, n_segments=S, eigengap_k=seg.eigengap_k,
                          root=top.root, parents=top.parents, cost=cost, joints=tuple(joints),
                          joint_centres=jc, rate_hz=float(rate_hz),
                          junctions=tuple(junctions))

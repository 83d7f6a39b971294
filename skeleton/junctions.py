"""Junctions: several segments meeting at one point, and which of them is the hub.

When two siblings' joints on their parent (nearly) coincide, the parent and both children
share one fixed rotation point, so every pair of them fits a joint within the noise and the
minimum spanning tree's choice among them is arbitrary (the trees are kinematically
equivalent). ``resolve_junctions`` finds such groups in a tree (adjacent tree edges whose
joint centres on the shared segment lie within ``tol_m``), and re-links each group as a star
around its hub: the member that moves least relative to the others (summed RMS relative
rotation, ``relative_spread``). A joint's rotation is one joint's motion; the rotation
between two segments hung from the same hub composes two, so it is usually the larger
(pelvis and thighs, a torso and its limbs). This is a prior, not an identification: on 40
synthetic three-way junctions (benchmarks/bench_junctions.py: random_tree, 1 mm noise) it
picked the parent in 37; the alternative prior "the hub's marker centroid is nearest the
junction" picked it in 31, and their normalised sum in 34. The hub is chosen by that
rotation prior plus the evidence the joint costs still carry when the siblings' joints are a
few mm apart (each summed over the hub's star and divided by its mean over the candidate
hubs, weight ``COST_WEIGHT``): on 93 junctions of the solver's own trees over seed sets
1000+, 2000+ and 3000+ of benchmarks/bench_skeleton.py (1 mm noise) the prior alone picked
the true hub in 88, the cost sum alone in 63, both in 90. Hinge fits are evidence, not a
prior: hubs whose star has the most hinge pairs are kept first (``is_hinge``). So is the
likelihood of the whole star: each remaining candidate's star is fitted as one articulated
model to all the group's markers (``skeleton.star_fit``: same markers, same number of
parameters), and a hub whose star's residual sum of squares is lower than every other
candidate's by more than ``STAR_MARGIN`` (200) times its residual variance per residual is
chosen without the prior. The threshold was set on the 188 true sibling pairs within 10 mm
of each other in seed sets 90000-92000 of benchmarks/bench_skeleton.py (1 mm noise,
low-passed, the parent and the two siblings alone, the true junction point), with the star
fit before the joints' pull of ``skeleton.star_fit`` and again with it: the parent's star
fitted best in 167 both times, and all 118 margins above 200x were the parent's (gaps
1.2-9.9 mm; with the pull 1.3-9.9). The largest margin of a wrong hub was 118x with the pull
(179x without): 90017, where a hinge's axis passes near the sibling's joint, so the wrong
star is nearly equivalent; among siblings under 1 mm apart, 24x. By gap, with the pull:
< 1 mm 11 of 23 best (none above 200x), 1-3 mm 36 of 42 (11 above), >= 3 mm 120 of 123
(107 above). Below the margin the fits still carry evidence: each candidate's sum of squares
above the best, in the margin's units, adds ``STAR_WEIGHT`` (1e-3) per unit to the prior's
score (a 100x margin: 0.1). On the solver's own junction decisions with the true hub among
>= 2 candidates (``/tmp`` trace of choose, seed sets 1000-20000, 1 mm noise, 591 decisions)
the prior alone was right in 583, the best star in 563, the margin rule in 586. Below the
margin, where the prior was wrong (5) its scores were 0.002-0.06 apart and the best star
17-107x better (in 4; 10040: both wrong); where the best star was wrong and the prior right
(27) the prior's choice led by 0.05-0.27 at 0.6-78x (0.0015-0.38 of score per unit of
margin), hence the weight: 588 right (8008 and 12030 fixed, none lost; 2e-3: 1004 fixed
too, 19039 lost). Held out, 152000-161000 (first run before the weight): 492 -> 494 of
500 exact (152003, 158003 fixed, none lost). A hub whose
star would use an edge costing more than ``max_cost`` is not considered. A group that no
member can join as a hub chained distinct junctions (each joint within the tolerance of the
next): it is split at half the tolerance, up to ``SPLIT_DEPTH`` times, and each tighter group
resolved (held-out seed 5027: siblings 1.5 mm apart inside a chain of nine segments).
A star cannot hold a chain inside the group (a child of the hub whose own child's joint
lies within the tolerance): the pipeline's sure hinge pairs (``keep``) stay linked when
they fit better than the costlier of their two hub links, the member with that link hung
from the other instead of the hub. Seeds 7013 and 7048 (1 mm noise) had the grandchild on
the hub (its true joint a hinge at 0.87x and 0.96x the floor, the hub link 1.04x and
1.63x); without the cost condition seed 8013 lost its topology (siblings with hinge axes
23 degrees apart fit a false hinge at 1.2x, against their hub links at 0.54x and 0.98x).
Exact topology over seed sets 1000+ to 10000+ of benchmarks/bench_skeleton.py (1 mm
noise): 484 -> 486 of 500, no figure lost. A pair is not kept where both its hub links are
sure hinge pairs too: three segments turning about one common axis through one point fit
a hinge in each of their three pairs (a hinge of a hinge about the same axis is one), so
the kept pair is no evidence there and the hub's star stands (seed 70012, 1 mm: sibling
hinges 2.2 mm and 4.5 degrees apart, the false pair a hinge at 0.89x the floor against
hub links at 0.94x and 1.01x; the tree hung one sibling from the other).
Groups are found by centre distance, except where a centre is unreliable: the fitted joint
of two 2-marker segments (or a world fit of one) may lie anywhere their few markers allow,
tens of mm off the point the segments share, so siblings linked to each other form no group
with their parent (seeds 12011, 12039, 13011, 13043: sibling joints 0.0-7.1 mm apart, the
false pair's centre 44-266 mm off). Two tree edges sharing a segment are therefore also
grouped when one edge's ball centre is a fixed point of the other edge's far segment: the
RMS sd of that segment's marker distances to it is at most ``FIXED_K`` x the joint-cost
floor. On the solver's trees over seed sets 1000+ to 14000+ (1 mm noise; 13,131 edge pairs
the distance test left apart), centres within 2 mm of the far segment's true pivot scored
2.0-2.6x the floor, those 35 mm or more away 17x at the 10th percentile (4 of 12,948 at or
below 4x, all on 2-marker far segments, whose two distances leave a circle free); exact
topology 675 -> 679 of 700, none lost (a threshold of 10x: +6, -4). A group so found takes
as its junction point the ball centre most nearly fixed in every member, not the mean.
Conventions: docs/conventions.md [arrays], [units].
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from skeleton.star_fit import margin_unit, star_misfit

__all__ = ["Junction", "joint_gap", "joint_spread", "junction_groups", "relative_spread",
           "resolve_junctions"]

SPREAD_FRAMES = 200
SPLIT_DEPTH = 2     # a group without a hub is split at half the tolerance, at most this often
FIXED_FRAMES = 200  # frames sampled for the fixed-point test of junction_groups
FIXED_K = 4.0       # ... its threshold, x the joint-cost floor (see the module docstring)
STAR_MARGIN = 200.0  # a hub whose star model (skeleton.star_fit) fits the group's markers
                     # better than every other candidate's by more than this x its residual
                     # variance per residual is chosen by that fit (see the module docstring)
COST_WEIGHT = 1.0   # the star's summed joint cost beside the summed relative rotation, each
                    # over its mean across the candidate hubs
STAR_WEIGHT = 1e-3  # below ``STAR_MARGIN`` each candidate's star sum of squares above the
                    # best, in the margin's units, adds this much per unit to that score
                    # (a 100x margin: 0.1; see the module docstring)


class Junction(NamedTuple):
    """A group of segments re-linked around a hub (``_star``): segments (sorted), the hub, and
    spread_m, the largest median distance between two of the group's joints on a shared
    segment (how far apart the joints are that the data can barely tell apart; the solver
    reports it over the final tree's joints, ``skeleton.pipeline``)."""

    segments: tuple[int, ...]
    hub: int
    spread_m: float


def _root(parent, k):
    """Union-find: the representative of ``k`` (``parent``: a list or dict, k -> parent)."""
    while parent[k] != k:
        k = parent[k]
    return k


def _nan_mean(stack: np.ndarray) -> np.ndarray:
    """Mean over axis 0 ignoring NaN; NaN where nothing is seen (np.nanmean without its
    'Mean of empty slice' warning, which the skeleton command shows to its user: frames where
    no joint of a group is seen are normal, e.g. ktk_basket_sprint)."""
    n = (~np.isnan(stack)).sum(0)
    return np.divide(np.nansum(stack, 0), n, out=np.full(stack.shape[1:], np.nan), where=n > 0)


def joint_gap(ca, aa, cb, ab) -> np.ndarray:
    """(T,) distance between two joints: centres (T, 3); a hinge's (axis (T, 3), else None)
    centre is anywhere on its axis, so the distance is taken to that line."""
    d = cb - ca
    gaps = []
    for ax in (aa, ab):
        if ax is not None:
            gaps.append(np.linalg.norm(d - (d * ax).sum(1, keepdims=True) * ax, axis=1))
    return np.linalg.norm(d, axis=1) if not gaps else np.fmin.reduce(gaps)


def joint_spread(edges, centres: dict, axes: dict | None = None) -> float:
    """The largest median distance (m) between the joints of two ``edges`` (frozensets) that
    share a segment (``joint_gap``: to a hinge's axis line); NaN without such a pair."""
    axes = axes or {}
    edges = list(edges)
    gaps = [np.nanmedian(joint_gap(centres[e], axes.get(e), centres[f], axes.get(f)))
            for i, e in enumerate(edges) for f in edges[i + 1:]
            if e & f and np.isfinite(centres[e]).any() and np.isfinite(centres[f]).any()]
    gaps = [g for g in gaps if np.isfinite(g)]
    return float(max(gaps)) if gaps else float("nan")


def _sphere_sd(traj: np.ndarray, idx, c: np.ndarray) -> float:
    """RMS over the markers ``idx`` of the sd over time of their distance to the point
    ``c`` (T, 3): ~0 when c is fixed in their segment."""
    T = traj.shape[0]
    sel = np.linspace(0, T - 1, min(T, FIXED_FRAMES)).astype(int)
    d = np.linalg.norm(traj[sel][:, np.asarray(idx, int)] - c[sel][:, None], axis=2)
    ok = ~np.isnan(d).any(1)
    if ok.sum() < 10:
        return np.inf
    return float(np.sqrt(np.mean(np.var(d[ok], axis=0))))


def junction_groups(edges, centres: dict, tol_m: float, axes: dict | None = None,
                    traj: np.ndarray | None = None, members=None, floor_m: float = 0.0
                    ) -> list[set]:
    """Groups (>= 3 segments) linked by tree edges whose joint centres coincide.

    ``edges``: (S-1, 2) tree edges; ``centres[frozenset(edge)]``: (T, 3) world joint centre
    of that edge (NaN where unknown); ``axes[frozenset(edge)]``: (T, 3) hinge axis or None.
    Two edges sharing a segment are merged when the median distance between their joints
    is below ``tol_m``, or - given ``traj`` (T, M, 3), ``members`` and ``floor_m`` > 0 (what
    a true joint's cost scores) - when one edge's ball-joint centre is a fixed point of the
    other edge's far segment too (its markers' distances to it vary by at most ``FIXED_K``
    x ``floor_m``, RMS of their sds): two 2-marker segments' fitted centre can lie anywhere
    their markers allow, far from the point they share (see the module docstring)."""
    axes = axes or {}
    edges = [tuple(int(v) for v in e) for e in edges]
    lab = {e: k for k, e in enumerate(edges)}
    parent = list(range(len(edges)))
    for i, e in enumerate(edges):
        for j in range(i + 1, len(edges)):
            f = edges[j]
            if not set(e) & set(f):
                continue
            fe, ff = frozenset(e), frozenset(f)
            d = joint_gap(centres[fe], axes.get(fe), centres[ff], axes.get(ff))
            near = bool(np.isfinite(d).any() and np.nanmedian(d) < tol_m)
            if not near and traj is not None and floor_m > 0:
                near = any(axes.get(g) is None and _sphere_sd(
                    traj, members[next(iter(h - g))], centres[g]) <= FIXED_K * floor_m
                    for g, h in ((fe, ff), (ff, fe)))
            if near:
                parent[_root(parent, lab[f])] = _root(parent, i)
    out: dict[int, set] = {}
    for i, e in enumerate(edges):
        out.setdefault(_root(parent, i), set()).update(e)
    return [g for g in out.values() if len(g) >= 3]


def _frames(traj: np.ndarray, idx, centre: np.ndarray) -> np.ndarray:
    """(F, 3, 3) world_from_segment rotations of a segment from its markers and the junction
    centre (a frame even for two markers), relative to the first frame (Kabsch)."""
    P = np.concatenate([traj[:, np.asarray(idx, int)], centre[:, None]], axis=1)   # (F, n, 3)
    P = P - P.mean(1, keepdims=True)
    H = np.einsum("ni,fnj->fij", P[0], P)          # cross-covariance of frame 0 -> frame f
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones((len(P), 3))
    D[:, 2] = d
    return np.einsum("fji,fj,fkj->fik", Vt, D, U)    # R_f with P_f ~ R_f P_0


def relative_spread(traj: np.ndarray, ma, mb, centre: np.ndarray) -> float:
    """RMS angle (rad) of segment b's rotation relative to segment a about its mean, over
    time; each segment's frame from its markers and the junction ``centre`` (T, 3)."""
    T = traj.shape[0]
    sel = np.linspace(0, T - 1, min(T, SPREAD_FRAMES)).astype(int)
    ok = sel[~np.isnan(traj[sel][:, np.concatenate([ma, mb])]).any((1, 2))
             & ~np.isnan(centre[sel]).any(1)]
    if ok.size < 3:
        return np.inf
    Ra, Rb = _frames(traj[ok], ma, centre[ok]), _frames(traj[ok], mb, centre[ok])
    Rr = np.swapaxes(Ra, 1, 2) @ Rb
    U, _, Vt = np.linalg.svd(Rr.sum(0))
    R0 = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt    # chordal mean
    cos = (np.trace(R0.T @ Rr, axis1=1, axis2=2) - 1) / 2
    return float(np.sqrt(np.mean(np.arccos(np.clip(cos, -1, 1)) ** 2)))


def _star(grp: set, hub: int, keep, cost: np.ndarray) -> set:
    """The group's links: the ``keep`` pairs inside it that fit better than the costlier
    of their two hub links, unless both of those are ``keep`` pairs too (one common hinge
    axis: see the module docstring; cheapest first, as long as they make no cycle), then
    the hub's star, cheapest link first, for the members not yet linked."""
    lab = {m: m for m in grp}
    nodes = sorted(grp)
    kept = [] if keep is None else sorted(
        ((a, b) for i, a in enumerate(nodes) for b in nodes[i + 1:] if keep[a, b]
         and (hub in (a, b) or (cost[a, b] < max(cost[hub, a], cost[hub, b])
                                and not (keep[hub, a] and keep[hub, b])))),
        key=lambda e: cost[e])
    star = sorted(((hub, m) for m in nodes if m != hub), key=lambda e: cost[e])
    out = set()
    for a, b in kept + star:
        ra, rb = _root(lab, a), _root(lab, b)
        if ra != rb:
            lab[ra] = rb
            out.add(frozenset((a, b)))
    return out


def resolve_junctions(traj: np.ndarray, members, edges, centres: dict, cost: np.ndarray,
                      tol_m: float, max_cost: float, axes: dict | None = None,
                      recost=None, is_hinge=None, record: list | None = None,
                      keep: np.ndarray | None = None, floor_m: float = 0.0,
                      star_margin: float | None = None) -> np.ndarray:
    """Tree edges (S-1, 2) with every junction group re-linked as a star around its hub
    (see the module docstring). A member whose star would use an edge costing more than
    ``max_cost`` is no candidate hub (a group without candidates is split, see the module
    docstring, or else left as it is);
    ``recost(a, b)``, when given, first re-evaluates such a pair (a quick cost may be an
    upper bound). ``is_hinge(a, b)``, when given, says whether the pair's relative motion
    is a rotation about one fixed axis: that is evidence, not a prior (the rotation between
    two segments hung from one hub composes two joints' rotations, which is a one-axis
    rotation only when both are hinges about one axis), so the hubs whose star has the most
    hinge edges are kept before the relative-rotation prior chooses among them.
    ``record``, when given, gets a ``Junction`` per group re-linked around a hub.
    ``keep`` (S, S) bool, when given: pairs the re-link keeps linked (the tree's sure hinge
    pairs); a member kept to another is hung from it instead of the hub. ``floor_m`` > 0:
    what a true joint's cost scores on ``traj``; groups are then also found by the
    fixed-point test of ``junction_groups``. ``star_margin``: the star fits' margin (default
    ``STAR_MARGIN``; inf: no star fits, the prior decides)."""
    margin = STAR_MARGIN if star_margin is None else float(star_margin)
    edges = {frozenset(int(v) for v in e) for e in edges}
    cost = np.array(cost, float)

    recosted: set = set()

    def ok(a, b):
        if not cost[a, b] <= max_cost and recost is not None and (a, b) not in recosted:
            cost[a, b] = cost[b, a] = min(cost[a, b], recost(a, b))
            recosted.update(((a, b), (b, a)))     # once: a pair still too costly stays so
        return cost[a, b] <= max_cost

    axes = axes or {}

    def choose(group, c):
        hubs = [h for h in sorted(group) if all(ok(h, m) for m in group if m != h)]
        if not hubs:
            return None
        if is_hinge is not None:
            n_hinge = [sum(bool(is_hinge(h, m)) for m in group if m != h) for h in hubs]
            hubs = [h for h, n in zip(hubs, n_hinge) if n == max(n_hinge)]
        evidence = np.zeros(len(hubs))
        if len(hubs) > 1 and np.isfinite(margin):
            fits = [star_misfit(traj, members, group, h, c) for h in hubs]
            ssq = np.array([f.ssq_m2 if f.ok else np.inf for f in fits])
            order = np.argsort(ssq)
            if np.isfinite(ssq[order[1]]) and fits[order[0]].n_res > 0:
                excess = (ssq - ssq[order[0]]) / margin_unit(fits[order[0]])
                if excess[order[1]] > margin:
                    return hubs[int(order[0])]
                if np.isfinite(excess).all():
                    evidence = STAR_WEIGHT * excess
        spread = np.array([sum(relative_spread(traj, members[h], members[m], c)
                               for m in group if m != h) for h in hubs])
        star = np.array([sum(cost[h, m] for m in group if m != h) for h in hubs])
        score = spread / spread.mean() if spread.mean() > 0 else np.zeros(len(hubs))
        if np.isfinite(star).all() and star.mean() > 0:   # noise-free costs are all ~0
            score = score + COST_WEIGHT * star / star.mean()
        score = score + evidence
        return hubs[int(np.argmin(score))]

    def relink(edges, grp, tol, depth):
        inner = [e for e in edges if e <= grp]
        # the centres are the input tree's joints: an edge an earlier group's star added
        # has none (a split group's second half can hold one of the first half's)
        known = [e for e in inner if e in centres]
        if not known:
            return edges
        ball = [e for e in known if axes.get(e) is None] or known   # a hinge's centre is
        c = _nan_mean(np.stack([centres[e] for e in ball]))          # arbitrary on its axis
        apart = [np.linalg.norm(centres[e] - centres[f], axis=1)
                 for i, e in enumerate(ball) for f in ball[i + 1:]]
        if floor_m > 0 and any(
                np.isfinite(d).any() and np.nanmedian(d) >= tol for d in apart):
            # found by the fixed-point test: a centre lies off the junction - take the ball
            # centre most nearly fixed in every member instead of the mean
            c = centres[min(ball, key=lambda e: np.mean(
                [_sphere_sd(traj, members[m], centres[e]) for m in grp]))]
        # Siblings linked among themselves leave their parent outside the group when their
        # fitted centres scatter (two-marker segments): a tree neighbour that fits a joint
        # with every member is a hub candidate too, and the group grows by it if it wins.
        hub = None
        for n in sorted({v for e in edges if len(e & grp) == 1 for v in e} - grp):
            if all(ok(n, m) for m in grp) and choose(grp | {n}, c) == n:
                hub, grp = n, grp | {n}
                inner = [e for e in edges if e <= grp]
                known = [e for e in inner if e in centres]
                break
        hub = choose(grp, c) if hub is None else hub
        if hub is None:
            # No member explains the whole group: it chained distinct junctions (joints
            # within ``tol`` of the next, not of each other). Its tighter groups are
            # resolved instead.
            if depth < SPLIT_DEPTH:
                for g in junction_groups(sorted(tuple(sorted(e)) for e in known), centres,
                                         tol / 2, axes, traj, members, floor_m):
                    edges = relink(edges, g, tol / 2, depth + 1)
            return edges
        if record is not None:
            record.append(Junction(tuple(sorted(int(m) for m in grp)), int(hub),
                                   joint_spread(known, centres, axes)))
        return (edges - set(inner)) | _star(grp, hub, keep, cost)

    for grp in junction_groups(sorted(tuple(sorted(e)) for e in edges), centres, tol_m,
                               axes, traj, members, floor_m):
        edges = relink(edges, grp, tol_m, 0)
    return np.array(sorted(tuple(sorted(e)) for e in edges), dtype=np.int64).reshape(-1, 2)

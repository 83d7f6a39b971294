"""Shared helpers for the skeleton output tests: truth <-> estimate segment maps, fragments."""
from __future__ import annotations

import numpy as np

from hw_sim.articulated import animate, random_tree


def bench_figure(seed, spacing_m=None):
    """(figure, motion): benchmarks/bench_skeleton.py's figure ``seed``: a random tree of 5-20
    segments with 2-4 markers each, 600 frames at 45-90 degrees range of motion, all drawn
    from ``default_rng(seed)`` (``spacing_m``: random_tree's min_marker_spacing_m)."""
    g = np.random.default_rng(seed)
    extra = {} if spacing_m is None else {"min_marker_spacing_m": spacing_m}
    fig = random_tree(int(g.integers(5, 21)), (2, 4), rng=g, **extra)
    return fig, animate(fig, 600, rng=g, rom_deg=float(g.uniform(45, 90)))



def members(fig):
    """Each true segment's marker indices."""
    return [np.flatnonzero(fig.marker_segment == s) for s in range(fig.n_segments)]

def segment_map(fig, labels):
    """truth segment -> estimated segment, or None if the clustering split/merged one."""
    m = []
    for s in range(fig.n_segments):
        lab = set(np.asarray(labels)[fig.marker_segment == s].tolist())
        if len(lab) != 1:
            return None
        m.append(lab.pop())
    return np.array(m) if len(set(m)) == fig.n_segments else None


def exact_topology(fig, res) -> bool:
    """Whether a ``SkeletonResult`` has the figure's segments and tree edges exactly."""
    sm = segment_map(fig, res.labels)
    if sm is None or res.n_segments != fig.n_segments:
        return False
    truth = {frozenset((int(sm[s]), int(sm[fig.parents[s]]))) for s in range(1, fig.n_segments)}
    est = {frozenset((s, int(res.parents[s]))) for s in range(res.n_segments)
           if res.parents[s] >= 0}
    return est == truth


def joint_errors(fig, motion, parents, joint_centres, segmap):
    """(T, S-1) distance between estimated and true joint centres (hinges: perpendicular
    to the axis); NaN where not estimated. ``joint_centres`` (T, S, 3) holds each estimated
    segment's proximal joint (the estimated tree may be rooted elsewhere)."""
    out = []
    for s in range(1, fig.n_segments):
        e, ep = segmap[s], segmap[fig.parents[s]]
        if parents[e] == ep:
            est = joint_centres[:, e]
        elif parents[ep] == e:
            est = joint_centres[:, ep]
        else:
            raise AssertionError(f"joint {fig.parents[s]}-{s} missing from the estimated tree")
        d = est - motion.joint_centres[:, s]
        if fig.joint_types[s] == "hinge":
            ax = np.einsum("tij,j->ti", motion.world_from_segment_R[:, s], fig.hinge_axes[s])
            d = d - (d * ax).sum(1, keepdims=True) * ax
        out.append(np.linalg.norm(d, axis=1))
    return np.stack(out, 1)


def solver_joint_errors(fig, motion, res, segmap) -> np.ndarray:
    """Per true joint, the median distance (m) between the solver's joint (``res.joints`` of
    the estimated child, or of the parent when the estimated tree is rooted the other way)
    and the true centre; hinges perpendicular to the axis. The topology must be right."""
    errs = []
    for s in range(1, fig.n_segments):
        e, ep = segmap[s], segmap[fig.parents[s]]
        j = res.joints[e] if res.parents[e] == ep else res.joints[ep]
        d = j.world - motion.joint_centres[:, s]
        if fig.joint_types[s] == "hinge":
            ax = np.einsum("tij,j->ti", motion.world_from_segment_R[:, s], fig.hinge_axes[s])
            d = d - (d * ax).sum(1, keepdims=True) * ax
        errs.append(np.nanmedian(np.linalg.norm(d, axis=1)))
    return np.array(errs)


def occlude(markers, rng, n_gaps=(1, 4), gap_frames=(3, 40)):
    """A copy of (T, M, 3) ``markers`` with every marker hidden (NaN) at 1-3 random
    occlusions of 3-40 frames (``n_gaps``, ``gap_frames``: numpy ``integers`` ranges), ids
    kept: what a tracker that re-identifies markers (or exact marker sets) delivers.
    ``rng``: a seed or a Generator (``fragment`` draws its gaps through it first)."""
    g = np.random.default_rng(rng)
    out = np.array(markers, np.float64)
    T, M, _ = out.shape
    for m in range(M):
        for _ in range(g.integers(*n_gaps)):
            s = g.integers(0, T)
            out[s:s + g.integers(*gap_frames), m] = np.nan
    return out


def fragment(markers, rng, n_gaps=(1, 4), gap_frames=(3, 40), n_ghosts=5):
    """Cut every marker trajectory at random occlusions into fragments with new ids (as a
    tracker does), add short ghost fragments, shuffle. Returns (T, F, 3) and owner (F,)
    (the physical marker of each fragment, -1 for a ghost)."""
    g = np.random.default_rng(rng)
    T, M, _ = markers.shape
    seen = ~np.isnan(occlude(markers, g, n_gaps, gap_frames)[..., 0])
    cols, owner = [], []
    for m in range(M):
        edges = np.flatnonzero(np.diff(np.concatenate([[0], seen[:, m].astype(int), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            c = np.full((T, 3), np.nan)
            c[a:b] = markers[a:b, m]
            cols.append(c)
            owner.append(m)
    for _ in range(n_ghosts):
        a = g.integers(0, T - 5)
        c = np.full((T, 3), np.nan)
        c[a:a + g.integers(1, 6)] = g.uniform(-1, 1, 3)
        cols.append(c)
        owner.append(-1)
    perm = g.permutation(len(cols))
    return np.stack(cols, 1)[:, perm], np.array(owner)[perm]


def coincident_joint_groups(fig, tol_m):
    """Groups of segments meeting at (nearly) one point: a parent and those of its children
    whose joints on it lie within ``tol_m`` of each other (single linkage). List of sets of
    truth segment indices, each holding the parent and >= 2 children."""
    groups = []
    for p in range(fig.n_segments):
        ch = np.flatnonzero(fig.parents == p)
        lab = list(range(ch.size))
        for i in range(ch.size):
            for j in range(i + 1, ch.size):
                if np.linalg.norm(fig.joint_offsets[ch[i]] - fig.joint_offsets[ch[j]]) < tol_m:
                    old, new = lab[j], lab[i]
                    lab = [new if x == old else x for x in lab]
        for c in set(lab):
            members = ch[[x == c for x in lab]]
            if members.size >= 2:
                groups.append({p, *members.tolist()})
    return groups


def topology_equivalent(fig, motion, res, tol_m):
    """Whether the solved tree is kinematically equivalent to the truth (an evaluation
    metric reported NEXT TO the exact-topology count, never instead of it).

    Equivalent: the segments are recovered, and every solved edge is either a true joint or
    links two segments of one group of coincident joints (``coincident_joint_groups`` with
    ``tol_m``: siblings whose joints on the parent lie within ``tol_m``; all of them and the
    parent then share a fixed rotation point, so each pair of them is a genuine joint and
    the trees differ only in which pairs are named), with that edge's solved joint centre
    within ``tol_m`` (median over frames) of the nearest true joint of the group. A spanning
    tree using only such edges links each group inside itself (the true tree offers no other
    path between its members), so the skeletons move alike."""
    segmap = segment_map(fig, res.labels)
    if segmap is None or res.n_segments != fig.n_segments:
        return False
    inv = np.empty(fig.n_segments, int)
    inv[segmap] = np.arange(fig.n_segments)
    truth = {frozenset((s, int(fig.parents[s]))) for s in range(1, fig.n_segments)}
    groups = coincident_joint_groups(fig, tol_m)
    for e in range(res.n_segments):
        p = int(res.parents[e])
        if p < 0:
            continue
        edge = frozenset((int(inv[e]), int(inv[p])))
        if edge in truth:
            continue
        grp = next((g for g in groups if edge <= g), None)
        if grp is None:
            return False
        kids = [s for s in grp if fig.parents[s] >= 0 and fig.parents[s] in grp]
        err = min(np.nanmedian(np.linalg.norm(res.joints[e].world - motion.joint_centres[:, s],
                                              axis=1)) for s in kids)
        if not err <= tol_m:
            return False
    return True


def min_sibling_joint_distance(fig):
    """Smallest distance (m) between two sibling joints on their common parent (inf if no
    segment has two children)."""
    d = np.inf
    for p in range(fig.n_segments):
        off = fig.joint_offsets[fig.parents == p]
        for i in range(len(off)):
            for j in range(i + 1, len(off)):
                d = min(d, float(np.linalg.norm(off[i] - off[j])))
    return d


def marker_spacing(fig) -> float:
    """Smallest distance (m) between two markers of one segment (hw_sim's random_tree keeps
    them ``min_marker_spacing_m`` apart, 20 mm by default; the benchmarks count figures
    below 20 mm apart)."""
    d = np.inf
    for s in range(fig.n_segments):
        P = fig.marker_offsets[fig.marker_segment == s]
        D = np.linalg.norm(P[:, None] - P[None], axis=2) + np.eye(len(P)) * 1e9
        d = min(d, D.min())
    return d


def largest_case():
    """The thesis' largest simulated case as benchmarks/bench_skeleton.py builds it: the
    first random_tree(13 segments, 2-3 markers) from default_rng(7) with 31 markers, and
    its 1500-frame motion (120 Hz). Returns (figure, motion)."""
    from hw_sim.articulated import animate, random_tree
    g = np.random.default_rng(7)
    while True:
        fig = random_tree(13, (2, 3), rng=g)
        if fig.n_markers == 31:
            return fig, animate(fig, 1500, rng=g)

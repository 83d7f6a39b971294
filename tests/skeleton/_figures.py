"""Shared helpers for the skeleton output tests: truth <-> estimate segment maps, fragments."""
from __future__ import annotations

import numpy as np


def segment_map(fig, labels):
    """truth segment -> estimated segment, or None if the clustering split/merged one."""
    m = []
    for s in range(fig.n_segments):
        lab = set(np.asarray(labels)[fig.marker_segment == s].tolist())
        if len(lab) != 1:
            return None
        m.append(lab.pop())
    return np.array(m) if len(set(m)) == fig.n_segments else None


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


def fragment(markers, rng, n_gaps=(1, 4), gap_frames=(3, 40), n_ghosts=5):
    """Cut every marker trajectory at random occlusions into fragments with new ids (as a
    tracker does), add short ghost fragments, shuffle. Returns (T, F, 3) and owner (F,)
    (the physical marker of each fragment, -1 for a ghost)."""
    g = np.random.default_rng(rng)
    T, M, _ = markers.shape
    cols, owner = [], []
    for m in range(M):
        alive = np.ones(T, bool)
        for _ in range(g.integers(*n_gaps)):
            s = g.integers(0, T)
            alive[s:s + g.integers(*gap_frames)] = False
        edges = np.flatnonzero(np.diff(np.concatenate([[0], alive.astype(int), [0]])))
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

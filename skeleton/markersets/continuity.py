"""Motion continuity: run ends, junction misses and the continuity cost (steps 3, 7b, 8, 10).

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

import numpy as np

from . import rules


def _run_ends(frames: np.ndarray, x: np.ndarray, n: int):
    """Per contiguous run of sorted ``frames`` (positions ``x`` (len, 3)): (first frame,
    last frame, position and velocity per frame of a straight-line fit to its first ``n``
    frames at the first frame, the same for its last ``n`` frames at the last frame)."""
    cut = np.flatnonzero(np.diff(frames) > 1) + 1
    out = []
    for lo, hi in zip(np.r_[0, cut], np.r_[cut, frames.size]):
        ends = []
        for sl, t0 in ((slice(lo, min(hi, lo + n)), frames[lo]),
                       (slice(max(lo, hi - n), hi), frames[hi - 1])):
            t = frames[sl] - t0
            if t.size < 2:
                ends.append((x[sl].mean(0), np.full(3, np.nan)))
                continue
            A = np.stack([np.ones(t.size), t], 1)
            c = np.linalg.lstsq(A, x[sl], rcond=None)[0]
            ends.append((c[0], c[1]))
        out.append((int(frames[lo]), int(frames[hi - 1]), ends[0], ends[1]))
    return out


def _junctions(ra, rb):
    """(gap frames, miss m) at every change of column between two never-overlapping columns
    (runs from ``_run_ends``): the miss is the distance at the middle of the gap between the
    end of the run before, extrapolated forward at constant velocity, and the start of the
    run after, extrapolated backward."""
    runs = sorted([(r, 0) for r in ra] + [(r, 1) for r in rb], key=lambda q: q[0][0])
    out = []
    for (r0, s0), (r1, s1) in zip(runs[:-1], runs[1:]):
        if s0 == s1:
            continue
        t1, t2 = r0[1], r1[0]
        mid = 0.5 * (t1 + t2)
        (p0, v0), (p1, v1) = r0[3], r1[2]
        miss = float(np.linalg.norm(p0 + v0 * (mid - t1) - p1 - v1 * (mid - t2)))
        out.append((t2 - t1, miss))               # NaN: a run too short for a velocity
    return out


def _continuity_cost(X, vis):
    """``cost(g)``: the motion-continuity cost of one marker's fragments ``g``: over each
    change from one fragment to the next (in time order), log(1 + (miss / m)^2), the miss
    that of step 3 (``_junctions``: constant-velocity lines fitted to the 10 frames each
    side, met at mid-gap) and m the typical miss of one marker across that gap,
    a x gap + b x gap^2 mm (``CONTINUITY_MM_PER_FRAME``: step 3's medians, 2 mm at 1-5
    frames to 36 mm at 31-45). A piece of another marker misses at both its ends."""
    ends = {}
    a_mm, b_mm = rules.CONTINUITY_MM_PER_FRAME

    def end(f):
        if f not in ends:
            fr = np.flatnonzero(vis[:, f])
            r = _run_ends(fr, X[fr, f], 10)
            ends[f] = (int(fr[0]), r[0], r[-1])
        return ends[f]

    def cost(g) -> float:
        g = sorted(g, key=lambda f: end(f)[0])
        c = 0.0
        for f0, f1 in zip(g[:-1], g[1:]):
            (gap, miss), = _junctions([end(f0)[2]], [end(f1)[1]])
            if np.isfinite(miss):
                c += float(np.log1p((miss * 1e3 / (a_mm * gap + b_mm * gap ** 2)) ** 2))
        return c
    return cost

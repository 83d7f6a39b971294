"""Gap filling of marker trajectories: cubic spline for short gaps, rigid-body fill from the
other markers of the same segment.

Conventions: docs/conventions.md [arrays] ((T, M, 3), NaN = gap), [rotations] (Kabsch with the
sign fix).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.interpolate import CubicSpline

__all__ = ["gap_runs", "fill_gaps_spline", "kabsch", "fill_gaps_rigid"]


def _check(positions) -> np.ndarray:
    p = np.array(positions, dtype=np.float64)
    if p.ndim != 3 or p.shape[2] != 3:
        raise ValueError(f"positions.shape={p.shape}, expected (T, M, 3)")
    return p


def gap_runs(present: np.ndarray) -> list[tuple[int, int]]:
    """Interior gaps of a (T,) bool series as (start, stop) frame ranges (stop exclusive).

    Gaps before the first or after the last sample are not interior and are not listed.
    """
    p = np.asarray(present, bool)
    idx = np.flatnonzero(p)
    if idx.size < 2:
        return []
    jumps = np.flatnonzero(np.diff(idx) > 1)
    return [(int(idx[j] + 1), int(idx[j + 1])) for j in jumps]


def fill_gaps_spline(positions, max_gap: int, *, context: int = 10
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Fill interior gaps of at most ``max_gap`` frames with a cubic spline.

    The spline (``scipy.interpolate.CubicSpline``, not-a-knot) runs through up to ``context``
    samples on each side of the gap (at least 2 each side are required).
    Returns (positions (T, M, 3), filled (T, M) bool).
    """
    p = _check(positions)
    if max_gap < 1:
        raise ValueError(f"max_gap={max_gap}, expected >= 1")
    T, M, _ = p.shape
    filled = np.zeros((T, M), bool)
    present = np.all(np.isfinite(p), axis=2)
    for m in range(M):
        for a, b in gap_runs(present[:, m]):
            if b - a > max_gap:
                continue
            before = np.flatnonzero(present[max(0, a - context):a, m]) + max(0, a - context)
            after = np.flatnonzero(present[b:b + context, m]) + b
            if before.size < 2 or after.size < 2:
                continue
            knots = np.concatenate([before, after])
            cs = CubicSpline(knots, p[knots, m], axis=0)
            p[a:b, m] = cs(np.arange(a, b))
            filled[a:b, m] = True
    return p, filled


def kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid transform (R, t) with ``dst ~ src @ R.T + t`` (det R = +1)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"src {src.shape} / dst {dst.shape}: expected equal (N >= 3, 3)")
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    H = (src - cs).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    s = np.sign(np.linalg.det(Vt.T @ U.T))
    D = np.diag([1.0, 1.0, s if s != 0 else 1.0])
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs


def fill_gaps_rigid(positions, segments: Sequence[Sequence[int]], *,
                    filled: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fill missing markers from >= 3 present markers of the same rigid segment.

    For a marker missing at frame t, the nearest frame (in time) where it and at least three
    of its segment's markers present at t were all measured serves as reference; the rigid
    transform (Kabsch) of those markers from the reference frame to t carries the missing
    marker over. ``segments`` lists marker indices per segment.
    Returns (positions, filled (T, M) bool), ``filled`` ORed with the given one.
    """
    p = _check(positions)
    T, M, _ = p.shape
    out_filled = np.zeros((T, M), bool) if filled is None else np.array(filled, bool)
    if out_filled.shape != (T, M):
        raise ValueError(f"filled.shape={out_filled.shape}, expected ({T}, {M})")
    measured = np.all(np.isfinite(p), axis=2) & ~out_filled
    src = p.copy()
    for seg in segments:
        seg = np.asarray(seg, dtype=np.int64).reshape(-1)
        if seg.size and (seg.min() < 0 or seg.max() >= M):
            raise ValueError(f"segment {seg.tolist()} has marker indices outside [0, {M})")
        if seg.size < 4:
            continue
        for m in seg:
            others = seg[seg != m]
            miss = np.flatnonzero(~np.all(np.isfinite(p[:, m]), axis=1))
            ref_frames = np.flatnonzero(measured[:, m])
            if not ref_frames.size:
                continue
            for t in miss:
                have = others[measured[t, others]]
                if have.size < 3:
                    continue
                cand = ref_frames[np.all(measured[np.ix_(ref_frames, have)], axis=1)]
                if not cand.size:
                    continue
                r = cand[np.argmin(np.abs(cand - t))]
                R, tr = kabsch(src[r, have], src[t, have])
                p[t, m] = R @ src[r, m] + tr
                out_filled[t, m] = True
    return p, out_filled

"""Rigidity test: flag samples where distances between markers of a rigid group stray from
their median.

For every pair of markers in a group, the distance d(t) is compared with its median over the
sequence; a pair fails at t when ``|d(t) - median| > threshold_m``. A marker is flagged at t
when at least half of its measured pairs in the group fail there (with a group of 3 or more
this isolates the marker that moved; in a group of 2 both are flagged).
Conventions: docs/conventions.md [arrays], [units].
"""
from __future__ import annotations

import warnings
from typing import Sequence

import numpy as np

__all__ = ["rigidity_flags"]


def rigidity_flags(positions, groups: Sequence[Sequence[int]], threshold_m: float = 0.01
                   ) -> np.ndarray:
    """(T, M) bool flags for ``positions`` (T, M, 3) and groups of marker indices."""
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 3 or p.shape[2] != 3:
        raise ValueError(f"positions.shape={p.shape}, expected (T, M, 3)")
    if not threshold_m > 0:
        raise ValueError(f"threshold_m={threshold_m}, expected > 0")
    T, M, _ = p.shape
    flags = np.zeros((T, M), bool)
    for g in groups:
        g = np.asarray(g, dtype=np.int64).reshape(-1)
        if g.size and (g.min() < 0 or g.max() >= M):
            raise ValueError(f"group {g.tolist()} has marker indices outside [0, {M})")
        if g.size < 2:
            continue
        iu, ju = np.triu_indices(g.size, 1)
        d = np.linalg.norm(p[:, g[iu]] - p[:, g[ju]], axis=2)          # (T, P)
        with warnings.catch_warnings(), np.errstate(invalid="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)   # all-NaN pairs: median NaN
            med = np.nanmedian(d, axis=0)
            fail = np.abs(d - med) > threshold_m                          # NaN -> False
        valid = np.isfinite(d)
        n_fail = np.zeros((T, g.size))
        n_valid = np.zeros((T, g.size))
        for k, (a, b) in enumerate(zip(iu, ju)):
            n_fail[:, a] += fail[:, k]
            n_fail[:, b] += fail[:, k]
            n_valid[:, a] += valid[:, k]
            n_valid[:, b] += valid[:, k]
        flags[:, g] |= (n_fail > 0) & (2 * n_fail >= n_valid)
    return flags

"""The result of the marker-set merge.

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, kw_only=True)
class MarkerSets:
    """positions (T, M, 3) m merged markers (ordered by first appearance); groups: M tuples
    of the input fragment columns merged into each marker (in time order); dropped: input
    columns dropped as too short; n_min: the most fragments seen in one frame (the lower
    bound on M); distance (F, F) m pose-aligned fragment distances (inf: overlapping,
    NaN: dropped or no partners to align on)."""

    positions: np.ndarray
    groups: tuple[tuple[int, ...], ...]
    dropped: tuple[int, ...]
    n_min: int
    distance: np.ndarray

    def __post_init__(self):
        p = np.asarray(self.positions)
        if p.ndim != 3 or p.shape[2] != 3 or p.shape[1] != len(self.groups):
            raise ValueError(f"positions.shape={p.shape}, expected (T, {len(self.groups)}, 3)")

    @property
    def n_markers(self) -> int:
        return len(self.groups)

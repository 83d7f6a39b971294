"""Zero-phase Butterworth low-pass filtering of marker trajectories with gaps.

The filter (``scipy.signal.butter`` as second-order sections, run forward and backward by
``sosfiltfilt``: zero phase, squared magnitude response) is applied to each contiguous run of
samples separately; gaps stay NaN. Runs too short for the filter's edge padding are padded
with what they have, runs shorter than ``min_run`` are left unfiltered.
Conventions: docs/conventions.md [arrays], [units] (cutoff in Hz).
"""
from __future__ import annotations

import numpy as np
from scipy.signal import butter, sosfiltfilt

__all__ = ["contiguous_runs", "butterworth_lowpass"]


def contiguous_runs(present: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of each run of True in a (T,) bool series (stop exclusive)."""
    p = np.concatenate([[False], np.asarray(present, bool), [False]])
    d = np.diff(p.astype(np.int8))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def butterworth_lowpass(positions, rate_hz: float, cutoff_hz: float, *, order: int = 2,
                        min_run: int = 4) -> np.ndarray:
    """Low-pass ``positions`` (T, M, 3) (or (T, K)) run by run; returns a new array.

    ``order`` is the order of the designed filter (the forward-backward pass doubles it).
    """
    p = np.array(positions, dtype=np.float64)
    if p.ndim < 2:
        raise ValueError(f"positions.shape={p.shape}, expected (T, ...)")
    if not rate_hz > 0:
        raise ValueError(f"rate_hz={rate_hz}, expected > 0")
    if not 0 < cutoff_hz < rate_hz / 2:
        raise ValueError(f"cutoff_hz={cutoff_hz}, expected in (0, {rate_hz / 2}) (Nyquist)")
    if order < 1:
        raise ValueError(f"order={order}, expected >= 1")
    sos = butter(order, cutoff_hz, btype="low", fs=rate_hz, output="sos")
    flat = p.reshape(p.shape[0], -1) if p.ndim == 2 else p.reshape(p.shape[0], p.shape[1], -1)
    if p.ndim == 2:
        flat = flat[:, :, None]
    T, M, D = flat.shape
    default_pad = 3 * (2 * len(sos) + 1)
    for m in range(M):
        present = np.all(np.isfinite(flat[:, m]), axis=1)
        for a, b in contiguous_runs(present):
            n = b - a
            if n < min_run:
                continue
            flat[a:b, m] = sosfiltfilt(sos, flat[a:b, m], axis=0,
                                       padlen=min(default_pad, n - 1))
    return flat.reshape(p.shape)

"""Least-squares rigid alignment (Kabsch/Horn with the det = +1 fix), batched over frames.

``kabsch(src (T, N, 3), dst (N, 3)) -> (R (T, 3, 3), t (T, 3))`` with ``dst ~ R @ src + t``.
Conventions: docs/conventions.md [rotations], [arrays].
"""
from __future__ import annotations

import numpy as np

__all__ = ["kabsch"]


def kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation per frame mapping ``src[t]`` onto ``dst`` (least squares)."""
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    if src.ndim != 3 or src.shape[2] != 3 or dst.shape != src.shape[1:]:
        raise ValueError(f"src.shape={src.shape}, dst.shape={dst.shape}, expected (T,N,3),(N,3)")
    cs = src.mean(1)
    cd = dst.mean(0)
    H = np.einsum("tni,nj->tij", src - cs[:, None], dst - cd)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("tij,tjk->tik", U, Vt)))
    D = np.zeros((src.shape[0], 3, 3))
    D[:, 0, 0] = 1
    D[:, 1, 1] = 1
    D[:, 2, 2] = d
    R = np.einsum("tji,tjk,tlk->til", Vt, D, U)
    t = cd - np.einsum("tij,tj->ti", R, cs)
    return R, t

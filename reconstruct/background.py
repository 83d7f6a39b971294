"""Static reflection masks: pixels bright in many marker-free frames (docs/conventions.md
[pixels]); pass the mask as ``BlobConfig.mask`` (True = ignored)."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["learn_static_mask"]


def learn_static_mask(frames, threshold: float, *, min_fraction: float = 0.5,
                      dilate_px: int = 2) -> np.ndarray:
    """(H, W) bool mask of pixels above ``threshold`` in at least ``min_fraction`` of
    ``frames`` (iterable of (H, W) images without markers), dilated by ``dilate_px``."""
    if not 0 < min_fraction <= 1:
        raise ValueError(f"min_fraction={min_fraction}, expected (0, 1]")
    if dilate_px < 0:
        raise ValueError(f"dilate_px={dilate_px}, expected >= 0")
    count, n = None, 0
    for img in frames:
        img = np.asarray(img)
        if img.ndim != 2:
            raise ValueError(f"frame.shape={img.shape}, expected (H, W)")
        if count is None:
            count = np.zeros(img.shape, np.int32)
        elif img.shape != count.shape:
            raise ValueError(f"frame.shape={img.shape} != {count.shape}")
        count += img > threshold
        n += 1
    if n == 0:
        raise ValueError("learn_static_mask: no frames")
    mask = (count >= min_fraction * n).astype(np.uint8)
    if dilate_px:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate_px + 1,) * 2)
        mask = cv2.dilate(mask, k)
    return mask.astype(bool)

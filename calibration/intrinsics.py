"""Chessboard intrinsics: ``cv2.findChessboardCorners`` + ``cornerSubPix`` + ``cv2.calibrateCamera``.

Per-view and overall reprojection RMS (px); views whose RMS exceeds ``reject_k`` x the median are
dropped and the calibration is repeated. When no view shows the configured pattern, the error
names the views and the pattern sizes that were found instead (transposed / neighbouring
inner-corner counts), e.g. "found 8x6 inner corners but 9x6 was configured".
Pixel convention: OpenCV's (docs/conventions.md [pixels]); distortion in OpenCV order
([camera-model]). ChArUco boards are not implemented yet.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.camera import Camera

_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE


@dataclass(frozen=True, kw_only=True)
class IntrinsicsResult:
    """camera: calibrated intrinsics (identity pose); rms_px overall; per_view_rms_px (V,)
    NaN for views not used; used: (V,) bool; ok / reason."""

    camera: Camera | None
    rms_px: float
    per_view_rms_px: np.ndarray
    used: np.ndarray
    ok: bool
    reason: str = ""


def _find(img, cols, rows):
    found, corners = cv2.findChessboardCorners(img, (cols, rows), _FLAGS)
    if not found:
        return None
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    return cv2.cornerSubPix(img, corners, (5, 5), (-1, -1), crit).reshape(-1, 2)


def _diagnose(images, cols, rows) -> str:
    tried = {(rows, cols), (cols - 1, rows), (cols + 1, rows), (cols, rows - 1),
             (cols, rows + 1)} - {(cols, rows)}
    for i, img in enumerate(images):
        for c, r in sorted(tried):
            if c >= 2 and r >= 2 and _find(img, c, r) is not None:
                return (f"view {i}: found {c}x{r} inner corners but {cols}x{rows} was "
                        "configured (inner corners = squares - 1)")
    return f"no view (of {len(images)}) shows a {cols}x{rows} chessboard or a neighbouring size"


def calibrate_chessboard(images, *, cols: int, rows: int, square_m: float, name: str = "cam",
                         reject_k: float = 3.0, min_views: int = 3) -> IntrinsicsResult:
    """Calibrate one camera from grayscale uint8 images (H, W) of a cols x rows inner-corner board."""
    if cols < 2 or rows < 2 or square_m <= 0:
        raise ValueError(f"board cols={cols}, rows={rows}, square_m={square_m}: invalid")
    images = [np.asarray(im) for im in images]
    if not images:
        raise ValueError("no images")
    h, w = images[0].shape[:2]
    obj = np.zeros((cols * rows, 3), np.float32)
    obj[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    V = len(images)
    corners = [_find(im, cols, rows) for im in images]
    used = np.array([c is not None for c in corners])
    per = np.full(V, np.nan)
    if used.sum() < min_views:
        if used.sum() == 0:
            raise ValueError(_diagnose(images, cols, rows))
        return IntrinsicsResult(camera=None, rms_px=np.nan, per_view_rms_px=per, used=used,
                                ok=False, reason=f"only {used.sum()} views with the board "
                                                 f"(views {np.flatnonzero(used).tolist()})")
    for _ in range(3):
        idx = np.flatnonzero(used)
        rms, K, dist, rv, tv = cv2.calibrateCamera([obj] * len(idx),
                                                   [corners[i].astype(np.float32) for i in idx],
                                                   (w, h), None, None)
        per[:] = np.nan
        for k, i in enumerate(idx):
            p, _ = cv2.projectPoints(obj, rv[k], tv[k], K, dist)
            per[i] = np.sqrt(np.mean(np.sum((p.reshape(-1, 2) - corners[i]) ** 2, axis=1)))
        bad = used & (per > reject_k * np.nanmedian(per))
        if not bad.any() or used.sum() - bad.sum() < min_views:
            break
        used &= ~bad
    cam = Camera(name=name, size=(w, h), K=K, dist=dist.ravel()[:5])
    return IntrinsicsResult(camera=cam, rms_px=float(rms), per_view_rms_px=per, used=used, ok=True)

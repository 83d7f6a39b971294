"""Chessboard intrinsics: ``cv2.findChessboardCorners`` + ``cornerSubPix`` + ``cv2.calibrateCamera``.

Per-view and overall reprojection RMS (px); views whose RMS exceeds ``reject_k`` x the median are
dropped and the calibration is repeated. When no view shows the configured pattern, the error
names the views and the pattern sizes that were found instead (transposed / neighbouring
inner-corner counts), e.g. "found 8x6 inner corners but 9x6 was configured".
ChArUco boards (``calibrate_charuco``, opencv-contrib ``cv2.aruco.CharucoDetector``): each view
contributes the corners it shows (partial views are fine, >= ``min_corners`` not collinear);
when no view shows the configured board the error names what was found instead (markers of
another dictionary, marker ids beyond the board's, the pre-4.6 "legacy" pattern).
Pixel convention: OpenCV's (docs/conventions.md [pixels]); distortion in OpenCV order
([camera-model]).
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
    return _calibrate_views([obj if c is not None else None for c in corners], corners, used,
                            (w, h), name=name, reject_k=reject_k, min_views=min_views)


def _calibrate_views(objs, corners, used, size, *, name, reject_k, min_views) -> IntrinsicsResult:
    """cv2.calibrateCamera over the used views, dropping views above reject_k x median RMS."""
    V = len(corners)
    used = used.copy()
    per = np.full(V, np.nan)
    for _ in range(3):
        idx = np.flatnonzero(used)
        rms, K, dist, rv, tv = cv2.calibrateCamera([objs[i].astype(np.float32) for i in idx],
                                                   [corners[i].astype(np.float32) for i in idx],
                                                   size, None, None)
        per[:] = np.nan
        for k, i in enumerate(idx):
            p, _ = cv2.projectPoints(objs[i].astype(np.float64), rv[k], tv[k], K, dist)
            per[i] = np.sqrt(np.mean(np.sum((p.reshape(-1, 2) - corners[i]) ** 2, axis=1)))
        bad = used & (per > reject_k * np.nanmedian(per))
        if not bad.any() or used.sum() - bad.sum() < min_views:
            break
        used &= ~bad
    cam = Camera(name=name, size=size, K=K, dist=dist.ravel()[:5])
    return IntrinsicsResult(camera=cam, rms_px=float(rms), per_view_rms_px=per, used=used, ok=True)


def aruco_dictionary(name: str):
    """A predefined ArUco dictionary from its OpenCV name, e.g. "DICT_5X5_100"."""
    key = str(name).upper()
    if not key.startswith("DICT_"):
        key = "DICT_" + key
    if not hasattr(cv2.aruco, key):
        known = sorted(d for d in dir(cv2.aruco) if d.startswith("DICT_"))
        raise ValueError(f"unknown ArUco dictionary {name!r}; known: {', '.join(known)}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, key))


def charuco_board(*, cols: int, rows: int, square_m: float, marker_m: float,
                  dictionary: str = "DICT_5X5_100", legacy: bool = False):
    """A ``cv2.aruco.CharucoBoard`` of cols x rows squares (not inner corners)."""
    if cols < 2 or rows < 2 or not 0 < marker_m < square_m:
        raise ValueError(f"charuco cols={cols}, rows={rows}, square_m={square_m}, "
                         f"marker_m={marker_m}: need >= 2x2 squares and 0 < marker < square")
    d = aruco_dictionary(dictionary)
    n_markers = (cols * rows) // 2
    if n_markers > d.bytesList.shape[0]:
        raise ValueError(f"a {cols}x{rows} ChArUco board needs {n_markers} markers; "
                         f"{dictionary} has {d.bytesList.shape[0]}")
    board = cv2.aruco.CharucoBoard((cols, rows), square_m, marker_m, d)
    board.setLegacyPattern(legacy)
    return board


def _dictionaries():
    """Predefined dictionary names, each family smallest first (DICT_4X4_50 before _100)."""
    names = [d for d in dir(cv2.aruco) if d.startswith("DICT_") and d.upper() == d]

    def key(n):
        head, _, tail = n.rpartition("_")
        return (head, int(tail)) if tail.isdigit() else (n, 0)
    return sorted(set(names), key=key)


def _charuco_find(board, img, min_corners):
    det = cv2.aruco.CharucoDetector(board)
    cc, ids, mc, mids = det.detectBoard(img)
    n_markers = 0 if mids is None else len(mids)
    if cc is None or ids is None or len(ids) < min_corners:
        return None, None, n_markers
    if board.checkCharucoCornersCollinear(ids):
        return None, None, n_markers
    obj, pts = board.matchImagePoints(cc, ids)
    return obj.reshape(-1, 3), pts.reshape(-1, 2).astype(np.float64), n_markers


def _charuco_diagnose(images, board, dictionary, cols, rows, legacy) -> str:
    n_board = len(board.getIds())
    msgs = []
    for i, img in enumerate(images):
        det = cv2.aruco.ArucoDetector(board.getDictionary())
        _, ids, _ = det.detectMarkers(img)
        if ids is not None and len(ids):
            ids = ids.ravel()
            if ids.max() >= n_board:
                return (f"view {i}: found {len(ids)} {dictionary} markers with ids up to "
                        f"{ids.max()}, but a {cols}x{rows} board has ids 0..{n_board - 1}: "
                        "the board has more squares than configured")
            other = cv2.aruco.CharucoBoard((cols, rows), board.getSquareLength(),
                                           board.getMarkerLength(), board.getDictionary())
            other.setLegacyPattern(not legacy)
            if _charuco_find(other, img, 4)[0] is not None:
                return (f"view {i}: the board matches the {'new' if legacy else 'legacy'} "
                        f"(pre-OpenCV-4.6) ChArUco pattern, not the configured one")
            msgs.append(f"view {i}: {len(ids)} markers (ids {sorted(ids.tolist())[:8]}...) "
                        "but too few corners interpolated: wrong COLSxROWS?")
            continue
        for name in _dictionaries():
            if name == dictionary.upper():
                continue
            _, ids2, _ = cv2.aruco.ArucoDetector(aruco_dictionary(name)).detectMarkers(img)
            if ids2 is not None and len(ids2) >= 4:
                return (f"view {i}: found {len(ids2)} markers of {name}, but {dictionary} "
                        "was configured")
    if msgs:
        return "; ".join(msgs[:3])
    return f"no view (of {len(images)}) shows {dictionary} ArUco markers"


def calibrate_charuco(images, *, cols: int, rows: int, square_m: float, marker_m: float,
                      dictionary: str = "DICT_5X5_100", legacy: bool = False,
                      name: str = "cam", reject_k: float = 3.0, min_views: int = 3,
                      min_corners: int = 6) -> IntrinsicsResult:
    """Calibrate one camera from grayscale uint8 images of a cols x rows-square ChArUco board.

    Views with fewer than ``min_corners`` interpolated corners (or collinear ones) are unused.
    Raises ValueError naming what was found when no view shows the configured board.
    """
    board = charuco_board(cols=cols, rows=rows, square_m=square_m, marker_m=marker_m,
                          dictionary=dictionary, legacy=legacy)
    images = [np.asarray(im) for im in images]
    if not images:
        raise ValueError("no images")
    h, w = images[0].shape[:2]
    found = [_charuco_find(board, im, min_corners) for im in images]
    objs = [f[0] for f in found]
    corners = [f[1] for f in found]
    used = np.array([c is not None for c in corners])
    if used.sum() < min_views:
        if used.sum() == 0:
            raise ValueError(_charuco_diagnose(images, board, dictionary, cols, rows, legacy))
        return IntrinsicsResult(camera=None, rms_px=np.nan, per_view_rms_px=np.full(len(images),
                                np.nan), used=used, ok=False,
                                reason=f"only {used.sum()} views with >= {min_corners} ChArUco "
                                       f"corners (views {np.flatnonzero(used).tolist()})")
    return _calibrate_views(objs, corners, used, (w, h), name=name, reject_k=reject_k,
                            min_views=min_views)

"""Reader for MultiCamSelfCal data folders (points.dat, IdMat.dat, Res.dat, camera_order.txt).

``points.dat``: 3 rows (x, y, 1) per camera, one column per frame, NaN = unseen; MATLAB
1-based pixel coordinates are converted to docs/conventions.md [pixels] (centre of the
top-left pixel = (0, 0)) by subtracting 1. ``IdMat.dat``: (C, T) visibility (1 = seen).
``Res.dat``: (C, 2) width height.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from capture.detections import Detections2D


def read_mcsc(folder) -> tuple[Detections2D, list[tuple[int, int]]]:
    """Single-point detections and the camera image sizes (width, height) of a MCSC folder."""
    folder = Path(folder)
    for n in ("points.dat", "Res.dat"):
        if not (folder / n).is_file():
            raise ValueError(f"{folder}: missing {n}")
    pts = np.loadtxt(folder / "points.dat")
    res = np.atleast_2d(np.loadtxt(folder / "Res.dat")).astype(int)
    C = len(res)
    if pts.shape[0] != 3 * C:
        raise ValueError(f"points.dat has {pts.shape[0]} rows, expected 3 x {C} cameras")
    seen = np.isfinite(pts[0::3]) & np.isfinite(pts[1::3])
    if (folder / "IdMat.dat").is_file():
        idm = np.loadtxt(folder / "IdMat.dat")
        if idm.shape == seen.shape:
            seen &= idm > 0
    names = [f"cam_{i}" for i in range(C)]
    order = folder / "camera_order.txt"
    if order.is_file():
        lines = [s.strip() for s in order.read_text().splitlines() if s.strip()]
        if len(lines) == C:
            names = lines
    c_idx, t_idx = np.nonzero(seen)
    xy = np.stack([pts[3 * c_idx, t_idx], pts[3 * c_idx + 1, t_idx]], axis=1) - 1.0
    o = np.lexsort((c_idx, t_idx))
    det = Detections2D(frame=t_idx[o].astype(np.int64), camera=c_idx[o].astype(np.int64),
                       xy=xy[o], camera_names=tuple(names))
    return det, [tuple(r) for r in res]


def calibrate_mcsc(folder, *, focal_guesses_px=(600.0, 1000.0, 1500.0),
                   refine_intrinsics: bool = False, min_inlier_fraction: float = 0.9):
    """Single-point calibration of a MCSC folder (no metric scale).

    The focal length is unknown in this format: each nominal focal guess is tried (principal
    point at the image centre, no distortion; refined with k1, k2 when ``refine_intrinsics``) and the result with the lowest mean reprojection
    error among those keeping ``min_inlier_fraction`` of the observations is returned,
    with its focal guess.
    """
    from calibration.camera import Camera
    from calibration.wand import calibrate_wand

    det, sizes = read_mcsc(folder)
    n = np.bincount(det.camera, minlength=det.n_cameras)
    best = None
    for f in focal_guesses_px:
        init = [Camera.from_params(name=nm, size=s, fx=f) for nm, s in zip(det.camera_names, sizes)]
        r = calibrate_wand(det, initial_intrinsics=init, single_point=True,
                           refine_intrinsics=refine_intrinsics)
        if not r.ok or np.any(r.report.n_obs < min_inlier_fraction * n):
            continue
        if best is None or r.report.mean_error_px < best[0].report.mean_error_px:
            best = (r, f)
    return best

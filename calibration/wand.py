"""Wand (or single-point) calibration of a camera rig, end to end.

``calibrate_wand``: wand detection (``wand_detect``) -> initial poses (``init_extrinsics``)
-> sparse bundle adjustment (``bundle``) -> report (``report``). The result's gauge is camera 0
at the identity pose; use ``calibration.world`` to set the floor and axes.
Conventions: docs/conventions.md ([frames], [pixels], [units], [camera-order]).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from calibration.bundle import bundle_adjust
from calibration.camera import Camera, Rig
from calibration.init_extrinsics import initial_poses, normalized, triangulate
from calibration.points import refine_points
from calibration.report import CalibrationReport, make_report
from calibration.wand_detect import (detect_single_point, detect_wand,
                                      recover_wand_observations)
from capture.detections import Detections2D


#: wand observations a camera must keep in the bundle to count as calibrated
MIN_CAMERA_OBS = 10


@dataclass(frozen=True, kw_only=True)
class WandCalibration:
    """rig: calibrated cameras (None when not ok); report; ok; reason when not ok."""

    rig: Rig | None
    report: CalibrationReport | None
    ok: bool
    reason: str = ""
    residual_px: np.ndarray | None = None


def _intrinsics(initial, det: Detections2D) -> list[Camera]:
    cams = list(initial)
    if len(cams) != det.n_cameras:
        raise ValueError(f"initial_intrinsics has {len(cams)} cameras, detections have "
                         f"{det.n_cameras}")
    names = [c.name for c in cams]
    if names != list(det.camera_names):
        raise ValueError(f"initial_intrinsics cameras {names} differ from detections "
                         f"{list(det.camera_names)}")
    return [Camera(name=c.name, size=c.size, K=c.K, dist=c.dist) for c in cams]


def calibrate_wand(detections: Detections2D, *, initial_intrinsics, wand_mm=(0.0, 250.0, 500.0),
                   single_point: bool = False, refine_intrinsics: bool = False, rng=None,
                   progress: Callable[[str], None] | None = None,
                   max_frames: int | None = None, jacobian: str = "analytic",
                   recover_gate_px: float | None = 2.0,
                   bundle_options: dict | None = None) -> WandCalibration:
    """Calibrate the extrinsics (and optionally intrinsics) of a rig from a waved wand.

    Args:
        detections: raw blob centroids (px).
        initial_intrinsics: a Rig or list of Camera giving K, size and distortion.
        wand_mm: marker positions along the wand (2 or 3 values, mm).
        single_point: one marker only (no metric scale: camera 0 to camera 1 distance = 1).
        refine_intrinsics: also refine f, cx, cy, k1, k2 per camera.
        rng: seed / Generator for OpenCV's RANSAC. The result does not depend on it: frame
            selection is deterministic and RANSAC's consensus is refined to the same optimum
            (tests/calibration/test_wand.py checks bit-identical rigs for several seeds).
        max_frames: use at most this many frames with the most views (evenly spread).
        jacobian: bundle adjustment Jacobian, "analytic" or "numeric" (``bundle.JACOBIANS``).
        recover_gate_px: after the first bundle adjustment, camera-frames the image-only
            detection skipped (extra blobs: ambiguous, or any extra blob with a 2-marker wand)
            are filled with the blobs within this distance of the projected wand, and the
            bundle is run again (``wand_detect.recover_wand_observations``). None: off.
        bundle_options: further keyword arguments of ``bundle.bundle_adjust`` (e.g. the
            benchmark's baseline settings).
    """
    say = progress or (lambda s: None)
    seed = int(np.random.default_rng(rng).integers(2**31)) if rng is not None else 0
    cv2.setRNGSeed(seed)
    cams = _intrinsics(initial_intrinsics, detections)
    if single_point:
        obs = detect_single_point(detections)
        spacing = None
    else:
        obs = detect_wand(detections, cams, wand_mm)
        spacing = obs.spacing_m
    xy = obs.xy
    n_views = np.all(np.isfinite(xy), axis=(2, 3)).sum(axis=0)
    frames = np.flatnonzero(n_views >= 2)
    if max_frames is not None and len(frames) > max_frames:
        frames = frames[np.linspace(0, len(frames) - 1, max_frames).round().astype(int)]
    xy = xy[:, frames]
    say(f"{len(frames)} frames with the wand in >= 2 cameras")
    if len(frames) < 10:
        return WandCalibration(rig=None, report=None, ok=False,
                               reason=f"only {len(frames)} usable frames")
    nxy = normalized(xy, cams)
    init, nxy = initial_poses(nxy, spacing_m=spacing, symmetric=obs.symmetric)
    if not init.ok:
        return WandCalibration(rig=None, report=None, ok=False, reason=init.reason)
    # the end order found in normalised coordinates applies to the pixels too
    flip = np.any(np.isfinite(nxy[:, :, 0]) & (np.abs(nxy[:, :, 0] - normalized(xy, cams)[:, :, 0])
                                               > 0), axis=-1)
    xy = np.where(flip[..., None, None], xy[:, :, ::-1], xy)
    cams = [Camera(name=c.name, size=c.size, K=c.K, dist=c.dist, R=init.R[i], t=init.t[i])
            for i, c in enumerate(cams)]
    C, T, M, _ = xy.shape
    use = np.ones(C, bool)
    X0 = np.stack([triangulate(nxy[:, :, m], init.R, init.t, use) for m in range(M)], axis=1)
    say("bundle adjustment")
    ba = bundle_adjust(cams, xy, X0, spacing_m=spacing, refine_intrinsics=refine_intrinsics,
                       jac=jacobian, **(bundle_options or {}))
    if recover_gate_px is not None:
        xy2 = recover_wand_observations(detections, obs.frames[frames], ba.cameras, ba.X, xy,
                                        gate_px=recover_gate_px)
        added = int(np.sum(np.all(np.isfinite(xy2), axis=(2, 3)))
                    - np.sum(np.all(np.isfinite(xy), axis=(2, 3))))
        if added:
            say(f"{added} camera-frames recovered near the calibrated wand; bundle adjustment")
            xy = xy2
            ba = bundle_adjust(ba.cameras, xy, np.where(np.isfinite(ba.X), ba.X, X0),
                               spacing_m=spacing, refine_intrinsics=refine_intrinsics,
                               jac=jacobian, **(bundle_options or {}))
    xin = np.where(ba.inlier[..., None], xy, np.nan)
    nf = normalized(xin, ba.cameras)
    Rf = np.stack([c.R for c in ba.cameras])
    tf = np.stack([c.t for c in ba.cameras])
    Xfree = np.stack([refine_points(ba.cameras, xin[:, :, m],
                                    triangulate(nf[:, :, m], Rf, tf, use)) for m in range(M)],
                     axis=1)
    # pixel noise from the residuals, corrected for the parameters the bundle fitted
    n_res = 2 * int(ba.inlier.sum())
    n_par = (6 * (C - 1) + (5 * C if refine_intrinsics else 0)
             + (5 if spacing is not None else 3 * M) * int(ba.inlier.any(axis=(0, 2)).sum()))
    noise = float(np.sqrt(np.nansum(ba.residual_px[ba.inlier] ** 2) / max(n_res - n_par, 1)))
    rep = make_report(ba.cameras, xy, ba.residual_px, ba.inlier, Xfree, spacing_m=spacing,
                      noise_px=noise)
    few = [c.name for c, n in zip(ba.cameras, rep.n_obs) if n < MIN_CAMERA_OBS]
    if few:       # a camera the bundle kept no views of is not calibrated, whatever its pose
        return WandCalibration(rig=None, report=rep, ok=False,
                               reason=f"camera(s) {', '.join(few)} kept fewer than "
                                      f"{MIN_CAMERA_OBS} wand observations (wrong intrinsics "
                                      f"or image size?)",
                               residual_px=ba.residual_px)
    return WandCalibration(rig=Rig(cameras=tuple(ba.cameras)), report=rep, ok=True,
                           residual_px=ba.residual_px)

"""Find a collinear calibration wand among each camera's blobs, per frame.

Input: ``Detections2D`` (raw distorted px, docs/conventions.md [pixels]). Output:
``WandObservations.xy`` (C, T, M, 2) px, NaN where the wand was not found ([arrays]).

For an M=3 wand, a triple of blobs is accepted when it is collinear (middle point within
``collinear_px`` of the end-to-end line, measured after undistortion with the initial
intrinsics) and the middle point divides it in a ratio within ``ratio_tol`` of the 3D ratio
(perspective shifts the image ratio; the exact invariant needs 4 points). A camera-frame with
more blobs than markers is kept only when exactly one triple passes (else ambiguous, rejected).
For a symmetric wand the two ends cannot be told apart in one image: ``symmetric`` is True and
the end order is resolved across cameras later (``init_extrinsics.resolve_end_order``).
A 2-marker wand has no in-image invariant: a camera-frame is used only when it holds exactly
two blobs (frames with extra blobs are skipped; with one spurious blob per image on average
about a third of the camera-frames remain).
Single-point mode: a camera-frame is used when it holds exactly one blob.
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from calibration.camera import Camera
from capture.detections import Detections2D


@dataclass(frozen=True, kw_only=True)
class WandObservations:
    """Per-camera wand marker pixels.

    Attributes:
        xy: (C, T, M, 2) raw px, NaN where not found; markers ordered along the wand.
        frames: (T,) frame indices of the detections table.
        spacing_m: (M,) marker positions along the wand (m), or None in single-point mode.
        symmetric: the wand's end order is ambiguous in an image (resolved later).
    """

    xy: np.ndarray
    frames: np.ndarray
    spacing_m: np.ndarray | None
    symmetric: bool

    def __post_init__(self):
        xy = np.asarray(self.xy, dtype=np.float64)
        if xy.ndim != 4 or xy.shape[-1] != 2:
            raise ValueError(f"xy.shape={xy.shape}, expected (C, T, M, 2)")
        if np.shape(self.frames) != (xy.shape[1],):
            raise ValueError(f"frames.shape={np.shape(self.frames)}, expected ({xy.shape[1]},)")
        if self.spacing_m is not None and np.shape(self.spacing_m) != (xy.shape[2],):
            raise ValueError(f"spacing_m.shape={np.shape(self.spacing_m)}, "
                             f"expected ({xy.shape[2]},)")
        object.__setattr__(self, "xy", xy)


def _frame_table(det: Detections2D):
    frames = np.unique(det.frame)
    t_of = np.searchsorted(frames, det.frame)
    return frames, t_of


def detect_single_point(det: Detections2D) -> WandObservations:
    """Single-point mode: keep camera-frames with exactly one blob."""
    frames, t_of = _frame_table(det)
    C, T = det.n_cameras, len(frames)
    key = t_of * C + det.camera
    counts = np.bincount(key, minlength=T * C)
    xy = np.full((C, T, 1, 2), np.nan)
    one = counts[key] == 1
    xy[det.camera[one], t_of[one], 0] = det.xy[one]
    return WandObservations(xy=xy, frames=frames, spacing_m=None, symmetric=False)


def detect_wand(det: Detections2D, cameras: list[Camera], spacing_mm, *,
                collinear_px: float = 2.0, ratio_tol: float = 0.2,
                max_blobs: int = 6) -> WandObservations:
    """Find the wand (2 or 3 collinear markers at ``spacing_mm``) in each camera-frame."""
    s = np.asarray(spacing_mm, dtype=np.float64).reshape(-1) / 1000.0
    if s.size not in (2, 3) or np.any(np.diff(s) <= 0):
        raise ValueError(f"spacing_mm={spacing_mm!r}: need 2 or 3 strictly increasing positions")
    if len(cameras) != det.n_cameras:
        raise ValueError(f"{len(cameras)} cameras given for {det.n_cameras} in the detections")
    M = s.size
    r0 = (s[1] - s[0]) / (s[-1] - s[0]) if M == 3 else 0.5
    symmetric = M == 2 or abs(r0 - 0.5) < ratio_tol
    frames, t_of = _frame_table(det)
    C, T = det.n_cameras, len(frames)
    xy_out = np.full((C, T, M, 2), np.nan)
    order = np.lexsort((det.camera, t_of))
    key = (t_of * C + det.camera)[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    ends = np.r_[starts[1:], len(key)]
    for a, b in zip(starts, ends):
        n = b - a
        if n < M or n > max_blobs:
            continue
        rows = order[a:b]
        c = int(det.camera[rows[0]])
        t = int(t_of[rows[0]])
        raw = det.xy[rows]
        if M == 2:
            if n == 2:
                xy_out[c, t] = raw
            continue
        cam = cameras[c]
        und = cam.undistort_pixels(raw)
        found = []
        for tri in combinations(range(n), 3):
            p = und[list(tri)]
            d = np.linalg.norm(p[:, None] - p[None], axis=-1)
            i, j = np.unravel_index(np.argmax(d), d.shape)
            k = 3 - i - j
            L = d[i, j]
            if L <= 0:
                continue
            u = (p[j] - p[i]) / L
            off = p[k] - p[i]
            perp = abs(u[0] * off[1] - u[1] * off[0])
            r = float(off @ u) / L
            if perp > collinear_px:
                continue
            if symmetric:
                if abs(r - r0) > ratio_tol:
                    continue
            elif abs(r - r0) <= ratio_tol:
                pass
            elif abs((1 - r) - r0) <= ratio_tol:
                i, j = j, i
            else:
                continue
            found.append((tri[i], tri[k], tri[j]))
        if len(found) == 1:
            xy_out[c, t] = raw[list(found[0])]
    return WandObservations(xy=xy_out, frames=frames, spacing_m=s - s[0], symmetric=symmetric)


def recover_wand_observations(det: Detections2D, frames: np.ndarray, cameras: list[Camera],
                              X: np.ndarray, xy: np.ndarray, *, gate_px: float = 2.0
                              ) -> np.ndarray:
    """Fill camera-frames the image-only detection skipped, from a calibrated first pass.

    frames: (T,) frame indices (of ``det``) of the columns of xy (C, T, M, 2) px; X: (T, M, 3)
    the wand per frame from the bundle (NaN = none). In each camera-frame without the wand
    whose blobs include, for every marker, exactly one blob within ``gate_px`` of the marker's
    projection (distinct blobs), those blobs are taken in the wand's order. Returns a new xy.
    """
    C, T, M, _ = xy.shape
    if np.shape(frames) != (T,) or np.shape(X) != (T, M, 3):
        raise ValueError(f"frames.shape={np.shape(frames)}, X.shape={np.shape(X)}: expected "
                         f"({T},), ({T}, {M}, 3)")
    out = xy.copy()
    t_of = np.full(int(max(det.frame.max(initial=0), np.max(frames, initial=0))) + 1, -1)
    t_of[frames] = np.arange(T)
    keep = (det.frame < len(t_of))
    rows = np.flatnonzero(keep)
    rows = rows[t_of[det.frame[rows]] >= 0]
    t_r, c_r = t_of[det.frame[rows]], det.camera[rows]
    missing = ~np.all(np.isfinite(xy), axis=(2, 3))                       # (C, T)
    has_x = np.all(np.isfinite(X), axis=(1, 2))
    sel = missing[c_r, t_r] & has_x[t_r]
    rows, t_r, c_r = rows[sel], t_r[sel], c_r[sel]
    order = np.lexsort((c_r, t_r))
    rows, t_r, c_r = rows[order], t_r[order], c_r[order]
    key = t_r * C + c_r
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if len(key) else np.zeros(0, int)
    ends = np.r_[starts[1:], len(key)]
    for a, b in zip(starts, ends):
        if b - a < M:
            continue
        c, t = int(c_r[a]), int(t_r[a])
        cam = cameras[c]
        if np.any(cam.depth(X[t]) <= 0):
            continue
        pred = cam.project(X[t])                                           # (M, 2)
        blobs = det.xy[rows[a:b]]
        d = np.linalg.norm(blobs[None, :, :] - pred[:, None, :], axis=2)   # (M, n)
        near = d <= gate_px
        if np.all(near.sum(axis=1) == 1) and np.all(near.sum(axis=0) <= 1):
            out[c, t] = blobs[np.argmax(near, axis=1)]
    return out

"""World alignment of a calibrated rig: L-frame / calibration square, or a floor plane fit.

The rig's frame after wand calibration is camera 0's. ``align_to_reference`` finds the rigid
transform (Kabsch with the sign fix, docs/conventions.md [rotations]) taking the measured
marker positions (rig frame, m) onto their known world coordinates (z up, floor z = 0,
[frames]) and applies it to every camera. ``floor_from_points`` fits a plane to floor markers
(SVD) and returns the rotation/translation putting it at z = 0 with z pointing towards the
cameras.
``match_reference`` finds which measured (unlabelled) point is which reference marker (the
assignment with the smallest Kabsch residual; a symmetric reference that leaves two
assignments equally good is reported, not guessed). ``align_world`` / ``align_floor`` return a
``WorldAlignment`` that says whether it worked and why not (e.g. cameras below the floor: the
reference geometry was given mirrored, which a right-handed z-up world cannot hold).
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import permutations

import numpy as np

from calibration.camera import Rig


@dataclass(frozen=True, kw_only=True)
class WorldAlignment:
    """rig: the rig in the world frame (None when not ok); R, t: ``world_from_old``;
    rms_m: residual of the reference markers (m); order: (M,) index of the measured point
    used for each reference marker; ok / reason."""

    rig: Rig | None
    R: np.ndarray | None
    t: np.ndarray | None
    rms_m: float
    order: np.ndarray | None
    ok: bool
    reason: str = ""


def l_frame_reference(x_mm: float, y_mm: float, x_mid_mm: float | None = None) -> np.ndarray:
    """Markers of an L-frame lying on the floor (m): corner at the origin, one at ``x_mm`` on
    the x axis, one at ``y_mm`` on the y axis, and optionally one at ``x_mid_mm`` on x."""
    pts = [[0, 0, 0], [x_mm, 0, 0], [0, y_mm, 0]]
    if x_mid_mm is not None:
        if not 0 < x_mid_mm < x_mm:
            raise ValueError(f"x_mid_mm={x_mid_mm}, expected between 0 and x_mm={x_mm}")
        pts.append([x_mid_mm, 0, 0])
    if x_mm <= 0 or y_mm <= 0:
        raise ValueError(f"x_mm={x_mm}, y_mm={y_mm}: arm lengths must be > 0")
    return np.array(pts, np.float64) / 1000.0


def kabsch(src, dst) -> tuple[np.ndarray, np.ndarray]:
    """R, t with ``dst ~ R @ src + t`` (least squares, proper rotation). src, dst (N, 3), N >= 3."""
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"src.shape={src.shape}, dst.shape={dst.shape}: expected equal (N>=3, 3)")
    ms, md = src.mean(0), dst.mean(0)
    H = (src - ms).T @ (dst - md)
    U, S, Vt = np.linalg.svd(H)
    if S[1] < 1e-12 * max(S[0], 1e-300):
        raise ValueError("reference points are collinear: the rotation is undetermined")
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, md - R @ ms


def transform_rig(rig: Rig, R, t) -> Rig:
    """Re-express the rig in a new world frame: ``x_new = R @ x_old + t``."""
    R = np.asarray(R, np.float64)
    t = np.asarray(t, np.float64).reshape(3)
    cams = []
    for c in rig:
        Rc = c.R @ R.T
        cams.append(c.with_pose(Rc, c.t - Rc @ t))
    return rig.replace_cameras(cams)


def align_to_reference(rig: Rig, measured, reference) -> tuple[Rig, float]:
    """Rigidly move the rig so the measured markers (N, 3) land on ``reference`` (N, 3) m.

    Returns the aligned rig and the RMS residual (m) of the markers after alignment.
    Typical reference: an L-frame ``[[0,0,0], [0.5,0,0], [0,0.3,0], ...]`` lying on the floor.
    """
    R, t = kabsch(measured, reference)
    res = np.asarray(reference) - (np.asarray(measured) @ R.T + t)
    return transform_rig(rig, R, t), float(np.sqrt(np.mean(np.sum(res ** 2, axis=1))))


def floor_from_points(rig: Rig, floor_points) -> tuple[np.ndarray, np.ndarray]:
    """R, t putting the plane through ``floor_points`` (N>=3, 3) at z = 0, cameras at z > 0.

    The x axis is the old x axis projected on the floor (or y if x is normal to it).
    """
    P = np.asarray(floor_points, np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 3:
        raise ValueError(f"floor_points.shape={P.shape}, expected (N>=3, 3)")
    c = P.mean(0)
    _, S, Vt = np.linalg.svd(P - c)
    n = Vt[2]
    centres = np.array([cam.center for cam in rig])
    if np.mean((centres - c) @ n) < 0:
        n = -n
    ax = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    x = ax - (ax @ n) * n
    x /= np.linalg.norm(x)
    y = np.cross(n, x)
    R = np.stack([x, y, n])
    return R, -R @ c


def match_reference(points, reference, *, ambiguity_ratio: float = 3.0):
    """(order, R, t, rms_m): measured points (N >= M, 3) assigned to the reference (M, 3).

    Raises ValueError when N < M, or when a second assignment with a different pose fits
    within ``ambiguity_ratio`` x the best residual (+1 mm): the reference is symmetric or the
    measured points do not show it.
    """
    P = np.asarray(points, np.float64)
    Q = np.asarray(reference, np.float64)
    if Q.ndim != 2 or Q.shape[1] != 3 or len(Q) < 3:
        raise ValueError(f"reference.shape={Q.shape}, expected (M>=3, 3)")
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < len(Q):
        raise ValueError(f"found {len(P)} static markers, the reference has {len(Q)}")
    if len(P) > 9:
        raise ValueError(f"found {len(P)} static markers: too many to match (remove clutter)")
    sv = np.linalg.svd(Q - Q.mean(0), compute_uv=False)
    if sv[1] < 1e-9 * max(sv[0], 1e-300):
        raise ValueError("the reference points are collinear: they fix no rotation about "
                         "their line (give three or more points not on one line)")
    fits = []
    for perm in permutations(range(len(P)), len(Q)):
        idx = np.array(perm)
        try:
            R, t = kabsch(P[idx], Q)
        except ValueError:
            continue
        res = Q - (P[idx] @ R.T + t)
        fits.append((float(np.sqrt(np.mean(np.sum(res ** 2, axis=1)))), idx, R, t))
    if not fits:
        raise ValueError("the measured points are collinear")
    fits.sort(key=lambda f: f[0])
    best = fits[0]
    for other in fits[1:]:
        if other[0] > ambiguity_ratio * best[0] + 1e-3:
            break
        if np.abs(other[2] - best[2]).max() > 1e-3 or np.abs(other[3] - best[3]).max() > 1e-3:
            raise ValueError(f"two assignments fit the reference ({best[0] * 1000:.2f} mm and "
                             f"{other[0] * 1000:.2f} mm RMS): it is symmetric, or the "
                             "measured points do not show it")
    return best[1], best[2], best[3], best[0]


def _cameras_above(rig: Rig) -> bool:
    return bool(np.mean([c.center[2] for c in rig]) > 0)


def align_world(rig: Rig, points, reference, *, max_rms_m: float = 0.005) -> WorldAlignment:
    """Move ``rig`` so the measured static markers (N, 3) land on ``reference`` (M, 3)."""
    try:
        order, R, t, rms = match_reference(points, reference)
    except ValueError as e:
        return WorldAlignment(rig=None, R=None, t=None, rms_m=np.nan, order=None, ok=False,
                              reason=str(e))
    if rms > max_rms_m:
        return WorldAlignment(rig=None, R=R, t=t, rms_m=rms, order=order, ok=False,
                              reason=f"reference residual {rms * 1000:.1f} mm > "
                                     f"{max_rms_m * 1000:.1f} mm: wrong geometry or markers")
    out = transform_rig(rig, R, t)
    if not _cameras_above(out):
        return WorldAlignment(rig=None, R=R, t=t, rms_m=rms, order=order, ok=False,
                              reason="cameras end up below the floor: the reference geometry "
                                     "is mirrored (x, y, z must be right-handed, z up)")
    return WorldAlignment(rig=out, R=R, t=t, rms_m=rms, order=order, ok=True)


def align_floor(rig: Rig, floor_points) -> WorldAlignment:
    """Plane fit: floor markers (N >= 3) at z = 0, cameras above; origin at their centroid."""
    P = np.asarray(floor_points, np.float64)
    try:
        R, t = floor_from_points(rig, P)
    except ValueError as e:
        return WorldAlignment(rig=None, R=None, t=None, rms_m=np.nan, order=None, ok=False,
                              reason=str(e))
    z = P @ R.T + t
    rms = float(np.sqrt(np.mean(z[:, 2] ** 2)))
    return WorldAlignment(rig=transform_rig(rig, R, t), R=R, t=t, rms_m=rms,
                          order=np.arange(len(P)), ok=True)

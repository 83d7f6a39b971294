"""World alignment of a calibrated rig: L-frame / calibration square, or a floor plane fit.

The rig's frame after wand calibration is camera 0's. ``align_to_reference`` finds the rigid
transform (Kabsch with the sign fix, docs/conventions.md [rotations]) taking the measured
marker positions (rig frame, m) onto their known world coordinates (z up, floor z = 0,
[frames]) and applies it to every camera. ``floor_from_points`` fits a plane to floor markers
(SVD) and returns the rotation/translation putting it at z = 0 with z pointing towards the
cameras.
"""
from __future__ import annotations

import numpy as np

from calibration.camera import Rig


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

"""A simulated motion-capture rig: C cameras ringed around a capture volume.

Public API::

    make_rig(n_cameras=8, *, size=(1280, 1024), fov_deg=56.0, radius_m=5.5, height_m=3.0,
             height_step_m=0.4, volume_m=(4.0, 4.0, 2.5), dist=None,
             position_jitter_m=0.05, aim_jitter_deg=1.0, rng=None) -> calibration.camera.Rig
    VOLUME_M, VOLUME_CENTRE            # the default 4 x 4 x 2.5 m volume, centre (0, 0, 1.25)
    volume_bounds(volume_m) -> (lo (3,), hi (3,))

Cameras are named ``cam_1 .. cam_N`` in ring order (counter-clockwise seen from above,
cam_1 on the +x axis) and aim at the volume centre; odd-numbered ring positions alternate in
height by ``height_step_m`` (as real rigs do, for a vertical baseline). A 56 deg horizontal
field of view on a 1280 px sensor is a focal length of ~1204 px, a typical mocap lens.

Conventions: docs/conventions.md [frames] (z up, floor z = 0, ``cam_from_world``),
[camera-model], [camera-order], [units].
"""
from __future__ import annotations

import numpy as np

from calibration.camera import Camera, Rig, look_at, rotation_from_rodrigues

__all__ = ["make_rig", "focal_from_fov", "volume_bounds", "VOLUME_M", "VOLUME_CENTRE"]

VOLUME_M = (4.0, 4.0, 2.5)
VOLUME_CENTRE = np.array([0.0, 0.0, 1.25])


def volume_bounds(volume_m=VOLUME_M) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) corners of a capture volume centred on the z axis, standing on the floor."""
    v = np.asarray(volume_m, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or np.any(v <= 0):
        raise ValueError(f"volume_m={volume_m!r}, expected three positive sizes (m)")
    return np.array([-v[0] / 2, -v[1] / 2, 0.0]), np.array([v[0] / 2, v[1] / 2, v[2]])


def focal_from_fov(width_px: int, fov_deg: float) -> float:
    """Focal length (px) giving a horizontal field of view ``fov_deg`` on ``width_px``."""
    if not 0 < fov_deg < 180:
        raise ValueError(f"fov_deg={fov_deg}, expected in (0, 180)")
    return (width_px / 2) / np.tan(np.radians(fov_deg) / 2)


def make_rig(n_cameras: int = 8, *, size=(1280, 1024), fov_deg: float = 56.0,
             radius_m: float = 5.5, height_m: float = 3.0, height_step_m: float = 0.4,
             volume_m=VOLUME_M, dist=None, position_jitter_m: float = 0.05,
             aim_jitter_deg: float = 1.0, rng=None) -> Rig:
    """A ring of ``n_cameras`` cameras around the capture volume, aimed at its centre.

    Args:
        n_cameras: number of cameras (>= 1); 8, 12 and 16 are typical.
        size: (width, height) px.
        fov_deg: horizontal field of view; focal length = (width/2) / tan(fov/2).
        radius_m: horizontal distance of the cameras from the volume axis.
        height_m: camera height above the floor; every second camera is ``height_step_m``
            lower.
        volume_m: (x, y, z) size of the volume; cameras aim at its centre
            ``(0, 0, z/2)``.
        dist: None (no distortion), a (5,) ``(k1, k2, p1, p2, k3)`` for every camera, or a
            (C, 5) array, one row per camera ([camera-model]).
        position_jitter_m, aim_jitter_deg: standard deviations of the pose jitter applied
            when ``rng`` is given (mounting is never perfect); ignored when ``rng`` is None.
        rng: None for an ideal ring, else a ``numpy.random.Generator`` or int seed.
    """
    n = int(n_cameras)
    if n < 1 or n != n_cameras:
        raise ValueError(f"n_cameras={n_cameras!r}, expected an integer >= 1")
    w, h = (int(s) for s in size)
    if w <= 0 or h <= 0:
        raise ValueError(f"size={size!r}, expected (width, height) > 0")
    if radius_m <= 0:
        raise ValueError(f"radius_m={radius_m}, expected > 0")
    lo, hi = volume_bounds(volume_m)
    centre = (lo + hi) / 2
    fx = focal_from_fov(w, fov_deg)
    if dist is None:
        dists = np.zeros((n, 5))
    else:
        d = np.asarray(dist, dtype=np.float64)
        if d.shape in ((5,), (4,)):
            dists = np.zeros((n, 5))
            dists[:, : d.size] = d
        elif d.shape == (n, 5):
            dists = d
        else:
            raise ValueError(f"dist.shape={d.shape}, expected (5,) or ({n}, 5)")
    gen = None if rng is None else np.random.default_rng(rng)
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        z = height_m - (height_step_m if i % 2 else 0.0)
        eye = np.array([radius_m * np.cos(a), radius_m * np.sin(a), z])
        R, _ = look_at(eye, centre)
        if gen is not None:
            eye = eye + gen.normal(0.0, position_jitter_m, 3)
            R = rotation_from_rodrigues(gen.normal(0.0, np.radians(aim_jitter_deg), 3)) @ R
        t = -R @ eye
        cams.append(Camera.from_params(name=f"cam_{i + 1}", size=(w, h), fx=fx,
                                       dist=dists[i], R=R, t=t))
    return Rig(cameras=tuple(cams))

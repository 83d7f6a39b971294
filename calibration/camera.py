"""Pinhole + Brown-Conrady camera model and multi-camera rigs.

Conventions: docs/conventions.md [pixels], [frames], [camera-model], [camera-order].
Poses are ``cam_from_world``: ``x_cam = R @ x_world + t``.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Iterable, Sequence

import numpy as np

__all__ = [
    "Camera",
    "Rig",
    "rotation_from_rodrigues",
    "rodrigues_from_rotation",
    "look_at",
]


def _as_points(a, width: int, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != width:
        raise ValueError(f"{name}.shape={arr.shape}, expected (N, {width})")
    return arr


def rotation_from_rodrigues(rvec) -> np.ndarray:
    """Rotation matrix from a rotation vector (axis * angle, rad); [rotations]."""
    r = np.asarray(rvec, dtype=np.float64).reshape(-1)
    if r.shape != (3,):
        raise ValueError(f"rvec.shape={np.shape(rvec)}, expected (3,)")
    theta = float(np.linalg.norm(r))
    if theta < 1e-12:
        k = np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])
        return np.eye(3) + k
    k = r / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * (kx @ kx)


def rodrigues_from_rotation(R) -> np.ndarray:
    """Rotation vector (axis * angle, rad) of a proper rotation matrix; [rotations]."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"R.shape={R.shape}, expected (3, 3)")
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """``cam_from_world`` (R, t) of a camera at ``eye`` looking at ``target``.

    Camera axes follow [frames]: z forward, x right, y down; ``up`` is the world up.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    z = target - eye
    nz = np.linalg.norm(z)
    if nz == 0:
        raise ValueError(f"eye == target == {eye.tolist()}")
    z /= nz
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f"viewing direction {z.tolist()} is parallel to up={up}")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world
    t = -R @ eye
    return R, t


@dataclass(frozen=True, kw_only=True)
class Camera:
    """One calibrated camera.

    Attributes:
        name: stable camera id ([camera-order]).
        size: (width, height) in pixels.
        K: (3, 3) intrinsic matrix, zero skew.
        dist: (5,) distortion ``(k1, k2, p1, p2, k3)``, OpenCV order ([camera-model]).
        R: (3, 3) rotation of ``cam_from_world``.
        t: (3,) translation of ``cam_from_world`` in metres.
    """

    name: str
    size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise TypeError(f"camera name must be a non-empty str, got {self.name!r}")
        size = tuple(int(s) for s in self.size)
        if len(size) != 2 or min(size) <= 0:
            raise ValueError(f"size={self.size!r}, expected (width, height) > 0")
        K = np.array(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K.shape={K.shape}, expected (3, 3)")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"focal lengths must be > 0, got fx={K[0,0]}, fy={K[1,1]}")
        dist = np.zeros(5)
        d = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if d.size not in (4, 5):
            raise ValueError(f"dist has {d.size} coefficients, expected 4 or 5 (k1,k2,p1,p2[,k3])")
        dist[: d.size] = d
        R = np.array(self.R, dtype=np.float64)
        if R.shape != (3, 3):
            raise ValueError(f"R.shape={R.shape}, expected (3, 3)")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError(f"R is not a proper rotation (det={np.linalg.det(R):.6f})")
        t = np.array(self.t, dtype=np.float64).reshape(-1)
        if t.shape != (3,):
            raise ValueError(f"t.shape={np.shape(self.t)}, expected (3,)")
        for a in (K, dist, R, t):
            a.setflags(write=False)
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    # ---- convenience -------------------------------------------------
    @classmethod
    def from_params(cls, *, name, size, fx, fy=None, cx=None, cy=None, dist=(0, 0, 0, 0, 0),
                    R=np.eye(3), t=np.zeros(3)) -> "Camera":
        w, h = size
        fy = fx if fy is None else fy
        cx = (w - 1) / 2 if cx is None else cx
        cy = (h - 1) / 2 if cy is None else cy
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        return cls(name=name, size=size, K=K, dist=dist, R=R, t=t)

    @property
    def rvec(self) -> np.ndarray:
        return rodrigues_from_rotation(self.R)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates (m)."""
        return -self.R.T @ self.t

    @property
    def P(self) -> np.ndarray:
        """(3, 4) projection matrix ``K [R | t]`` (ignores distortion)."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    def with_pose(self, R, t) -> "Camera":
        return replace(self, R=R, t=t)

    # ---- projection --------------------------------------------------
    def world_to_cam(self, points) -> np.ndarray:
        p = _as_points(points, 3, "points")
        return p @ self.R.T + self.t

    def distort_normalized(self, xy) -> np.ndarray:
        """Apply distortion to normalised coordinates (N, 2) -> (N, 2)."""
        xy = _as_points(xy, 2, "xy")
        k1, k2, p1, p2, k3 = self.dist
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=1)

    def project(self, points) -> np.ndarray:
        """Project world points (N, 3) m to pixels (N, 2) [pixels].

        Points at or behind the camera (z <= 0) project to NaN.
        """
        pc = self.world_to_cam(points)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = pc[:, :2] / z[:, None]
        xy[z <= 0] = np.nan
        xyd = self.distort_normalized(xy)
        K = self.K
        u = K[0, 0] * xyd[:, 0] + K[0, 1] * xyd[:, 1] + K[0, 2]
        v = K[1, 1] * xyd[:, 1] + K[1, 2]
        return np.stack([u, v], axis=1)

    def depth(self, points) -> np.ndarray:
        """Depth (z in the camera frame, m) of world points (N, 3)."""
        return self.world_to_cam(points)[:, 2]

    def pixel_to_normalized(self, pixels, iterations: int = 20) -> np.ndarray:
        """Undistort pixels (N, 2) to normalised image coordinates (N, 2) (z = 1 plane).

        Gauss-Newton on the forward model; exact to ~1e-12 for the distortions real lenses have.
        """
        px = _as_points(pixels, 2, "pixels")
        K = self.K
        yd = (px[:, 1] - K[1, 2]) / K[1, 1]
        xd = (px[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
        target = np.stack([xd, yd], axis=1)
        if not np.any(self.dist):
            return target
        k1, k2, p1, p2, k3 = self.dist
        xy = target.copy()
        for _ in range(iterations):
            x, y = xy[:, 0], xy[:, 1]
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            drad = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
            fx_ = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - target[:, 0]
            fy_ = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - target[:, 1]
            j11 = radial + x * drad * 2 * x + 2 * p1 * y + p2 * 6 * x
            j12 = x * drad * 2 * y + 2 * p1 * x + p2 * 2 * y
            j21 = y * drad * 2 * x + p1 * 2 * x + 2 * p2 * y
            j22 = radial + y * drad * 2 * y + p1 * 6 * y + 2 * p2 * x
            det = j11 * j22 - j12 * j21
            dx = (j22 * fx_ - j12 * fy_) / det
            dy = (-j21 * fx_ + j11 * fy_) / det
            xy[:, 0] -= dx
            xy[:, 1] -= dy
            if np.nanmax(np.abs(np.concatenate([dx, dy])), initial=0.0) < 1e-15:
                break
        return xy

    def undistort_pixels(self, pixels) -> np.ndarray:
        """Remove lens distortion: pixels (N, 2) -> ideal pinhole pixels (N, 2) with the same K."""
        xy = self.pixel_to_normalized(pixels)
        K = self.K
        return np.stack([K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2],
                         K[1, 1] * xy[:, 1] + K[1, 2]], axis=1)

    def unproject(self, pixels) -> tuple[np.ndarray, np.ndarray]:
        """Rays through pixels (N, 2): (origin (3,), unit directions (N, 3)) in the world frame."""
        xy = self.pixel_to_normalized(pixels)
        d_cam = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        d = d_cam @ self.R  # R.T @ d for each row
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return self.center, d

    def in_image(self, pixels, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: pixel inside the sensor, ``margin`` px from the border."""
        px = _as_points(pixels, 2, "pixels")
        w, h = self.size
        with np.errstate(invalid="ignore"):
            return ((px[:, 0] >= -0.5 + margin) & (px[:, 0] <= w - 0.5 - margin)
                    & (px[:, 1] >= -0.5 + margin) & (px[:, 1] <= h - 0.5 - margin))


@dataclass(frozen=True, kw_only=True)
class Rig:
    """An ordered set of cameras ([camera-order]). Index ``i`` is camera ``cameras[i]``."""

    cameras: tuple[Camera, ...]

    def __post_init__(self):
        cams = tuple(self.cameras)
        if not cams:
            raise ValueError("a rig needs at least one camera")
        for c in cams:
            if not isinstance(c, Camera):
                raise TypeError(f"rig member {c!r} is not a Camera")
        names = [c.name for c in cams]
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise ValueError(f"duplicate camera names in rig: {dup}")
        object.__setattr__(self, "cameras", cams)

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self):
        return iter(self.cameras)

    def __getitem__(self, i) -> Camera:
        return self.cameras[i]

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def index(self, name_or_index) -> int:
        """Camera index from its name, or from an index given as int or digit string."""
        names = self.names
        if isinstance(name_or_index, (int, np.integer)):
            i = int(name_or_index)
            if not 0 <= i < len(names):
                raise ValueError(f"camera index {i} out of range for a {len(names)}-camera rig")
            return i
        s = str(name_or_index)
        if s in names:
            return names.index(s)
        if s.isdigit() and int(s) < len(names):
            return int(s)
        raise ValueError(f"unknown camera {s!r}; rig has {names}")

    def project(self, points) -> np.ndarray:
        """Project world points (N, 3) into every camera: (C, N, 2) px, NaN behind a camera."""
        return np.stack([c.project(points) for c in self.cameras])

    def replace_cameras(self, cameras: Iterable[Camera]) -> "Rig":
        return Rig(cameras=tuple(cameras))


def stack_projection_matrices(cameras: Sequence[Camera]) -> np.ndarray:
    """(C, 3, 4) ``K [R|t]`` for the cameras."""
    return np.stack([c.P for c in cameras])

"""Multi-view triangulation: linear DLT, Gauss-Newton refinement of the reprojection error,
and rejection of one bad ray; vectorised over many points.

Works on undistorted normalised image coordinates (``Camera.pixel_to_normalized``), so the
model is the pinhole ``x = (R X + t)_xy / (R X + t)_z`` per camera. Reprojection errors are
measured in pixels as ``f * (normalised error)`` with ``f = (fx + fy) / 2`` (the distortion
Jacobian is ~1 at the scale of a residual). ``residual_mm`` is the mean distance (mm) from the
point to its rays.
Conventions: docs/conventions.md [frames] (``cam_from_world``), [arrays] (``(C, N, 2)`` with NaN
for "not seen"), [units].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.camera import Rig

__all__ = ["RigArrays", "TriangulationResult", "rig_arrays", "triangulate_dlt", "refine_points",
           "triangulate_normalized", "triangulate"]


@dataclass(frozen=True, kw_only=True)
class RigArrays:
    """Stacked camera geometry: R (C, 3, 3), t (C, 3), f (C,) px, centres (C, 3) m."""

    R: np.ndarray
    t: np.ndarray
    f: np.ndarray
    centres: np.ndarray

    @property
    def n_cameras(self) -> int:
        return int(self.R.shape[0])


def rig_arrays(rig: Rig) -> RigArrays:
    R = np.stack([c.R for c in rig])
    t = np.stack([c.t for c in rig])
    f = np.array([(c.K[0, 0] + c.K[1, 1]) / 2 for c in rig])
    centres = np.stack([c.center for c in rig])
    return RigArrays(R=R, t=t, f=f, centres=centres)


@dataclass(frozen=True, kw_only=True)
class TriangulationResult:
    """Triangulated points with their quality.

    Attributes:
        points: (N, 3) m; NaN where ``ok`` is False.
        residual_px: (N,) RMS reprojection error over the used rays, px.
        residual_mm: (N,) mean point-to-ray distance over the used rays, mm.
        used: (N, C) bool, the rays kept (a rejected bad ray is False).
        ray_error_px: (N, C) reprojection error of every observed ray (also rejected ones), px;
            NaN where the camera has no observation.
        ok: (N,) bool: >= 2 rays and the point is in front of every used camera.
    """

    points: np.ndarray
    residual_px: np.ndarray
    residual_mm: np.ndarray
    used: np.ndarray
    ray_error_px: np.ndarray
    ok: np.ndarray


def _check_xy(xy, C) -> np.ndarray:
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 3 or xy.shape[0] != C or xy.shape[2] != 2:
        raise ValueError(f"xy.shape={xy.shape}, expected ({C}, N, 2)")
    return xy


def triangulate_dlt(xy_norm: np.ndarray, geo: RigArrays, mask: np.ndarray | None = None
                    ) -> np.ndarray:
    """Linear (DLT) triangulation of normalised observations ``(C, N, 2)`` -> ``(N, 3)``.

    ``mask`` (N, C) selects the rays (default: the finite observations). Points with fewer than
    two rays come back NaN.
    """
    C = geo.n_cameras
    xy = _check_xy(xy_norm, C)
    N = xy.shape[1]
    seen = np.all(np.isfinite(xy), axis=2).T if mask is None else np.asarray(mask, bool)
    P = np.concatenate([geo.R, geo.t[:, :, None]], axis=2)             # (C, 3, 4)
    x = np.where(seen.T[..., None], xy, 0.0)                           # (C, N, 2)
    rows_u = x[..., 0:1] * P[:, None, 2, :] - P[:, None, 0, :]         # (C, N, 4)
    rows_v = x[..., 1:2] * P[:, None, 2, :] - P[:, None, 1, :]
    w = seen.T[..., None].astype(np.float64)
    A = np.concatenate([rows_u * w, rows_v * w], axis=0).transpose(1, 0, 2)  # (N, 2C, 4)
    out = np.full((N, 3), np.nan)
    good = seen.sum(axis=1) >= 2
    if not good.any():
        return out
    Ag = A[good]
    # smallest right singular vector = eigenvector of A^T A with the smallest eigenvalue
    # (4 x 4 per point: much cheaper than an SVD of the 2C x 4 system; refinement follows).
    scale = np.linalg.norm(Ag, axis=2, keepdims=True)
    Ag = Ag / np.where(scale > 0, scale, 1.0)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", Ag, Ag))
    h = vecs[:, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        out[good] = h[:, :3] / h[:, 3:4]
    return out


def _reproject(X, geo: RigArrays):
    """Camera-frame points (N, C, 3) of world points (N, 3)."""
    return np.einsum("cij,nj->nci", geo.R, X) + geo.t[None]


def refine_points(X0: np.ndarray, xy_norm: np.ndarray, geo: RigArrays, mask: np.ndarray,
                  iterations: int = 6) -> np.ndarray:
    """Gauss-Newton minimisation of the pixel reprojection error of each point, batched.

    ``X0`` (N, 3) start, ``xy_norm`` (C, N, 2), ``mask`` (N, C) rays to use. A tiny
    Levenberg damping keeps near-degenerate (2-ray, small-angle) systems solvable.
    """
    X = np.array(X0, dtype=np.float64)
    obs = np.where(mask.T[..., None], xy_norm, 0.0).transpose(1, 0, 2)  # (N, C, 2)
    w = mask.astype(np.float64)                                         # (N, C)
    f = geo.f[None, :]
    R = geo.R
    todo = np.all(np.isfinite(X), axis=1) & (mask.sum(axis=1) >= 2)
    for _ in range(iterations):
        if not todo.any():
            break
        Xi = X[todo]
        pc = _reproject(Xi, geo)                                        # (n, C, 3)
        z = pc[..., 2]
        z = np.where(np.abs(z) < 1e-9, 1e-9, z)
        u = pc[..., 0] / z
        v = pc[..., 1] / z
        wi = w[todo] * f ** 2
        ru = u - obs[todo, :, 0]
        rv = v - obs[todo, :, 1]
        # d(u)/dX = (R0 - u R2) / z ; d(v)/dX = (R1 - v R2) / z
        Ju = (R[None, :, 0, :] - u[..., None] * R[None, :, 2, :]) / z[..., None]   # (n, C, 3)
        Jv = (R[None, :, 1, :] - v[..., None] * R[None, :, 2, :]) / z[..., None]
        H = (np.einsum("nc,nci,ncj->nij", wi, Ju, Ju)
             + np.einsum("nc,nci,ncj->nij", wi, Jv, Jv))
        g = np.einsum("nc,nci->ni", wi, Ju * ru[..., None] + Jv * rv[..., None])
        lam = 1e-12 * np.trace(H, axis1=1, axis2=2)
        H = H + lam[:, None, None] * np.eye(3)
        step = -np.linalg.solve(H, g[..., None])[..., 0]
        X[todo] = Xi + step
        small = np.max(np.abs(step), axis=1) < 1e-13 * (1 + np.max(np.abs(Xi), axis=1))
        idx = np.flatnonzero(todo)
        todo[idx[small]] = False
    return X


def _errors(X, xy_norm, geo: RigArrays, seen):
    """Per-ray pixel error (N, C) (NaN where not seen) and depth (N, C)."""
    pc = _reproject(X, geo)
    z = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = pc[..., 0] / z
        v = pc[..., 1] / z
    obs = xy_norm.transpose(1, 0, 2)
    e = np.hypot(u - obs[..., 0], v - obs[..., 1]) * geo.f[None]
    e = np.where(seen, e, np.nan)
    return e, z


def _ray_distance_mm(X, xy_norm, geo: RigArrays, used):
    d_cam = np.concatenate([xy_norm, np.ones(xy_norm.shape[:2] + (1,))], axis=2)  # (C, N, 3)
    d = np.einsum("cji,cnj->nci", geo.R, d_cam)                        # R.T @ d
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    v = X[:, None, :] - geo.centres[None]
    dist = np.linalg.norm(np.cross(v, d), axis=2)
    dist = np.where(used, dist, 0.0)
    n = used.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return 1000.0 * dist.sum(axis=1) / n


def triangulate_normalized(xy_norm: np.ndarray, geo: RigArrays, *, mask: np.ndarray | None = None,
                           bad_ray_px: float = 2.0, max_rejected: int = 1,
                           iterations: int = 6) -> TriangulationResult:
    """DLT + refinement + bad-ray rejection for normalised observations ``(C, N, 2)``.

    A ray is rejected when its error exceeds ``bad_ray_px`` and it is the worst ray of a point
    seen by >= 3 cameras; the point is then re-solved without it (up to ``max_rejected`` rays
    per point).
    """
    C = geo.n_cameras
    xy = _check_xy(xy_norm, C)
    N = xy.shape[1]
    seen = np.all(np.isfinite(xy), axis=2).T
    used = seen.copy() if mask is None else (np.asarray(mask, bool) & seen)
    X = refine_points(triangulate_dlt(xy, geo, used), xy, geo, used, iterations)
    err, z = _errors(X, xy, geo, used)
    for _ in range(max_rejected):
        e = np.where(used, err, -np.inf)
        worst = np.argmax(e, axis=1)
        bad = (e[np.arange(N), worst] > bad_ray_px) & (used.sum(axis=1) >= 3)
        if not bad.any():
            break
        used[np.flatnonzero(bad), worst[bad]] = False
        sub = np.flatnonzero(bad)
        Xs = refine_points(triangulate_dlt(xy[:, sub], geo, used[sub]), xy[:, sub], geo,
                           used[sub], iterations)
        X[sub] = Xs
        err[sub], z[sub] = _errors(Xs, xy[:, sub], geo, used[sub])
    ray_err, z = _errors(X, xy, geo, seen)
    nused = used.sum(axis=1)
    with np.errstate(invalid="ignore"):
        front = np.all(~used | (z > 0), axis=1)
    ok = (nused >= 2) & front & np.all(np.isfinite(X), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(np.nansum(np.where(used, ray_err, 0.0) ** 2, axis=1) / nused)
    res_mm = _ray_distance_mm(np.where(ok[:, None], X, 0.0), np.where(np.isfinite(xy), xy, 0.0),
                              geo, used)
    X[~ok] = np.nan
    rms[~ok] = np.nan
    res_mm[~ok] = np.nan
    return TriangulationResult(points=X, residual_px=rms, residual_mm=res_mm,
                               used=used & ok[:, None], ray_error_px=ray_err, ok=ok)


def triangulate(rig: Rig, xy_px, **kwargs) -> TriangulationResult:
    """Triangulate raw (distorted) pixel observations ``(C, N, 2)`` (NaN = not seen) of ``rig``.

    Keyword arguments as :func:`triangulate_normalized`.
    """
    C = len(rig)
    xy = _check_xy(xy_px, C)
    norm = np.full_like(xy, np.nan)
    for c, cam in enumerate(rig):
        ok = np.all(np.isfinite(xy[c]), axis=1)
        if ok.any():
            norm[c, ok] = cam.pixel_to_normalized(xy[c, ok])
    return triangulate_normalized(norm, rig_arrays(rig), **kwargs)

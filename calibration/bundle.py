"""Sparse bundle adjustment of camera poses (and optionally intrinsics) from wand/points.

``scipy.optimize.least_squares`` (method='trf', explicit ``jac_sparsity``, ``x_scale='jac'``,
robust loss). Residuals: reprojection in px of every observed wand marker / point, plus
wand-length residuals ``(|X_j - X_i| - (s_j - s_i)) * length_weight`` (px per m) that fix the
metric scale. Gauge: camera 0 is fixed at its initial pose (identity after init). In single-point
mode the scale is fixed by camera 1's distance from camera 0. Outliers are removed over rounds
with shrinking thresholds (``thresholds_px``, then ``sigma_k`` x robust sigma).
Intrinsics refinement (optional): fx=fy, cx, cy, k1, k2 per camera.
Units and conventions: docs/conventions.md [units], [pixels], [camera-model], [frames].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from calibration.camera import Camera


@dataclass(frozen=True, kw_only=True)
class BundleResult:
    """cameras: refined cameras; X: (T, M, 3) points (m); inlier: (C, T, M) bool;
    residual_px: (C, T, M, 2) final reprojection residuals (NaN where unused)."""

    cameras: list
    X: np.ndarray
    inlier: np.ndarray
    residual_px: np.ndarray
    cost: float
    n_rounds: int


def _project(Xc_all, fx, cx, cy, dist):
    z = Xc_all[:, 2]
    x, y = Xc_all[:, 0] / z, Xc_all[:, 1] / z
    k1, k2, p1, p2, k3 = dist.T
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([fx * xd + cx, fx * yd + cy], axis=1)


class _Problem:
    def __init__(self, cameras, xy, spacing_m, refine_intrinsics, length_weight, scale_ref):
        self.cams = cameras
        self.C, self.T, self.M, _ = xy.shape
        self.xy = xy
        self.spacing = spacing_m
        self.refine = refine_intrinsics
        self.lw = length_weight
        self.scale_ref = scale_ref
        self.nI = 5 if refine_intrinsics else 0
        self.nc = 6 * (self.C - 1) + self.nI * self.C
        self.dist0 = np.stack([c.dist for c in cameras])
        self.pairs = []  # wand mode: rigid wand parameterisation, no length residuals
        self.P = 5 if spacing_m is not None else 3 * self.M

    def set_frames(self, X0):
        """Per-frame tangent basis of the wand direction from the initial points (T, M, 3)."""
        if self.spacing is None:
            return
        d0 = X0[:, -1] - X0[:, 0]
        d0 /= np.linalg.norm(d0, axis=1, keepdims=True)
        a = np.where(np.abs(d0[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
        e1 = np.cross(d0, a)
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
        self.d0, self.e1, self.e2 = d0, e1, np.cross(d0, e1)
        self.mid = (self.spacing[0] + self.spacing[-1]) / 2

    def frame_points(self, q):
        if self.spacing is None:
            return q.reshape(self.T, self.M, 3)
        d = self.d0 + q[:, 3:4] * self.e1 + q[:, 4:5] * self.e2
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return q[:, None, :3] + (self.spacing - self.mid)[None, :, None] * d[:, None, :]

    def frame_params(self, X0):
        if self.spacing is None:
            return X0.reshape(self.T, -1)
        q = np.zeros((self.T, 5))
        q[:, :3] = X0.mean(axis=1) - 0.0
        q[:, :3] = (X0[:, 0] + X0[:, -1]) / 2
        return q

    def set_mask(self, mask):
        self.ci, self.ti, self.mi = np.nonzero(mask)
        self.obs = self.xy[self.ci, self.ti, self.mi]

    def pack(self, R, t, X):
        rv = Rotation.from_matrix(R[1:]).as_rotvec()
        parts = [np.concatenate([rv, t[1:]], axis=1).ravel()]
        if self.refine:
            parts.append(np.array([[c.K[0, 0], c.K[0, 2], c.K[1, 2], c.dist[0], c.dist[1]]
                                   for c in self.cams]).ravel())
        parts.append(self.frame_params(X).ravel())
        return np.concatenate(parts)

    def unpack(self, p):
        C = self.C
        e = p[: 6 * (C - 1)].reshape(C - 1, 6)
        R = np.concatenate([self.cams[0].R[None], Rotation.from_rotvec(e[:, :3]).as_matrix()])
        t = np.concatenate([self.cams[0].t[None], e[:, 3:]])
        o = 6 * (C - 1)
        if self.refine:
            I = p[o:o + 5 * C].reshape(C, 5)
            fx, cx, cy = I[:, 0], I[:, 1], I[:, 2]
            dist = self.dist0.copy()
            dist[:, 0], dist[:, 1] = I[:, 3], I[:, 4]
        else:
            fx = np.array([c.K[0, 0] for c in self.cams])
            cx = np.array([c.K[0, 2] for c in self.cams])
            cy = np.array([c.K[1, 2] for c in self.cams])
            dist = self.dist0
        X = self.frame_points(p[self.nc:].reshape(self.T, self.P))
        return R, t, fx, cx, cy, dist, X

    def reproj(self, p):
        R, t, fx, cx, cy, dist, X = self.unpack(p)
        ci = self.ci
        Xw = X[self.ti, self.mi]
        Xc = np.einsum("nij,nj->ni", R[ci], Xw) + t[ci]
        return _project(Xc, fx[ci], cx[ci], cy[ci], dist[ci]) - self.obs

    def fun(self, p):
        r = [self.reproj(p).ravel()]
        R, t, *_, X = self.unpack(p)
        for i, j in self.pairs:
            L = np.linalg.norm(X[:, j] - X[:, i], axis=1)
            r.append((L - (self.spacing[j] - self.spacing[i])) * self.lw)
        if self.scale_ref is not None:
            r.append(np.array([(np.linalg.norm(R[1].T @ t[1]) - self.scale_ref) * self.lw]))
        return np.concatenate(r)

    def sparsity(self):
        n_obs = len(self.ci)
        n_res = 2 * n_obs + len(self.pairs) * self.T + (self.scale_ref is not None)
        A = lil_matrix((n_res, self.nc + self.P * self.T), dtype=np.int8)
        rows = np.arange(n_obs)
        for k in range(2):
            rr = 2 * rows + k
            for j in range(6):
                sel = self.ci > 0
                A[rr[sel], 6 * (self.ci[sel] - 1) + j] = 1
            if self.refine:
                for j in range(5):
                    A[rr, 6 * (self.C - 1) + 5 * self.ci + j] = 1
            base = self.nc + self.P * self.ti
            if self.spacing is None:
                base = base + 3 * self.mi
            for j in range(self.P if self.spacing is not None else 3):
                A[rr, base + j] = 1
        r0 = 2 * n_obs
        for i, j in self.pairs:
            tt = np.arange(self.T)
            for m in (i, j):
                for d in range(3):
                    A[r0 + tt, self.nc + 3 * (tt * self.M + m) + d] = 1
            r0 += self.T
        if self.scale_ref is not None:
            A[r0, 0:6] = 1
        return A.tocsr()


def bundle_adjust(cameras: list[Camera], xy: np.ndarray, X0: np.ndarray, *, spacing_m=None,
                  refine_intrinsics: bool = False, length_weight: float = 1e5,
                  thresholds_px=(10.0, 3.0), sigma_k: float = 5.0, f_scale_px: float = 1.0,
                  max_nfev: int = 200) -> BundleResult:
    """Refine poses (and intrinsics) from xy (C, T, M, 2) raw px with initial points X0 (T, M, 3)."""
    C, T, M, _ = xy.shape
    if np.shape(X0) != (T, M, 3):
        raise ValueError(f"X0.shape={np.shape(X0)}, expected ({T}, {M}, 3)")
    R = np.stack([c.R for c in cameras])
    t = np.stack([c.t for c in cameras])
    scale_ref = None
    if spacing_m is None and C > 1:
        scale_ref = float(np.linalg.norm(cameras[1].center - cameras[0].center))
    prob = _Problem(cameras, xy, spacing_m, refine_intrinsics, length_weight, scale_ref)
    # frames whose points are not triangulated are dropped
    good_frame = np.all(np.isfinite(X0), axis=(1, 2))
    X0 = np.where(good_frame[:, None, None], X0, 0.0)
    mask = np.all(np.isfinite(xy), axis=3) & good_frame[None, :, None]
    prob.set_frames(np.where(good_frame[:, None, None], X0, np.array([0, 0, 1.0])
                             * np.arange(M)[None, :, None]))
    p = prob.pack(R, t, X0)
    limits = list(thresholds_px) + ["sigma"]
    cost = np.nan
    rnd = 0
    for rnd in range(len(limits) + 1):
        prob.set_mask(mask)
        res = least_squares(prob.fun, p, jac_sparsity=prob.sparsity(), method="trf",
                            x_scale="jac", loss="soft_l1", f_scale=f_scale_px,
                            max_nfev=max_nfev, tr_solver="lsmr")
        p, cost = res.x, float(res.cost)
        if rnd == len(limits):
            break
        e = np.linalg.norm(prob.reproj(p).reshape(-1, 2), axis=1)
        if limits[rnd] == "sigma":
            limit = sigma_k * 1.4826 * np.median(e) * 1.2  # e is a 2D norm: ~1.18 sigma median
            limit = min(limit, thresholds_px[-1]) if thresholds_px else limit
        else:
            limit = limits[rnd]
        keep = e <= limit
        mask = np.zeros_like(mask)
        mask[prob.ci[keep], prob.ti[keep], prob.mi[keep]] = True
    R, t, fx, cx, cy, dist, X = prob.unpack(p)
    out = []
    for c in range(C):
        K = np.array([[fx[c], 0, cx[c]], [0, fx[c], cy[c]], [0, 0, 1.0]])
        out.append(Camera(name=cameras[c].name, size=cameras[c].size, K=K, dist=dist[c],
                          R=R[c], t=t[c]))
    resid = np.full((C, T, M, 2), np.nan)
    resid[prob.ci, prob.ti, prob.mi] = prob.reproj(p).reshape(-1, 2)
    X = np.where(good_frame[:, None, None], X, np.nan)
    return BundleResult(cameras=out, X=X, inlier=mask, residual_px=resid, cost=cost,
                        n_rounds=rnd + 1)

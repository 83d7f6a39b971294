"""Sparse bundle adjustment of camera poses (and optionally intrinsics) from wand/points.

``scipy.optimize.least_squares`` (method='trf', ``tr_solver='lsmr'``, ``x_scale='jac'``, robust
``soft_l1`` loss) with an explicit, analytic Jacobian returned as a ``scipy.sparse`` CSR matrix
(``jac="analytic"``, default): each reprojection residual depends only on its camera's pose
(6), its camera's intrinsics (5, when refined) and its frame's wand (5) or point (3)
parameters, and those blocks are computed in closed form, vectorised over all observations.
``jac="numeric"`` keeps the previous path (finite differences grouped by ``jac_sparsity``) as
the benchmark's baseline; both have the same sparsity pattern.

Residuals: reprojection in px of every observed wand marker / point. In wand mode each frame's
wand is rigid (centre + direction, 5 parameters, markers at their configured spacing), so the
wand length is exact by construction and fixes the metric scale. Gauge: camera 0 is fixed at its
initial pose (identity after init). In single-point mode the scale is fixed by a residual on
camera 1's distance from camera 0. Outliers are removed over rounds with shrinking thresholds
(``thresholds_px``, then ``sigma_k`` x robust sigma).
Intrinsics refinement (optional): fx=fy, cx, cy, k1, k2 per camera.
Units and conventions: docs/conventions.md [units], [pixels], [camera-model], [frames].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, csr_matrix
from scipy.spatial.transform import Rotation

try:  # installed with scikit-learn (a dependency); only a speed-up
    from threadpoolctl import threadpool_limits
except ImportError:  # pragma: no cover
    from contextlib import nullcontext

    def threadpool_limits(**_):
        return nullcontext()

from calibration.camera import Camera

JACOBIANS = ("analytic", "numeric")


@dataclass(frozen=True, kw_only=True)
class BundleResult:
    """cameras: refined cameras; X: (T, M, 3) points (m); inlier: (C, T, M) bool;
    residual_px: (C, T, M, 2) final reprojection residuals (NaN where unused);
    nfev / njev: function / Jacobian evaluations summed over the rounds."""

    cameras: list
    X: np.ndarray
    inlier: np.ndarray
    residual_px: np.ndarray
    cost: float
    n_rounds: int
    nfev: int = 0
    njev: int = 0


def _project(Xc_all, fx, cx, cy, dist):
    z = Xc_all[:, 2]
    x, y = Xc_all[:, 0] / z, Xc_all[:, 1] / z
    k1, k2, p1, p2, k3 = dist.T
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([fx * xd + cx, fx * yd + cy], axis=1)


def project_and_jacobian(Xc, fx, fy, cx, cy, dist):
    """Pixels (n, 2) of camera-frame points Xc (n, 3) and d(u, v)/d Xc (n, 2, 3).

    fx, fy, cx, cy (n,), dist (n, 5) per point ([camera-model]). Also returns the normalised
    (x, y), r^2 and the radial factor for callers differentiating w.r.t. the intrinsics.
    """
    z = Xc[:, 2]
    x, y = Xc[:, 0] / z, Xc[:, 1] / z
    k1, k2, p1, p2, k3 = dist.T
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    uv = np.stack([fx * xd + cx, fy * yd + cy], axis=1)
    dxx = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x      # d(xd, yd) / d(x, y)
    dxy = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    dyy = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    iz = 1 / z
    A = np.empty((len(z), 2, 3))                                 # f * D @ d(x, y)/d Xc
    A[:, 0, 0] = fx * dxx * iz
    A[:, 0, 1] = fx * dxy * iz
    A[:, 0, 2] = -fx * (dxx * x + dxy * y) * iz
    A[:, 1, 0] = fy * dxy * iz
    A[:, 1, 1] = fy * dyy * iz
    A[:, 1, 2] = -fy * (dxy * x + dyy * y) * iz
    return uv, A, (x, y, r2, rad)


def _skew(v):
    """(N, 3) -> (N, 3, 3) cross-product matrices."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def _left_jacobian(w):
    """SO(3) left Jacobian J_l of rotation vectors w (N, 3): R(w + dw) ~ exp([J_l dw]x) R(w)."""
    th = np.linalg.norm(w, axis=1)
    W = _skew(w)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th ** 2 / 24, (1 - np.cos(ths)) / ths ** 2)
    b = np.where(small, 1 / 6 - th ** 2 / 120, (ths - np.sin(ths)) / ths ** 3)
    return np.eye(3) + a[:, None, None] * W + b[:, None, None] * (W @ W)


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
        """(T, M, 3) points from the frame parameters; wand mode also returns the direction
        d (T, 3) and |n| (T,) of the unnormalised direction (for the Jacobian)."""
        if self.spacing is None:
            return q.reshape(self.T, self.M, 3), None, None
        n = self.d0 + q[:, 3:4] * self.e1 + q[:, 4:5] * self.e2
        nn = np.linalg.norm(n, axis=1)
        d = n / nn[:, None]
        X = q[:, None, :3] + (self.spacing - self.mid)[None, :, None] * d[:, None, :]
        return X, d, nn

    def frame_params(self, X0):
        if self.spacing is None:
            return X0.reshape(self.T, -1)
        q = np.zeros((self.T, 5))
        q[:, :3] = (X0[:, 0] + X0[:, -1]) / 2
        return q

    def set_mask(self, mask):
        self.ci, self.ti, self.mi = np.nonzero(mask)
        self.obs = self.xy[self.ci, self.ti, self.mi]
        self._pattern = None

    def pack(self, R, t, X):
        rv = Rotation.from_matrix(R[1:]).as_rotvec()
        parts = [np.concatenate([rv, t[1:]], axis=1).ravel()]
        if self.refine:
            parts.append(np.array([[c.K[0, 0], c.K[0, 2], c.K[1, 2], c.dist[0], c.dist[1]]
                                   for c in self.cams]).ravel())
        parts.append(self.frame_params(X).ravel())
        return np.concatenate(parts)

    def unpack(self, p, full=False):
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
        X, d, nn = self.frame_points(p[self.nc:].reshape(self.T, self.P))
        if full:
            return R, t, fx, cx, cy, dist, X, e[:, :3], d, nn
        return R, t, fx, cx, cy, dist, X

    def reproj(self, p):
        R, t, fx, cx, cy, dist, X = self.unpack(p)
        ci = self.ci
        Xw = X[self.ti, self.mi]
        Xc = np.einsum("nij,nj->ni", R[ci], Xw) + t[ci]
        return _project(Xc, fx[ci], cx[ci], cy[ci], dist[ci]) - self.obs

    def fun(self, p):
        r = [self.reproj(p).ravel()]
        if self.scale_ref is not None:
            R, t, *_ = self.unpack(p)
            r.append(np.array([(np.linalg.norm(R[1].T @ t[1]) - self.scale_ref) * self.lw]))
        return np.concatenate(r)

    # ---- Jacobian ------------------------------------------------------------------------
    def _blocks(self):
        """Row / column index arrays of the Jacobian blocks (fixed for one mask).

        Per observation n (rows 2n, 2n+1): pose columns (6, cameras > 0), intrinsics (5, when
        refined), frame columns (5 wand / 3 point). Returned as (rows, cols) per block, each of
        shape (n_sel, 2, k)."""
        n = len(self.ci)
        rows2 = (2 * np.arange(n))[:, None] + np.arange(2)[None, :]      # (n, 2)
        blocks = {}
        sel = self.ci > 0
        cols = 6 * (self.ci[sel] - 1)[:, None] + np.arange(6)[None, :]
        blocks["pose"] = (sel, np.broadcast_to(rows2[sel][:, :, None], (sel.sum(), 2, 6)),
                          np.broadcast_to(cols[:, None, :], (sel.sum(), 2, 6)))
        if self.refine:
            cols = 6 * (self.C - 1) + 5 * self.ci[:, None] + np.arange(5)[None, :]
            blocks["intr"] = (None, np.broadcast_to(rows2[:, :, None], (n, 2, 5)),
                              np.broadcast_to(cols[:, None, :], (n, 2, 5)))
        if self.spacing is not None:
            cols = self.nc + 5 * self.ti[:, None] + np.arange(5)[None, :]
            k = 5
        else:
            cols = self.nc + self.P * self.ti[:, None] + 3 * self.mi[:, None] + np.arange(3)
            k = 3
        blocks["frame"] = (None, np.broadcast_to(rows2[:, :, None], (n, 2, k)),
                           np.broadcast_to(cols[:, None, :], (n, 2, k)))
        return blocks

    def n_res(self):
        return 2 * len(self.ci) + (self.scale_ref is not None)

    def n_par(self):
        return self.nc + self.P * self.T

    def jac(self, p):
        """Analytic Jacobian of ``fun`` (sparse CSR, n_res x n_par)."""
        R, t, fx, cx, cy, dist, X, w, d, nn = self.unpack(p, full=True)
        ci, ti, mi = self.ci, self.ti, self.mi
        Rn = R[ci]
        Xw = X[ti, mi]
        RX = np.einsum("nij,nj->ni", Rn, Xw)
        Xc = RX + t[ci]
        f = fx[ci]
        _, A, (x, y, r2, rad) = project_and_jacobian(Xc, f, f, cx[ci], cy[ci], dist[ci])
        k1, k2, p1, p2, k3 = dist[ci].T
        data = {}
        blocks = self._pattern if self._pattern is not None else self._blocks()
        self._pattern = blocks
        sel = blocks["pose"][0]
        if sel.any():
            Jl = _left_jacobian(w)                        # cameras 1..C-1
            dR = -_skew(RX[sel]) @ Jl[ci[sel] - 1]         # d Xc / d w
            data["pose"] = np.concatenate([A[sel] @ dR, A[sel]], axis=2)
        if self.refine:
            xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            J = np.zeros((len(ci), 2, 5))
            J[:, 0, 0], J[:, 1, 0] = xd, yd
            J[:, 0, 1] = J[:, 1, 2] = 1.0
            J[:, 0, 3], J[:, 1, 3] = f * x * r2, f * y * r2
            J[:, 0, 4], J[:, 1, 4] = f * x * r2 * r2, f * y * r2 * r2
            data["intr"] = J
        AR = A @ Rn                                       # d(u, v) / d Xw
        if self.spacing is not None:
            off = (self.spacing - self.mid)[mi]
            dt = d[ti]
            proj = (np.eye(3) - dt[:, :, None] * dt[:, None, :]) / nn[ti][:, None, None]
            E = np.stack([self.e1[ti], self.e2[ti]], axis=2)            # (n, 3, 2)
            dXdab = off[:, None, None] * (proj @ E)
            data["frame"] = np.concatenate([AR, AR @ dXdab], axis=2)
        else:
            data["frame"] = AR
        rows, cols, vals = [], [], []
        for k, (_, r, c) in blocks.items():
            if k in data:
                rows.append(r.ravel())
                cols.append(c.ravel())
                vals.append(data[k].ravel())
        if self.scale_ref is not None:
            n_t = np.linalg.norm(t[1])
            rows.append(np.full(3, 2 * len(ci)))
            cols.append(np.arange(3, 6))
            vals.append(self.lw * t[1] / n_t)
        J = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                       shape=(self.n_res(), self.n_par()))
        return J.tocsr()

    def sparsity(self):
        """The Jacobian's sparsity pattern (same as ``jac``'s), for the numeric path."""
        blocks = self._blocks()
        rows = np.concatenate([r.ravel() for _, r, _ in blocks.values()])
        cols = np.concatenate([c.ravel() for _, _, c in blocks.values()])
        if self.scale_ref is not None:
            rows = np.r_[rows, np.full(6, 2 * len(self.ci))]
            cols = np.r_[cols, np.arange(6)]
        return csr_matrix((np.ones(len(rows), np.int8), (rows, cols)),
                          shape=(self.n_res(), self.n_par()))


def bundle_adjust(cameras: list[Camera], xy: np.ndarray, X0: np.ndarray, *, spacing_m=None,
                  refine_intrinsics: bool = False, length_weight: float = 1e5,
                  thresholds_px=(10.0, 3.0), sigma_k: float = 5.0, f_scale_px: float = 1.0,
                  max_nfev: int = 200, jac: str = "analytic",
                  ftol_outlier_rounds: float = 1e-4, blas_threads: int | None = 1
                  ) -> BundleResult:
    """Refine poses (and intrinsics) from xy (C, T, M, 2) raw px with initial points X0 (T, M, 3).

    jac: "analytic" (closed-form sparse Jacobian) or "numeric" (finite differences with
    ``jac_sparsity``; the baseline the benchmark compares against).
    blas_threads: BLAS threads inside the solver (None: leave the library default). One by
    default: its vectors (~1e5) are too short to gain from threads, and on a shared 2-core
    machine threaded level-1 BLAS in ``lsmr`` cost 3x the time.
    ftol_outlier_rounds: ``ftol`` of the rounds before the last (the last uses 1e-8).
    """
    if jac not in JACOBIANS:
        raise ValueError(f"jac={jac!r}, expected one of {JACOBIANS}")
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
    rnd = nfev = njev = 0
    for rnd in range(len(limits) + 1):
        prob.set_mask(mask)
        kw = dict(jac=prob.jac) if jac == "analytic" else dict(jac_sparsity=prob.sparsity())
        last = rnd == len(limits)
        # outlier rounds only need the residuals to ~1e-4 of the cost (their long flat tails
        # with outliers present cost hundreds of iterations at ftol 1e-8); the last is strict
        with threadpool_limits(limits=blas_threads, user_api="blas"):
            res = least_squares(prob.fun, p, method="trf", x_scale="jac", loss="soft_l1",
                                f_scale=f_scale_px, max_nfev=max_nfev, tr_solver="lsmr",
                                ftol=1e-8 if last else ftol_outlier_rounds, **kw)
        p, cost = res.x, float(res.cost)
        nfev += int(res.nfev)
        njev += int(res.njev or 0)
        if last:
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
                        n_rounds=rnd + 1, nfev=nfev, njev=njev)

"""Maximum-likelihood refinement of triangulated points for calibration diagnostics.

``refine_points``: Gauss-Newton on the pixel reprojection error of each point, from a linear
(DLT) start, with the full camera model ([camera-model]); vectorised over points.
``point_covariance``: first-order covariance of such a point for an isotropic pixel noise
``sigma_px`` per coordinate, ``(sum_c J_c^T J_c)^-1 sigma^2`` -- the floor any triangulation
reaches. Conventions: docs/conventions.md [pixels], [frames], [units], [arrays].
"""
from __future__ import annotations

import numpy as np

from calibration.bundle import project_and_jacobian


def _stack(cameras):
    R = np.stack([c.R for c in cameras])
    t = np.stack([c.t for c in cameras])
    K = np.stack([c.K for c in cameras])
    dist = np.stack([c.dist for c in cameras])
    return R, t, K, dist


def _normal_equations(cameras, xy, X):
    """Per point: J^T J (N, 3, 3), J^T r (N, 3), sum r^2 (N,) over the cameras seeing it."""
    R, t, K, dist = _stack(cameras)
    C, N, _ = xy.shape
    seen = np.all(np.isfinite(xy), axis=2) & np.all(np.isfinite(X), axis=1)[None]
    H = np.zeros((N, 3, 3))
    g = np.zeros((N, 3))
    e = np.zeros(N)
    for c in range(C):
        s = seen[c]
        if not s.any():
            continue
        n = int(s.sum())
        Xc = X[s] @ R[c].T + t[c]
        uv, A, _ = project_and_jacobian(Xc, np.full(n, K[c, 0, 0]), np.full(n, K[c, 1, 1]),
                                        np.full(n, K[c, 0, 2]), np.full(n, K[c, 1, 2]),
                                        np.broadcast_to(dist[c], (n, 5)))
        J = A @ R[c]
        r = uv - xy[c, s]
        H[s] += np.einsum("nki,nkj->nij", J, J)
        g[s] += np.einsum("nki,nk->ni", J, r)
        e[s] += np.sum(r * r, axis=1)
    return H, g, e, seen.sum(axis=0)


def refine_points(cameras, xy, X0, *, iterations: int = 10) -> np.ndarray:
    """Points (N, 3) m minimising the pixel reprojection error of xy (C, N, 2) raw px (NaN =
    unseen), from X0 (N, 3). Points seen by fewer than 2 cameras come back NaN."""
    xy = np.asarray(xy, np.float64)
    X = np.array(X0, np.float64)
    if xy.ndim != 3 or xy.shape[0] != len(cameras) or xy.shape[2] != 2:
        raise ValueError(f"xy.shape={xy.shape}, expected ({len(cameras)}, N, 2)")
    if X.shape != (xy.shape[1], 3):
        raise ValueError(f"X0.shape={X.shape}, expected ({xy.shape[1]}, 3)")
    for _ in range(iterations):
        H, g, _, n = _normal_equations(cameras, xy, X)
        ok = (n >= 2) & np.isfinite(X[:, 0])
        if not ok.any():
            break
        step = np.zeros_like(X)
        step[ok] = np.linalg.solve(H[ok], -g[ok][:, :, None])[:, :, 0]
        X[ok] += step[ok]
        if np.abs(step[ok]).max() < 1e-12:
            break
    _, _, _, n = _normal_equations(cameras, xy, X)
    X[n < 2] = np.nan
    return X


def point_covariance(cameras, seen, X, sigma_px: float) -> np.ndarray:
    """(N, 3, 3) first-order covariance (m^2) of points X (N, 3) seen by the cameras in
    ``seen`` (C, N) bool, for pixel noise ``sigma_px`` per coordinate. NaN where < 2 views."""
    seen = np.asarray(seen, bool)
    X = np.asarray(X, np.float64)
    if seen.shape != (len(cameras), len(X)):
        raise ValueError(f"seen.shape={seen.shape}, expected ({len(cameras)}, {len(X)})")
    xy = np.where(seen[..., None], 0.0, np.nan)       # residual values do not enter J^T J
    H, _, _, n = _normal_equations(cameras, xy, X)
    cov = np.full((len(X), 3, 3), np.nan)
    ok = (n >= 2) & np.isfinite(X[:, 0])
    cov[ok] = np.linalg.inv(H[ok]) * sigma_px ** 2
    return cov

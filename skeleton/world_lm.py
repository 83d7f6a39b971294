"""The thesis' world-frame joint cost minimised by Levenberg-Marquardt, compiled.

``world_lm(X (B, F, N, 3), c (B, F, 3), r (B, N), iters) -> (c, r, ssr)`` minimises
``sum_fn (|x_fn - c_f| - r_n)^2`` over per-frame centres ``c_f`` and constant marker-centre
distances ``r_n`` for B independent problems (one 2+2 segment pair's candidate starts). The
normal equations are block-arrow shaped: a 3x3 block per frame (inverted in closed form by
cofactors) and an N x N block for the distances, solved by the Schur complement on ``r``.
Damping is Marquardt's (the diagonal scaled by 1 + lambda); a step is taken only when it
lowers the sum of squares; a problem stops when the relative decrease falls below ``rtol``,
the rms below ``atol_m``, or lambda rises above 1e8.

Why compiled (numba): the skeleton solver runs thousands of these iterations per figure on
arrays of 4 markers x 20-200 frames; vectorised NumPy spent ~0.5 ms per iteration in call
overhead (about 60 array operations of a few hundred elements each). The loop below takes
~15x less time on the same calls (``benchmarks/bench_world_lm.py``). The first call in a
fresh checkout compiles (~15 s); the machine code is cached next to this file.
Conventions: docs/conventions.md [arrays], [errors].
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["world_lm", "warm_up"]


@njit(cache=True)
def _residuals(X, c, r, D, d, e):
    """D = X - c, d = |D|, e = d - r for one problem (F, N); returns sum e^2."""
    F, N = X.shape[0], X.shape[1]
    s = 0.0
    for f in range(F):
        for n in range(N):
            dx = X[f, n, 0] - c[f, 0]
            dy = X[f, n, 1] - c[f, 1]
            dz = X[f, n, 2] - c[f, 2]
            D[f, n, 0] = dx
            D[f, n, 1] = dy
            D[f, n, 2] = dz
            dd = np.sqrt(dx * dx + dy * dy + dz * dz)
            d[f, n] = dd
            ee = dd - r[n]
            e[f, n] = ee
            s += ee * ee
    return s


@njit(cache=True)
def _world_lm_kernel(X, c, r, iters, rtol, atol2):
    """X (B, F, N, 3); c (B, F, 3) and r (B, N) are updated in place; returns ssr (B,)."""
    B, F, N = X.shape[0], X.shape[1], X.shape[2]
    out = np.empty(B)
    D = np.empty((F, N, 3))
    d = np.empty((F, N))
    e = np.empty((F, N))
    D2 = np.empty((F, N, 3))
    d2 = np.empty((F, N))
    e2 = np.empty((F, N))
    u = np.empty((N, 3))
    W = np.empty((F, N, 3))       # A_f^-1 u_fn
    Aig = np.empty((F, 3))        # A_f^-1 J_c^T e
    Ai = np.empty((3, 3))
    Sm = np.empty((N, N))         # Schur complement on r
    rhs = np.empty(N)
    c2 = np.empty((F, 3))
    r2 = np.empty(N)
    for b in range(B):
        Xb = X[b]
        cb = c[b]
        rb = r[b]
        ssr = _residuals(Xb, cb, rb, D, d, e)
        lam = 1e-3
        for _ in range(iters):
            for i in range(N):
                for j in range(N):
                    Sm[i, j] = 0.0
                Sm[i, i] = (1 + lam) * F          # J_r^T J_r = F I, damped
                s = 0.0
                for f in range(F):
                    s += e[f, i]
                rhs[i] = s                        # -J_r^T e
            for f in range(F):
                a00 = a01 = a02 = a11 = a12 = a22 = 0.0
                g0 = g1 = g2 = 0.0
                for n in range(N):                # J_c = -u (unit vectors centre -> marker)
                    inv = 1.0 / max(d[f, n], 1e-12)
                    ux = D[f, n, 0] * inv
                    uy = D[f, n, 1] * inv
                    uz = D[f, n, 2] * inv
                    u[n, 0] = ux
                    u[n, 1] = uy
                    u[n, 2] = uz
                    a00 += ux * ux
                    a01 += ux * uy
                    a02 += ux * uz
                    a11 += uy * uy
                    a12 += uy * uz
                    a22 += uz * uz
                    en = e[f, n]
                    g0 -= ux * en
                    g1 -= uy * en
                    g2 -= uz * en
                a = a00 + lam * a00 + 1e-12
                dd = a11 + lam * a11 + 1e-12
                ff = a22 + lam * a22 + 1e-12
                c00 = dd * ff - a12 * a12
                c01 = a02 * a12 - a01 * ff
                c02 = a01 * a12 - a02 * dd
                c11 = a * ff - a02 * a02
                c12 = a01 * a02 - a * a12
                c22 = a * dd - a01 * a01
                idet = 1.0 / (a * c00 + a01 * c01 + a02 * c02)
                Ai[0, 0] = c00 * idet
                Ai[0, 1] = c01 * idet
                Ai[0, 2] = c02 * idet
                Ai[1, 0] = c01 * idet
                Ai[1, 1] = c11 * idet
                Ai[1, 2] = c12 * idet
                Ai[2, 0] = c02 * idet
                Ai[2, 1] = c12 * idet
                Ai[2, 2] = c22 * idet
                for n in range(N):
                    for k in range(3):
                        W[f, n, k] = Ai[k, 0] * u[n, 0] + Ai[k, 1] * u[n, 1] + Ai[k, 2] * u[n, 2]
                for k in range(3):
                    Aig[f, k] = Ai[k, 0] * g0 + Ai[k, 1] * g1 + Ai[k, 2] * g2
                for n in range(N):
                    rhs[n] += u[n, 0] * Aig[f, 0] + u[n, 1] * Aig[f, 1] + u[n, 2] * Aig[f, 2]
                    for m in range(N):
                        Sm[n, m] -= (u[n, 0] * W[f, m, 0] + u[n, 1] * W[f, m, 1]
                                     + u[n, 2] * W[f, m, 2])
            dr = np.linalg.solve(Sm, rhs)
            for f in range(F):
                for k in range(3):
                    s = -Aig[f, k]
                    for n in range(N):
                        s -= W[f, n, k] * dr[n]
                    c2[f, k] = cb[f, k] + s
            for n in range(N):
                r2[n] = rb[n] + dr[n]
            ssr2 = _residuals(Xb, c2, r2, D2, d2, e2)
            if ssr2 < ssr:
                small = (ssr - ssr2 < rtol * ssr) or (ssr2 < atol2 * F * N)
                cb[:, :] = c2
                rb[:] = r2
                D[:, :, :] = D2
                d[:, :] = d2
                e[:, :] = e2
                ssr = ssr2
                lam = max(lam / 4, 1e-9)
                if small:
                    break
            else:
                lam *= 8
                if lam > 1e8:
                    break
        out[b] = ssr
    return out


def world_lm(X: np.ndarray, c: np.ndarray, r: np.ndarray, iters: int, rtol: float,
             atol_m: float):
    """Levenberg-Marquardt on ``sum (|x_fn - c_f| - r_n)^2`` from centres ``c`` and distances
    ``r``: X (F, N, 3), c (F, 3), r (N,) -> (c, r, ssr float); or batched, X (B, F, N, 3),
    c (B, F, 3), r (B, N) -> (c, r, ssr (B,)). The inputs are not modified."""
    X = np.asarray(X, np.float64)
    single = X.ndim == 3
    if X.ndim not in (3, 4) or X.shape[-1] != 3:
        raise ValueError(f"X.shape={X.shape}, expected (F, N, 3) or (B, F, N, 3)")
    if single:
        X, c, r = X[None], np.asarray(c)[None], np.asarray(r)[None]
    B, F, N = X.shape[:3]
    c = np.array(c, np.float64, order="C")
    r = np.array(r, np.float64, order="C")
    if c.shape != (B, F, 3) or r.shape != (B, N):
        raise ValueError(f"c.shape={c.shape}, r.shape={r.shape}, expected {(B, F, 3)}, "
                         f"{(B, N)} for X.shape={X.shape}")
    ssr = _world_lm_kernel(np.ascontiguousarray(X), c, r, int(iters), float(rtol),
                           float(atol_m) ** 2)
    if single:
        return c[0], r[0], float(ssr[0])
    return c, r, ssr


def warm_up() -> None:
    """Compiles the kernel, or loads it from the cache (~0.3 s), now: call before forking
    worker processes, which otherwise each load it on their first fit."""
    world_lm(np.ones((1, 4, 3)), np.zeros((1, 3)), np.ones(4), 1, 0.0, 0.0)

"""The star model's Levenberg-Marquardt (``skeleton.star_fit``), compiled.

``star_lm(X, seg, R, t, y, js, z, j0, pull_mm, max_iter, tol, stop_var)`` refines, in place,
a star of K members around a hub: per frame f the hub's rotation ``R[0, f]`` and translation
``t[f]`` and member k's rotation ``R[k + 1, f]``; over all frames the hub's marker offsets
``y``, the joints ``js`` in the hub's frame and the members' marker offsets ``z`` from their
joints. Marker m of the hub is modelled at ``R0 y_m + t``, marker q of member k at
``R_k z_q + t + R0 j_k``; ``X`` (F, N, 3) holds the hub's markers first, then each member's
(``seg``: 0 for the hub's, k + 1 for member k's). Rotations change by left increments
(Rodrigues); the normal equations are reduced to the global parameters by the Schur
complement of the per-frame blocks (bundle adjustment's structure); the first frame's pose
parameters stay at their start (the gauge); each joint is pulled towards ``j0`` with weight
``1 / pull_mm^2``. Damping is Marquardt's plus 1e-9 x the mean diagonal; a step is taken
only when it lowers the sum of squares (damping x10 otherwise, giving up above 1e8); the
fit stops when an accepted step lowers it by less than ``max(tol x ssq, stop_var x ssq / n)``.
Units are the caller's (``skeleton.star_fit`` works in mm).

Returns (status, ssq of the data alone, iterations); status 0: done, 1: the damping ran
out (the state is the last accepted one), 2: a normal-equation block was not positive
definite or a step not finite.

Why compiled (numba): per iteration the NumPy version assembled the Jacobian block by block
(~40 small array operations per marker group) and solved per-frame systems as batched LAPACK
calls; at 600 frames a star took ~0.15-0.5 s. The loops below assemble each frame's
normal-equation blocks directly (``benchmarks/bench_star_fit.py``).
Conventions: docs/conventions.md [arrays], [rotations].
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["star_lm", "warm_up"]


@njit(cache=True)
def _cholesky(A, L):
    """A = L L^T (A symmetric positive definite, n x n) into L; False when A is not."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i + 1):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            if i == j:
                if not s > 0.0:
                    return False
                L[i, i] = np.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    return True


@njit(cache=True)
def _cholesky_solve(A, B, L):
    """Solves A X = B (A symmetric positive definite, n x n; B n x m) by Cholesky into B;
    L is scratch (n x n). Returns False when A is not positive definite."""
    if not _cholesky(A, L):
        return False
    n = A.shape[0]
    m = B.shape[1]
    for c in range(m):
        for i in range(n):
            s = B[i, c]
            for k in range(i):
                s -= L[i, k] * B[k, c]
            B[i, c] = s / L[i, i]
        for i in range(n - 1, -1, -1):
            s = B[i, c]
            for k in range(i + 1, n):
                s -= L[k, i] * B[k, c]
            B[i, c] = s / L[i, i]
    return True


@njit(cache=True)
def _rotate_left(R, w):
    """R <- Rodrigues(w) R in place (3 x 3)."""
    th = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    if th <= 1e-12:
        return
    kx, ky, kz = w[0] / th, w[1] / th, w[2] / th
    s, c = np.sin(th), 1.0 - np.cos(th)
    Q = np.empty((3, 3))
    Q[0, 0] = 1.0 - c * (ky * ky + kz * kz)
    Q[0, 1] = -s * kz + c * kx * ky
    Q[0, 2] = s * ky + c * kx * kz
    Q[1, 0] = s * kz + c * kx * ky
    Q[1, 1] = 1.0 - c * (kx * kx + kz * kz)
    Q[1, 2] = -s * kx + c * ky * kz
    Q[2, 0] = -s * ky + c * kx * kz
    Q[2, 1] = s * kx + c * ky * kz
    Q[2, 2] = 1.0 - c * (kx * kx + ky * ky)
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = Q[i, 0] * R[0, j] + Q[i, 1] * R[1, j] + Q[i, 2] * R[2, j]
    R[:, :] = out


@njit(cache=True)
def _residuals(X, seg, R, t, y, js, z, r):
    """r (F, N, 3) = model - X; returns sum r^2."""
    F, N = X.shape[0], X.shape[1]
    n0 = y.shape[0]
    s = 0.0
    for f in range(F):
        for m in range(N):
            k = seg[m]
            for i in range(3):
                if k == 0:
                    v = R[0, f, i, 0] * y[m, 0] + R[0, f, i, 1] * y[m, 1] + R[0, f, i, 2] * y[m, 2]
                else:
                    q = m - n0
                    j = js[k - 1]
                    v = (R[k, f, i, 0] * z[q, 0] + R[k, f, i, 1] * z[q, 1]
                         + R[k, f, i, 2] * z[q, 2]
                         + R[0, f, i, 0] * j[0] + R[0, f, i, 1] * j[1] + R[0, f, i, 2] * j[2])
                e = v + t[f, i] - X[f, m, i]
                r[f, m, i] = e
                s += e * e
    return s


@njit(cache=True)
def _frame_jacobian(f, seg, R, y, js, z, n_fr, n_y, K, Jf, Jg, gcol):
    """Frame f's Jacobian: Jf (3N, n_fr) own parameters, Jg (3N, 6) the nonzero global
    columns of each residual row (gcol (3N, 6) their indices, -1 unused)."""
    N = seg.shape[0]
    n0 = y.shape[0]
    Jf[:, :] = 0.0
    for m in range(N):
        k = seg[m]
        if k == 0:
            p0 = R[0, f, 0, 0] * y[m, 0] + R[0, f, 0, 1] * y[m, 1] + R[0, f, 0, 2] * y[m, 2]
            p1 = R[0, f, 1, 0] * y[m, 0] + R[0, f, 1, 1] * y[m, 1] + R[0, f, 1, 2] * y[m, 2]
            p2 = R[0, f, 2, 0] * y[m, 0] + R[0, f, 2, 1] * y[m, 1] + R[0, f, 2, 2] * y[m, 2]
        else:
            j = js[k - 1]
            p0 = R[0, f, 0, 0] * j[0] + R[0, f, 0, 1] * j[1] + R[0, f, 0, 2] * j[2]
            p1 = R[0, f, 1, 0] * j[0] + R[0, f, 1, 1] * j[1] + R[0, f, 1, 2] * j[2]
            p2 = R[0, f, 2, 0] * j[0] + R[0, f, 2, 1] * j[1] + R[0, f, 2, 2] * j[2]
        row = 3 * m
        # hub rotation: -skew(p); translation: identity
        Jf[row + 0, 1] = p2
        Jf[row + 0, 2] = -p1
        Jf[row + 1, 0] = -p2
        Jf[row + 1, 2] = p0
        Jf[row + 2, 0] = p1
        Jf[row + 2, 1] = -p0
        Jf[row + 0, 3] = 1.0
        Jf[row + 1, 4] = 1.0
        Jf[row + 2, 5] = 1.0
        for i in range(3):
            for c in range(6):
                gcol[row + i, c] = -1
                Jg[row + i, c] = 0.0
        if k == 0:
            for i in range(3):
                for c in range(3):
                    Jg[row + i, c] = R[0, f, i, c]
                    gcol[row + i, c] = 3 * m + c
        else:
            q = m - n0
            w0 = R[k, f, 0, 0] * z[q, 0] + R[k, f, 0, 1] * z[q, 1] + R[k, f, 0, 2] * z[q, 2]
            w1 = R[k, f, 1, 0] * z[q, 0] + R[k, f, 1, 1] * z[q, 1] + R[k, f, 1, 2] * z[q, 2]
            w2 = R[k, f, 2, 0] * z[q, 0] + R[k, f, 2, 1] * z[q, 1] + R[k, f, 2, 2] * z[q, 2]
            c0 = 6 + 3 * (k - 1)
            Jf[row + 0, c0 + 1] = w2
            Jf[row + 0, c0 + 2] = -w1
            Jf[row + 1, c0 + 0] = -w2
            Jf[row + 1, c0 + 2] = w0
            Jf[row + 2, c0 + 0] = w1
            Jf[row + 2, c0 + 1] = -w0
            for i in range(3):
                for c in range(3):
                    Jg[row + i, c] = R[0, f, i, c]                  # the joint
                    gcol[row + i, c] = n_y + 3 * (k - 1) + c
                    Jg[row + i, 3 + c] = R[k, f, i, c]              # the marker offset
                    gcol[row + i, 3 + c] = n_y + 3 * K + 3 * q + c
    if f == 0:      # gauge: the first frame's pose parameters stay at their start
        Jf[:, :] = 0.0


@njit(cache=True)
def star_lm(X, seg, R, t, y, js, z, j0, pull_mm, max_iter, tol, stop_var):
    F, N = X.shape[0], X.shape[1]
    K = js.shape[0]
    n_y = 3 * y.shape[0]
    n_fr = 6 + 3 * K
    n_g = n_y + 3 * K + 3 * z.shape[0]
    n_res = 3 * N * F
    w_pull = 1.0 / (pull_mm * pull_mm)
    r = np.empty((F, N, 3))
    r_new = np.empty((F, N, 3))
    Jf = np.empty((3 * N, n_fr))
    Jg = np.empty((3 * N, 6))
    gcol = np.empty((3 * N, 6), np.int64)
    U = np.empty((F, n_fr, n_fr))
    W = np.empty((F, n_fr, n_g))
    ef = np.empty((F, n_fr))
    V = np.empty((n_g, n_g))
    eg = np.empty(n_g)
    Ud = np.empty((n_fr, n_fr))
    Lf = np.empty((F, n_fr, n_fr))          # Cholesky factors of the damped frame blocks
    M = np.empty((F * n_fr, n_g))           # L_f^-1 W_f, stacked
    mv = np.empty(F * n_fr)                 # L_f^-1 ef_f, stacked
    Sc = np.empty((n_g, n_g))
    Lg = np.empty((n_g, n_g))
    bg = np.empty((n_g, 1))
    df = np.empty((F, n_fr))
    R_old = R.copy()
    t_old = t.copy()
    y_old = y.copy()
    js_old = js.copy()
    z_old = z.copy()

    def prior(js):
        s = 0.0
        for k in range(K):
            for i in range(3):
                d = (js[k, i] - j0[k, i]) / pull_mm
                s += d * d
        return s

    data = _residuals(X, seg, R, t, y, js, z, r)
    ssq = data + prior(js)
    lam = 1e-4
    it = 0
    for it in range(1, max_iter + 1):
        # normal equations
        V[:, :] = 0.0
        eg[:] = 0.0
        diag_sum = 0.0
        for f in range(F):
            _frame_jacobian(f, seg, R, y, js, z, n_fr, n_y, K, Jf, Jg, gcol)
            for a in range(n_fr):
                s = 0.0
                for row in range(3 * N):
                    s += Jf[row, a] * r[f, row // 3, row % 3]
                ef[f, a] = s
                for b in range(n_fr):
                    s = 0.0
                    for row in range(3 * N):
                        s += Jf[row, a] * Jf[row, b]
                    U[f, a, b] = s
                diag_sum += U[f, a, a]
            W[f, :, :] = 0.0
            for row in range(3 * N):
                e = r[f, row // 3, row % 3]
                for c in range(6):
                    g = gcol[row, c]
                    if g < 0:
                        continue
                    v = Jg[row, c]
                    eg[g] += v * e
                    for a in range(n_fr):
                        W[f, a, g] += Jf[row, a] * v
                    for c2 in range(6):
                        g2 = gcol[row, c2]
                        if g2 >= 0:
                            V[g, g2] += v * Jg[row, c2]
        for k in range(3 * K):
            V[n_y + k, n_y + k] += w_pull
            eg[n_y + k] += (js[k // 3, k % 3] - j0[k // 3, k % 3]) * w_pull
        for g in range(n_g):
            diag_sum += V[g, g]
        scale = diag_sum / (F * n_fr + n_g)
        while True:
            # damped normal equations by the Schur complement on the global parameters:
            # (U + D) df + W dg = -ef, W^T df + (V + D) dg = -eg
            for i in range(n_g):
                for j in range(n_g):
                    Sc[i, j] = V[i, j]
                Sc[i, i] += lam * (V[i, i] + 1e-9 * scale)
                bg[i, 0] = -eg[i]
            # per frame: Ud_f = L L^T; M_f = L^-1 W_f, m_f = L^-1 ef_f; then
            # W^T Ud^-1 W = M^T M and W^T Ud^-1 ef = M^T m over all frames (one product)
            ok = True
            for f in range(F):
                for a in range(n_fr):
                    for b in range(n_fr):
                        Ud[a, b] = U[f, a, b]
                    Ud[a, a] += lam * (U[f, a, a] + 1e-9 * scale)
                if not _cholesky(Ud, Lf[f]):
                    ok = False
                    break
                base = f * n_fr
                for a in range(n_fr):
                    la = Lf[f, a, a]
                    for g in range(n_g):
                        s = W[f, a, g]
                        for k in range(a):
                            s -= Lf[f, a, k] * M[base + k, g]
                        M[base + a, g] = s / la
                    s = ef[f, a]
                    for k in range(a):
                        s -= Lf[f, a, k] * mv[base + k]
                    mv[base + a] = s / la
            if not ok:
                return 2, data, it
            Sc -= np.dot(M.T, M)
            corr = np.dot(M.T, mv)
            for g in range(n_g):
                bg[g, 0] += corr[g]
            if not _cholesky_solve(Sc, bg, Lg):
                return 2, data, it
            # df_f = -Ud_f^-1 (ef_f + W_f dg) = -L^-T (m_f + M_f dg)
            finite = True
            for f in range(F):
                base = f * n_fr
                for a in range(n_fr):
                    s = mv[base + a]
                    for g in range(n_g):
                        s += M[base + a, g] * bg[g, 0]
                    df[f, a] = s
                for a in range(n_fr - 1, -1, -1):
                    s = df[f, a]
                    for k in range(a + 1, n_fr):
                        s -= Lf[f, k, a] * df[f, k]
                    df[f, a] = s / Lf[f, a, a]
                for a in range(n_fr):
                    df[f, a] = -df[f, a]
                    if not np.isfinite(df[f, a]):
                        finite = False
            for g in range(n_g):
                if not np.isfinite(bg[g, 0]):
                    finite = False
            if not finite:
                return 2, data, it
            # the step (rotations by left increments), the old state kept
            R_old[:] = R
            t_old[:] = t
            y_old[:] = y
            js_old[:] = js
            z_old[:] = z
            for f in range(F):
                _rotate_left(R[0, f], df[f, 0:3])
                for i in range(3):
                    t[f, i] += df[f, 3 + i]
                for k in range(K):
                    _rotate_left(R[k + 1, f], df[f, 6 + 3 * k:9 + 3 * k])
            for g in range(n_y):
                y[g // 3, g % 3] += bg[g, 0]
            for g in range(3 * K):
                js[g // 3, g % 3] += bg[n_y + g, 0]
            for g in range(3 * z.shape[0]):
                z[g // 3, g % 3] += bg[n_y + 3 * K + g, 0]
            data_new = _residuals(X, seg, R, t, y, js, z, r_new)
            s_new = data_new + prior(js)
            if s_new < ssq:
                break
            R[:] = R_old
            t[:] = t_old
            y[:] = y_old
            js[:] = js_old
            z[:] = z_old
            lam *= 10.0
            if lam > 1e8:
                return 1, data, it
        done = ssq - s_new < max(tol * ssq, stop_var * s_new / n_res)
        r[:] = r_new
        ssq = s_new
        data = data_new
        lam = max(lam / 3.0, 1e-9)
        if done:
            break
    return 0, data, it


def warm_up() -> None:
    """Compiles the kernel, or loads it from the cache, now (on a two-frame star)."""
    g = np.random.default_rng(0)
    R = np.broadcast_to(np.eye(3), (2, 2, 3, 3)).copy()
    star_lm(g.normal(size=(2, 2, 3)), np.array([0, 1], np.int64), R, np.zeros((2, 3)),
            np.ones((1, 3)), np.ones((1, 3)), np.ones((1, 3)), np.ones((1, 3)), 20.0, 1,
            0.0, 0.0)

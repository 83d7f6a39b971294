"""The 2+2 world-frame Levenberg-Marquardt: compiled (skeleton.world_lm) against the
vectorised NumPy version it replaced (stop 22's ``skeleton.joints._world_lm``, kept below as
the named baseline), on the problem shapes the skeleton solver runs (batch x frames: 1 x 200
at 30 and 100 iterations, 4 x 67, 18 x 20 and 66 x 20 at 25 iterations), with 1 mm marker
noise and starts 10 mm off.

Usage: python benchmarks/bench_world_lm.py [repeats=20]
Prints per shape: seconds per call of each, the ratio, and the largest relative difference
of their sums of squares (both stop on a relative decrease below 1e-7, so converged sums
agree to about that).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from skeleton.joints import LM_ATOL_M, LM_RTOL  # noqa: E402
from skeleton.world_lm import world_lm  # noqa: E402

SHAPES = ((1, 200, 30), (1, 200, 100), (4, 67, 25), (18, 20, 25), (66, 20, 25))


def _inv3_sym(A):
    a, b, c = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    d, e, f = A[..., 1, 1], A[..., 1, 2], A[..., 2, 2]
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * c00 + b * c01 + c * c02
    out = np.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], -1)
    return (out / det[..., None]).reshape(A.shape)


def numpy_world_lm(X, c, r, iters):
    """Baseline: stop 22's vectorised NumPy Levenberg-Marquardt (same algorithm)."""
    X, c, r = np.asarray(X, float), np.array(c, float), np.array(r, float)
    B, F, N = X.shape[:3]

    def resid(c, r):
        D = X - c[:, :, None]
        d = np.sqrt(np.einsum("bfni,bfni->bfn", D, D))
        return D, d, d - r[:, None]

    D, d, e = resid(c, r)
    ssr = (e**2).sum((1, 2))
    lam = np.full(B, 1e-3)
    live = np.ones(B, bool)
    eye = np.eye(3)
    for _ in range(iters):
        u = D / np.maximum(d, 1e-12)[..., None]
        ut = np.swapaxes(u, 2, 3)
        A = ut @ u
        gc = -(ut @ e[..., None])[..., 0]
        gr = -e.sum(1)
        Ad = A + lam[:, None, None, None] * (A * eye).sum(3)[..., None] * eye + 1e-12 * eye
        Ainv = _inv3_sym(Ad)
        AiB = Ainv @ ut
        Sm = ((1 + lam) * F)[:, None, None] * np.eye(N) - (u @ AiB).sum(1)
        Aig = (Ainv @ gc[..., None])[..., 0]
        rhs = -gr + (u @ Aig[..., None])[..., 0].sum(1)
        dr = np.linalg.solve(Sm, rhs[..., None])[..., 0]
        dc = -Aig - (AiB @ dr[:, None, :, None])[..., 0]
        D2, d2, e2 = resid(c + dc, r + dr)
        ssr2 = (e2**2).sum((1, 2))
        acc = live & (ssr2 < ssr)
        small = acc & ((ssr - ssr2 < LM_RTOL * ssr) | (ssr2 < (LM_ATOL_M**2) * F * N))
        c[acc] += dc[acc]
        r[acc] += dr[acc]
        D[acc], d[acc], e[acc], ssr[acc] = D2[acc], d2[acc], e2[acc], ssr2[acc]
        lam = np.where(acc, np.maximum(lam / 4, 1e-9), lam * 8)
        live &= ~small & (lam <= 1e8)
        if not live.any():
            break
    return c, r, ssr


def problems(B, F, seed):
    g = np.random.default_rng(seed)
    c = np.cumsum(g.normal(0, 0.005, (B, F, 3)), 1) + [0.1, 0.2, 1.0]
    r = g.uniform(0.05, 0.3, (B, 4))
    v = g.normal(size=(B, F, 4, 3))
    v /= np.linalg.norm(v, axis=3, keepdims=True)
    X = c[:, :, None] + r[:, None, :, None] * v + g.normal(0, 0.001, (B, F, 4, 3))
    return X, c + g.normal(0, 0.01, c.shape), r + g.normal(0, 0.01, r.shape)


def main(repeats: int = 20) -> None:
    t0 = time.perf_counter()
    world_lm(*problems(1, 20, 0), 5, LM_RTOL, LM_ATOL_M)
    print(f"first call (compile, or load from the cache): {time.perf_counter() - t0:.2f} s")
    tot_np = tot_nb = 0.0
    for B, F, iters in SHAPES:
        probs = [problems(B, F, s) for s in range(repeats)]
        t = time.perf_counter()
        ref = [numpy_world_lm(X, c, r, iters)[2] for X, c, r in probs]
        t_np = (time.perf_counter() - t) / repeats
        t = time.perf_counter()
        new = [world_lm(X, c, r, iters, LM_RTOL, LM_ATOL_M)[2] for X, c, r in probs]
        t_nb = (time.perf_counter() - t) / repeats
        dev = max(float(np.max(np.abs(a - b) / b)) for a, b in zip(new, ref))
        tot_np, tot_nb = tot_np + t_np, tot_nb + t_nb
        print(f"batch {B:2d} x {F:3d} frames, {iters:3d} iterations: NumPy {t_np * 1e3:7.2f} ms, "
              f"compiled {t_nb * 1e3:6.2f} ms (ratio {t_nb / t_np:.3f}); largest relative "
              f"difference of the sums of squares {dev:.1e}")
    print(f"all shapes: compiled / NumPy = {tot_nb / tot_np:.3f}")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:2]))

"""Least-squares rigid alignment (Horn's quaternion solution of absolute orientation),
batched over frames and compiled.

``kabsch(src (T, N, 3), dst (N, 3)) -> (R (T, 3, 3), t (T, 3))`` with ``dst ~ R @ src + t``.
Per frame, the cross-covariance S of the centred points gives Horn's symmetric 4x4 matrix;
its eigenvector of the largest eigenvalue is the unit quaternion of the best proper
rotation (the same rotation as Kabsch's SVD with the det = +1 fix). The eigenvector comes
from cyclic Jacobi rotations, to machine precision.

Why compiled (numba): the skeleton solver aligns a segment over every frame in each of ~100
joint fits per figure; NumPy's batched 3x3 SVD, determinants and einsums took ~13 ms per
1500 frames, this loop ~2.3 ms (``benchmarks/bench_kabsch.py``), with rotations equal to
1e-14. A frame with a NaN coordinate gets a NaN rotation and translation.
Conventions: docs/conventions.md [rotations], [arrays].
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["kabsch", "kabsch_svd"]

JACOBI_SWEEPS = 30       # a 4x4 converges in 4-6; NaN input runs them all


@njit(cache=True, error_model="numpy")
def _top_eigvec4(N, V, q):
    """The unit eigenvector of the largest eigenvalue of the symmetric 4x4 ``N`` into ``q``
    (cyclic Jacobi; N and the work matrix V are overwritten)."""
    for i in range(4):
        for j in range(4):
            V[i, j] = 1.0 if i == j else 0.0
    for _ in range(JACOBI_SWEEPS):
        off = 0.0
        tot = 0.0
        for i in range(4):
            for j in range(4):
                v = N[i, j] * N[i, j]
                tot += v
                if i != j:
                    off += v
        if off <= 1e-30 * tot:
            break
        small = 1e-16 * np.sqrt(tot)    # an element this small is rounding: zeroed (else
        for p in range(3):              # planar point sets, whose N has eigenvalue pairs,
            for r in range(p + 1, 4):   # kept recreating it and ran every sweep)
                apr = N[p, r]
                if abs(apr) <= small:
                    N[p, r] = 0.0
                    N[r, p] = 0.0
                    continue
                theta = (N[r, r] - N[p, p]) / (2.0 * apr)
                t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(4):
                    akp = N[k, p]
                    akr = N[k, r]
                    N[k, p] = c * akp - s * akr
                    N[k, r] = s * akp + c * akr
                for k in range(4):
                    apk = N[p, k]
                    ark = N[r, k]
                    N[p, k] = c * apk - s * ark
                    N[r, k] = s * apk + c * ark
                for k in range(4):
                    vkp = V[k, p]
                    vkr = V[k, r]
                    V[k, p] = c * vkp - s * vkr
                    V[k, r] = s * vkp + c * vkr
    best = 0
    for i in range(1, 4):
        if N[i, i] > N[best, best]:
            best = i
    for k in range(4):
        q[k] = V[k, best]


@njit(cache=True, error_model="numpy")
def _kabsch_kernel(src, dst, R, t):
    """src (T, N, 3), dst (N, 3) -> R (T, 3, 3), t (T, 3) filled in place."""
    T, M = src.shape[0], src.shape[1]
    cd = np.zeros(3)
    for m in range(M):
        for i in range(3):
            cd[i] += dst[m, i]
    for i in range(3):
        cd[i] /= M
    S = np.empty((3, 3))
    N = np.empty((4, 4))
    V = np.empty((4, 4))
    q = np.empty(4)
    cs = np.empty(3)
    for f in range(T):
        for i in range(3):
            acc = 0.0
            for m in range(M):
                acc += src[f, m, i]
            cs[i] = acc / M
        for i in range(3):
            for j in range(3):
                S[i, j] = 0.0
        for m in range(M):
            for i in range(3):
                a = src[f, m, i] - cs[i]
                for j in range(3):
                    S[i, j] += a * (dst[m, j] - cd[j])
        sxx, sxy, sxz = S[0, 0], S[0, 1], S[0, 2]
        syx, syy, syz = S[1, 0], S[1, 1], S[1, 2]
        szx, szy, szz = S[2, 0], S[2, 1], S[2, 2]
        N[0, 0] = sxx + syy + szz
        N[0, 1] = N[1, 0] = syz - szy
        N[0, 2] = N[2, 0] = szx - sxz
        N[0, 3] = N[3, 0] = sxy - syx
        N[1, 1] = sxx - syy - szz
        N[1, 2] = N[2, 1] = sxy + syx
        N[1, 3] = N[3, 1] = szx + sxz
        N[2, 2] = -sxx + syy - szz
        N[2, 3] = N[3, 2] = syz + szy
        N[3, 3] = -sxx - syy + szz
        _top_eigvec4(N, V, q)
        w, x, y, z = q[0], q[1], q[2], q[3]
        R[f, 0, 0] = w * w + x * x - y * y - z * z
        R[f, 0, 1] = 2.0 * (x * y - w * z)
        R[f, 0, 2] = 2.0 * (x * z + w * y)
        R[f, 1, 0] = 2.0 * (x * y + w * z)
        R[f, 1, 1] = w * w - x * x + y * y - z * z
        R[f, 1, 2] = 2.0 * (y * z - w * x)
        R[f, 2, 0] = 2.0 * (x * z - w * y)
        R[f, 2, 1] = 2.0 * (y * z + w * x)
        R[f, 2, 2] = w * w - x * x - y * y + z * z
        for i in range(3):
            t[f, i] = cd[i] - (R[f, i, 0] * cs[0] + R[f, i, 1] * cs[1] + R[f, i, 2] * cs[2])


def _check(src, dst):
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    if src.ndim != 3 or src.shape[2] != 3 or dst.shape != src.shape[1:]:
        raise ValueError(f"src.shape={src.shape}, dst.shape={dst.shape}, expected (T,N,3),(N,3)")
    return src, dst


def kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation per frame mapping ``src[t]`` onto ``dst`` (least squares)."""
    src, dst = _check(src, dst)
    T = src.shape[0]
    R = np.empty((T, 3, 3))
    t = np.empty((T, 3))
    _kabsch_kernel(np.ascontiguousarray(src), np.ascontiguousarray(dst), R, t)
    return R, t


def kabsch_svd(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``kabsch`` by NumPy's batched SVD with the det = +1 fix (the solver's until stop 24:
    the reference of the tests and of ``benchmarks/bench_kabsch.py``)."""
    src, dst = _check(src, dst)
    cs = src.mean(1)
    cd = dst.mean(0)
    H = np.einsum("tni,nj->tij", src - cs[:, None], dst - cd)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("tij,tjk->tik", U, Vt)))
    D = np.zeros((src.shape[0], 3, 3))
    D[:, 0, 0] = 1
    D[:, 1, 1] = 1
    D[:, 2, 2] = d
    R = np.einsum("tji,tjk,tlk->til", Vt, D, U)
    t = cd - np.einsum("tij,tj->ti", R, cs)
    return R, t


def warm_up() -> None:
    """Compiles the kernel, or loads it from the cache, now (before forking workers)."""
    kabsch(np.eye(3)[None], np.eye(3))

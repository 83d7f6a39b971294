"""Rigid alignment per frame: the compiled Horn quaternion solution (``skeleton.rigid.kabsch``)
against NumPy's batched SVD it replaced (``skeleton.rigid.kabsch_svd``, the named baseline),
on the skeleton solver's shapes: a segment of 3, 4 or 5 markers (plus an anchor point) over
200 frames (a pair's topology cost) and 1500 frames (the tree's joint fits in the thesis'
largest case), with 1 mm marker noise.

Usage: python benchmarks/bench_kabsch.py [repeats=30]
Prints per shape: milliseconds per call of each, the ratio, and the largest difference of
their rotations and translations.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from skeleton.rigid import kabsch, kabsch_svd  # noqa: E402

SHAPES = ((200, 3), (200, 4), (1500, 3), (1500, 4), (1500, 5))


def problem(T: int, N: int, seed: int):
    g = np.random.default_rng(seed)
    P = g.normal(0, 0.08, (N, 3))
    R = Rotation.random(T, random_state=seed).as_matrix()
    src = np.einsum("tij,nj->tni", R, P) + g.normal(0, 0.5, (T, 1, 3))
    return src + g.normal(0, 1e-3, src.shape), P


def main(repeats: int = 30) -> None:
    t0 = time.perf_counter()
    kabsch(*problem(2, 3, 0))
    print(f"first call (compile, or load from the cache): {time.perf_counter() - t0:.2f} s")
    tot_svd = tot_horn = 0.0
    for T, N in SHAPES:
        probs = [problem(T, N, s) for s in range(repeats)]
        t = time.perf_counter()
        ref = [kabsch_svd(*p) for p in probs]
        t_svd = (time.perf_counter() - t) / repeats
        t = time.perf_counter()
        new = [kabsch(*p) for p in probs]
        t_horn = (time.perf_counter() - t) / repeats
        dR = max(float(np.abs(a[0] - b[0]).max()) for a, b in zip(new, ref))
        dt = max(float(np.abs(a[1] - b[1]).max()) for a, b in zip(new, ref))
        tot_svd, tot_horn = tot_svd + t_svd, tot_horn + t_horn
        print(f"{T:5d} frames x {N} markers: SVD {t_svd * 1e3:6.2f} ms, compiled Horn "
              f"{t_horn * 1e3:5.2f} ms (ratio {t_horn / t_svd:.3f}); largest difference: "
              f"rotation {dR:.1e}, translation {dt:.1e} m")
    print(f"all shapes: compiled / SVD = {tot_horn / tot_svd:.3f}")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:2]))

"""Acceptance (issue 6, point 6): 50 seeded random figures, topology and joint centres.

hw_sim random trees of 5-20 segments, 2-4 markers per segment, 45-90 degrees range of motion
per joint, 600 frames at 120 Hz (the figures of benchmarks/bench_skeleton.py). Slow (minutes).
"""
from __future__ import annotations

import numpy as np
import pytest

from skeleton.pipeline import solve_skeleton
from tests.skeleton._figures import (bench_figure, exact_topology, segment_map,
                                     solver_joint_errors, topology_equivalent)

N_FIGURES = 50
NOISE_M = 1e-3
MIN_EXACT = 49              # topology exactly right (issue 6, point 6)
MEDIAN_CLEAN_M = 0.5e-3     # median joint-centre error, noise-free
MEDIAN_NOISY_M = 3e-3       # median joint-centre error, 1 mm marker noise
EQUIV_TOL_FACTOR = 3.0      # equivalence metric: coincident joints within 3x the median error


def figures():
    for k in range(N_FIGURES):
        yield (k, *bench_figure(1000 + k))


def evaluate(fig, mo, res):
    """(topology exactly right, per-joint median centre errors m; hinges perpendicular)."""
    if not exact_topology(fig, res):
        return False, []
    return True, list(solver_joint_errors(fig, mo, res, segment_map(fig, res.labels)))


@pytest.mark.slow
def test_fifty_random_figures_noise_free():
    """The targets (>= 49/50, median <= 0.5 mm) and what this code measures: 50/50 exact,
    median joint error 8e-13 m (noise-free joints are exact up to rounding)."""
    exact, errs = 0, []
    for k, fig, mo in figures():
        ok, e = evaluate(fig, mo, solve_skeleton(mo.markers, mo.rate_hz, rng=0))
        exact += ok
        errs += e
    assert exact >= MIN_EXACT and np.median(errs) <= MEDIAN_CLEAN_M
    assert exact == N_FIGURES and np.median(errs) < 1e-6


@pytest.mark.slow
def test_fifty_random_figures_noisy():
    """1 mm noise: the joint-centre median bound (over figures whose topology is right) and
    the exact-topology target. Measured on this code: 49/50 exact (figure 4 fails: siblings
    whose joints on the parent lie within the noise; skeleton.junctions picks the hub by a
    motion prior), median joint error 0.76 mm. The count of solved trees kinematically
    equivalent to the truth (``topology_equivalent``: edges differ only inside a group of
    sibling joints within 3x the median joint error) is printed, not asserted."""
    errs, exact, kept = [], 0, []
    for k, fig, mo in figures():
        noisy = mo.markers + np.random.default_rng(k).normal(0, NOISE_M, mo.markers.shape)
        res = solve_skeleton(noisy, mo.rate_hz, rng=0)
        ok, e = evaluate(fig, mo, res)
        exact += ok
        errs += e
        kept.append((fig, mo, res))
    assert np.median(errs) <= MEDIAN_NOISY_M
    tol = EQUIV_TOL_FACTOR * float(np.median(errs))
    equiv = sum(topology_equivalent(f, m, r, tol) for f, m, r in kept)
    print(f"noisy topology exact on {exact}/{N_FIGURES}, kinematically equivalent within "
          f"{tol * 1e3:.2f} mm on {equiv}/{N_FIGURES}")
    assert exact >= MIN_EXACT

"""Skeleton solver on the real marker recordings of ../shared/data/c3d: the thesis' measure for
captured data (mean deviation between measured and fitted markers after the fit back), with
the star-likelihood rules (skeleton.junctions' star margin, skeleton.relink) and without them
(``star_margin=inf``) in the same run, and each tree as marker names per segment.

Usage: python benchmarks/bench_real_skeleton.py [names=arm_4-2-3_markers_120fps,cmu_85_02,...]
(file stems under ../shared/data/c3d; default: every full-body recording and the arm).
Skips with a message when ../shared/data is absent. There is no ground truth for these:
the deviation measures how well the solved skeleton explains the markers, and the trees are
printed for a reader to judge against the marker names (CMU's 41-marker set, kineticstoolkit's
OptiTrack recordings).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reconstruct.marker_files import read_markers  # noqa: E402
from skeleton.app import run_skeleton  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "c3d"
DEFAULT = ("arm_4-2-3_markers_120fps,cmu_85_02,cmu_85_12,ktk_tennis_serve_optitrack,"
           "ktk_tennis_serve_with_gaps,ktk_basket_sprint")


def solve(path: Path, stars: bool):
    t0 = time.perf_counter()
    run = run_skeleton(read_markers(path), rng=0, star_margin=None if stars else np.inf)
    return run, time.perf_counter() - t0


def tree(run) -> str:
    res = run.result
    names = [str(n).split(":")[-1] for n in run.rigid.marker_names]
    segs = [" ".join(names[m] for m in np.flatnonzero(res.labels == s))
            for s in range(res.n_segments)]
    return "\n".join(f"    {s:2d} <- {int(res.parents[s]):2d}  {segs[s]}"
                     for s in range(res.n_segments))


def main(names=DEFAULT):
    if not DATA.is_dir():
        print(f"{DATA} not present: nothing to measure")
        return
    for name in str(names).split(","):
        path = DATA / f"{name}.c3d"
        out = {}
        for stars in (False, True):
            run, dt = solve(path, stars)
            out[stars] = run
            print(f"{name} {'with' if stars else 'without'} star rules: {run.result.n_segments} "
                  f"segments, mean marker deviation "
                  f"{1e3 * run.deviation.overall_mean_m:.3f} mm, {dt:.1f} s", flush=True)
        same = (out[False].result.parents == out[True].result.parents).all()
        print("  tree (segment <- parent, markers): " + ("unchanged" if same else
              "without:\n" + tree(out[False]) + "\n  with:") + "\n" + tree(out[True]),
              flush=True)


if __name__ == "__main__":
    main(*sys.argv[1:2])

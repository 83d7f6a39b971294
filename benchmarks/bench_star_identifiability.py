"""How far apart a junction's stars are on noise-free data: whether a failing figure's tree
is an identifiability limit or a solver error.

Usage: python benchmarks/bench_star_identifiability.py [cases=154035:1-15,158005:5-14,...]
(each case: a seed of benchmarks/bench_skeleton.py and two true siblings a-b). For the
parent and the two siblings, every candidate hub's star (``skeleton.star_fit``) is fitted to
the figure's noise-free markers, each joint started at the true joint of that member (the
fit moves it where its star wants it): the true star fits exactly, a wrong star by its model
misfit. That misfit, in units of the residual variance per residual the solver's stars reach
on the same figure at 1 mm noise (low-passed as the solver does), is the margin the true star
can be expected to win by (at most: from other starts a wrong star may fit better still) -
the star rules need ``skeleton.junctions.STAR_MARGIN`` (200).
Prints per case the markers per segment, each hub's noise-free sum of squares and RMS, and
the expected margin of the best wrong star.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from skeleton.pipeline import lowpass  # noqa: E402
from skeleton.star_fit import margin_unit, star_misfit  # noqa: E402
from tests.skeleton._figures import bench_figure  # noqa: E402

DEFAULT = ("154035:1-15,158005:5-14,161024:7-10,170010:1-4,174036:1-2,147028:5-13,"
           "145043:1-2,170025:2-5,162024:4-8")


def case(seed: int, a: int, b: int) -> None:
    fig, mo = bench_figure(seed)
    p = int(fig.parents[a])
    if p < 0 or int(fig.parents[b]) != p:
        raise SystemExit(f"seed {seed}: {a} and {b} are not siblings")
    grp = [p, a, b]
    members = [np.flatnonzero(fig.marker_segment == s) for s in range(fig.n_segments)]
    nm = [int(members[s].size) for s in grp]
    noisy = mo.markers + np.random.default_rng(seed % 1000).normal(0, 1e-3, mo.markers.shape)
    smooth = lowpass(noisy, mo.rate_hz)
    starts = {s: mo.joint_centres[:, s] for s in (a, b)}
    starts[p] = mo.joint_centres[:, a]       # a wrong hub's joint with p: start at p-a's
    out, unit = [], None
    for hub in grp:
        st = {m: starts[m] for m in grp if m != hub}
        clean = star_misfit(mo.markers, members, set(grp), hub, st)
        if hub == p:
            unit = margin_unit(star_misfit(smooth, members, set(grp), hub, st))
        out.append((hub, clean))
    wrong = min(f.ssq_m2 for h, f in out if h != p)
    print(f"seed {seed}: parent {p}, siblings {a}, {b}; markers {nm}; "
          + "; ".join(f"hub {h}{' (true)' if h == p else ''} {f.ssq_m2 * 1e6:.4f} mm^2 "
                      f"(RMS {np.sqrt(f.ssq_m2 / f.n_res) * 1e3:.4f} mm)" for h, f in out)
          + f"; 1 mm low-passed residual variance {unit * 1e6:.4f} mm^2: best wrong star's "
          f"expected margin {wrong / unit:.1f}x", flush=True)


def main(cases=DEFAULT):
    for c in str(cases).split(","):
        seed, pair = c.split(":")
        a, b = map(int, pair.split("-"))
        case(int(seed), a, b)


if __name__ == "__main__":
    main(*sys.argv[1:2])

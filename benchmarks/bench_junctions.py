"""Hub choice at three-way junctions (skeleton.junctions): how often each prior picks the
parent.

Usage: python benchmarks/bench_junctions.py [n_junctions=40] [noise_mm=1]
Each case: an hw_sim random_tree (8 segments) whose first parent with two children gets both
children's joints at one point; 600 frames at 120 Hz, 45-90 degrees range of motion, marker
noise, the 6 Hz low-pass of the solver; the junction centre is the truth. Prints how often
the parent is picked by (1) the least summed relative rotation (``relative_spread``, used
by the solver), (2) the marker centroid nearest the junction, (3) their normalised sum.
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hw_sim.articulated import animate, random_tree  # noqa: E402
from skeleton.junctions import relative_spread  # noqa: E402
from skeleton.pipeline import lowpass  # noqa: E402


def junction_figure(seed):
    for s in range(seed, seed + 200):
        fig = random_tree(8, (2, 4), rng=s)
        for p in range(fig.n_segments):
            ch = np.flatnonzero(fig.parents == p)
            if ch.size >= 2:
                off = np.array(fig.joint_offsets)
                off[ch[1]] = off[ch[0]]
                return dataclasses.replace(fig, joint_offsets=off), p, ch[0], ch[1]
    raise RuntimeError(f"no figure with two siblings from seed {seed}")


def main(n=40, noise_mm=1.0):
    hits = np.zeros(3, int)
    for k in range(n):
        fig, p, a, b = junction_figure(300 * k)
        g = np.random.default_rng(300 * k)
        mo = animate(fig, 600, rng=g, rom_deg=float(g.uniform(45, 90)))
        tr = lowpass(mo.markers + g.normal(0, noise_mm * 1e-3, mo.markers.shape), mo.rate_hz)
        members = [np.flatnonzero(fig.marker_segment == s) for s in range(fig.n_segments)]
        c, grp = mo.joint_centres[:, a], (p, a, b)
        sp = np.array([sum(relative_spread(tr, members[h], members[m], c) for m in grp
                           if m != h) for h in grp])
        rc = np.array([np.median(np.linalg.norm(tr[:, members[h]].mean(1) - c, axis=1))
                       for h in grp])
        hits += [np.argmin(sp) == 0, np.argmin(rc) == 0,
                 np.argmin(sp / sp.mean() + rc / rc.mean()) == 0]
    print(f"{n} junctions, {noise_mm:g} mm noise: parent picked by least relative rotation "
          f"{hits[0]}/{n}, nearest marker centroid {hits[1]}/{n}, normalised sum "
          f"{hits[2]}/{n}")


if __name__ == "__main__":
    main(*(float(a) if i else int(a) for i, a in enumerate(sys.argv[1:])))

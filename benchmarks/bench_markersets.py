"""Marker sets (skeleton/markersets/) on random simulated figures, with and without the
repairs (steps 4-12), and without step 12 (the model check) alone, in the same run.

Usage: python benchmarks/bench_markersets.py [first=0] [last=80] [n_frames=400]
Figures k in [first, last), exactly as bench_skeleton_outputs.py's marker-set part: random
tree (5-20 segments, 2-4 markers per segment, seed 1000 + k, 60 deg range of motion), 1 mm
noise, every trajectory cut at 1-3 occlusions of 3-40 frames into new ids plus 5 ghosts. A
figure is merged when every physical marker gets exactly one id and no id mixes two
markers. Counts per block of 40 figures: all, physical (every two markers of one segment
>= 20 mm apart, as in real marker sets: 14 mm markers cannot be closer) and the rest, never
dropped. Since commit 70ca108 hw_sim's random_tree keeps a segment's markers
``min_marker_spacing_m`` (20 mm by default) apart, so the rest is empty unless figures are
built with a smaller ``min_marker_spacing_m`` (random_tree takes up to 400 draws per marker;
with 60, figure 59 kept two markers 7.8 mm apart). Merge time: the
sum over the figures, and its ratio to the merge without the repair (``repair_swaps=False``:
steps 1-3 of skeleton/markersets/ only), and with to without step 12 (``rules.MODEL_CHECK``
False), and to stop 86's rules (without stop 87's ``CONTRAST_EXCHANGES``).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hw_sim.articulated import animate, random_tree  # noqa: E402
from skeleton.markersets import merge_fragments, rules  # noqa: E402
from tests.skeleton._figures import fragment, marker_spacing  # noqa: E402

# name: (merge_fragments keywords, skeleton.markersets.rules constants set for it)
VARIANTS = {"repair": ({}, {}), "no step 12": ({}, {"MODEL_CHECK": False}),
            "stop 86 rules": ({}, {"CONTRAST_EXCHANGES": False}),
            "no repair": ({"repair_swaps": False}, {})}


def one_figure(k, T=400):
    g = np.random.default_rng(1000 + k)
    fig = random_tree(int(g.integers(5, 21)), (2, 4), rng=1000 + k)
    mo = animate(fig, T, rng=1000 + k, rom_deg=60.0)
    X, owner = fragment(mo.markers + g.normal(0, 1e-3, mo.markers.shape), k,
                        n_gaps=(1, 4), gap_frames=(3, 40))
    r = {"k": k, "M": fig.n_markers, "F": X.shape[1], "spacing": marker_spacing(fig)}
    for name, (kw, consts) in VARIANTS.items():
        kept = {c: getattr(rules, c) for c in consts}
        for c, v in consts.items():
            setattr(rules, c, v)
        try:
            t0 = time.perf_counter()
            ms = merge_fragments(X, **kw)
            t_merge = time.perf_counter() - t0
        finally:
            for c, v in kept.items():
                setattr(rules, c, v)
        pure = all(len({owner[f] for f in grp}) == 1 for grp in ms.groups)
        one = sorted(owner[grp[0]] for grp in ms.groups) == list(range(fig.n_markers))
        r[name] = {"merged": pure and one, "pure": pure, "n": ms.n_markers, "t": t_merge}
    return r


def main(first=0, last=80, T=400):
    rows = []
    for k in range(first, last):
        r = one_figure(k, T)
        rows.append(r)
        print(f"fig {k}: M={r['M']:2d} fragments={r['F']:3d} spacing {1e3 * r['spacing']:5.1f} mm"
              + "".join(f" | {name}: merged={v['merged']!s:5} pure={v['pure']!s:5} ids={v['n']:2d}"
                        f" {v['t']:.2f}s" for name, v in ((n, r[n]) for n in VARIANTS)),
              flush=True)
    print()
    for lo in range(first, last, 40):
        block = [r for r in rows if lo <= r["k"] < min(lo + 40, last)]
        for lab, sel in (("all", lambda r: True),
                         ("physical (>= 20 mm)", lambda r: r["spacing"] >= 0.02),
                         ("markers < 20 mm apart", lambda r: r["spacing"] < 0.02)):
            b = [r for r in block if sel(r)]
            print(f"figures {lo}-{lo + len(block) - 1} {lab:22s}: "
                  + ", ".join(f"{name} {sum(r[name]['merged'] for r in b)}/{len(b)}"
                              for name in VARIANTS))
    t = {name: sum(r[name]["t"] for r in rows) for name in VARIANTS}
    print(f"merge time: repair {t['repair']:.1f} s, no repair {t['no repair']:.1f} s, "
          f"ratio {t['repair'] / t['no repair']:.2f}; without step 12 (MODEL_CHECK) "
          f"{t['no step 12']:.1f} s, ratio with it {t['repair'] / t['no step 12']:.2f}; "
          f"with stop 86's rules (CONTRAST_EXCHANGES off) "
          f"{t['stop 86 rules']:.1f} s, ratio {t['repair'] / t['stop 86 rules']:.2f}; "
          f"largest figure "
          f"({max(r['F'] for r in rows)} fragments) "
          f"{max(rows, key=lambda r: r['F'])['repair']['t']:.2f} s")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:4]))

"""Screen of the marker-set merge (issue 6, point 1) on the benchmark figures, one
``merge_fragments(X)`` per figure as ``bench_markersets.py`` builds them (``_bench_figure(k)``
of ``tests/skeleton/test_markersets.py``: seed 1000 + k, 400 frames, 1 mm noise, 1-3 gaps of
3-39 frames per marker, 5 ghosts).

A rule of steps 4-11 of ``skeleton/markersets/`` does not change what steps 1-3 (the
linkage, two thirds of the merge time) give, so their groups can be cached: with ``--cache
FILE`` (JSON lines, gzip where the name ends in .gz) a figure found there is resumed at step 4
(``skeleton.markersets._repairs_from``), and a figure not found there is merged in full and
its step-4 groups appended. The cache holds for as long as steps 1-3, ``hw_sim`` and the figure
builder are unchanged; ``--check`` merges cached figures in full too and reports any
difference (a stale cache).

``benchmarks/cache/markersets_step4.jsonl.gz`` (stop 65, steps 1-3 unchanged since e80e2f2)
holds figures 0-1737, 2146-3573, 3880-5917, 6400-7793, 9160-9185, 9521-28833, 29001-29221,
29401-33807, 34001-46725 and others named in the tests and the step
modules' docstrings (43,308; 17565-20318 added at stop 68, first runs of stops 66-68;
20319-21576 at stop 69,
21577-22280 at stop 70, 22281-22748 at stop 71, 22749-23257 at stop 72, 23258-24454 at stop 73,
24455-25353 at stop 74, 25354-26507 at stop 75, 26508-27727 at stop 76, 27728-28833 and
29001-29221 at stop 77, 29401-33000 at stop 78 (29401-30606: stop 77's last first runs),
33001-33807, 34001-34757 and 34761-35000 at stop 79, 34758-34760, 35001-37691 and
38001-38284 at stop 80, 37692-38000 and 38285-39428 at stop 81, 39429-41000 at stop 82,
41001-42470 at stop 83, 42471-43600 at stop 84, 43601-45100 at stop 85, 45101-46725 at stop 86; their first runs).

Usage: python benchmarks/screen_markersets.py FIGURES OUT [--cache FILE] [--check]
       [--set NAME=VALUE ...] [--compare NAME=VALUE ...]
FIGURES is FIRST-LAST or a comma list; OUT gets one line per figure (appended):
``k OK|BAD pure=.. one=.. n=.. nmin=.. seconds from=cache|full``. ``--set`` sets a module
constant of skeleton.markersets.rules first (``--set SPHERE_JOINS=False``; Python literals).
``--compare NAME=VALUE`` (a constant of steps 4-11; may be repeated) resumes each figure at
step 4 again with it set so and adds ``NAME:acted=yes|no`` (whether the groups differ: the
rule acted) and ``NAME:compared=OK|BAD`` to the line: a rule is screened by the figures it
acts on.
Prints the count right at the end.
"""
from __future__ import annotations

import ast
import gzip
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "skeleton"))

import skeleton.markersets as ms  # noqa: E402


def figures(spec: str) -> list[int]:
    if "," in spec:
        return [int(k) for k in spec.split(",") if k]
    a, _, b = spec.partition("-")
    return list(range(int(a), int(b or a) + 1))


def _open(path: Path, mode: str):
    return gzip.open(path, mode + "t") if path.suffix == ".gz" else open(path, mode)


def load_cache(path: Path | None) -> dict[int, list]:
    out: dict[int, list] = {}
    if path is not None and path.exists():
        with _open(path, "r") as f:
            for line in f:
                d = json.loads(line)
                out[int(d["k"])] = d["pre_repair"]
    return out


def full_merge(X):
    """merge_fragments(X) and the groups entering step 4 (None where the repairs do not
    run: fewer than 3 markers)."""
    seen = []
    orig = ms._repair_swaps

    def record(X_, groups, *a, **kw):
        if not seen:
            seen.append([list(map(int, g)) for g in groups])
        return orig(X_, groups, *a, **kw)
    ms._repair_swaps = record
    try:
        res = ms.merge_fragments(X)
    finally:
        ms._repair_swaps = orig
    return res, (seen[0] if seen else None)


def judge(fig, owner, groups) -> tuple[bool, bool]:
    """(every id holds one physical marker, every marker has exactly one id)"""
    pure = all(len({int(owner[f]) for f in g}) == 1 for g in groups)
    ids = [int(owner[g[0]]) for g in groups]
    return pure, len(ids) == len(set(ids)) == fig.n_markers


def main(argv: list[str]) -> int:
    args = list(argv)
    cache_path, check, sets = None, False, []
    if "--cache" in args:
        i = args.index("--cache")
        cache_path = Path(args[i + 1])
        del args[i:i + 2]
    if "--check" in args:
        args.remove("--check")
        check = True
    compares = []
    while "--compare" in args:
        i = args.index("--compare")
        compares.append(args[i + 1])
        del args[i:i + 2]
    while "--set" in args:
        i = args.index("--set")
        sets.append(args[i + 1])
        del args[i:i + 2]
    if len(args) != 2:
        print(__doc__)
        return 2
    for s in sets:
        name, _, value = s.partition("=")
        if not hasattr(ms.rules, name):
            raise SystemExit(f"--set {s}: skeleton.markersets.rules has no {name}")
        setattr(ms.rules, name, ast.literal_eval(value))
    compared = []
    for c in compares:
        c_name, _, c_value = c.partition("=")
        if not hasattr(ms.rules, c_name):
            raise SystemExit(f"--compare {c}: skeleton.markersets.rules has no {c_name}")
        compared.append((c_name, ast.literal_eval(c_value)))
    from test_markersets import _bench_figure

    ks, out_path = figures(args[0]), Path(args[1])
    cache = load_cache(cache_path)
    right = done = stale = 0
    with open(out_path, "a") as out:
        for k in ks:
            t = time.perf_counter()
            fig, _, X, owner = _bench_figure(k)
            if k in cache and cache[k] is not None and not check:
                res, src = ms._repairs_from(X, cache[k]), "cache"
            else:
                res, pre = full_merge(X)
                src = "full"
                if k in cache and cache[k] is not None:
                    again = ms._repairs_from(X, cache[k])
                    if cache[k] != pre or again.groups != res.groups:
                        stale += 1
                        src = "full(STALE)"
                elif cache_path is not None:
                    with _open(cache_path, "a") as c:
                        c.write(json.dumps({"k": k, "pre_repair": pre}) + "\n")
            pure, one = judge(fig, owner, res.groups)
            right += pure and one
            done += 1
            extra = ""
            for c_name, c_value in compared:
                groups = cache[k] if src == "cache" else pre
                other = res
                if groups is not None:
                    kept = getattr(ms.rules, c_name)
                    setattr(ms.rules, c_name, c_value)
                    try:
                        other = ms._repairs_from(X, groups)
                    finally:
                        setattr(ms.rules, c_name, kept)
                extra += (f" {c_name}:acted={'yes' if other.groups != res.groups else 'no'}"
                          f" {c_name}:compared="
                          f"{'OK' if all(judge(fig, owner, other.groups)) else 'BAD'}")
            out.write(f"{k} {'OK' if pure and one else 'BAD'} pure={pure} one={one} "
                      f"n={res.n_markers} nmin={res.n_min} {time.perf_counter() - t:.1f}s "
                      f"from={src}{extra}\n")
            out.flush()
    print(f"{right}/{done} merged right" + (f", {stale} stale cache entries" if check else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

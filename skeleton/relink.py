"""Re-link a skeleton tree where a neighbouring star fits the markers decisively better.

``relink_by_stars(traj, members, parents, joint_starts, cost, floor_m) -> (parents, moves)``.
Every two tree edges that share a segment b (a - b - c) form a triple whose three trees are
the three stars around a, b and c. The minimum spanning tree picked b as the hub on pairwise
joint costs, which compare fits over different markers; here the triple's stars are fitted
as articulated models to the *same* markers (``skeleton.star_fit``: same markers, same
number of parameters, so the residual sums of squares compare directly). Where the star
around a neighbour fits better than b's by more than ``STAR_MARGIN`` times the residual
variance per residual (the junction step's margin, ``skeleton.junctions``), c is re-hung
from a (and symmetrically). An alternative is only fitted where its new pair is a plausible
joint at all (cost at most ``PLAUSIBLE`` x the floor): otherwise the MST's choice stands
without a fit. One move per round, the most decisive first, until none is left (at most
``MAX_MOVES``); fits are cached per triple and hub. Before a move, each of the two stars
is fitted again, started at the joints the other one found (the same two points), and the
better of each star's two fits is compared: the fits are local, and the tree's joints can
start a star far from its best fit. The two re-fits repeat, each star started at the joints
the other's last fit found, while either improves (at most ``REFIT_ROUNDS``, 3): held-out
seed 235004 (stop 35, 2-marker siblings 9.2 mm apart on a 2-marker parent): the true star,
re-fitted once, hit its 50 iterations at 167.8 mm^2 against the wrong star's 81.9 (2835x);
a second round took it to 79.3 in 5 iterations and the move was not made.
- Seed 109048 (1 mm): siblings 3.1 mm apart; the current star, started 46-57 mm off the
  true joints, stopped after 50 iterations at 2.1x the winner's sum of squares (a 4012x
  margin); from the winner's joints it fits better than the winner.
- Held-out seed 195045 (stop 33): the current star, started at a world fit of two 2-marker
  segments, converged in 33 iterations at 4178 mm^2 against the wrong star's 534 (6746x);
  from the winner's joints it fits 168 mm^2. 196001, 197043 alike (263x, 634x wrong).
- Re-fitting only the current star (stops 24-32 did so where it stopped unconverged; tried
  at stop 33 before every move) left the tennis serve's right foot on the left upper arm,
  which two moves (2001x, 566x) had taken on to the left thigh (mean marker deviation
  16.50 -> 20.88 mm); fitting both stars from both starts moves it once, to the upper back
  (LSHO T10, 222x): 17.16 mm. The tree is wrong every way (soft tissue). Seed sets
  1000-20000 and 180000-199000 (1 mm): see the README's stop 33 row.

A star fit stopped at its iteration limit (``skeleton.star_fit.MAX_ITER``) is continued
from the joints it reached, while that improves it (at most ``CONTINUE_FITS`` times):
held-out seed 267024 (stop 36, 1 mm): siblings 1 and 9 of the 2-marker root 0, joints
89.5 mm apart; the tree hung 1 from 9, and the true star around 0, started at the false
joint 9-1, stopped at 1078.4 mm^2 after 50 iterations against the current star's 532.4
(also stopped there), so no move was tried; continued, they reach 120.5 and 278.0 mm^2.
The most decisive move of a round goes first, except that a move removing an edge that
another decisive move's triple needs waits for that move when it leaves the first one's
triple whole (``ORDER_MOVES``): held-out seed 240014 (stop 35, 1 mm; 2-marker segments 5,
8, 9, the tree hung 5 and 9 from 8): 5 from 8 to 6 (3747x) went first and took the edge
5-8 that 9's move from 8 to 5 (344x) needs; the other way round both are made.
Seed 4043 of benchmarks/bench_skeleton.py (1 mm): siblings 2 (2 markers) and 4 (3 markers)
hang from 1 with joints 116 mm apart; the tree hung 2 from 4 (cost 1.26x the floor against
1.03x for the true 1-2, chosen in the junction step); the star around 1 fits 289x the
residual variance better than the star around 4.
Conventions: docs/conventions.md [arrays], [units].
"""
from __future__ import annotations

import numpy as np

from skeleton import star_fit
from skeleton.junctions import STAR_MARGIN
from skeleton.star_fit import margin_unit, star_misfit
from skeleton.topology import tree_from_edges

__all__ = ["relink_by_stars", "PLAUSIBLE", "MAX_MOVES"]

PLAUSIBLE = 5.0       # an alternative pair is fitted when its cost is <= this x the floor
                      # (stop 23, 3 -> 5: seed 101022, 1 mm: the true pair of two 2-marker
                      # segments cost 3.09x, its world fit's cost is an upper bound; its star
                      # won by 1083x. 97000-102000: 296 -> 297/300; 1000-7000: 347/350 and
                      # 103000-104000 (first run): 98/100, the same figures with 3 and 5)
MAX_MOVES = 10        # re-links at most
REFIT_ROUNDS = 3      # rounds of the two stars re-fitted from each other's joints before a move
ORDER_MOVES = True    # a move that would break another decisive move's triple waits for it
CONTINUE_FITS = 2     # a star stopped at its iteration limit is continued at most this often


def relink_by_stars(traj: np.ndarray, members, parents, joint_starts, cost: np.ndarray,
                    floor_m: float, margin: float = STAR_MARGIN, log=None):
    """``parents`` (S,) a rooted tree (-1 at the root); ``joint_starts(parents)`` -> dict
    child -> (T, 3) world start of the joint with its parent (the solver's joint fits);
    ``cost`` (S, S) pair costs and ``floor_m`` what a true joint scores (``PLAUSIBLE``).
    Returns the new parents (the same root where it stays in the tree's centre: the tree is
    re-rooted by ``tree_from_edges``) and the moves made: (segment, old neighbour, new
    neighbour, margin)."""
    parents = np.asarray(parents, np.int64)
    S = parents.size
    if cost.shape != (S, S):
        raise ValueError(f"cost.shape={cost.shape}, expected ({S}, {S})")
    say = log or (lambda msg: None)
    cache: dict = {}
    refit: set = set()      # (triple, current hub, alternative hub) re-fitted from the winner
    moves = []
    if not np.isfinite(margin):
        return parents, moves

    def fit(tri, hub, starts):
        key = (tri, hub)
        if key not in cache:
            f = star_misfit(traj, members, set(tri), hub, starts)
            for _ in range(CONTINUE_FITS):
                # stopped at its iteration limit: continued from where it stopped
                if not (f.ok and f.n_iter >= star_fit.MAX_ITER):
                    break
                g = star_misfit(traj, members, set(tri), hub, f.joints)
                if not (g.ok and g.ssq_m2 < f.ssq_m2):
                    break
                f = g
            cache[key] = f
        return cache[key]

    for _ in range(MAX_MOVES):
        starts = joint_starts(parents)
        edges = {frozenset((int(s), int(parents[s]))) for s in range(S) if parents[s] >= 0}

        def J(a, b):
            return starts[b] if parents[b] == a else starts[a]

        nb = {s: sorted(v for e in edges if s in e for v in e if v != s) for s in range(S)}
        best = None
        decisive = []   # every move above the margin: (margin, moved, b, hub)
        for b in range(S):
            for i, a in enumerate(nb[b]):
                for c in nb[b][i + 1:]:
                    tri = tuple(sorted((a, b, c)))
                    for hub, moved, kept in ((a, c, b), (c, a, b)):
                        # alternative: `moved` hangs from `hub` instead of from b
                        if not cost[hub, moved] <= PLAUSIBLE * floor_m:
                            continue
                        cur = fit(tri, b, {a: J(a, b), c: J(b, c)})
                        alt = fit(tri, hub, {kept: J(hub, b), moved: J(b, moved)})
                        if not (cur.ok and alt.ok):
                            continue
                        m = _margin(cur, alt)
                        if m > margin and (tri, b, hub) not in refit:
                            # before a move: each star again, started at the joints the
                            # other found (the same two points: the joint b - hub, and
                            # moved's joint, with b or with hub), and the better of each
                            # star's two fits compared
                            refit.add((tri, b, hub))
                            for _ in range(REFIT_ROUNDS):
                                again = star_misfit(traj, members, set(tri), b,
                                                    {hub: alt.joints[b],
                                                     moved: alt.joints[moved]})
                                alt2 = star_misfit(traj, members, set(tri), hub,
                                                   {b: cur.joints[hub],
                                                    moved: cur.joints[moved]})
                                better = False
                                if again.ok and again.ssq_m2 < cur.ssq_m2:
                                    cache[tri, b] = cur = again
                                    better = True
                                if alt2.ok and alt2.ssq_m2 < alt.ssq_m2:
                                    cache[tri, hub] = alt = alt2
                                    better = True
                                if not better:
                                    break
                            m = _margin(cur, alt)
                        if m > margin:
                            decisive.append((m, moved, b, hub))
                        if m > margin and (best is None or m > best[0]):
                            best = (m, moved, b, hub)
        if best is None:
            break
        # A move that removes an edge another decisive move's triple needs waits for it,
        # when that move leaves this one's triple whole (``ORDER_MOVES``; see the module
        # docstring)
        m, moved, old, new = best
        if ORDER_MOVES:
            # a triple's edges: the moved segment's and the new hub's with b
            first = [d for d in decisive if d[1] != moved
                     and frozenset((moved, old)) in (frozenset(d[1:3]), frozenset(d[2:4]))
                     and frozenset(d[1:3]) not in (frozenset((moved, old)),
                                                   frozenset((new, old)))]
            if first:
                m, moved, old, new = max(first)
        edges = (edges - {frozenset((moved, old))}) | {frozenset((moved, new))}
        parents = tree_from_edges(S, sorted(tuple(sorted(e)) for e in edges)).parents
        moves.append((int(moved), int(old), int(new), float(m)))
        say(f"star re-link: segment {moved} from {old} to {new} (its star fits "
            f"{m:.0f}x the residual variance better)")
    return parents, moves


def _margin(cur, alt) -> float:
    """How much better ``alt`` fits than ``cur``: the drop in the sum of squares in units
    of the better fit's residual variance (floored at ``VAR_FLOOR_M2``; widened where its
    residuals are correlated over frames: ``skeleton.star_fit.margin_unit``)."""
    return (cur.ssq_m2 - alt.ssq_m2) / margin_unit(cur if cur.ssq_m2 <= alt.ssq_m2 else alt)

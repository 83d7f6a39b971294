"""Step 4 of the marker-set merge: swap repair between two markers of one segment.

4. swap repair: the linkage decides each gap on one minimum distance, and two markers of one
   segment that vanish together can come back exchanged (each id then holds fragments of
   both). For every two merged markers that are rigid with respect to each other (sd of
   their distance <= ``rigid_pair`` (5) times the measured sd of a rigid pair, the median
   over markers of the smallest sd to another marker), every exchange of a run of their
   fragments (in time order) that keeps both free of overlaps is scored by the sum over
   their segment partners of log(1 + sd / measured sd) of the distance to each; the best
   exchange is made when it lowers the sum by at least ``swap_margin`` (1). Segment
   partners are the other markers rigid (sd <= 3 times the measured sd) to the fragments
   themselves over >= 80 % of their common frames, so the choice of partners does not
   depend on the assignment being judged (with every other marker as a partner, partners
   across a joint add noise: on figures 0-39 that undid the swaps of figures 26 and 39 but
   made new wrong exchanges in figures 30 and 31). On figures 0-39 the exchanges made
   without a margin gained 2.2-6.1 when right and 0-0.3 when wrong, hence the margin of 1.
   A short piece barely moves an sd over a whole track (figure 28: the last 14 frames of
   another marker of the segment, 1.9 mm further from the one partner, change the sd by
   0.03 mm), so when that rule makes no exchange the jumps decide (``_jumps``): over the
   partners rigid to every fragment of the pair they are seen with, the sum over fragments
   of their frames seen with the partner x (their mean distance to it - their marker's)^2,
   counting only the partners whose fragments fit two constant distances in some
   assignment (least sum <= ``jump_margin`` (10.8) times the measured sd squared: a marker
   across a joint can be rigid to each fragment yet drift 10 mm between them, figure 87).
   The best exchange is made when it lowers the sum by ``jump_margin`` times the measured
   sd squared (10.8: chi-square with one degree of freedom at p = 0.001; not tuned).
   A pair without segment partners (a segment with two markers, or whose others are not
   seen with them) is judged instead by the direction from one marker to the other, which a
   swap flips. The cost is the sum,
   over the changes of fragment in either marker (on their common frames), of the angle
   between the mean direction over the 5 common frames before and the 5 after; the best
   exchange is made when it turns at least ``turn_margin`` (60 deg) less. A right
   assignment turns by the segment's rotation across the gap, a wrong one by 180 deg minus
   it, i.e. 180 deg minus twice the rotation more: on figures 0, 2, .., 38 the direction
   of two markers of one segment turned over 40 frames (the longest simulated gap) by at
   most 79 deg, 99 % below 56 deg, so a wrong assignment turns >= 68 deg more across 99 %
   of such gaps (the margin was set from this, before running the benchmark). Partners
   that decide nothing leave a pair moving as one body (sd <= 1.5 x s0) to its direction
   too (``TURN_FALLBACK``; figure 896: the two markers of a 2-marker segment swapped at
   their start pieces, with one partner, a marker of the parent 101 mm from their joint
   and nearly in line with the segment, whose distances to them drift by 3.0-3.2 x s0 as
   the joint turns: the right exchange gained 0.51 in sd cost, under the margin, and the
   jumps dropped it as drifting, while the direction turns 35 deg across the gap when
   right and 156 deg as merged);

The swap repair, ``python benchmarks/bench_markersets.py 0 120`` (same figures, with and
without the repair in one run): figures 0-39 (margin chosen here)
36/40 merged exactly (34/40 without it), physical figures 20/22 (20/22); figures 40-79
35/40 (33/40), physical 20/22 (19/22) (held out for the margin, but the partner rule was
chosen after seeing a wrong exchange in figure 53); figures 80-119 (looked at once, at the
end) 32/40 (31/40), physical 20/23 (20/23). Of the figures with two markers of one segment
< 20 mm apart 16/18, 15/18, 12/17 (14/18, 14/18, 11/17). No figure got worse. Merge time
x1.04 (3.1 s at 176 fragments).

Since hw_sim 70ca108 (a segment's markers >= 20 mm apart; all figures physical), the
same benchmark, before -> after the turning rule and step 5: figures 0-39 34/40 -> 36/40,
40-79 34/40 -> 38/40, 80-119 31/40 -> 35/40 (steps 1-3 alone 33, 32, 30); no figure lost;
merge time x1.04 of steps 1-3 alone in both runs. Fixed: swaps on two-marker segments
(figures 20, 48, 64, 82, 92, 118) and splits beside a repaired swap (16, 62, 79, 107). Still
failing (1, 25, 30, 31, 61, 85, 93, 96, 98, 110; 59 merges since random_tree takes up
to 400 draws per marker - with 60 it kept two 7.8 mm apart): a fragment merged with a
marker of another segment, mostly where the right continuation's pose-aligned distance is above
``max_distance_m`` or the loose pass decides (alignment on a segment with two markers, or
with its partners hidden, leaves the pose free). Two vetoes were measured and rejected: "the
merged fragments share a partner rigid over both" (on figures 0-119, 128 of 6700 right and
146 of 219 wrong candidate pairs of step 3 lack one at 4 mm: a fragment's segment partners
are often not seen with the other fragment, and the vetoed right pairs become splits), and
"a loose merge keeps each track rigid to its most rigid partner" (on the failing figures
1, 16, 30, 59, 62, 93, 96, 110 it blocked right merges too: more splits, none fixed).


The jumps of step 4 and the veto in 4b (stop 18, designed on the failures of 0-399; the
partner filter was added after a first form lost figure 87): figures 0-199 196 -> 198 of
200 (fixed 28, 93), 200-399 194 -> 197 (fixed 341, 371, 372), none lost; held out, first
run at stop 18, 400-519 119 -> 119 of 120 and 520-639 115 -> 115 of 120 (failing 403,
524, 556, 569, 611, 617: pieces of another segment's marker or 2-marker segments, none a
short piece on a marker of its own segment, the class the rule is for). Merge time x1.35
-> x1.36 of steps 1-3 alone. Still failing in 0-399: 157, 186, 221, 339, 379.

A partner fits an assignment only where it sees two or more fragments of one of its
markers (``JUMPS_SEEN_TWICE``, stop 64): one that sees a single fragment of each fits there
at no cost, whatever the fragments are. Held-out figure 16029: marker 50's last 19 frames,
left an id of their own, were rigid to marker 0 (root) over their 19 common frames; the
partners rigid to every fragment were markers of two child segments of the root, drifting
between marker 0's two long fragments (52.6 and 25,274 mm^2 as merged), and the exchange
that split marker 0, giving its first fragment to the piece, left each seeing one fragment
per marker: cost 0, so both "fitted" it and it was made.

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

import numpy as np

from . import rules
from .cross import _repair_cross
from .judges import _best_by_jumps, _best_by_turning
from .misfits import _move_misfits
from .tracks import (
    _exchange, _paced, _pair_sd, _partner_frames, _run_exchanges, _sd_to, _spans, _tracks
)


def _repair_swaps(X, groups, min_frames, margin, rigid_pair=5.0, rigid_partner=3.0,
                  rigid_share=0.8, max_rounds=3, turn_margin=np.pi / 3, cross_margin=None,
                  jump_margin=10.8, one_body=1.5, max_step=np.inf):
    """Step 4: exchange runs of fragments between two mutually rigid markers when that makes
    both more rigid with respect to their segment partners, else when that lowers the
    jumps of their distances to partners rigid to every fragment (``_jumps``, by at least
    ``jump_margin`` times the measured sd squared) or, without segment partners, makes the
    direction between them turn less across the fragment changes (by at least
    ``turn_margin`` rad; module docstring); then step 4b between markers of different
    segments (``_repair_cross``, least gain ``cross_margin``, default ``margin``) and step
    4c (``_move_misfits``). No step makes a change of fragment cross its gap faster than
    ``max_step`` per frame (``_paced``)."""
    vis = ~np.isnan(X[..., 0])
    span = _spans(vis, groups)
    P = _tracks(X, groups)
    M = len(groups)
    S, s0 = _pair_sd(P, min_frames)
    if not s0 > 0:
        return groups

    def cost(sd):
        return float(np.nansum(np.log1p(sd / s0)))

    first = {f: int(np.flatnonzero(vis[:, f])[0]) for g in groups for f in g}
    for _ in range(max_rounds):
        changed = False
        for a in range(M):
            for b in range(a + 1, M):
                if not S[a, b] <= rigid_pair * s0 or len(groups[a]) + len(groups[b]) < 3:
                    continue
                frs = sorted(groups[a] + groups[b], key=first.get)
                alts = [al for al in _run_exchanges(frs, groups[a],
                                                    lambda g: vis[:, g].sum(1).max() <= 1)
                        if _paced(X, span, al[0], max_step)
                        and _paced(X, span, al[1], max_step)]
                if not alts:
                    continue
                # segment partners: rigid to the fragments themselves (whatever their marker)
                others = np.r_[0:a, a + 1:b, b + 1:M]
                seen, rigid = _partner_frames(X, vis, P, frs, others, min_frames,
                                              rigid_partner * s0)
                # partners rigid to every fragment they are seen with: they judge the jumps
                strict = others[(seen > 0) & (rigid == seen)]
                others = others[(seen > 0) & (rigid >= rigid_share * seen)]
                if others.size == 0:
                    # no segment partners (a segment with two markers): the pair's direction
                    found = _best_by_turning(X, vis, groups[a], groups[b], alts,
                                             turn_margin)
                    if found is not None:
                        _exchange(X, groups, P, S, a, b, *found, min_frames)
                        changed = True
                    continue
                Po = P[:, others]
                best = cost(S[a, others]) + cost(S[b, others]) - margin
                found = None
                for ga, gb in alts:
                    pa, pb = _tracks(X, [ga, gb]).transpose(1, 0, 2)
                    c = cost(_sd_to(Po, pa, min_frames)) + cost(_sd_to(Po, pb, min_frames))
                    if c < best:
                        best, found = c, (ga, gb)
                if found is None and strict.size:
                    # a short piece barely moves the sd: the jumps between fragments instead
                    ga = _best_by_jumps(X, vis, groups[a], groups[b], alts, P[:, strict],
                                        jump_margin * s0 ** 2, s0)
                    if ga is not None:
                        found = ga
                if found is None and rules.TURN_FALLBACK and S[a, b] <= one_body * s0:
                    # partners that cannot tell (figure 896: a marker across the joint,
                    # nearly in line with the segment, drifts by ~3 x s0 only): one body's
                    # direction, as without partners
                    found = _best_by_turning(X, vis, groups[a], groups[b], alts, turn_margin)
                if found is None:
                    continue
                _exchange(X, groups, P, S, a, b, *found, min_frames)
                changed = True
        if not changed:
            break
    groups = _repair_cross(X, groups, min_frames, s0, margin if cross_margin is None
                           else cross_margin, jump_margin=jump_margin, max_step=max_step)
    return _move_misfits(X, groups, min_frames, s0, jump_margin=jump_margin,
                         max_step=max_step)

"""Step 4b of the marker-set merge: exchanges between any two markers, judged by voters.

4b. exchange by voting fragments (``_repair_cross``): the linkage can also give two markers
   of different segments each other's piece (both vanish at about the same time and each
   continuation lies nearer the wrong one), and step 4 misses swaps whose partners it
   cannot pool. Every fragment seen in >= 100 frames votes with its own partners: the
   markers rigid to it (distance sd <= 3 times the measured sd over its frames) - its
   segment, whatever else its track holds. A track scores, summed over the partners of each
   voter it holds, log(1 + sd / measured sd) of its distance to each. For a marker whose
   track is not rigid to a partner of one of its voters (or that holds a piece off its
   other fragments on every judge, step 4c's misfit, ``MISFITS_ARE_BAD``: over 400 frames
   a short piece barely moves a track's sd; figure 1464, two sibling segments' markers
   holding each other's end pieces of 65 and 49 frames, found by a jump of 1.34 x the
   bound, the exchange then gaining 2.98), and every other marker, each
   overlap-free exchange of a run of their fragments is scored (the pair's own tracks left
   out of the partners, so each alternative sums the same terms) and the best is made when
   it lowers the sum by ``swap_margin`` (1), one exchange per round (or by
   ``BODY_CONFIRMS_FRACTION`` (0.5) of it where every piece it moves leaves a body it does not move
   as one with for one it does, ``BODY_CONFIRMS``, ``_onto_bodies``, stop 57: figure 3464,
   below). An exchange may not put
   a fragment where no partner of the receiving track's voters is seen with it for
   ``min_frames`` frames (else a piece could be dumped where nothing judges it; where
   every fragment the receiving marker keeps is shorter than a voter's 100 frames, the
   partners of the track they make together, over >= 100 frames, judge - unless the
   fragment moved in is a voter itself, whose own partners then score it on a track it
   mostly makes: figure 569, markers of two segments both back at frame 326 with each
   other's last 74 frames, the 2-marker one's fragments 69, 78 and 87 frames long; its
   kept track has its segment partner, rigid to the piece at 1.0 x the measured sd.
   Figure 313: without the voter exception a 141-frame voter moved onto a marker of two
   short fragments first, 4.64 against 4.06 for the right exchange, and a mixed pair of
   short pieces was left that no voter judges. ``/tmp`` screen of figures 0-1839, as
   bench_markersets.py builds them (stop 38): 1829 -> 1830/1840 (fixed 569, none lost;
   without the exception 1829, 313 lost); held out, first run 2600-2839: 238/240 with and
   without the rule, the same two failures (2710, 2738); real recordings' merged groups
   identical with and without; since stop 56 a voter moving in is judged so too where
   that exchange gains the margin more than every other split of the pair's fragments,
   ``CLEAR_VOTER_MOVES``, ``_clear_voter_moves``, figure 10199), nor one
   that raises step 4's jump cost of the two markers by ``jump_margin`` times the measured
   sd squared (a voter's partners may be rigid over its frames only: in figure 372 they
   put back a piece that step 4's jumps had moved), nor one that makes the direction
   between two markers moving as one rigid body (distance sd <= 1.5 times the measured sd)
   turn by ``turn_margin`` more across fragment changes (figure 939: the two markers of a
   2-marker segment, 40.5 -> 172.6 deg), nor one that moves a fragment off a body it was
   on: rigid (sd <= 3 x s0) to every track moving as one body with its old marker's other
   fragments (sd <= 1.5 x s0 over >= 100 frames), and not rigid to one moving as one body
   with its new marker's (it cannot be a marker of that body; figure 379: a marker's last 26
   frames went to a marker of the next segment, 4.1 x s0 off its one-body partner there, on
   voters' partners across a joint that were rigid over the voters' frames only). A
   fragment already off its body may move: figure 799's three mixed markers are put right
   by two exchanges, the first of which leaves a piece on a wrong marker - but not onto a
   body it is further off than the one it leaves (``LESS_OFF_BODY``; figure 4579, held
   out at stop 42: marker 12's last 53 frames (a 2-marker segment) went to marker 22 of
   another 2-marker segment, on voters' partners across a joint that barely moved until
   then; at home the piece sat 1.3 x s0 from its segment partner and 3.9 x from a marker
   across that joint, on marker 22 9.2 x from its segment partner; since stop 61 "further
   off" compares the median sd to each body's one-body tracks, not the largest,
   ``MEDIAN_OFF_BODY``: in held-out figure 13314 marker 12's last 71 frames, on marker 4 of
   the parent segment, were kept from home by marker 23, one body with marker 12's first
   268 frames only while the joint between was still, 6.13 x s0 off the piece against the
   3.62 of the farthest track it left; the medians are 1.10 and 3.21) - nor one that makes a
   moved piece step 4c's misfit (above the jump bound on every judge of its new marker's
   fragments) where a judge at home finds it fitting (``NO_NEW_MISFITS``; figure 4430,
   held out at stop 42: marker 12's first 16 frames went to marker 9 of another segment on
   voters' partners in the next segment, one body with marker 12 after those frames; its
   segment partners put it at 2.35 and 4.25 x s0 squared at home, bound 10.8, marker 9's
   at 30.3. A first version, stop 44, also refused the move of a piece no judge placed at
   home, and lost figure 799, where such a move is a step on the way to the right
   markers). A voter's partner counts in the scores only where it is rigid (sd <= 3 x s0)
   to one of the tracks the pair makes, as merged or in some alternative
   (``RIGID_SOMEWHERE``, stop 53; figure 7429: the 30-frame end piece of marker 5, a
   2-marker segment, went to marker 7 of a sibling 2-marker segment on partners across a
   joint that were rigid over a 137-frame voter only and 5.7-21 x s0 on every whole
   track; such partners then decide any move: SCREEN53). The jump veto asks of each partner
   and each of the two markers apart whether the partner sits at constant distances from
   that marker's fragments in some assignment (``JUMPS_PER_MARKER``, stop 53; held-out
   figure 9533: markers 15 and 27 of a 4- and a 3-marker segment across a ball joint held
   each other's end pieces, 30 and 18 frames; the exchange gained 15.23, but of its three
   jump partners, all rigid to every fragment at <= 3 x s0, two were each one marker's
   segment partner and across the joint from the other, so fitted no pair and were left
   out; the third, across the joint from marker 15, drifting, put the right assignment at
   42.9 mm^2 against 14.4, over the 21 mm^2 margin. Per marker, the two segment partners
   count for their own marker: 2.0e6 against 47 mm^2);

A body confirms an exchange that gains less than the margin (``BODY_CONFIRMS``, stop 57):
from a gain of ``BODY_CONFIRMS_FRACTION`` (0.5) x the margin it is judged like one above
it where every fragment it moves has, among the tracks moving as one body with the fragments
its old marker keeps (sd <= 1.5 x s0 over >= 100 frames, ``_body_sds``), one it is further
than 1.5 x s0 from, and is within 1.5 x s0 of every such track of its new marker's kept
fragments. Figure 3464 (right until stop 53's ``RIGID_SOMEWHERE`` dropped a partner): the
linkage gave marker 29's last 49 frames (segment 10) to marker 55 of its child segment 18,
and marker 55's last 17 to marker 29, while the joint between barely moved; the right
exchange gained 0.92. The two pieces sat up to 2.0 and 1.93 x s0 off their markers'
one-body tracks and within 1.18 and 1.15 x s0 of every one of the other marker's.
``/tmp`` driver on all 8,370 figures of the step-4 cache (``_repairs_from`` on the cached
groups, re-run with the rule off wherever ``_onto_bodies`` confirmed an exchange): 8370/8370
right; it confirmed one on 1620, 3224, 3464, 4668, 4855, 5430 and 10847 and changed the
groups of 3464 only (the other six merged the same groups with it off).

The voters cannot tell apart two exchanges whose gains lie within the margin of each other
(``PIECES_BREAK_TIES``, stop 71): a short piece barely moves a track's sd. Of the exchanges
of the best pair gaining within the margin of the best (and the margin at least), unvetoed,
the first by gain that puts every piece the two place differently where step 4c's judges
fit it (``_fits`` of ``_misfit`` against the fragments both put on that marker) and where
the best puts it has no judge or is above the bound on every one, is made in its place.
Held-out figure 21448: the linkage merged marker 22's first fragment (frames 0-143) and its
14-frame piece (149-162) with marker 26's last two (2-marker segments 7 and 9); the voters
gave marker 22 the first fragment back (gain 3.504) or it and the piece (3.490). One judge
fits the piece on marker 22 (0.14 x the bound), none sees it on marker 26, where no later
step could move it: step 4c and step 12 move a piece on one judge's 14 frames nowhere
(``UNJUDGED_EVIDENCE``; figure 556 is right only because they do not).

Step 4b (stop 16), ``bench_markersets.py`` (the failures of stop 15's code: 1-119: 28, 30,
85, 93, 119; 120-199: 131, 135, 157, 166, 186, 188, 195; 200-279: 221, 225, 227, 242,
256, 261 - 262 of 280 merged). A first form (each track against its longest fragment's
partners only, both longest fragments kept in place) merged 272 of 280, no figure lost;
it could not fix 242 (both longest fragments were one marker's) nor 261 and 119 (the two
markers' tracks, mixed, looked rigid to each other and were left to step 4). The voting
form, designed on 131, 186, 188, 195, 242, 261: 274 of 280 (still failing 28: a 14-frame
end piece on a marker of its own segment; 93: three markers of two segments; 157: two
markers of one segment exchanged at the start; 166: a marker of a two-marker segment split
across a 50-frame gap; 186: the foreign piece sits in a track with no fragment of >= 100
frames; 221). Voters from 50 frames: 275 of 280 (fixed 93 and 186, lost 256) at 1.38x the
merge time of voters from 100 frames, which were kept. Without the check that a moved
fragment is seen with a partner of the receiving track, figures 1 and 23 (merged before)
lost a correct fragment to a track with no voter. Held out, figures 280-399 (repair
variant only, same run): stop 15's code 111 of 120, this 114 (fixed 313, 368, 382, 390;
lost 379: a correct 26-frame end piece moved to a marker of another segment; still
failing 292, 339, 341, 371, 372). Tried and dropped: also requiring a moved fragment to be
rigid, at the kept fragments' distance, to at least half the receiving partners it is
seen with - figures 0-399 388 -> 387 of 400 (fixed 379, lost 135 and 195).
Merge time x1.33 of steps 1-3 alone on figures 0-59 (x1.07 before; 1.36 before the
partner columns of a pair were measured once per alternative, not once per voter).

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

import numpy as np

from . import rules
from .judges import _body_sds, _fits, _jumps, _misfit, _turning
from .tracks import (
    _cross_alternatives, _fragment_sd, _paced, _rigid_to_all, _sd_to, _spans, _tracks
)


def _clear_voter_moves(cands, margin) -> set:
    """Indices of the candidate exchanges ``cands`` ((na, nb, gain, judged) of one pair of
    markers) that move a voter onto a marker with none (not ``judged`` by the voter
    exception of ``KEPT_TRACK_VOTES``) and gain at least ``margin`` more than every
    candidate splitting the pair's fragments another way (``CLEAR_VOTER_MOVES``). Figure
    10199 (held out at stop 54): markers 39 and 48 of two segments exchanged their runs
    around frames 206-250; the one holding the two voters (fragments of 191 and 150 frames)
    could only give one away, and the right exchange, gaining 14.33, was never judged.
    In figure 313, for which the exception was made, the wrong move gained 4.64 and a right
    one 4.59: not clear, so neither is made."""
    out = set()
    for i, (na, nb, gain, judged) in enumerate(cands):
        if judged:
            continue
        key = frozenset((frozenset(na), frozenset(nb)))
        others = [g for ma, mb, g, _ in cands if frozenset((frozenset(ma), frozenset(mb))) != key]
        if gain >= margin + max(others + [0.0]):
            out.add(i)
    return out


def _onto_bodies(vis, P, sd_of, ga, na, gb, nb, excl, body_sd, body_frames) -> bool:
    """Every fragment an exchange moves (from marker a's fragments ``ga`` into ``nb``, from
    ``gb`` into ``na``) leaves a body it does not move as one with for one it does: some
    track moving as one body with the fragments its old marker keeps (``_body_sds``) is
    further than ``body_sd`` from it, and every one moving as one body with those its new
    marker keeps is within ``body_sd`` (one at least, both sides) (``BODY_CONFIRMS``)."""
    for g, new, h in ((ga, na, gb), (gb, nb, ga)):
        kept = [f for f in new if f in g]
        stay = [f for f in h if f not in new]
        for f in new:
            if f in g:
                continue
            _, home = _body_sds(vis, P, sd_of, f, stay, excl, body_sd, body_frames)
            _, there = _body_sds(vis, P, sd_of, f, kept, excl, body_sd, body_frames)
            if not (home.size and there.size and there.max() <= body_sd < home.max()):
                return False
    return True


def _repair_cross(X, groups, min_frames, s0, margin, rigid=3.0, voter_frames=100,
                  max_rounds=10, jump_margin=10.8, one_body=1.5, turn_margin=np.pi / 3,
                  body_veto=True, max_step=np.inf):
    """Step 4b (module docstring): runs of fragments exchanged between two markers, judged
    by voting fragments. Every fragment seen in >= ``voter_frames`` frames votes with its
    partners: the markers rigid to it (distance sd <= ``rigid`` x the measured sd ``s0``
    over its frames). A track scores, summed over the partners of each voter it holds,
    log(1 + sd / s0) of its distance to each. For a marker whose track is not rigid to a
    partner of one of its voters, and every other marker, each overlap-free exchange of a
    run of their fragments is scored (the pair's own tracks left out of the partners, so
    every alternative sums the same terms); the best of a round is made when it lowers the
    sum by at least ``margin`` (at most ``max_rounds`` rounds). No fragment is moved where
    no partner of the receiving track's voters is seen with it for ``min_frames`` frames,
    and no exchange is made that raises step 4's jump cost (``_jumps``, partners rigid to
    every fragment of the two markers) by ``jump_margin`` times s0 squared, nor - between
    two markers that move as one rigid body (distance sd <= ``one_body`` (1.5) x s0, the
    factor at which skeleton.segments merges two clusters) - one that makes the direction
    between them turn by ``turn_margin`` more across fragment changes (``_turning``: a swap
    flips it), nor one that moves a fragment off a one-body track it was rigid to onto one
    it is not (``body_veto``; figures 379 and 799), nor onto a body it is further off than
    the one it leaves (``LESS_OFF_BODY``; figure 4579), nor one that makes a moved piece
    step 4c's misfit where a judge at home finds it fitting (``NO_NEW_MISFITS``; figure
    4430; not where no judge places it at home, figure 799).
    Step 4's looser ``rigid_pair`` (5 x s0) let the veto block a right exchange
    in figure 261: markers of two segments at 4.8 x s0, whose direction turned 99 -> 161 deg
    when put right. Figure 939: the two markers of a 2-marker segment had
    their first runs exchanged on voters whose partners across joints were rigid over the
    voters' frames only; the jump test did not block it (its two judges are markers of the
    next segment, rigid to both markers), and the turning went 40.5 -> 172.6 deg."""
    vis = ~np.isnan(X[..., 0])
    span = _spans(vis, groups)

    def cost(sd):
        return float(np.nansum(np.log1p(sd / s0)))

    for _ in range(max_rounds):
        P = _tracks(X, groups)
        M = len(groups)
        part = {}
        for m, g in enumerate(groups):
            for f in g:
                if vis[:, f].sum() >= voter_frames:
                    sd = _sd_to(P[vis[:, f]], X[vis[:, f], f], voter_frames)
                    sd[m] = np.nan
                    part[f] = np.flatnonzero(sd <= rigid * s0)

        def score(g, t, q, keep=None):
            """the track t of fragments g against its voters' partners, among columns q
            (only those in ``keep``, where given)"""
            sd = np.full(M, np.nan)
            sd[q] = _sd_to(P[:, q], t, min_frames)
            if keep is not None:
                sd[~keep] = np.nan
            return sum(cost(sd[part[f]]) for f in g if f in part)

        def checked(g, old, excl, voters=False):
            """every fragment moved into g shares >= min_frames frames with a partner of
            one of the voters g kept: nothing is put where no partner can judge it. Where
            g kept no voter (every fragment it kept is shorter than voter_frames) and no
            voter moves in, the partners of the track the kept fragments make together
            judge (``KEPT_TRACK_VOTES``; module docstring, step 4b); a voter moving in
            there is judged so too with ``voters`` (``CLEAR_VOTER_MOVES``)"""
            kept = [f for f in g if f in old]
            q = np.setdiff1d(np.concatenate([part[f] for f in kept if f in part]
                                            + [[]]), excl).astype(int)
            if (rules.KEPT_TRACK_VOTES and kept and not any(f in part for f in kept)
                    and (rules.KEPT_TRACK_JUDGES_VOTERS or voters
                         or not any(f in part for f in g if f not in old))):
                t = _tracks(X, [kept])[:, 0]
                seen = ~np.isnan(t[:, 0])
                if seen.sum() >= voter_frames:
                    sd = _sd_to(P[seen], t[seen], voter_frames)
                    sd[list(excl)] = np.nan
                    q = np.flatnonzero(sd <= rigid * s0)
            return all(q.size and (~np.isnan(P[vis[:, f]][:, q, 0])).sum(0).max()
                       >= min_frames for f in set(g) - set(old))

        sd_of = _fragment_sd(X, vis, P, min_frames)

        def turning_judged(a, b):
            """the pair's turning (``_turning``) where the two move as one rigid body
            (distance sd <= ``one_body`` x s0), else None"""
            if not _sd_to(P[:, [b]], P[:, a], min_frames)[0] <= one_body * s0:
                return None
            return _turning(X, vis, groups[a], groups[b])

        def strict(a, b):
            """the tracks (not a, b) rigid to every fragment of a and b they are seen with
            for min_frames frames (step 4's jump partners)"""
            ok = _rigid_to_all(sd_of, groups[a] + groups[b], rigid * s0)
            ok[[a, b]] = False
            return np.flatnonzero(ok)

        def holds_misfit(m, g):
            """a fragment of marker m sits off its other fragments on every judge
            (``_misfit`` above the jump bound: step 4c's misfit)"""
            bound = jump_margin * s0 ** 2
            for f in g if len(g) > 1 else ():
                c = _misfit(X, vis, P, sd_of, f, [h for h in g if h != f], [m], rigid * s0,
                            bound, voter_frames)
                if c.size and c.min() > bound:
                    return True
            return False

        def displaced(g, new, h, ex):
            """a fragment moves from marker h into marker g (``new``: g's fragments after
            the exchange) off a body it was on: rigid (sd <= ``rigid`` x s0) to every track
            moving as one body with the fragments h keeps (one at least), and not rigid to
            one moving as one body with those g keeps. It cannot be a marker of that body
            (figure 379: a marker's last 26 frames moved to a marker of the next segment,
            4.1 x s0 off its one-body partner there, 0.9 x s0 from its own; the voters'
            partners across a joint outweighed it). A fragment already off its body may
            move (figure 799: three markers' pieces put right in two exchanges, the first
            leaving a piece on a wrong marker), but not onto a body it is further off: the
            largest sd to the new one-body tracks above the largest to the old ones
            (``LESS_OFF_BODY``; figure 4579, 9.2 against 3.9 x s0)"""
            kept = [f for f in new if f in g]
            stay = [f for f in h if f not in new]
            for f in new:
                if f in g:
                    continue
                _, home = _body_sds(vis, P, sd_of, f, stay, ex, one_body * s0, voter_frames)
                if not home.size:
                    continue
                _, there = _body_sds(vis, P, sd_of, f, kept, ex, one_body * s0, voter_frames)
                if not (there > rigid * s0).any():
                    continue
                if (home <= rigid * s0).all():
                    return True
                further = (np.median(there) > np.median(home) if rules.MEDIAN_OFF_BODY
                           else there.max() > home.max())
                if rules.LESS_OFF_BODY and further:
                    # off both bodies, further off the new one (figure 4579); by the
                    # median sd, where a track one body with the kept fragments only while
                    # a joint was still is off the piece (MEDIAN_OFF_BODY, figure 13314)
                    return True
            return False

        def misfit_made(g, new, h, ex):
            """a fragment moves from marker h into marker g (``new``: g's fragments after
            the exchange) where it is step 4c's misfit (``_misfit`` above the jump bound on
            every judge of the fragments g keeps) though a judge of the fragments h keeps
            finds it fitting (figure 4430; a piece no judge places at home may move, figure
            799: such a move can be a step on the way to the right markers)"""
            bound = jump_margin * s0 ** 2
            kept = [f for f in new if f in g]
            stay = [f for f in h if f not in new]
            for f in new:
                if f in g:
                    continue
                there = _misfit(X, vis, P, sd_of, f, kept, ex, rigid * s0, bound,
                                voter_frames)
                if not (there.size and there.min() > bound):
                    continue
                home = _misfit(X, vis, P, sd_of, f, stay, ex, rigid * s0, bound,
                               voter_frames)
                if home.size and home.min() <= bound:
                    return True
            return False

        def placed_better(alt, other, ex):
            """every fragment the exchange ``alt`` ((na, nb)) puts on another marker than
            ``other`` does fits there (``_fits`` of ``_misfit`` against the fragments both
            put on that marker) and, where ``other`` puts it, has no judge or is above the
            jump bound on every one (``PIECES_BREAK_TIES``; figure 21448: a 14-frame piece
            that one judge fits at 0.14 x the bound, and none sees on the marker the voters
            put it on, gaining 3.504 against 3.490)"""
            bound = jump_margin * s0 ** 2
            moved = set(alt[0]) ^ set(other[0])
            for f in moved:
                g = alt[0] if f in alt[0] else alt[1]
                h = other[0] if f in other[0] else other[1]
                on_alt = _misfit(X, vis, P, sd_of, f, [e for e in g if e not in moved], ex,
                                 rigid * s0, bound, voter_frames)
                on_other = _misfit(X, vis, P, sd_of, f, [e for e in h if e not in moved], ex,
                                   rigid * s0, bound, voter_frames)
                if not (_fits(on_alt, bound)
                        and (on_other.size == 0 or on_other.min() > bound)):
                    return False
            return bool(moved)

        bad = [m for m, g in enumerate(groups) if any(
            part[f].size and np.nanmax(_sd_to(P[:, part[f]], P[:, m], min_frames)) > rigid * s0
            for f in g if f in part)]
        if rules.MISFITS_ARE_BAD:
            # a marker holding a piece that sits off its other fragments on every judge
            # (step 4c's misfit) is examined too: a short piece barely moves a track's sd
            bad += [m for m, g in enumerate(groups) if m not in bad and holds_misfit(m, g)]
        best = None
        for a in bad:
            for b in range(M):
                if b == a:
                    continue
                alts = _cross_alternatives(span, groups[a], groups[b])
                if not alts:
                    continue
                ex = [a, b]
                q = np.setdiff1d(np.concatenate(
                    [part[f] for f in groups[a] + groups[b] if f in part] + [[]]),
                    ex).astype(int)
                keep = None
                if rules.RIGID_SOMEWHERE:
                    # a partner counts where it is rigid to one of the tracks the pair
                    # makes in some alternative (figure 7429: partners across a joint,
                    # rigid over a voter's frames only, decided a move)
                    keep = np.zeros(M, bool)
                    tr = [P[:, a], P[:, b]] + [t for na, nb in alts
                                               for t in _tracks(X, [na, nb]).transpose(1, 0, 2)]
                    for t in tr:
                        sdq = _sd_to(P[:, q], t, min_frames)
                        keep[q[sdq <= rigid * s0]] = True
                now = score(groups[a], P[:, a], q, keep) + score(groups[b], P[:, b], q, keep)
                cands = []              # (na, nb, gain, judged without moving a voter in)
                for na, nb in alts:
                    judged = checked(na, groups[a], ex) and checked(nb, groups[b], ex)
                    if not judged and not (rules.CLEAR_VOTER_MOVES
                                           and checked(na, groups[a], ex, voters=True)
                                           and checked(nb, groups[b], ex, voters=True)):
                        continue
                    if not (_paced(X, span, na, max_step) and _paced(X, span, nb, max_step)):
                        continue
                    ta, tb = _tracks(X, [na, nb]).transpose(1, 0, 2)
                    gain = now - score(na, ta, q, keep) - score(nb, tb, q, keep)
                    cands.append((na, nb, gain, judged))
                clear = _clear_voter_moves(cands, margin) if rules.CLEAR_VOTER_MOVES else set()
                state = {}

                def allowed(na, nb):
                    """no veto (module docstring) stops the exchange (na, nb)"""
                    # never an exchange that step 4's jump test would undo
                    if "jumps" not in state:
                        state["jumps"] = _jumps(X, vis, groups[a], groups[b], alts,
                                                P[:, strict(a, b)], jump_margin * s0 ** 2,
                                                rules.JUMPS_PER_MARKER)
                    now_j, alt_j = state["jumps"]
                    if alt_j[alts.index((na, nb))] >= now_j + jump_margin * s0 ** 2:
                        return False
                    if "turns" not in state:
                        state["turns"] = turning_judged(a, b)
                    turns = state["turns"]
                    if turns is not None and _turning(X, vis, na, nb) >= turns + turn_margin:
                        return False
                    if body_veto and (displaced(groups[a], na, groups[b], ex)
                                      or displaced(groups[b], nb, groups[a], ex)):
                        return False
                    return not (rules.NO_NEW_MISFITS
                                and (misfit_made(groups[a], na, groups[b], ex)
                                     or misfit_made(groups[b], nb, groups[a], ex)))

                here = None
                for i, (na, nb, gain, judged) in enumerate(cands):
                    if not (judged or i in clear):
                        continue
                    if gain < margin and not (
                            rules.BODY_CONFIRMS and gain >= rules.BODY_CONFIRMS_FRACTION * margin
                            and (best is None or gain > best[0])
                            and _onto_bodies(vis, P, sd_of, groups[a], na, groups[b], nb, ex,
                                             one_body * s0, voter_frames)):
                        continue
                    if (best is None or gain > best[0]) and allowed(na, nb):
                        best = here = (gain, a, b, na, nb)
                if here is not None and here[0] >= margin and rules.PIECES_BREAK_TIES:
                    # the voters cannot tell exchanges within the margin apart: the pieces
                    # they place differently go where a judge fits them (figure 21448)
                    for i in sorted(range(len(cands)), key=lambda i: -cands[i][2]):
                        na, nb, gain, judged = cands[i]
                        if (margin <= gain and here[0] - margin < gain
                                and (na, nb) != here[3:] and (judged or i in clear)
                                and placed_better((na, nb), here[3:], ex)
                                and allowed(na, nb)):
                            best = (here[0], a, b, na, nb)
                            break
        if best is None:
            break
        _, a, b, na, nb = best
        groups[a], groups[b] = na, nb
    return groups

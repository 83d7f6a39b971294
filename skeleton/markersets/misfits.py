"""Step 4c of the marker-set merge: misfit pieces move to the marker they fit.

4c. misfit pieces (``_move_misfits``): a piece too short to move a track's sd (figure 617:
   the first 11 frames of a marker whose next piece starts 26 frames later, given to a
   marker of another segment 4.6-9.4 mm from it over those frames) is judged by the jumps
   instead: a fragment that sits off its marker's other fragments on every judge
   (``_misfit`` above ``jump_margin`` times the measured sd squared on each track rigid to
   it and to them for >= 100 frames; one judge at the same distance is support enough:
   in figure 31 a marker of another segment rigid to both fragments of one marker sat
   9.7 mm further from the first) - or that a track moving as one body with them (sd <=
   1.5 x s0 to each, over >= 100 frames: a segment partner, not a marker across a joint
   rigid for a while, as in figure 31) finds not rigid to it (> 3 x s0) or at another
   distance (jump above the bound): figures 186 and 925, a piece of another segment's
   marker whose one-body partners there were 5.2-15.2 x s0 off rigid to it, so no judge
   saw it - moves to the one marker, sharing no frame with it, that it fits (within that
   bound on every judge, and off no one-body partner), one move per round, the largest
   misfit first. A piece that no track judges on its own marker (no judge, and off no
   one-body track) moves, after the misfits, to the one marker on which judges at its
   distance from that marker's fragments see it for >= ``UNJUDGED_EVIDENCE`` (20) frames
   in all, twice what one judge needs (``UNJUDGED_MOVES``; figure 556: marker 8's last 10
   frames, no partner of it seen, sat on a marker of the next segment at the distance of
   one marker there, rigid to them over those 10 frames; there a judge rigid
   for the piece's few frames only may disagree: figure 3019, marker 1's first 18 frames
   on a marker of another segment, its two segment partners at the same distance from
   them as from the rest of marker 1 (0.01 and 0.58 x the bound) and a marker of the next
   segment, rigid to both by the sd bound, 3.55 x the bound off; figures 403 and 3016,
   the first pieces of a marker given to another segment's marker, whose partners are not
   rigid to them). With fewer frames of evidence it moves to a free marker where every
   judge fits it only when its motion continues there better than on its own marker
   (``UNJUDGED_CONTINUES``, stop 74, ``_continues_best``: of one such marker, when it raises
   that marker's continuity cost less than taking it off its own lowers that; of several,
   the clear best). Held-out figure 24267 (stop 73): marker 23's last 16 frames (2-marker
   segment 7, its partner seen) sat at the end of marker 3 (2-marker segment 1, hidden from
   4 frames before, its partner from 10 before); on marker 23 the partner fitted them at
   0.08 x the bound over 16 frames, and the piece raised marker 23's cost by 0.60 where
   taking it off marker 3 lowered that by 5.80; the move must lower the sum by
   ``CONTINUITY_OPEN_MARGIN`` (2) at least (figure 556's piece: 5.65 against 1.94, it
   stays; figure 1304's, 1.40 against 3.00, to the wrong marker, stays). A misfit that no
   marker free over its frames takes is exchanged (``MISFIT_EXCHANGES``): the one
   overlap-free exchange of a run of fragments between its marker and another that moves
   it there and after which every moved fragment fits the fragments its new marker kept
   (``_fits``, and off no one-body track) is made (figure
   3224, held out at stop 39: the linkage gave marker 5 (a 4-marker segment) marker 19's
   first 11 frames and marker 19 (a 2-marker segment) marker 5's first 27. Marker 19's
   piece sat 13.5-35.2 x the bound off on all three of marker 5's segment partners and
   fitted marker 19 (0.57 x the bound on its partner), but marker 19 was seen then; step
   4b's sd gain of the exchange was 0.63, under its margin of 1). A piece off its
   marker's body that some judge still finds where it is moves (or is exchanged) only
   where a judge on the new marker is not one of those (``TELLING_JUDGES``, ``_tells``;
   figure 4083, held out at stop 41: the linkage merged every marker right, but a track
   across a joint, one body with marker 8 until then, sat 3.1 mm further from its last
   23 frames, and on marker 10 (same segment) the piece's one judge was segment partner
   9, 90.2 mm from marker 8 and 89.5 from marker 10, which finds it on marker 8 too).
   A piece that a track moving as one body with its marker's other fragments finds not
   rigid to it (> 3 x s0), that no judge finds where it is and that no marker fits on a
   judge moves to the one marker free over its frames (and paced), where no judge finds
   it at another distance and no one-body track off it (``ONLY_FREE_MARKER``; figure
   4662, held out at stop 42: the linkage put marker 13's first 32 frames at the start of
   marker 4, another segment's, 5.5 x s0 off its segment partner; marker 13's partner is
   seen with the piece for 8 frames, so no judge placed it. Off by the jump test alone,
   or with a judge at home, it moved right pieces in figures 339, 1306, 2539 and 4465);
   where several markers are free, to the one of them where no judge or one-body track
   finds it off when every other has one that does (``ONE_UNJUDGED_FREE``; figure 5221,
   held out at stop 45: marker 58's last 13 frames, its partner hidden by then, sat on
   marker 28 of another segment 6.8 and 7.3 x s0 off its partners; of the four markers
   free over those frames, three had a track finding the piece off). A piece every
   judge at home finds at other distances (none finds it there), that no marker fits and
   no exchange takes, goes to the marker free over its frames, with no judge or one-body
   track finding it off there, that its motion continues best: of two or more such
   markers, the one whose step-8 continuity cost it raises least, by at least
   ``CONTINUITY_OPEN_MARGIN`` (2) less than the next and by less than taking it off its
   marker lowers that marker's (``CONTINUITY_OPEN``; figure 4462, failing since stop 44:
   marker 30's first 17 frames sat on marker 1 of the root segment, over 1000 x s0
   squared off its three partners; markers 29 and 30 were free and unjudged, with added
   costs 3.78 and 1.61, and taking the piece off marker 1 lowered its cost by 2.49).
   Where one marker only is free and unjudged it goes there when it raises that marker's
   cost by ``CONTINUITY_OPEN_MARGIN`` less than taking it off lowers its own (``ONE_OPEN``,
   figure 9778: 1.34 against 3.36; the margin since stop 75, ``ONE_OPEN_CLEAR``: held-out
   figure 25854, marker 26's first 19 frames on their own marker, 82.9 and 3.47 x the
   bound off two markers of the parent segment across a ball joint, went to marker 27,
   its segment partner, at 2.19 against 3.17).
   An off-body piece of ``ONLY_FREE_MARKER``'s kind with several free markers where
   nothing finds it off goes the same way (``CONTINUITY_OFF_BODY``; figure 2738, failing
   since stop 38: marker 0's first 23 frames sat on marker 6, 6.1 x s0 off its one-body
   track; markers 0 and 1 free and unjudged, added costs 0.69 and 4.46; off marker 6,
   3.66). Such a piece (off its marker's body, found there by no judge) that no marker
   fits and no exchange takes goes to the one free marker whose one-body tracks all hold
   it (sd <= 1.5 x s0, at their distances: not ``_off_body``) when every other free
   marker has a one-body track it is off (``BODY_FITS_FREE``; held-out figure 10847,
   stop 55: marker 11's first 39 frames sat on marker 25 of the next segment, 382 x s0
   squared off its segment partner; on marker 11 a judge on segment 16, rigid to it
   but not one body with it, found the piece 191 x s0 squared off while its three one-body
   tracks found it at 0.01-2.3).
   In an exchange the misfit itself may go where no track judges it (no judge, off no
   one-body track) when a piece judged to fit comes back in its place
   (``EXCHANGE_UNJUDGED``; figure 4251, held out at stop 41: the linkage exchanged the
   first pieces of marker 13 (a 3-marker segment) and marker 46 (a 2-marker sibling
   segment); marker 46's piece sat 216.9 x s0 squared off marker 13's partner 12, marker
   13's fitted marker 13 on both its partners, but marker 46's partner is not seen with
   marker 46's piece). A piece off its marker's body that every judge there fits, and that
   a one-body track there holds too (rigid to it at its distance from the marker's other
   fragments, ``_body_holds``), is not off its body: the one-body tracks that find it at
   another distance are across a joint that moved while the marker was hidden
   (``SPLIT_BODY_STAYS``, stop 57; held-out figure 11934: marker 4's first 13 frames, at
   0.0 and 0.32 x the bound from its segment partners and 2.86 and 2.67 x off two markers
   of the child segment, moved to a marker two joints away). ``/tmp`` driver, one
   ``_repairs_from`` per cached figure with the rule on (it withdraws an off-body flag on
   most figures, so it was not re-run off): 4738/4738, every cached figure of 0-1737,
   2146-3573, 3880-5136 and 11737-11999 and 52 others; not run on the other 4,383 then
   (stop 58, on 6e5b524: all 4,383 right, 2175/2175 and 2242/2242 with named figures).
   An off-body piece that no judge places, no marker fits, no exchange and no one-body
   track takes, with several free markers where nothing finds it off and none that
   continues it clearly best, goes to the one whose joint sphere it lies on
   (``SPHERE_OFF_BODY``, stop 60, ``bodies._sphere_pick``: step 11's test in the frame of
   each body one joint away, also where the body shows three of four or more tracks,
   ``_partial_frames``, or two and a borrowed joint; within ``SPHERE_FIT_Z`` (3) x the
   sphere's rms there and off no body's by ``SPHERE_MISFIT_Z`` (6), every other such
   marker off its own by 6 on some body). Held-out figure 12527: marker 50's last 19
   frames (2-marker segment 16, both markers hidden then) sat on marker 23 of another
   segment; markers 49 and 50 were free with no track seen with the piece; in the frame
   of segment 13 (the parent, three of its four markers seen) the piece lay on marker
   50's sphere (234 mm) at 1.2 x its rms and 27 x off marker 49's (205 mm).
   On the marker a piece would move to, a judge that drifts across a joint (rigid to that
   marker's fragments within 3 x s0, but with a distance sd above the one-body 1.5 x s0)
   allows for its drift: its ``_jump_ss`` of the piece is divided by 1 + n x (sd^2 -
   (1.5 s0)^2) / s0^2 for the piece's n frames with it (``DRIFT_JUDGES``, stop 61,
   ``judges._drift_allowance``). Held-out figure 12450: marker 8's last 17 frames sat on
   marker 28 of another segment, 1.18 and 7.79 x the bound off both its segment partners;
   on marker 8 the segment partner fitted the piece at 0.00, but a marker of the child
   segment, at distance sd 2.64 x s0, found it 13.7 x off (0.17 with the allowance).
   An off-body piece most of whose judges at home fit it (two at least, more than half)
   moves, or is exchanged, only onto a marker where at least as many judges fit it
   (``HOME_MAJORITY_STAYS``, stop 72; step 12's ``MODEL_HALF_FITS`` asks the same of its
   mates). Held-out figure 22706 (stop 71): marker 3's last 66 frames (3-marker segment
   1), off a one-body track of marker 3 and 13.3 x the bound off one judge, but at 0.53
   and 0.38 x on the other two, went by a one-sided exchange onto marker 36's first piece
   (2-marker segment 12), free once step 4c had taken marker 35's piece off it, where one
   judge fitted it over 19 frames.
   At home, a track that finds a piece off (a judge beyond the bound, or a one-body track)
   is set aside where it is at a pose to a judge that fits the piece not seen over the
   marker's other fragments (``NOVEL_POSE_ASIDE``, stop 80, ``judges._novel_pose``: the two
   not rigid over those frames, distance sd above ``NOVEL_POSE_SD`` (3) x s0, and over the
   piece at a mean distance out of their range there by more than that). A marker near a
   joint axis moves as one body with markers across the joint over the angles seen, and
   the piece may be at another angle. Held-out figure 33057 (stop 79): marker 1's first 10
   frames (2-marker root segment {0, 1}) fitted marker 0 (0.16 x the bound) but were 47.9
   and 5.8 x off markers 7 and 8 (a hinge child, one body with marker 1 over its other
   frames, sd 1.81 and 2.24 mm), and moved to marker 10, whose partner fitted them. Over
   the piece marker 7 is 200.3-203.4 mm from marker 0, against 137.1-191.8 mm (sd 14.5)
   over marker 1's other frames; marker 8 343.7-347.0 against 281.7-335.2 mm.

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

import numpy as np

from . import rules
from .bodies import _sphere_pick
from .continuity import _continuity_cost
from .judges import (
    _body_sds, _fits, _fits_on, _jump_ss, _misfit, _novel_pose, _off_body, _off_tracks, _placed,
    _tells, _unjudged_on
)
from .tracks import (
    _cross_alternatives, _fragment_sd, _paced, _pair_sd, _spans, _tracks
)


def _move_misfits(X, groups, min_frames, s0, rigid=3.0, jump_margin=10.8, voter_frames=100,
                  max_rounds=10, one_body=1.5, max_step=np.inf):
    """Step 4c (module docstring): a fragment that fits the other fragments of its marker
    on no judge (``_misfit`` above ``jump_margin`` x s0 squared on every track rigid to it
    and to them: it sits at other distances from all their segment partners; one judge at
    the same distance is support enough - in figure 31 a marker of another segment, rigid
    to both fragments, sat 9.7 mm further from one) - or that is off a track moving as one
    body with them (``_off_body``; ``one_body`` x s0, 0 turns it off) - moves to the one
    marker it fits (``_fits``, and not ``_off_body``) without sharing a frame with it,
    where a judge there does not also find it on its own marker (``_tells``) - a piece
    not rigid to a one-body track of its marker, found there by no judge and fitting no
    marker on a judge, to the one marker free over its frames where no judge or one-body
    track finds it off (``ONLY_FREE_MARKER``; of several free markers, the one where
    nothing finds it off, ``ONE_UNJUDGED_FREE``) - a misfit no marker fits and no
    exchange takes, to the free marker that continues it best (``CONTINUITY_OPEN``,
    ``_continues_best``); one move per round (the largest misfit first; a piece no judge
    sees, first of all), at most ``max_rounds``."""
    vis = ~np.isnan(X[..., 0])
    span = _spans(vis, groups)
    bound = jump_margin * s0 ** 2
    for _ in range(max_rounds):
        P = _tracks(X, groups)
        M = len(groups)
        sd_of = _fragment_sd(X, vis, P, min_frames)

        seen = [vis[:, g].any(1) for g in groups]
        drift = (s0, one_body * s0) if rules.DRIFT_JUDGES else None
        moves = []
        for a, g in enumerate(groups):
            if len(g) < 2:
                continue
            for f in g:
                kept = [h for h in g if h != f]
                miss, judges = _misfit(X, vis, P, sd_of, f, kept, [a], rigid * s0, bound,
                                       voter_frames, with_judges=True,
                                       drift=drift if rules.HOME_DRIFT else None)
                aside, off_ = [], None
                if rules.NOVEL_POSE_ASIDE and (miss <= bound).any():
                    # tracks that find f off at a pose to a home judge that fits it never
                    # seen over its marker's other frames: across a joint (figure 33057)
                    fit = judges[miss <= bound]
                    off_ = _off_tracks(X, vis, P, sd_of, f, kept, [a], rigid * s0,
                                       one_body * s0, bound, voter_frames)
                    aside = _novel_pose(vis, P, f, kept, fit,
                                        sorted((set(judges[miss > bound].tolist())
                                                | set(off_.tolist())) - set(fit.tolist())),
                                        rules.NOVEL_POSE_SD * s0, voter_frames)
                    stay = ~np.isin(judges, aside)
                    miss, judges = miss[stay], judges[stay]
                # judges that find f where its marker is (an off-body piece can have some)
                at_home = set(judges[miss <= bound].tolist())
                if off_ is None:
                    off = _off_body(X, vis, P, sd_of, f, kept, [a], rigid * s0,
                                    one_body * s0, bound, voter_frames)
                else:            # per-track results: those of off_ not set aside
                    off = bool(set(off_.tolist()) - set(aside))
                if (off and rules.SPLIT_BODY_STAYS and _fits(miss, bound)
                        and _body_holds(X, vis, P, sd_of, f, kept, [a], rigid * s0,
                                        one_body * s0, bound, voter_frames)):
                    off = False          # its body's tracks disagree (figure 11934)
                unjudged = rules.UNJUDGED_MOVES and miss.size == 0 and not off
                # an off-body piece most of whose judges at home fit it (two at least)
                held = (rules.HOME_MAJORITY_STAYS and off and len(at_home) >= 2
                        and 2 * len(at_home) > miss.size)
                if not (miss.size and miss.min() > bound) and not off and not unjudged:
                    continue

                def as_held(kept, b):
                    # a held piece moves only where as many judges fit it as at home (22706)
                    return not held or _misfit(X, vis, P, sd_of, f, kept, [a, b], rigid * s0,
                                               bound, voter_frames,
                                               drift=drift).size >= len(at_home)

                judged_on = {}    # an unjudged piece's judges on each free marker

                def fits_in(b):
                    if unjudged:
                        judged_on[b] = _misfit(X, vis, P, sd_of, f, groups[b], [a, b],
                                               rigid * s0, bound, voter_frames,
                                               with_frames=True)
                        return _placed(judged_on[b], bound)
                    if not _fits_on(X, vis, P, sd_of, f, groups[b], [a, b], rigid * s0,
                                    one_body * s0, bound, voter_frames, drift=drift):
                        return False
                    return as_held(groups[b], b) and _tells(
                        X, vis, P, sd_of, f, groups[b], [a, b], rigid * s0, bound,
                        voter_frames, at_home)

                free = [b for b in range(M) if b != a and not (seen[b] & vis[:, f]).any()
                        and _paced(X, span, groups[b] + [f], max_step)]
                to = [b for b in free if fits_in(b)]

                def open_free():
                    # the free markers where no track judges f (``_unjudged_on``)
                    return [b for b in free if _unjudged_on(
                        X, vis, P, sd_of, f, groups[b], [a, b], rigid * s0, one_body * s0,
                        bound, voter_frames)]

                key = -1.0 if unjudged else float(miss.max()) if miss.size else np.inf
                if len(to) == 1:
                    moves.append((key, f, a, to[0], None))
                elif (not to and off and rules.ONLY_FREE_MARKER and not at_home
                      and (len(free) == 1 or rules.ONE_UNJUDGED_FREE)
                      and (_body_sds(vis, P, sd_of, f, kept, [a], one_body * s0,
                                     voter_frames)[1] > rigid * s0).any()
                      and (open_ := open_free())
                      and (len(open_) == 1 or rules.CONTINUITY_OFF_BODY and (
                          b := _continues_best(X, vis, groups, f, a, open_)) is not None)):
                    # off its marker's body (not rigid to a one-body track; no judge finds
                    # it there), and one marker only is free over its frames, with no track
                    # there to judge it (figure 4662) - or, of several free markers, the
                    # others all have a track that finds it off (ONE_UNJUDGED_FREE, figure
                    # 5221) - or, of several with none, the one that continues it best
                    # (CONTINUITY_OFF_BODY, figure 2738)
                    moves.append((key, f, a, open_[0] if len(open_) == 1 else b, None))
                elif (not to and unjudged and rules.UNJUDGED_CONTINUES
                      and (b := _continues_best(
                          X, vis, groups, f, a,
                          [c for c in free if _fits(judged_on[c][0], bound)],
                          clear=rules.CONTINUITY_OPEN_MARGIN)) is not None):
                    # no judge at home, and judges that fit it on free markers too few
                    # frames to place it: the one of those that its motion continues clearly
                    # better than its own marker does (figure 24267; not 1304)
                    moves.append((key, f, a, b, None))
                elif not to and not unjudged and rules.MISFIT_EXCHANGES:
                    swaps = _misfit_exchanges(X, vis, P, sd_of, span, groups, f, a, rigid * s0,
                                              one_body * s0, bound, voter_frames, max_step,
                                              at_home)
                    swaps = [w for w in swaps
                             if as_held([h for h in w[2] if h in groups[w[0]]], w[0])]
                    if len(swaps) == 1:
                        moves.append((key, f, a, swaps[0][0], swaps[0][1:]))
                    elif (rules.CONTINUITY_OPEN and not swaps and not at_home and miss.size
                          and miss.min() > bound and (b := _continues_best(
                              X, vis, groups, f, a, open_free())) is not None):
                        # every judge at home finds it away, no marker fits it and no
                        # exchange takes it: the free marker with no track to find it off
                        # that continues its motion clearly best (figure 4462)
                        moves.append((key, f, a, b, None))
                    elif (rules.BODY_FITS_FREE and not swaps and off and not at_home
                          and (b := _one_body_fits(X, vis, P, sd_of, f, groups, free, [a],
                                                   rigid * s0, one_body * s0, bound,
                                                   voter_frames)) is not None):
                        # off its marker's body, found there by no judge, taken by no
                        # marker or exchange: the one free marker whose one-body tracks
                        # all hold it as their own, every other free marker off one of
                        # its one-body tracks (figure 10847)
                        moves.append((key, f, a, b, None))
                    elif (rules.SPHERE_OFF_BODY and not swaps and off and not at_home
                          and (_body_sds(vis, P, sd_of, f, kept, [a], one_body * s0,
                                         voter_frames)[1] > rigid * s0).any()
                          and len(open_ := open_free()) > 1
                          and (b := _sphere_pick(X, P, *_pair_sd(P, min_frames), f, a,
                                                 open_, one_body)) is not None):
                        # the same, with several free markers where nothing finds it off
                        # and none that continues it clearly best: the one whose joint
                        # sphere it lies on, the others' off (figure 12527)
                        moves.append((key, f, a, b, None))
        if not moves:
            break
        _, f, a, b, swap = max(moves, key=lambda m: m[:3])
        if swap is None:
            groups[a] = [h for h in groups[a] if h != f]
            groups[b] = groups[b] + [f]
        else:
            groups[a], groups[b] = swap
    return groups


def _body_holds(X, vis, P, sd_of, f, kept, excl, rigid_sd, body_sd, bound, body_frames):
    """Some track moving as one body with the fragments ``kept`` (``_body_sds``) holds
    fragment ``f`` as theirs: rigid to it (sd <= ``rigid_sd``) at the distance it keeps from
    them (``_jump_ss`` of kept + [f] within ``bound`` of kept's) (``SPLIT_BODY_STAYS``).
    Where others find f off (``_off_body``) and every judge fits it (``_fits``), those
    others are across a joint that was still while the marker's other fragments were seen:
    figure 11934 (held out at stop 57), marker 4's first 13 frames, at 0.0 and 0.32 x the
    bound from its segment partners (markers 2 and 3) and 2.86 and 2.67 x off markers 27
    and 28 of the child segment, one body with marker 4 over >= 100 frames, moved to
    marker 42 of a segment two joints away, where its one judge fitted it (0.08)."""
    js, sd = _body_sds(vis, P, sd_of, f, kept, excl, body_sd, body_frames)
    if js.size == 0:
        return False
    ss = _jump_ss(X, vis, kept + [f], P[:, js])
    return bool(((sd <= rigid_sd) & (ss(kept + [f]) - ss(kept) <= bound)).any())


def _one_body_fits(X, vis, P, sd_of, f, groups, free, excl, rigid_sd, body_sd, bound,
                   partner_frames):
    """The one marker of ``free`` (indices into ``groups``) whose one-body tracks
    (``_body_sds``: moving as one body with its fragments, seen with fragment ``f``; one at
    least) all move as one body with f too (sd <= ``body_sd``) at the distances they keep
    from that marker (not ``_off_body``), where every other marker of ``free`` has a
    one-body track f is off (sd > ``rigid_sd``); else None (``BODY_FITS_FREE``, step 4c).
    A judge rigid to a marker but not one body with it can be across a joint that was
    still while that marker was seen: in figure 10847, marker 11's first 39 frames sat on
    marker 25 of the next segment (its segment partner there put the piece 382 x s0
    squared off), and on marker 11 one judge, marker 44 of segment 16, rigid to it,
    found it 191 x s0 squared off, where its three one-body tracks (sd 0.7-1.06 x s0) found
    it at 0.01-2.3; the other free marker's one-body tracks were 11-13 x s0 off it."""
    takes, off = [], 0
    for b in free:
        js, sd = _body_sds(vis, P, sd_of, f, groups[b], excl + [b], body_sd, partner_frames)
        if js.size and (sd > rigid_sd).any():
            off += 1
        elif (js.size and (sd <= body_sd).all()
              and not _off_body(X, vis, P, sd_of, f, groups[b], excl + [b], rigid_sd,
                                body_sd, bound, partner_frames)):
            takes.append(b)
    return takes[0] if len(takes) == 1 and off == len(free) - 1 else None


def _continues_best(X, vis, groups, f, a, open_, clear=0.0):
    """Step 4c's ``CONTINUITY_OPEN`` and ``CONTINUITY_OFF_BODY``: of the markers ``open_``
    (free over fragment ``f``'s frames, no track judging it there: ``_unjudged_on``), the
    one whose continuity cost (step 8's ``_continuity_cost``) f raises least, when that is
    less than taking f off its marker ``a`` lowers it and at least
    ``CONTINUITY_OPEN_MARGIN`` less than the next such marker's; else None (also with fewer
    than two such markers, unless ``ONE_OPEN``: then the one, when f raises its cost less
    than taking f off a lowers a's, by ``CONTINUITY_OPEN_MARGIN`` less with
    ``ONE_OPEN_CLEAR``). ``UNJUDGED_CONTINUES`` passes, for a piece no track
    judges at home, the free markers where judges fit it over too few frames to place it,
    and asks the move to lower the sum of the two costs by ``clear``
    (``CONTINUITY_OPEN_MARGIN``) at least: figure 24267, 0.60 against 5.80, moves; figure
    1304, marker 3's last 18 frames on marker 2, fitted on marker 4 of the same segment by
    one judge (marker 3 held marker 4's last piece), 1.40 against 3.00, does not: the
    wrong marker, which later steps put right. Figure 9778: marker 20's 13-frame first
    piece, 527 and 1057 x the bound off both judges of marker 10 it sat on, one marker
    free, 1.34 against 3.36. Figure 4462: marker 30's first 17 frames, rigid to markers 0,
    2 and 3 of the root segment while the chain between barely moved (but at other
    distances than marker 1), sat on marker 1; markers 29 and 30 were both free and
    unjudged, and f raised their costs by 3.78 and 1.61 (taking it off marker 1 lowered
    that by 2.49).
    Figure 2738: marker 0's first 23 frames, off the one-body track of marker 6 it sat on,
    no judge placing it; markers 0 and 1 free and unjudged, added costs 0.69 and 4.46
    (taking it off marker 6, 3.66)."""
    if len(open_) < (1 if rules.ONE_OPEN else 2):
        return None
    cost = _continuity_cost(X, vis)
    gain = cost(groups[a]) - cost([h for h in groups[a] if h != f])   # f off its marker
    if len(open_) == 1:
        # one marker free and unjudged: it continues f better than its marker does
        # (``ONE_OPEN``; figure 9778)
        # by CONTINUITY_OPEN_MARGIN at least (``ONE_OPEN_CLEAR``; held-out figure 25854:
        # marker 26's first 19 frames, on their own marker, 2.19 against 3.17, moved)
        b = open_[0]
        if rules.ONE_OPEN_CLEAR:
            clear = max(clear, rules.CONTINUITY_OPEN_MARGIN)
        return b if cost(groups[b] + [f]) - cost(groups[b]) + clear < gain else None
    (best, b), (second, _) = sorted((cost(groups[b] + [f]) - cost(groups[b]), b)
                                    for b in open_)[:2]
    return (b if best + clear < gain and second - best >= rules.CONTINUITY_OPEN_MARGIN
            else None)


def _misfit_exchanges(X, vis, P, sd_of, span, groups, f, a, rigid_sd, body_sd, bound,
                      partner_frames, max_step, at_home=frozenset()) -> list:
    """Step 4c's exchanges for misfit fragment ``f`` of marker ``a`` that no marker free
    over its frames takes: every overlap-free exchange of a run of fragments between a and
    another marker b (``_cross_alternatives``) that moves f to b and after which every
    moved fragment fits the fragments its new marker kept (``_fits`` of ``_misfit``: some
    judge, every one within ``bound``; and not ``_off_body``; f itself may be unjudged
    there, ``_unjudged_on``, when a fragment moves into a, ``EXCHANGE_UNJUDGED``) and no
    change of fragment crosses its gap faster than ``max_step`` (``_paced``). Returns (b,
    a's fragments, b's fragments) for each."""
    def takes(new, old, ex, unjudged=()):
        kept = [h for h in new if h in old]
        return bool(kept) and _paced(X, span, new, max_step) and all(
            _fits_on(X, vis, P, sd_of, h, kept, ex, rigid_sd, body_sd, bound, partner_frames)
            or (h in unjudged and _unjudged_on(X, vis, P, sd_of, h, kept, ex, rigid_sd,
                                               body_sd, bound, partner_frames))
            for h in new if h not in old)

    # the misfit itself may go where no track judges it when a piece judged to fit comes
    # back in its place (``EXCHANGE_UNJUDGED``, figure 4251)
    own = (f,) if rules.EXCHANGE_UNJUDGED else ()
    return [(b, na, nb) for b in range(len(groups)) if b != a
            for na, nb in _cross_alternatives(span, groups[a], groups[b])
            if f in nb and takes(na, groups[a], [a, b])
            and takes(nb, groups[b], [a, b], own if set(na) - set(groups[a]) else ())
            and _tells(X, vis, P, sd_of, f, [h for h in nb if h in groups[b]], [a, b],
                       rigid_sd, bound, partner_frames, at_home)]

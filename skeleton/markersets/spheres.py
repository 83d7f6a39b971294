"""Steps 8, 11 and 12b of the marker-set merge: joint spheres, directions and continuity.

8. joint spheres (``_sphere_exchanges``): a marker turns about its segment's joint with a
   neighbouring segment, so in that segment's frame it stays on a sphere about the joint.
   Two markers moving as one body (sd <= 1.5 x s0 over >= 100 frames) that no earlier step
   could tell apart (a 2-marker segment whose markers are both hidden across one gap,
   figures 221 and 718: no partner, and the direction turned too far to judge) are told by
   it. A body is three or more tracks moving as one body with each other (its frame: Kabsch
   onto their positions in the first frame all are seen); a pair's every overlap-free
   exchange of a run of fragments (each partition once) is fitted, in the frame of every
   body that holds neither, by one sphere centre (the joint, common to both markers) and a
   radius per marker (Kasa's algebraic fit), for the current assignment and the exchanged
   one. A body judges when the better assignment fits within ``fit_rms`` (1.5) x s0 rms (a
   neighbour across one joint; bodies further away fit worse). The exchange is made when
   on some judge the exchanged pieces (the smaller side) sit >= ``min_misfit`` (2) residual
   sds off rms under the current assignment and under half that under the exchanged one,
   and no judge finds the reverse; the largest gain in the sum of squares first, one per
   round. Designed on figures 0-199 (all merged right by steps 1-7; 227 exchanges a judge
   preferred by up to 241 residual variances were effects of 1.32 sd at most, 1.4x the
   exchanged fit) and the failures 221, 718, 1056, 1097 (2.78-16.7 sd, 3.0-17x the
   exchanged fit). ``/tmp`` screen, one ``merge_fragments`` per figure as
   ``bench_markersets.py`` builds them: figures 0-999 991 -> 993 of 1000 (fixed 221, 718),
   1000-1119 116 -> 118 (fixed 1056, 1097), none lost; held out, first run 1120-1239 (the
   code before step 8 and this one): 116 -> 117 of 120 (fixed 1126, none lost); 1240-1359:
   117 and 117, identical per figure (1304 and 1306 are same-segment swaps it measured below
   its thresholds: 2.17 sd at 1.99x the exchanged fit, and 1.34 sd). It cannot
   judge a 2-marker segment whose neighbours have fewer than three markers (157: its only
   neighbour has two; 1210), nor pieces of two segments (569, 1026, 1037, 1183, 1239: the
   test compares two markers on one centre; 569's siblings share no body of >= 3 markers).
   Where the spheres cannot decide (the two markers about as far from their joint), the
   direction between the two markers does (stop 34): in a body's frame it turns only by the
   joints' ranges of motion between them (a neighbour's: one joint's), and an exchange of a
   run of fragments flips it over the frames it moves. For both assignments, the mean
   resultant length of the unit direction over the frames both markers are seen with the
   body (at least ``DIRECTION_FRAMES``); on the body where the larger of the two is highest,
   an exchange that raises it by ``DIRECTION_MARGIN`` (0.1) is made when no body finds the
   reverse by as much and no sphere judge vetoes it; only when no sphere exchange is found,
   the largest rise first. 1 mm noise on markers 20 mm apart lowers the length by ~0.005.
   Measured before the margin was chosen (``/tmp`` collector, figures 0-299, the 4753
   overlap-free alternatives step 8 scored): none of the 4750 that would have left a
   marker less pure raised the length on that body (largest rise 0.000); the two right
   ones raised it by 0.144 (157) and 0 (221, which the spheres repair). A piece seen only
   where the other marker is hidden leaves the direction blind (1304: an 18-frame end
   piece). Fixed: 157 (failing since stop 16; its only neighbour has two markers, and a
   sibling, two joints away, judges: 0.83 -> 0.98) and held-out 1504 and 1646 (first runs at
   stop 34: 2-marker segments whose markers sit about equally far from their joint; in
   1646's parent's frame 0.36 -> 0.94). ``/tmp`` screen of figures 0-1719, one
   ``merge_fragments`` per figure as ``bench_markersets.py`` builds them: 0-999 993 -> 994
   of 1000, 1000-1479 (held out at stops 25-31) the same 11 failures, 1480-1719 (first run
   at stop 34, on the code before) 235 -> 237 of 240; none lost. Held out, first run
   1720-1839 with and without it: 117 of 120 both, identical per figure (1749, 1750:
   pieces of two segments; 1833: two ids for one marker). Real recordings: merged groups
   identical with and without it (all 9 files of ../shared/data/c3d). A body judges the
   direction only where it sees the moved pieces for >= ``DIRECTION_MOVED_FRAMES`` (5)
   frames (``DIRECTION_SEES_MOVED``): a body whose frames miss them finds both
   assignments alike and, holding the direction tightest, hid every other body's verdict
   (figure 2710: two start pieces of a 2-marker segment's markers exchanged, 32 and 46
   frames; a body seeing none of those frames held the direction at 0.985 both ways,
   eight others rose by 0.07-0.29 with the exchange). Where neither the spheres nor the
   direction find an exchange, motion continuity may (``CONTINUITY_EXCHANGES``): a piece
   seen only while the other marker is hidden leaves the direction blind, and two markers
   about as far from their joint leave the spheres alike, but a piece of the other marker
   jumps at both its ends. A marker's continuity cost is the sum over its changes of
   fragment of log(1 + (miss / m)^2): the miss of step 3's constant-velocity lines, m the
   typical miss of one marker across that gap (0.6 mm x gap + 0.009 mm x gap^2, step 3's
   medians). The exchange that lowers the pair's cost most is made when it lowers it by
   ``CONTINUITY_EXCHANGE_MARGIN`` (2; 4 until stop 46), no sphere judge vetoes it and no
   body finds its direction worse by the direction margin - unless another body finds it
   better by as much (``CONTESTED_DIRECTIONS``, stop 53; held-out figure 8759: markers 52
   and 53 of a 2-marker segment, 20.5 mm apart, held each other's end pieces; the exchange
   gained 5.80, and 1 of 14 bodies held the direction tighter as merged, by 0.104, while 7
   held it tighter exchanged, by 0.1-0.32; held-out 9460: markers 36 and 37 of a
   2-marker segment stay exchanged without the rule). Measured before the margin was
   first chosen (``/tmp`` collector, figures 0-299, all merged right: the best alternative
   of each of the 4026 one-body pairs step 8 looks at in the final merge; before the later
   vetoes): every one would have mixed markers, and the largest cost they lowered was 2.41
   (7 of 4026 at 1 or more). The failures it fixes lowered it by 8.51 (3293, held out at
   stop 39: marker 43's 18-frame piece on marker 42, 79 and 53 mm off at gaps of 11 and 4
   frames, 6.3 and 16.4 mm on its own marker at 7 and 14; spheres 1.51 and 1.35 residual
   sds), 12.07 (611), 4.18 (1210) and 8.92 (1306); 1304's right exchange lowers it by 2.43
   only and stayed. At stop 46 a ``/tmp`` screen of figures 0-2699, 4040-4759 and 5480-5719
   (3660) logged every alternative that reached this test (with the later vetoes: the jump
   veto below, the direction seen on moved pieces) and lowered the cost by 1 or more: of
   28, 24 took the frames on a wrong marker to 0 (1.27-12.07) and three (1306, 2.15) from
   122 to 58; the other, in 1304 at 1.59, moved as many as it mended. The margin went to 2,
   fixing 1304 and 4385 (held out at stop 42, 3.52); the figures with an alternative at 2-4
   (1306, 1672, 1773, 2395, 4063) were merged again with it and stay right.
   ``/tmp`` screen with stop 40's three rules (4c's exchanges, step 7b, this), one
   ``merge_fragments`` per figure as ``bench_markersets.py`` builds them: figures 0-1839
   1834 -> 1839/1840 (fixed 339, 611, 1210, 1306, 1371; none lost), 1840-3559 1718/1720
   (2539, 2738 fail); held out, first run 3800-4039 with the rules off and on: 240/240
   both; real recordings' merged groups identical with and without them. No exchange is
   made (sphere, direction or continuity) that step 4's jump test would undo: one that
   raises ``_jumps`` on the tracks rigid to every fragment of both markers by
   ``jump_margin`` x s0 squared (``STEP8_JUMPS``; figure 4455, held out at stop 41: the
   direction test exchanged the last runs of two markers of a 4-marker segment, 130 mm
   apart, whose two segment partners put the jump cost at 7.8 mm^2 before and 2.2e6 after,
   bound 19.7; step 4b has the same veto).
   Where a body is seen in full over fewer than 5 of the moved pieces' frames (or a marker
   has < 50 points), the spheres are fitted again in the body's frame extended to the
   frames where it shows two or more of its tracks (``VIRTUAL_FRAMES``, stop 54): the
   joint it shares with a neighbouring body seen in full there (``_fixed_point``: the
   point fixed in both frames, linear least squares; the neighbour fitting best, within
   ``VIRTUAL_JOINT_RMS`` (5) x s0, the joint >= 20 mm off the line through the two tracks)
   is the third point of a Kabsch fit. Such a judge counts within ``VIRTUAL_FIT_RMS`` (2)
   x s0 rms, not 1.5: measured with the true groups on figures 0-39 (``/tmp`` collector,
   every same-segment one-body pair and every one-segment body), the sphere rms in a body
   across one joint is <= 1.5 x s0 for 77 % of 2014 (body, pair) cases in full frames and
   80 % of 1876 in the extended frames, <= 2 for 88 % and 91 % (median 1.15 and 1.08: the
   extended frames are no worse), while bodies further away fit within 1.5 for 3 % and
   within 2 for 6-7 % of ~10,000. Figure 6245 (held out at stop 48): both markers of
   2-marker segment 2 are lost (marker 8 at frame 356, 7 at 365) and marker 8's last 16
   frames come back alone, given to marker 7 by the linkage; the parent's three markers
   are seen together over 2 of them. In its extended frame (two markers and its joint
   with the root) the piece sits 5.2 mm inside marker 7's sphere and 0.4 mm off marker
   8's; that sphere fits at 1.59 x s0. ``benchmarks/screen_markersets.py --compare
   VIRTUAL_FRAMES=False`` (stop 54): 4892 cached figures (0-1737, 2146-2690, 3880-5917,
   7760-7793, 9160-9185, 9521-9999 and 32 named) all right with it, acting on 6245 only;
   2691-3572 and held-out first runs 10000-10881 (full merges) it acted on none.
   Last, where no sphere decides, no direction and no continuity: an exchange that two or
   more bodies across one joint prefer, each by ``AGREEING_SPHERES_GAIN`` (10) in the
   residual sum of squares over its variance, and none opposes (``AGREEING_SPHERES``,
   ``_spheres_agree``; stop 56, held-out figure 10034). Since stop 68 not where a body
   holds the two markers' direction tighter as merged by the direction margin, none
   holding it tighter exchanged (``AGREED_DIRECTIONS``, the veto continuity exchanges
   have): about a hinge the spheres cannot tell the two markers apart, since each keeps a
   circle about the axis and two coaxial circles lie on one sphere. Held-out figure
   18946 (first run at stop 67): markers 0 and 1 form the 2-marker root segment, its three
   children hinged; exchanging their first pieces gained 31.5 and 30.2 on the two 3-marker
   children, which held the direction at 0.991 and 0.982 as merged, 0.718 and 0.157
   exchanged. After that, where still nothing
   decides, the spheres in the frame of a two-track body (two tracks moving as one that
   no body of three holds, with their joint to the body of three or more they fit best,
   within ``PAIR_JOINT_RMS`` (2) x s0, as the third point; ``_pair_frames``; figure 7375
   was lost at 5, a joint three joints away at 4.57), judged as above within
   ``VIRTUAL_FIT_RMS`` (``PAIR_FRAMES``, stop 60, ``_pair_exchange``). Held-out figure
   12020: marker 21's first 23 frames (2-marker leaf segment 8, whose parent has two
   markers) joined to marker 20, its partner, hidden then; continuity gained 1.81, under
   its margin; in the frame of the parent's two markers and their joint with the
   grandparent the piece sat 32 residual sds off as merged, 1.3 exchanged (fit 1.42 x s0).
   Since stop 65 the two-track bodies take a frame per lending body whose joint fits
   (``PAIR_EVERY_LENDER``; lenders seen in part too, ``_partial_frames``, as in step 11),
   and they also judge the alternatives step 4's jump test would undo, which nothing else
   in step 8 may make (``PAIR_OVER_JUMPS``). Figure 14892 (first run at stop 62): step 4
   exchanged the end pieces of markers 10 and 11 (16 and 25 frames; 3-marker segment 3,
   the two 33 mm apart and 199 and 202 mm from the third). Of the partners rigid to every
   fragment the third marker fits neither assignment within the jumps' bound (193.9 mm^2
   as merged, 21.9 exchanged, bound 21.2), and a child segment's marker 50 mm from its
   joint puts 1.8 against 196.5, so ``STEP8_JUMPS`` kept the exchange. The best lender of
   parent segment 1 (two markers) is segment 3 itself, which holds the two; with the
   joint the root lends (3 of its 4 markers seen over the pieces) the pieces sit 3.6
   residual sds off as merged and 0.8 exchanged (gain 689, the fit 0.93 x s0).
   Since stop 66 the two-track bodies' verdicts count within ``PAIR_FIT_RMS`` (2.5) x s0,
   not ``VIRTUAL_FIT_RMS`` (2), which steps 11 and 12b keep. Held-out figure 17442 (first
   run at stop 65): marker 35's first 19 frames (2-marker segment 13, under 2-marker
   segment 6) merged onto marker 34, hidden then. Of every frame step 8 judges the move in,
   one is a neighbour across one joint: segment 6's two markers with the joint segment 1
   lends, where the piece sits 5.13 residual sds off as merged and 1.03 moved (gain 1269.5),
   the better fit at 2.13 x s0; the next frame fits at 10.2. With the true groups of
   figures 0-39 (``/tmp`` collector, every two-track body with every lender), a marker
   across one joint from the two-track body keeps a sphere within 2 x s0 in 73.8 % of 1310
   cases and within 2.5 in 83.1 % (median 1.35: these frames are noisier than a body of
   three's), a marker further away in 7.6 % and 9.7 % of 8694.
   Since stop 70 a two-track body makes an exchange step 4's jumps would undo only where
   its gain (in residual variances) is above their cost, the rise in the jumps over
   ``s0`` squared (``PAIR_OUTWEIGHS_JUMPS``). Held-out figure 21752 (first run at stop
   70): the first pieces of markers 33 and 34 (4-marker segment 11; 204.8 and 108.6 mm
   from marker 35, both other markers seen over them) were exchanged on one body's frame
   fitting at 2.04 x s0 with gain 887, where the jumps rise from 19.6 to 913,530 mm^2
   (about 481,000 s0^2). Figure 2422 (right until 573fa35 raised the fit gate to 2.5):
   gain 217 at 2.29 x s0 against about 9,400. 14892's exchange: 689 against 99.
11. sphere joins (``_join_by_spheres``, ``SPHERE_JOINS``): where the steps above still end
   with more markers than the bound, a short piece may have no continuation that motion
   or pose alignment can judge (figure 8203, held out at stop 51: marker 21's first 11
   frames, seen while the other two markers of its segment are hidden, lie 126.5 mm
   pose-aligned on partners across a joint and 90 mm off the motion from their own marker
   38 frames on). In the frame of each body (step 8's: >= 3 tracks moving as one, >= 100
   frames) a marker turning about its joint with that body keeps a sphere (Kasa fit, rms
   <= 1.5 x s0): two markers that never share a frame are joined when the one with fewer
   points in a body lies on the other's sphere within ``SPHERE_FIT_Z`` (3) x its rms on
   some body and off it on none (``SPHERE_MISFIT_Z``, 6), and every other marker either of
   them could join is off, by >= 6 x the rms, on some body; the best fit first, none that
   crosses a gap faster than step 3's gate. On 8203 the piece lies on its marker's sphere
   about the parent at 1.7 x its rms and 89 and 172 x off the two other markers' (113 and
   222 mm). On the benchmark's figures (400 frames, 1-3 gaps of 3-39 frames per marker,
   fragments < 10 frames dropped: at most 3 of the <= 4 runs) every marker is seen in
   >= 400 - 117 - 27 = 256 frames, so two markers share >= 112 frames and the step finds
   nothing to join on a figure merged right: it can only change figures left wrong.
   With step 7b off it also joins figure 1371's 10-frame end piece, which step 7b joins.
   Since stop 64 (``SPHERE_JOINS_PAIRS``) it judges in two-track bodies' frames too (step
   8's ``_pair_frames``, the lending body's frame extended to frames where it shows three
   or more of its four or more tracks, ``_partial_frames``), within ``VIRTUAL_FIT_RMS`` (2)
   x s0 there. Figure 14980 (first run at stop 62): marker 33's first 11 frames (2-marker
   hinge segment 11, its mate hidden) were left an id of their own; no body of three is one
   joint away, but 2-marker segment 10 is, with its joint to 4-marker segment 3 (seen in
   part over those 11 frames). There the piece lies on marker 33's sphere at 1.26 x its rms
   and 10, 72 and 517 x off the other free markers' (marker 32's sphere fits at 1.87 x s0:
   above 1.5, within 2).
12b. sphere check (``_sphere_check``, ``SPHERE_CHECK``, stop 65): after step 12, a piece
   (one fragment of a marker of two or more, at most a quarter of its points in a body's
   frame) that lies >= ``SPHERE_MISFIT_Z`` x the sphere's rms off the joint sphere its
   marker keeps without it (step 11's bodies, ``_partial_frames`` and two-track bodies
   with every lending joint; fit within 1.5 x s0, ``VIRTUAL_FIT_RMS`` in a two-track
   body's frame), while a fragment of another marker seen within its span (not moving as
   one body with it) lies on that sphere within ``SPHERE_FIT_Z``, is exchanged with that
   fragment where two or more bodies agree and none opposes: each body where either
   marker keeps a sphere without its own piece must find its own piece off
   (>= ``SPHERE_MISFIT_Z``) and the incoming one on (<= ``SPHERE_FIT_Z``) wherever it sees
   them. Step 12 then runs again keeping the exchanged pieces where they are (its
   ``fixed``); a round whose result step 12 has already given ends the check. Distances
   cannot tell two 2-marker segments with about equal spacing apart: figure 12175 (wrong
   since stop 60's code first met it) had the first pieces of markers 24 and 25 (segment
   8) and of 45 and 46 (its 2-marker child) exchanged pairwise, the pairs 179.1 and 179.4
   mm apart. In segment 6's frame (the parent, two markers, with the joint lent by segment
   5, and again with segment 14's) and in sibling segment 14's, marker 46's piece on marker
   25 lies 63-85 x the sphere's rms off marker 25's sphere and marker 25's own piece, on
   marker 46, 1.7-2.5 x on it; no body finds marker 46's sphere. After that exchange step 12
   exchanges the other pair by distance (it would otherwise have undone the first). The
   need for two agreeing bodies and for the other marker's verdict come from figures 0-185
   (``/tmp`` collector on their final groups, all right): 60 offered a candidate (a piece
   off on one body, another marker's fragment on it); on two, all bodies keeping the
   marker's sphere found the piece off and the fragment on: figure 30 (two bodies, where
   the other marker's sphere finds the piece 44-75 x off it, an opposing verdict) and 113
   (three, one at 5.9 x, above ``SPHERE_FIT_Z``).
   With ``SPHERE_MOVES`` (stop 81; off by default there, as it made held-out figure 39328
   wrong on its first run; on again since stop 82) a piece so found off its marker's
   sphere also moves, with nothing coming back, to a marker that shares no frame with it
   and whose sphere (all its fragments) it lies on within ``SPHERE_FIT_Z``, judged the
   same way: two or more agreeing
   verdicts, none opposing (``SPHERE_MOVES``; that marker may move as one body with the
   piece's, which an exchange's may not), and every other marker free over the piece's
   frames finds it >= ``SPHERE_MISFIT_Z`` off its sphere on some body (without that,
   figure 12669 with ``MODEL_STRONGER`` and ``NOVEL_POSE_ASIDE`` off sent marker 7's
   piece to marker 11, the first of two free markers whose spheres it lay on: marker 7
   the other, and marker 39, free too, found it off on no body). Nor is a move made
   against step 12's rigid model: where the piece fits its own marker's one-body mates or
   is off the new marker's (``model._fits``, ``model._off``; ``MOVES_KEEP_MODEL``, stop 82).
   On 39328 the move took marker 8's first piece (3-marker segment) to marker 10 (another
   3-marker segment), on verdicts from the frames of one 2-marker segment with two
   lenders (marker 8's sphere 6.7 and 27.7 x its rms off, marker 10's 2.3 x on); its two
   mates fit it at home at 0.90 and 0.84 x their sd, marker 10's find it 89.6 x off.
   Verdicts are counted once per body and marker, and a two-track body's frames with
   different lenders (``_pair_frames(every_lender=True)``) as one body (``LENDERS_ONCE``,
   stop 81): held-out figure 37858 (first run at stop 81) had the first pieces of markers
   18 and 28 (segments 6 and 9) exchanged on two such frames of 2-marker segment 7, the
   parent of 9, with the joints lent by its child 11 and by sibling 1: marker 28's sphere
   without its piece (frames 80-399) fitted at 0.95 and 1.04 x s0, but about a centre
   55 mm off the joint with radius 279 mm against the true 334 (a cap of a sphere), so
   its own piece (frames 0-53, a pose the cap misses) sat 15.8 and 12.1 x off it and
   marker 18's 2.9 and 2.8 x on it; no other body judged.
   Held-out figure 34087 (first run at stop 79):
   marker 18's first 13 frames (2-marker segment {18, 19}, marker 18 hidden until frame
   24) sat on its partner 19; in the frame of the hinged child (three markers) marker
   19's sphere without them (rms 1.42 x s0) has them 53.5 x its rms off, marker 18's
   (1.29 x s0) 1.41 x on, and a two-track body's frame has them 1.11 x on marker 18's.
   Step 8's common-centre fit had taken them in: about a hinge a marker keeps a circle,
   and a sphere's centre slides along the axis to take in a few points off it (2.79
   residual sds off as merged, 1.43 exchanged).

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

import numpy as np

from . import rules
from .bodies import (
    _direction_spread, _one_body_frames, _pair_frames, _partial_frames, _points_in,
    _sphere_fit, _sphere_verdict, _sphere_z, _virtual_frames
)
from .continuity import _continuity_cost
from .judges import _jumps
from .model import _against_model, _Model
from .tracks import (
    _cross_alternatives, _exchange, _fragment_sd, _paced, _pair_sd, _rigid_to_all, _spans,
    _tracks
)


def _judging_frames(P, one, full, s0, fit_rms, partial=True) -> tuple:
    """(frames, gate, lent): the body frames that steps 11 and 12b judge spheres in, the fit
    gate of each (x s0), and the bodies lent to the two-track ones. Step 8's bodies
    (``full``, ``_one_body_frames``), with ``partial`` extended where four or more tracks
    show three (``_partial_frames``), gated at ``fit_rms``; and two-track bodies with the
    joint of each body that fits, those seen in part too as lenders
    (``_pair_frames(every_lender=True)``), gated at ``VIRTUAL_FIT_RMS``."""
    seen_in_part = {**full, **_partial_frames(P, full)}
    frames = seen_in_part if partial else dict(full)
    gate = dict.fromkeys(frames, fit_rms)
    pairs, lent = _pair_frames(P, one, seen_in_part, s0, every_lender=True)
    gate.update(dict.fromkeys(pairs, rules.VIRTUAL_FIT_RMS))
    return {**frames, **pairs}, gate, lent


def _join_by_spheres(X, groups, n_min, min_frames, max_step=np.inf, body_sd=1.5,
                     body_frames=100, fit_rms=1.5) -> list:
    """Step 11 (module docstring): while there are more markers than ``n_min``, two
    markers that never share a frame are joined where the joint spheres decide: in the
    frame of a body (``_bodies``: >= 3 tracks moving as one, >= ``body_frames`` frames) the
    marker with more points there keeps a sphere about its joint (Kasa fit, rms <=
    ``fit_rms`` x s0: a neighbour across one joint) and the other's points (>=
    ``SPHERE_POINTS``) lie on it within ``SPHERE_FIT_Z`` x that rms, on no body off it,
    while every other marker either of the two could join (no common frame, paced) has
    their points off its sphere by >= ``SPHERE_MISFIT_Z`` x its rms on some body. The
    best-fitting join first, none that crosses a gap faster than ``max_step`` per frame."""
    vis = ~np.isnan(X[..., 0])
    groups = [list(g) for g in groups]
    span = _spans(vis, groups)
    while len(groups) > n_min:
        P = _tracks(X, groups)
        S, s0 = _pair_sd(P, min_frames)
        if not s0 > 0:
            return groups
        common, one, frames = _one_body_frames(P, S, s0, body_sd, body_frames)
        gate = dict.fromkeys(frames, fit_rms)
        if rules.SPHERE_JOINS_PAIRS and frames:
            # two-track bodies too, with the joint of each body that fits, seen in part
            # (14980, 16029)
            frames, gate, _ = _judging_frames(P, one, frames, s0, fit_rms, partial=False)
        M = len(groups)
        free = [[b for b in range(M) if b != a and not common[a, b]
                 and _paced(X, span, groups[a] + groups[b], max_step)] for a in range(M)]
        if not any(free) or not frames:
            return groups
        spheres = {}
        points = _points_in(frames, P)         # (body, track) -> its points in the body's frame

        def judge(a, b) -> tuple:
            """(best z where the fewer points lie on the other's sphere, worst z): z the
            rms of their radius residual in units of the sphere's rms; NaN unjudged."""
            zs = []
            for body in frames:
                if a in body or b in body:
                    continue
                ya, yb = points(body, a), points(body, b)
                if len(ya) > len(yb):
                    ya, yb = yb, ya
                if len(yb) < 50 or len(ya) < rules.SPHERE_POINTS:
                    continue
                key = (body, b if len(points(body, b)) >= len(points(body, a)) else a)
                if key not in spheres:
                    spheres[key] = _sphere_fit(yb)
                if not spheres[key][2] <= gate[body] * s0:
                    continue                 # not a neighbour across one joint
                zs.append(_sphere_z(ya, spheres[key]))
            return (min(zs), max(zs)) if zs else (np.nan, np.nan)

        verdict = {}
        for a in range(M):
            for b in free[a]:
                if (b, a) not in verdict:
                    verdict[a, b] = verdict[b, a] = judge(a, b)
        best = None
        for a in range(M):
            for b in free[a]:
                if b < a:
                    continue
                lo, hi = verdict[a, b]
                if not (lo <= rules.SPHERE_FIT_Z and hi < rules.SPHERE_MISFIT_Z):
                    continue
                rivals = [(a, c) for c in free[a] if c != b] + [(b, c) for c in free[b]
                                                                if c != a]
                if all(verdict[r][1] >= rules.SPHERE_MISFIT_Z for r in rivals) and (
                        best is None or lo < best[0]):
                    best = (lo, a, b)
        if best is None:
            return groups
        _, a, b = best
        groups[a] = groups[a] + groups[b]
        del groups[b]
    return groups


def _spheres_agree(gains, min_gain=None) -> float | None:
    """The second largest of ``gains`` (per body across one joint: the drop in the
    residual sum of squares, over its variance, that an exchange makes in the body's
    common sphere fit) where two or more are at least ``min_gain``
    (``AGREEING_SPHERES_GAIN``) and none is negative; else None. No single body's verdict
    needs to be decisive (step 8's ``min_misfit``): figure 10034 (held out at stop 54), a
    19-frame end piece of a 2-marker segment's marker on its partner, 1.77 and 1.94 residual
    sds off in the two bodies one joint away, which gain 139 and 112 from the exchange. On
    the final groups of figures 0-184 merged right (every alternative wrong), none of 2159
    alternatives, 889 of them judged by two or more bodies, had two gains above 0."""
    min_gain = rules.AGREEING_SPHERES_GAIN if min_gain is None else min_gain
    g = sorted(gains)
    if len(g) < 2 or g[0] < 0 or g[-2] < min_gain:
        return None
    return float(g[-2])


def _sphere_exchanges(X, groups, min_frames, body_sd=1.5, body_frames=100, fit_rms=1.5,
                      min_misfit=2.0, max_rounds=3, direction_margin=rules.DIRECTION_MARGIN,
                      max_step=np.inf, rigid=3.0, jump_margin=10.8) -> tuple[list, bool]:
    """Step 8 (module docstring): exchanges between two markers moving as one body judged
    by the sphere each keeps about its joint in the frame of a neighbouring body, then by
    how their direction stays within a joint's range in that frame
    (``direction_margin``). None that step 4's jump test would undo (``STEP8_JUMPS``:
    raising ``_jumps`` on the tracks rigid to every fragment of both markers by
    ``jump_margin`` x s0 squared), unless a two-track body's frame decides it
    (``PAIR_OVER_JUMPS``). Returns the groups and whether any changed."""
    vis = ~np.isnan(X[..., 0])
    groups = [list(g) for g in groups]
    P = _tracks(X, groups)
    S, s0 = _pair_sd(P, min_frames)
    if not s0 > 0:
        return groups, False
    span = _spans(vis, groups)
    continuity = _continuity_cost(X, vis)
    changed = False
    for _ in range(max_rounds):
        common, one, frames = _one_body_frames(P, S, s0, body_sd, body_frames)
        points = _points_in(frames, X)    # (body, fragment) -> its points in the body's frame
        virtual = points_v = None   # the same with two tracks and a borrowed joint, as needed

        best = turn = cont = agreed = None
        pending = []          # alternatives no body vetoes, for the two-track bodies
        sd_of = _fragment_sd(X, vis, P, min_frames) if rules.STEP8_JUMPS else None
        for a, b in zip(*np.nonzero(np.triu(one, 1))):
            ga, gb = groups[a], groups[b]
            if len(ga) + len(gb) < 3:
                continue
            undone = {}        # alternatives step 4's jump test would undo -> their cost
            if rules.STEP8_JUMPS:
                alts = _cross_alternatives(span, ga, gb)
                js = _rigid_to_all(sd_of, ga + gb, rigid * s0)
                js[[a, b]] = False
                js = np.flatnonzero(js)
                if alts and js.size:
                    now_j, alt_j = _jumps(X, vis, ga, gb, alts, P[:, js],
                                          jump_margin * s0 ** 2)
                    undone = {frozenset((frozenset(na), frozenset(nb))): (c - now_j) / s0 ** 2
                              for (na, nb), c in zip(alts, alt_j)
                              if c >= now_j + jump_margin * s0 ** 2}
            done = set()
            kept = {}                     # body -> the current assignment's direction spread
            kept_ends = P[:, [a, b]]        # the current tracks (kept current by _exchange)
            smooth_now = None               # the current assignment's continuity cost
            for na, nb in _cross_alternatives(span, ga, gb):
                key = frozenset((frozenset(na), frozenset(nb)))
                # one step 4's jumps would undo: only a two-track body may make it
                late = key in undone
                if key in done or (late and not (rules.PAIR_OVER_JUMPS and rules.PAIR_FRAMES)
                                   ) or not (_paced(X, span, na, max_step)
                                             and _paced(X, span, nb, max_step)):
                    continue
                done.add(key)
                moved = (set(ga) - set(na)) | (set(gb) - set(nb))
                rest = set(ga + gb) - moved
                if (sum(span[f][1] - span[f][0] for f in moved)
                        > sum(span[f][1] - span[f][0] for f in rest)):
                    moved = rest           # the smaller side is the exchanged piece
                gain, veto = 0.0, False
                gains = []                # per body across one joint: the drop it measures
                spread = []               # (kept, exchanged) direction spread per body
                ends = _tracks(X, [na, nb])
                for body in frames:
                    if a in body or b in body:
                        continue
                    pts = {f: points(body, f) for f in ga + gb}
                    v = _sphere_verdict(pts, ga, gb, na, nb, moved)
                    gate = fit_rms
                    if v is None and rules.VIRTUAL_FRAMES:
                        # too few points with the body seen in full: with two of its
                        # tracks and its joint to a neighbour as the third point
                        if virtual is None:
                            virtual = _virtual_frames(P, frames, s0)
                            points_v = _points_in(virtual, X)
                        if body in virtual:
                            v = _sphere_verdict({f: points_v(body, f) for f in ga + gb},
                                                ga, gb, na, nb, moved)
                            gate = rules.VIRTUAL_FIT_RMS
                    if body not in kept:
                        kept[body] = _direction_spread(kept_ends, frames[body])
                    if not rules.DIRECTION_SEES_MOVED or (sum(len(pts[f]) for f in moved)
                                                    >= rules.DIRECTION_MOVED_FRAMES):
                        spread.append((kept[body], _direction_spread(ends, frames[body])))
                    if v is None or (j := _judgement(v, gate * s0, min_misfit)) is None:
                        continue                 # not a neighbour across one joint
                    gains.append(j[0])
                    if j[1]:
                        gain = max(gain, j[0])
                    veto = veto or j[2]
                if gain > 0 and not veto and not late and (best is None or gain > best[0]):
                    best = (gain, a, b, na, nb)
                if rules.PAIR_FRAMES and not veto:
                    # what step 4's jumps held against it, in s0^2 (PAIR_OUTWEIGHS_JUMPS),
                    # and what these bodies' spheres did (PAIR_OUTWEIGHS_BODIES)
                    against = -sum(g for g in gains if g < 0)
                    pending.append((a, b, na, nb, moved, undone.get(key, 0.0), against))
                if late:
                    continue
                spread = np.array([r for r in spread if np.isfinite(r).all()]).reshape(-1, 2)
                # a body that holds their direction tighter as merged, by the margin (and,
                # with CONTESTED_DIRECTIONS, none that holds it tighter exchanged)
                worse = bool((spread[:, 0] - spread[:, 1] >= direction_margin).any())
                turned = worse and not (
                    rules.CONTESTED_DIRECTIONS
                    and (spread[:, 1] - spread[:, 0] >= direction_margin).any())
                if rules.AGREEING_SPHERES and not veto and not (
                        rules.AGREED_DIRECTIONS and turned):
                    agree = _spheres_agree(gains)
                    if agree is not None and (agreed is None or agree > agreed[0]):
                        agreed = (agree, a, b, na, nb)
                if not veto and spread.size:
                    # the body that holds their direction tightest (their neighbour)
                    rk, rx = spread[np.argmax(spread.max(1))]
                    if (rx - rk >= direction_margin
                            and not worse
                            and (turn is None or rx - rk > turn[0])):
                        turn = (rx - rk, a, b, na, nb)
                if rules.CONTINUITY_EXCHANGES and not veto and not turned:
                    if smooth_now is None:
                        smooth_now = continuity(ga) + continuity(gb)
                    smooth = smooth_now - continuity(na) - continuity(nb)
                    if (smooth >= rules.CONTINUITY_EXCHANGE_MARGIN
                            and (cont is None or smooth > cont[0])):
                        cont = (smooth, a, b, na, nb)
        if best is None:
            best = turn
        if best is None:
            best = cont
        if best is None:
            best = agreed
        if best is None and pending:
            best = _pair_exchange(X, P, one, frames, s0, groups, pending, min_misfit)
        if best is None:
            break
        _exchange(X, groups, P, S, *best[1:], min_frames)
        changed = True
    return groups, changed


def _judgement(v, fit_rms, min_misfit) -> tuple | None:
    """(gain, decides, vetoes) of a sphere verdict ``v`` (``_sphere_verdict``): the drop in
    the residual sum of squares over its variance, whether the moved pieces sit >=
    ``min_misfit`` residual sds off as merged and under 1 / ``min_misfit`` of that
    exchanged, or the reverse; None where the better fit is worse than ``fit_rms`` (m) rms
    (not a neighbour across one joint)."""
    sk, sm, pk, pm, n = v
    var = min(sk, sm) / (n - 5)
    if not var <= fit_rms ** 2 * n / (n - 5):
        return None
    kp, mv = np.sqrt(pk / var), np.sqrt(pm / var)
    return ((sk - sm) / var, bool(kp >= min_misfit and kp >= min_misfit * mv),
            bool(mv >= min_misfit and mv >= min_misfit * kp))


def _pair_exchange(X, P, one, frames, s0, groups, pending, min_misfit) -> tuple | None:
    """Last in step 8 (``PAIR_FRAMES``): of the alternatives ``pending`` (a, b, na, nb,
    moved) that no body vetoed, the one with the largest gain on which the spheres in a
    two-track body's frame (``_pair_frames``: its joint to a body of three or more tracks
    as the third point, one frame per such body with ``PAIR_EVERY_LENDER``, else the
    best-fitting one's; neither a nor b in it or in the body lent) decide as step 8's
    bodies do (the moved pieces >= ``min_misfit`` residual sds off as merged and under half
    that exchanged, within ``PAIR_FIT_RMS`` x s0 rms; figure 17442's fit 2.13), none finding
    the reverse, and its gain above the jump cost each alternative carries (its sixth
    item, in s0^2; ``PAIR_OUTWEIGHS_JUMPS``) and above what the bodies of three or more
    tracks that judged it lose by it, summed (its seventh; ``PAIR_OUTWEIGHS_BODIES``,
    24196: 56.3 against 155.4); else None. Figure 12020 (held out at stop
    60): marker 21's first 23 frames, a 2-marker leaf segment whose parent has two
    markers, joined to marker 20 (its partner, hidden then), 21 frames on; the continuity
    exchange gains 1.81, under its margin of 2. In the frame of the parent's two markers
    and its joint with the grandparent (three markers) the piece sits 32.2 residual sds
    off as merged and 1.32 exchanged (the fit at 1.42 x s0): the two markers are 253 and
    361 mm from their joint."""
    if rules.PAIR_EVERY_LENDER:
        # a frame per lending body, seen in part too (as step 11's; 14892)
        pf, lent = _pair_frames(P, one, {**frames, **_partial_frames(P, frames)}, s0,
                                every_lender=True)
    else:
        pf, lent = _pair_frames(P, one, frames, s0)
    if not pf:
        return None
    points = _points_in(pf, X)
    best = None
    for a, b, na, nb, moved, jumped, against in pending:
        ga, gb = groups[a], groups[b]
        gain, veto = 0.0, False
        for body in pf:
            if a in body or b in body or a in lent[body] or b in lent[body]:
                continue
            v = _sphere_verdict({f: points(body, f) for f in ga + gb}, ga, gb, na, nb, moved)
            if v is None or (j := _judgement(v, rules.PAIR_FIT_RMS * s0,
                                              min_misfit)) is None:
                continue
            if j[1]:
                gain = max(gain, j[0])
            veto = veto or j[2]
        if rules.PAIR_OUTWEIGHS_JUMPS and gain <= jumped:
            # its gain does not outweigh what the jumps cost (21752)
            continue
        if rules.PAIR_OUTWEIGHS_BODIES and gain <= against:
            # nor what the bodies of three or more tracks lose by it (24196)
            continue
        if gain > 0 and not veto and (best is None or gain > best[0]):
            best = (gain, a, b, na, nb)
    return best


def _sphere_check(X, groups, max_step=np.inf, min_frames=10, body_sd=1.5, body_frames=100,
                  fit_rms=1.5, max_share=0.25) -> list | None:
    """Step 12b (``SPHERE_CHECK``, module docstring): one exchange of two pieces that the
    joint spheres decide, or None. In the frame of each body (step 8's bodies, extended
    where four or more show three, ``_partial_frames``; two-track bodies with each lending
    body's joint, ``_pair_frames(every_lender=True)``, within ``VIRTUAL_FIT_RMS``), a
    marker ``a`` keeps a sphere about its joint without its piece ``f`` (Kasa fit of >= 50
    points, rms <= ``fit_rms`` x s0; f at most ``max_share`` of a's points there, >=
    ``SPHERE_POINTS``). Where f lies >= ``SPHERE_MISFIT_Z`` x that rms off it and a
    fragment ``h`` of another marker ``b`` (not moving as one body with a), seen within
    f's span, lies on it within ``SPHERE_FIT_Z``, the exchange of f and h is judged on
    every body: where a's sphere without f fits, it agrees when f is off and h on it, and
    opposes when either is not; where b's sphere without h fits, it agrees when f is on it
    and h off, and opposes otherwise. Made where two or more bodies agree and none
    opposes, the result overlap-free and paced; the piece furthest off first. With
    ``SPHERE_MOVES`` the candidates include f alone moved to a marker b sharing no frame
    with it (b may move as one body with a) whose sphere f lies on within
    ``SPHERE_FIT_Z``, judged alike with no piece coming back, where every other marker
    sharing no frame with f has some body finding f >= ``SPHERE_MISFIT_Z`` off its
    sphere (figure 34087), and step 12's rigid model neither fits f on a nor finds it off
    on b (``MOVES_KEEP_MODEL``, figure 39328). Agreement is counted per body and marker, a
    two-track body's frames with different lenders as one body (``LENDERS_ONCE``, figure 37858)."""
    vis = ~np.isnan(X[..., 0])
    P = _tracks(X, groups)
    S, s0 = _pair_sd(P, min_frames)
    if not s0 > 0:
        return None
    _, one, full = _one_body_frames(P, S, s0, body_sd, body_frames)
    if not full:
        return None
    frames, gate, lent = _judging_frames(P, one, full, s0, fit_rms)
    span = _spans(vis, groups)
    points = _points_in(frames, X)        # (body, fragment) -> its points in the body's frame
    spheres = {}

    def outside(body, m):
        return m in body or m in lent.get(body, ())

    def sphere(body, m, f):
        """Marker m's sphere in body without its fragment f, or None (too few points or
        not a neighbour across one joint)."""
        if (body, m, f) not in spheres:
            rest = [points(body, h) for h in groups[m] if h != f]
            s = None
            if sum(map(len, rest)) >= 50:
                s = _sphere_fit(np.concatenate(rest))
                if not s[2] <= gate[body] * s0:
                    s = None
            spheres[body, m, f] = s
        return spheres[body, m, f]

    def z(body, f, s):
        if f is None:                 # a move: no piece comes back
            return np.nan
        y = points(body, f)
        return _sphere_z(y, s) if len(y) >= rules.SPHERE_POINTS else np.nan

    free = {}

    def free_of(b, f):
        # marker b shares no frame with fragment f (f can move onto it)
        if (b, f) not in free:
            free[b, f] = not vis[:, groups[b]][vis[:, f]].any()
        return free[b, f]

    def off_some(a, f, c):
        # some body holding neither a nor c finds fragment f off marker c's sphere
        for body in frames:
            if not (outside(body, a) or outside(body, c)):
                sc = sphere(body, c, None)
                if sc is not None and z(body, f, sc) >= rules.SPHERE_MISFIT_Z:
                    return True
        return False

    found = {}
    for a, g in enumerate(groups):
        if len(g) < 2:
            continue
        for body in frames:
            if outside(body, a):
                continue
            n = sum(len(points(body, f)) for f in g)
            for f in g:
                if not rules.SPHERE_POINTS <= len(points(body, f)) <= max_share * n:
                    continue
                s = sphere(body, a, f)
                if s is None or not z(body, f, s) >= rules.SPHERE_MISFIT_Z:
                    continue
                lo, hi = span[f]
                for b, gb in enumerate(groups):
                    if b == a or outside(body, b):
                        continue
                    if rules.SPHERE_MOVES and free_of(b, f):
                        # f itself on b's sphere, b never seen with it: a move
                        sb = sphere(body, b, None)
                        if sb is not None and z(body, f, sb) <= rules.SPHERE_FIT_Z:
                            found[a, f, b, None] = max(found.get((a, f, b, None), 0.0),
                                                       z(body, f, s))
                    if one[a, b]:
                        continue
                    for h in gb:
                        if (span[h][1] >= lo and span[h][0] <= hi
                                and z(body, h, s) <= rules.SPHERE_FIT_Z):
                            found[a, f, b, h] = max(found.get((a, f, b, h), 0.0),
                                                    z(body, f, s))
    best, model = None, None
    for (a, f, b, h), score in sorted(found.items(), key=lambda c: -c[1]):
        agree, oppose = set(), False
        for body in frames:
            if outside(body, a) or outside(body, b):
                continue
            # a two-track body's frames with different lenders are one body's verdicts
            core = body[:2] if rules.LENDERS_ONCE and body in lent else body
            for m, own, new in ((a, f, h), (b, h, f)):
                s = sphere(body, m, own)
                if s is None:
                    continue
                zo, zn = z(body, own, s), z(body, new, s)
                if np.isnan(zo) and np.isnan(zn):
                    continue
                # its own piece off its sphere, the other's on it
                ok = ((np.isnan(zo) or zo >= rules.SPHERE_MISFIT_Z)
                      and (np.isnan(zn) or zn <= rules.SPHERE_FIT_Z))
                if not ok:
                    oppose = True
                    break
                agree.add((core, m))
            if oppose:
                break
        if oppose or len(agree) < 2:
            continue
        if h is None and not all(off_some(a, f, c) for c in range(len(groups))
                                 if c not in (a, b) and free_of(c, f)):
            continue        # a move: every other marker f could go to is off somewhere
        if h is None and rules.MOVES_KEEP_MODEL:
            # nor against step 12's rigid model: it finds f off on b, or fits it at home
            # where b's mates do not (``model._against_model``, ``VETO_NEEDS_CONTRAST``)
            if model is None:
                model = _Model(X, vis, groups)
            if _against_model(model, f, a, b):
                continue
        new_a = [x for x in groups[a] if x != f] + ([] if h is None else [h])
        new_b = [x for x in groups[b] if x != h] + [f]
        if (h is not None and any((vis[:, h] & vis[:, x]).any() for x in new_a if x != h)
                ) or any((vis[:, f] & vis[:, x]).any() for x in new_b if x != f):
            continue
        if not (_paced(X, span, new_a, max_step) and _paced(X, span, new_b, max_step)):
            continue
        best = (a, b, new_a, new_b)
        break
    if best is None:
        return None
    a, b, new_a, new_b = best
    out = [list(g) for g in groups]
    out[a], out[b] = new_a, new_b
    return out

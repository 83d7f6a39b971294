"""Marker identity: merge trajectory fragments into physical markers (the thesis' Marker Sets).

``merge_fragments(trajectories (T, F, 3), min_frames=10, max_distance_m=0.012,
n_markers=None, rng=None) -> MarkerSets``. A tracker starts a new id whenever it loses a
marker (occlusion), so one physical marker arrives as several fragments, each a column with
NaN outside its life. Following the thesis (000, section 3.3, after Kirk, O'Brien & Forsyth
2005):

1. fragments seen in fewer than ``min_frames`` frames are dropped (ghosts, flicker);
2. the distance between two fragments that are never seen in the same frame is the minimum,
   over sampled frame pairs (a from one, b from the other), of the distance between the
   first at a and the second at b after aligning the pose at b onto the pose at a
   (Horn/Kabsch). Overlapping fragments cannot be one marker: their distance is infinite.
   Where the thesis aligns the whole body, the alignment here uses the ``neighbours``
   fragments that are most rigid with respect to both fragments (smallest larger sd of
   distance over either's life: a short fragment finds everything rigid), which makes the
   alignment exact on an articulated figure. An alignment counts at least
   ``partner_sd_weight`` (0.5) times the larger sd of its least rigid partner: partners
   across a joint leave the pose free, and over a long gap a wrong partner could otherwise
   fit within a few mm. For the order of the joins (step 3) the floor is
   ``order_sd_weight`` (1.0) times that sd: held-out figure 5991 (stop 48) joined a
   marker's fragment, aligned at 3.78 mm on partners across a joint (sd 5.53 mm), to a
   marker of another segment before that marker's own fragment came at 2.68 mm + 26
   frames' gap. The threshold keeps the half: with the whole sd there too, figure 2356
   lost a join of two fragments of one marker to the loose pass (stop 49);
3. clustering: constrained single linkage: pairs are merged in order of distance (floored
   at the whole sd, step 2) plus ``gap_weight_m`` (0.1 mm) per frame of gap between them
   (the longer the gap, the less a few mm of residual proves; the order only, the
   threshold stays on the distance) while the distance is below ``max_distance_m``, never
   merging clusters seen in the same frame (the cannot-link constraint a spectral
   clustering cannot guarantee), and never below the thesis' lower bound on the number of
   markers (the most fragments seen in one frame).
   Motion continuity adds candidates the pose alignment misses (a segment with two markers,
   or with its partners hidden, leaves the pose free): a pair is also a candidate, at key
   ``miss`` plus the gap term, when at every change from one to the other (gaps of at most
   ``continuity_max_gap`` (45) frames) a straight line fitted to the last
   ``continuity_frames`` (10) frames before the gap, extrapolated at constant velocity to
   the middle of the gap, and one fitted to the first 10 after, extrapolated backward, meet
   within ``continuity_m`` (10 mm); the key is the smaller of that miss and the distance.
   Long gaps wait (``defer_gap``, 60 frames): the first passes merge only pairs at most
   60 frames apart, repeated until they stop merging, and only then are longer gaps
   judged. A minimum over sample pairs across a long gap can fall below the threshold by
   chance, and a short fragment aligns only on partners seen across both lives, which
   are often across a joint (figure 1749: the first 94 frames of a marker sat 7.6 mm from
   a marker of another segment 209 frames later, while the marker's own next fragment, 27
   frames on, measured 16.7 mm; once the short gaps are merged, the partners span it).
   No merge makes a marker cross a gap faster than ``speed_gate`` (1.5) times the fastest
   frame-to-frame step of any fragment of the recording (the straight line from the end of
   one run to the start of the next, per frame of the gap): a body's markers do not move
   faster unseen than they are ever seen to. On figures 0-99 of bench_markersets.py the
   6195 joins of the merged markers (all right) crossed their gaps at <= 0.88 times that
   fastest step; figure 1026 (held out at stop 35) put a 14-frame piece of another
   segment's marker into a 5- and a 7-frame gap of a marker, at 3.3 and 2.5 times it
   (246 mm in 5 frames). ``/tmp`` screen of figures 0-1839, one ``merge_fragments`` per
   figure as ``bench_markersets.py`` builds them (stop 36): 1827 -> 1829/1840 (fixed 1026
   and 1704), none lost; the real recordings' merged groups are identical with and without.
   A loose pass (``loose_distance_m``, after the strict passes converge) orders its joins
   by the worse of the distance and the continuity miss where motion continuity judges
   the pair (``LOOSE_BY_CONTINUITY``: every change of column within 45 frames; the largest
   miss over its changes), each miss divided by max(1, (gap / ``ACCEL_GAP_FRAMES``)^2)
   (10 frames): an acceleration, since over long gaps right joins of fast motion miss the
   extrapolation by 169-250 mm (figures 93, 5990: the miss unscaled lost them). Held-out
   figure 7107 (stop 48): a 2-marker segment's 20-frame end piece joined, 5 frames on, a
   marker of another segment at 13.0 mm aligned, while it missed that marker's motion by
   31.2 mm; its own marker, 22 frames on, was 21.0 mm aligned and missed by 20.0 mm
   (scaled 4.1). Figure 6555 (a cycle of three markers across a common gap) is put right
   by it too. ``/tmp`` screen of figures 0-7759 (stops 50-51, one ``merge_fragments`` per
   figure as bench_markersets.py builds them): none of those merged right before is lost,
   in-sample 0-5959 all right; 5960-7759 1798/1800 against 1796 (figures it was designed
   on, so in-sample too).
   The steps below keep the gate: none makes an exchange or a move after which a marker
   crosses a gap that fast (``_paced``; held-out figure 2555, first run at stop 36: step
   4b moved the last 15 frames of a marker onto another segment's marker, 557 mm in 9
   frames, 3.7 times the fastest step);
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
   seen with them) is judged instead by the direction from one marker to the other, which a swap flips. The cost is the sum,
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
   it lowers the sum by ``swap_margin`` (1), one exchange per round. An exchange may not put
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
   identical with and without), nor one
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
   across that joint, on marker 22 9.2 x from its segment partner) - nor one that makes a
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
   rigid to them). A misfit that no marker free over its frames takes is exchanged
   (``MISFIT_EXCHANGES``): the one overlap-free exchange of a run of fragments between its
   marker and another that moves it there and after which every moved fragment fits the
   fragments its new marker kept (``_fits``, and off no one-body track) is made (figure
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
   marker 46's piece);
5. the repair can leave a marker as two ids (the swap made its pieces overlap one merged
   marker, so the linkage could not join them): merging (step 3, ``max_distance_m``) is
   repeated on the repaired markers while there are more than the thesis' bound, then one
   loose pass (``loose_distance_m``) as before the repair;
6. join by partners (``_join_by_partners``): while there are still more markers than the
   bound, two markers that never share a frame, are rigid to the same partners and sit at
   the same mean distance from each (within 3x the measured sd), and match no other marker
   so, are one marker. A marker of a two-marker segment hidden for longer than the
   continuity window has no pose to align on and no continuity to join it (figure 166: 50
   frames);
7. two markers left as three ids (``_two_of_three``): on a segment with two markers the
   linkage can join a fragment of one marker to a fragment of the other across a long gap
   (figure 524: 77 frames, 8.1 mm pose-aligned on partners across joints; the right
   continuation 20.1 mm), and the rest of the first marker then overlaps the rest of the
   second: three ids, one mixed, that no merge or join can reduce. While there are still
   more markers than the bound, three markers rigid to each other wherever two are seen
   together (step 4's ``rigid_pair``; at least two of the three pairs measured) and with no
   segment partner (step 4's: no other track rigid to their fragments over 80 % of their
   frames) whose fragments split into two overlap-free markers in more than one way become
   the split whose direction turns least across fragment changes (step 4's turning), when
   it turns at least ``turn_margin`` (60 deg) less than every other split and its two
   markers are rigid to each other (``rigid_pair``). Where the overlaps leave one split
   only, that split, when its two markers are rigid (``ONE_SPLIT``, stop 53; held-out
   figure 9476: on a 2-marker segment whose parent has two markers, marker 27's first 103
   frames were joined to marker 28's last two fragments, leaving 28's first 132 frames
   and 27's last 271 as ids alone; 28's first overlaps 27's first and last fragments and
   27's last overlaps 28's later ones, so the one split gives each marker its own). On
   figures merged right three distinct markers always share frames pairwise (each is seen
   in >= 256 of 400 frames), so no split exists. On a two-marker segment every split is
   rigid (figures 524, 719: 1.0 s0) and a wrong one flips the direction at a change
   (524: right 27.5 deg, other 176.4; 719: 92.3 and 228.7); the rigidity keeps apart
   markers of two segments rigid where seen together (figure 403: m9 and m19 at 3.0 s0,
   with a piece of m9's partner m8: both splits 9.7 s0). Two markers may also be left as
   four ids, each pair seen together and never in one frame with the other pair (figure
   3024: a 2-marker segment whose markers are lost before frame 79, one over frames 29-56,
   the other over 57-78); such pairs of pairs are judged as three ids are
   (``TWO_OF_FOUR``; 3024's right pairing turns 74 deg across the change, the other 155).
   Ids with a segment partner are judged too where they split more than one way
   (``PARTNER_SPLITS``, stop 53): the split that turns least by the margin, when the
   partners' distances also jump least on it (``_jump_ss`` summed over the partners, by
   step 4's ``jump_margin`` x s0 squared below every other split). Held-out figure 9471:
   both markers of a 2-marker hinge segment whose parent has two markers were each left as
   two ids, their pieces before and after gaps of 33-73 frames; a marker 420 mm away across
   the hinge stays at <= 3 x s0 to all four (sd 1.2-3.6 mm) and counted as a segment
   partner, so step 7 left them; the right pairing turns 52.7 deg against 158.4 and puts
   that partner's jumps at 3603 mm^2 against 10847.
7b. join by continuity (``_join_by_continuity``, ``CONTINUITY_JOINS``): while there are
   still more markers than the bound, two markers that never share a frame are joined
   when the join costs at most ``CONTINUITY_MARGIN`` (4) in step 8's continuity cost (the
   changes of fragment it makes) and every other join of either costs at least 4 more,
   the cheapest first. An end piece of a 2-marker segment's marker whose partner is
   hidden across the gap has no pose to align on and no partner to join by (figure 339:
   marker 39's last 62 frames, 37 frames after the rest, its partner seen in 8 of them:
   1.93, the next join 7.96; 1371: marker 33's last 10 frames, 1.12 against 7.80).
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
9. step 8 can leave a marker as two ids, as the swap repair can (step 5): in figure 1833
   (held out, first run at stop 34) the linkage merged marker 17 right, the swap repair
   moved its first fragment out and a piece of marker 15 (same segment) in, and step 8
   moved that piece back out, leaving two ids 5.1 mm apart (pose-aligned). Where step 8
   exchanged, merging within ``max_distance_m`` (step 5's strict passes, not its loose one)
   runs again while there are more markers than the bound. ``/tmp`` screen of figures
   0-1839 as for step 8's direction rule: 1818 of 1840 against 1817 before, the same
   failures but 1833 (fixed); none lost. Where the two ids are further apart than that,
   step 7b's continuity join runs again (``JOINS_AFTER_EXCHANGES``; figure 4881, first
   run at stop 47: step 8's exchange at gain 3.05 put marker 40 together and left marker
   41's last 153 frames an id alone, 28 frames after its first fragment ends; the join
   costs 2.87 and is the piece's only one).
10. split joins (``_split_joins``, ``SPLIT_JOINS``): where the steps above end with more
   markers than the bound, one marker may hold the pieces of two others: its earlier
   fragments belong to one marker and its later ones to another (figure 2539, held out at
   stop 36: the linkage put marker 27's last 38 frames onto the end of marker 47, whose
   own last fragment stayed an id alone; the swap repair then gave marker 47 its fragments
   back but its first 63 frames, which stayed with marker 27's piece, 300 frames apart).
   Each cut of a marker's fragments (in time order) into an earlier and a later part,
   each part joined to another marker it shares no frame with, is scored by step 8's
   continuity cost (the changes of fragment the joins make, less the marker's own); the
   cheapest is made when it costs at most ``CONTINUITY_MARGIN`` (4), each moved fragment
   fits the fragments of the marker it joins (no judge of step 4c sees it at another
   distance, no track moving as one body with them is off it: ``_misfit``, ``_off_body``)
   and every other split join or plain join of the marker that fits so costs at least 4
   more; none that crosses a gap faster than step 3's gate. One per round, while there
   are more markers than the bound. On 2539 the right split join costs 0.93; the next,
   marker 27's piece onto marker 26 (same segment, hidden 9 frames before it), 3.04, is
   off marker 26's body.

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

The partner floor and the gap order, measured with bench_skeleton_outputs.py's figures
(1 mm noise, 1-3 gaps of 3-40 frames per marker, 5 ghosts, 400 frames): figures 0-39 (on
which the weights were chosen) 32/40 merged exactly without either, 33/40 with the floor,
34/40 with both; figures 40-79 (held out) 29/40, 32/40, 33/40 (physical figures, markers
>= 20 mm apart: 17/22, 17/22, 19/22). Gap weights 0.05 and 0.15 mm per frame did worse on
figures 0-39 (33/40 and 32/40).

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

Motion continuity (step 3) measured on figures 0-39 before choosing it: over every pair of
kept fragments where one starts 1-80 frames after the other ends (2655 pairs of one marker,
34687 of two, 1963 of these within 0.1 m pose-aligned distance), constant-velocity fits on
10 frames meeting at mid-gap separated best of those tried (quadratic fits on 15 or 20
frames; each end extrapolated to the other's first frame). One marker, median / 99th
percentile of the miss: gaps of 1-5 frames 2 / 25 mm, 6-10 4 / 49, 11-20 7.5 / 78, 21-30
20 / 156, 31-45 36 / 217; two markers within 0.1 m, smallest: 16, 24, 17, 14, 18 mm (5th
percentile 38-55 mm). No pair of two markers missed by less than 13.7 mm (at any gap up to
80 frames), and 10 mm accepts 135 of the 542 one-marker pairs above ``max_distance_m``
with gaps <= 45 frames, hence ``continuity_m``. Held out, figures 40-119 (5482 and 75756
pairs): one marker 2 / 27, 3.5 / 54, 8 / 79, 20 / 158, 39 / 227 mm; two markers within
0.1 m, smallest 18, 21, 8, 8, 13 mm: 10 mm accepts 239 of 1053 one-marker pairs above
``max_distance_m`` and 2 of 4154 two-marker pairs (8.0 mm in figures 56 and 71, which
still merge: a better candidate takes the fragment first). The
miss cannot veto a pair: one marker's miss reached 8.7 mm per frame of gap on figures
0-39 but 15 mm per frame on figure 41 (fast distal segments), and a veto at 10 mm plus
10 mm per frame (chosen on 0-39) split five markers there. ``bench_markersets.py 0 120``
(HEAD measured in the same tree: 36/40, 38/40, 35/40, failing 1, 25, 30, 31, 64, 85, 93,
96, 98, 110, 119) -> 38/40, 40/40, 37/40 (115 of 120). Fixed: 1, 25, 31, 64, 96, 98,
110 (a right continuation above ``max_distance_m`` now merges before the wrong one).
Lost: 28 (the rescued merges change the tracks the loose pass aligns on: a 14-frame
fragment then lies 5.5 mm, not 66 mm, from another marker of its segment across a 7-frame
gap, and joins it). Still failing: 30, 85, 93 (cross-segment merges; the right continuations
miss by more than 10 mm or across more than 45 frames) and 119 (two markers of a segment exchanged, not repaired). The
rescue alone also left one marker as two ids in figures 23, 41 and 51 (changed alignments
put the pieces above ``max_distance_m``); the loose pass of step 5 joins them, and alone
(``continuity_m=0``) changes no figure (109 of 120). Merge time x1.07 of steps 1-3 alone
in the same run (218 s for 120 figures; HEAD 196 s in a separate run).

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
Step 6 (stop 17, designed on figure 166): figures 0-279 274 -> 275 of 280 (fixed 166),
held out 280-399 114 -> 115 of 120 (fixed 292, a split marker too), none lost; still
failing 28, 93, 157, 186, 221; 339, 341, 371, 372, 379. Merge time x1.35 of steps 1-3
alone over figures 0-399 (``bench_markersets.py 0 200`` and ``200 400``, both x1.35).
The jumps of step 4 and the veto in 4b (stop 18, designed on the failures of 0-399; the
partner filter was added after a first form lost figure 87): figures 0-199 196 -> 198 of
200 (fixed 28, 93), 200-399 194 -> 197 (fixed 341, 371, 372), none lost; held out, first
run at stop 18, 400-519 119 -> 119 of 120 and 520-639 115 -> 115 of 120 (failing 403,
524, 556, 569, 611, 617: pieces of another segment's marker or 2-marker segments, none a
short piece on a marker of its own segment, the class the rule is for). Merge time x1.35
-> x1.36 of steps 1-3 alone. Still failing in 0-399: 157, 186, 221, 339, 379.
Step 7 (stop 20, designed on figures 524 and 719; the split's rigidity added after it
joined a piece of m8 to m19 in figure 403, which was failing already), one merge per figure
with the groups before and after step 7 (before = the code without it, exact since step 7
is the last step and changes nothing where it finds no triple): figures 0-199 198 -> 198,
200-399 197 -> 197, 400-639 235 -> 236 (524), 640-759 118 -> 119 (719), none lost; held
out, first run at stop 20, 760-879 120 -> 120 (``bench_markersets.py 760 880``, identical
per figure; merge time x1.40 -> x1.41 of steps 1-3 alone). Step 7 took 10 s of 1679 s of
merging over 0-759. Still failing: 157, 186, 221, 339, 379, 403, 556, 569, 611, 718.

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

from dataclasses import dataclass

import warnings

import numpy as np

__all__ = ["MarkerSets", "merge_fragments"]

DIRECTION_MARGIN = 0.1  # step 8: the least gain in the mean resultant length of two markers'
                        # direction, in the frame of the body that holds it tightest, for an
                        # exchange (module docstring); 1 mm noise on markers >= 20 mm apart
                        # costs ~0.005
DIRECTION_FRAMES = 50   # ... over at least this many frames both are seen with the body
DIRECTION_SEES_MOVED = True   # step 8: a body judges the direction only where it sees the
DIRECTION_MOVED_FRAMES = 5    # ... moved pieces for at least this many frames


@dataclass(frozen=True, kw_only=True)
class MarkerSets:
    """positions (T, M, 3) m merged markers (ordered by first appearance); groups: M tuples
    of the input fragment columns merged into each marker (in time order); dropped: input
    columns dropped as too short; n_min: the most fragments seen in one frame (the lower
    bound on M); distance (F, F) m pose-aligned fragment distances (inf: overlapping,
    NaN: dropped or no partners to align on)."""

    positions: np.ndarray
    groups: tuple[tuple[int, ...], ...]
    dropped: tuple[int, ...]
    n_min: int
    distance: np.ndarray

    def __post_init__(self):
        p = np.asarray(self.positions)
        if p.ndim != 3 or p.shape[2] != 3 or p.shape[1] != len(self.groups):
            raise ValueError(f"positions.shape={p.shape}, expected (T, {len(self.groups)}, 3)")

    @property
    def n_markers(self) -> int:
        return len(self.groups)


def _kabsch_batch(src, dst):
    """(R, t) per batch with dst ~ R src + t, src/dst (B, K, 3)."""
    cs, cd = src.mean(1), dst.mean(1)
    H = np.einsum("bki,bkj->bij", dst - cd[:, None], src - cs[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    U[:, :, 2] *= d[:, None]
    R = U @ Vt
    return R, cd - np.einsum("bij,bj->bi", R, cs)


def _samples(frames: np.ndarray, n: int) -> np.ndarray:
    """Up to n frames of a fragment: both ends (nearest the gaps) and evenly in between."""
    if frames.size <= n:
        return frames
    k = max(1, n // 4)
    mid = frames[np.linspace(k, frames.size - 1 - k, n - 2 * k).astype(int)]
    return np.unique(np.concatenate([frames[:k], mid, frames[-k:]]))


def merge_fragments(trajectories, min_frames: int = 10, max_distance_m: float = 0.012,
                    n_markers: int | None = None, samples: int = 12, neighbours: int = 3,
                    max_passes: int = 4, loose_distance_m: float = 0.1,
                    repair_swaps: bool = True, swap_margin: float = 1.0,
                    continuity_m: float = 0.01, defer_gap: int | None = 60,
                    speed_gate: float | None = 1.5, rng=None) -> MarkerSets:
    """Merge fragment columns of ``trajectories`` (T, F, 3) into physical markers.

    ``max_distance_m`` (12 mm) sits below the spacing of markers on one segment (real
    marker sets keep them >= 20 mm apart): on 20 random figures with 1 mm noise, 12 mm
    merged 18 exactly, 20 mm 15 (a marker vanishing 1 frame before its 21 mm neighbour
    reappears looked like one marker). ``n_markers`` (optional) is the known number of
    physical markers: merging continues
    to it (below ``max_distance_m`` only) instead of stopping at the frame-count bound.
    The merge is repeated on its own output (at most ``max_passes`` times) while it still
    merges: merged neighbours span the gaps, so the next pass aligns poses on better
    partners. A last pass then keeps merging, in order of distance up to
    ``loose_distance_m``, while there are more markers than the thesis' bound (the most
    fragments seen in one frame): fast motion across a gap in which every same-segment
    partner was hidden too leaves only partners across a joint to align on.
    ``repair_swaps`` then runs steps 4, 4b, 4c, 5, 6, 7, 7b, 8, 9, 10 and 11 of the module
    docstring
    (``swap_margin``: the least gain in the rigidity cost for which fragments change
    marker).
    ``continuity_m`` (10 mm; 0 turns it off): the largest miss of the motion-continuity
    extrapolations across a gap for which a pair beyond ``max_distance_m`` still merges
    (module docstring, step 3).
    ``defer_gap`` (60 frames; None turns it off): the longest gap merged before longer
    gaps are judged (module docstring, step 3).
    ``speed_gate`` (1.5; None turns it off): no merge whose marker would cross a gap faster
    than this x the fastest frame-to-frame step of any fragment (module docstring, step 3).
    ``rng`` is unused (the method is deterministic) and accepted for the pipeline's
    uniform signature."""
    X = np.asarray(trajectories, np.float64)
    if X.ndim != 3 or X.shape[2] != 3:
        raise ValueError(f"trajectories.shape={X.shape}, expected (T, F, 3)")
    if min_frames < 1:
        raise ValueError(f"min_frames={min_frames!r}, expected >= 1")
    if not max_distance_m > 0:
        raise ValueError(f"max_distance_m={max_distance_m!r}, expected > 0")
    if not swap_margin >= 0:
        raise ValueError(f"swap_margin={swap_margin!r}, expected >= 0")
    if not continuity_m >= 0:
        raise ValueError(f"continuity_m={continuity_m!r}, expected >= 0")
    if defer_gap is not None and not defer_gap >= 1:
        raise ValueError(f"defer_gap={defer_gap!r}, expected >= 1 frame or None")
    if speed_gate is not None and not speed_gate > 0:
        raise ValueError(f"speed_gate={speed_gate!r}, expected > 0 or None")
    if neighbours < 3:
        raise ValueError(f"neighbours={neighbours!r}, expected >= 3 (a pose needs 3 points)")
    max_step = _max_step(X, speed_gate)
    first = _merge_pass(X, min_frames, max_distance_m, n_markers, samples, neighbours,
                        continuity_m=continuity_m, max_gap=defer_gap, max_step=max_step)
    merge_again = _merge_again(X, first.n_min, max_distance_m, loose_distance_m, n_markers,
                               samples, neighbours, continuity_m, max_step, max_passes)
    res = first
    if defer_gap is not None:
        res = merge_again(res, False, rounds=max_passes, max_gap=defer_gap)
    for k in range(max_passes):
        last = k == max_passes - 1
        nxt = _merge_pass(res.positions, 1, loose_distance_m if last else max_distance_m,
                          n_markers, samples, neighbours, continuity_m=continuity_m,
                          max_step=max_step, loose=last)
        if nxt.n_markers == res.n_markers:
            if last or nxt.n_markers <= first.n_min:
                break
            max_passes = k + 2          # converged: one loose pass next
            continue
        res = _regroup(X, res, nxt)
    if repair_swaps and res.n_markers >= 3:
        res = _repairs(X, res, first.n_min, min_frames, swap_margin, max_step, merge_again)
    return res


def _max_step(X, speed_gate) -> float:
    """Step 3's speed gate: ``speed_gate`` x the fastest frame-to-frame step of any
    fragment of ``X`` (m per frame); inf where ``speed_gate`` is None."""
    if speed_gate is None:
        return np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        steps = np.linalg.norm(np.diff(X, axis=0), axis=2)
    return speed_gate * float(np.nanmax(steps)) if np.isfinite(steps).any() else np.inf


def _merge_again(X, n_min, max_distance_m, loose_distance_m, n_markers, samples, neighbours,
                 continuity_m, max_step, max_passes):
    """``merge_again(res, loose_last, rounds, max_gap)``: strict merge passes on the merged
    markers of ``res`` while they merge and there are more markers than ``n_min``, then
    (``loose_last``) loose ones likewise (``merge_fragments``)."""
    def merge_again(res, loose_last, rounds=max_passes + 1, max_gap=None):
        loose = False
        for _ in range(rounds):
            if res.n_markers <= n_min:
                break
            nxt = _merge_pass(res.positions, 1, loose_distance_m if loose else max_distance_m,
                              n_markers, samples, neighbours, continuity_m=continuity_m,
                              max_gap=max_gap, max_step=max_step, loose=loose)
            if nxt.n_markers == res.n_markers:
                if loose or not loose_last:
                    break
                loose = True
                continue
            res = _regroup(X, res, nxt)
        return res
    return merge_again


def _repairs(X, res: MarkerSets, n_min, min_frames, swap_margin, max_step,
             merge_again) -> MarkerSets:
    """Steps 4-11 (module docstring) on the linkage's markers ``res``."""
    res = _with_groups(X, res, _repair_swaps(X, [list(g) for g in res.groups],
                                             min_frames, swap_margin, max_step=max_step))
    # a marker left as two ids beside a swap (the swap made them overlap) can merge now
    res = merge_again(res, True)
    groups = _join_by_partners(X, [list(g) for g in res.groups], min_frames, n_min)
    groups = _two_of_three(X, groups, min_frames, n_min)
    if CONTINUITY_JOINS:
        groups = _join_by_continuity(X, groups, n_min, max_step)
    groups, exchanged = _sphere_exchanges(X, groups, min_frames, max_step=max_step)
    if len(groups) < res.n_markers or exchanged:
        res = _with_groups(X, res, groups)
    if exchanged:
        # step 8 can leave a marker as two ids likewise: merged within max_distance_m
        res = merge_again(res, False)
        if JOINS_AFTER_EXCHANGES and res.n_markers > n_min:
            # and, further apart, joined by motion continuity as in step 7b (4881)
            groups = _join_by_continuity(X, [list(g) for g in res.groups], n_min, max_step)
            if len(groups) < res.n_markers:
                res = _with_groups(X, res, groups)
    if SPLIT_JOINS and res.n_markers > n_min:
        groups = _split_joins(X, [list(g) for g in res.groups], n_min, min_frames,
                              max_step=max_step)
        if len(groups) < res.n_markers:
            res = _with_groups(X, res, groups)
    if SPHERE_JOINS and res.n_markers > n_min:
        groups = _join_by_spheres(X, [list(g) for g in res.groups], n_min, min_frames,
                                  max_step=max_step)
        if len(groups) < res.n_markers:
            res = _with_groups(X, res, groups)
    return res


def _repairs_from(X, groups, min_frames: int = 10, max_distance_m: float = 0.012,
                  n_markers=None, samples: int = 12, neighbours: int = 3, max_passes: int = 4,
                  loose_distance_m: float = 0.1, swap_margin: float = 1.0,
                  continuity_m: float = 0.01, speed_gate=1.5) -> MarkerSets:
    """Steps 4-11 of ``merge_fragments`` (its defaults) resumed from the linkage's fragment
    ``groups`` (those entering step 4): what ``merge_fragments(X)`` returns when steps 1-3
    gave these groups. For screens of later steps (``benchmarks/screen_markersets.py``)."""
    X = np.asarray(X, np.float64)
    vis = ~np.isnan(X[..., 0])
    keep = vis.sum(0) >= min_frames
    n_min = int(vis[:, keep].sum(1).max()) if keep.any() else 0
    start = MarkerSets(positions=np.zeros((X.shape[0], 0, 3)), groups=(), n_min=n_min,
                       dropped=tuple(int(f) for f in np.flatnonzero(~keep)),
                       distance=np.full((X.shape[1],) * 2, np.nan))
    res = _with_groups(X, start, [list(g) for g in groups])
    max_step = _max_step(X, speed_gate)
    merge_again = _merge_again(X, n_min, max_distance_m, loose_distance_m, n_markers, samples,
                               neighbours, continuity_m, max_step, max_passes)
    if res.n_markers < 3:
        return res
    return _repairs(X, res, n_min, min_frames, swap_margin, max_step, merge_again)


def _partner_frames(X, vis, P, frs, others, min_frames, rigid_sd) -> tuple:
    """For the tracks ``others`` (columns of ``P``): the frames each is seen with the
    fragments ``frs``, and of those the frames of fragments it is rigid to (distance sd <=
    ``rigid_sd``): a segment partner of the fragments (step 4) is rigid over most of them."""
    seen, rigid = np.zeros(others.size), np.zeros(others.size)
    for f in frs:
        Pf = P[vis[:, f]][:, others]
        sf = _sd_to(Pf, X[vis[:, f], f], min(min_frames, int(vis[:, f].sum())))
        n = (~np.isnan(Pf[..., 0])).sum(0)
        ok = ~np.isnan(sf)
        seen[ok] += n[ok]
        rigid[ok] += n[ok] * (sf[ok] <= rigid_sd)
    return seen, rigid


def _colourings(X, vis, frags, limit=8) -> list:
    """Every split of ``frags`` into two lists with no two fragments of one list seen in the
    same frame (up to the order of the two), or [] when there is none (three fragments seen
    together) or more than 2 ** ``limit``."""
    F = len(frags)
    ov = vis[:, frags].T.astype(int) @ vis[:, frags].astype(int) > 0
    np.fill_diagonal(ov, False)
    side = np.full(F, -1)
    comps = []
    for s in range(F):
        if side[s] >= 0:
            continue
        side[s], stack, comp = 0, [s], [s]
        while stack:
            i = stack.pop()
            for j in np.flatnonzero(ov[i]):
                if side[j] < 0:
                    side[j] = 1 - side[i]
                    stack.append(j)
                    comp.append(j)
                elif side[j] == side[i]:
                    return []                       # an odd cycle: three markers
        comps.append(comp)
    if len(comps) - 1 > limit:
        return []
    out = []
    for flips in range(2 ** (len(comps) - 1)):
        lab = side.copy()
        for c, comp in enumerate(comps[1:]):
            if flips >> c & 1:
                lab[comp] = 1 - lab[comp]
        out.append(([frags[i] for i in range(F) if lab[i] == 0],
                    [frags[i] for i in range(F) if lab[i] == 1]))
    return [(ga, gb) for ga, gb in out if ga and gb]


def _two_of_three(X, groups, min_frames, n_min, rigid_pair=5.0, rigid_partner=3.0,
                  rigid_share=0.8, turn_margin=np.pi / 3, jump_margin=10.8) -> list:
    """Step 7 (module docstring): while there are more markers than ``n_min``, three markers
    rigid to each other wherever they are seen together (distance sd <= ``rigid_pair`` x the
    measured sd s0, at least two of the three pairs measured), with no segment partner
    (no other track rigid to their fragments, <= ``rigid_partner`` x s0, over
    ``rigid_share`` of the frames: the turning rule's case of step 4), whose fragments split
    into two overlap-free markers in more than one way, become the two markers of the split
    whose direction turns least across fragment changes (``_turning``), when it turns at
    least ``turn_margin`` less than every other split and its two markers are rigid to each
    other (``rigid_pair``; figure 403: two markers of different segments, 3.0 s0 where seen
    together, with a piece of a third would become a marker jumping between two distances).
    Fragments that split one way only take that split, when its markers are rigid
    (``ONE_SPLIT``; figure 9476). Ids with a segment partner that split more than one way
    take the split that turns least where the partners' distances also jump least on it,
    by ``jump_margin`` x s0 squared (``PARTNER_SPLITS``; figure 9471)."""
    vis = ~np.isnan(X[..., 0])
    while len(groups) > n_min:
        P = _tracks(X, groups)
        M = len(groups)
        S, s0 = _pair_sd(P, min_frames)
        if not s0 > 0:
            return groups
        ok = S <= rigid_pair * s0
        bad = S > rigid_pair * s0
        triples = []
        for a in range(M):
            for b in np.flatnonzero(ok[a]):
                # a-b rigid; c rigid to a or b, and not off either
                for c in np.flatnonzero(ok[a] | ok[b]):
                    if c != a and c != b and not (bad[a, c] or bad[b, c]):
                        triples.append(tuple(sorted((a, int(b), int(c)))))
        sets = sorted(set(triples))
        if TWO_OF_FOUR:
            sets += _pairs_of_pairs(vis, groups, ok, bad)
        found = None
        for ids in sets:
            frs = [f for m in ids for f in groups[m]]
            splits = _colourings(X, vis, frs)
            if len(splits) < (1 if ONE_SPLIT else 2):
                continue
            others = np.setdiff1d(np.arange(M), ids)
            seen, rigid = _partner_frames(X, vis, P, frs, others, min_frames,
                                          rigid_partner * s0)
            partners = others[(seen > 0) & (rigid >= rigid_share * seen)]
            if partners.size and not (PARTNER_SPLITS and len(splits) > 1):
                continue
            turns = np.array([_turning(X, vis, ga, gb) for ga, gb in splits])
            order = np.argsort(turns)
            if len(splits) > 1 and turns[order[0]] > turns[order[1]] - turn_margin:
                continue
            if partners.size:
                # segment partners: their distances must not jump less on another split
                ss = _jump_ss(X, vis, frs, P[:, partners])
                jumps = np.array([float((ss(ga) + ss(gb)).sum()) for ga, gb in splits])
                if (np.delete(jumps, order[0]) < jumps[order[0]] + jump_margin * s0 ** 2
                        ).any():
                    continue
            # the two markers of the split are one segment's: rigid to each other
            ta, tb = _tracks(X, list(splits[order[0]])).transpose(1, 0, 2)
            if _sd_to(tb[:, None], ta, min_frames)[0] <= rigid_pair * s0:
                found = (ids, splits[order[0]])
                break
        if found is None:
            return groups
        ids, (ga, gb) = found
        groups = [g for m, g in enumerate(groups) if m not in ids] + [ga, gb]
    return groups


TWO_OF_FOUR = True   # step 7 also takes two rigid pairs of ids that never share a frame
ONE_SPLIT = True     # step 7 takes the one split where the fragments split only one way
PARTNER_SPLITS = True   # ... and judges ids with a segment partner too, by turns and jumps


def _pairs_of_pairs(vis, groups, ok, bad) -> list:
    """Step 7's second case: four ids (a, b, c, d), a-b and c-d each rigid where seen
    together (``ok``), the two pairs never seen in one frame and no cross pair off rigid
    (``bad``): the two markers of a segment each left as two ids, their pieces before a
    gap both markers shared and after it (figure 3024: both markers of a 2-marker segment
    hidden over frames 29-56, each lost at its own time, and no merge across)."""
    seen = np.array([vis[:, g].any(1) for g in groups])
    pairs = [(a, b) for a in range(len(groups)) for b in np.flatnonzero(ok[a])
             if b > a and (seen[a] & seen[b]).any()]
    out = []
    for i, (a, b) in enumerate(pairs):
        for c, d in pairs[i + 1:]:
            if len({a, b, c, d}) < 4 or ((seen[a] | seen[b]) & (seen[c] | seen[d])).any():
                continue
            if not bad[np.ix_([a, b], [c, d])].any():
                out.append(tuple(sorted((a, int(b), c, int(d)))))
    return sorted(set(out))


def _with_groups(X, res: MarkerSets, groups) -> MarkerSets:
    """``res`` with new fragment groups (each in order of first sight, the groups too) and
    their tracks."""
    groups = sorted((sorted(g, key=lambda f: _first_seen(X, f)) for g in groups),
                    key=lambda g: _first_seen(X, g[0]))
    return MarkerSets(positions=_tracks(X, groups), groups=tuple(tuple(g) for g in groups),
                      n_min=res.n_min, dropped=res.dropped, distance=res.distance)


def _join_by_partners(X, groups, min_frames, n_min, rigid=3.0, match=3.0) -> list:
    """Step 6 (module docstring): while there are more markers than ``n_min``, two markers
    that never share a frame are joined when they are rigid (distance sd <= ``rigid`` x the
    measured sd s0) to the same partners at the same distances (mean distance within
    ``match`` x s0 for every partner both see for ``min_frames`` frames), and no other
    marker matches either of them so. This joins a marker split across a gap too long for
    motion continuity on a segment too small (two markers) to align a pose on."""
    while len(groups) > n_min:
        P = _tracks(X, groups)
        M = len(groups)
        vis = ~np.isnan(P[..., 0])
        S, s0 = _pair_sd(P, min_frames)
        if not s0 > 0:
            return groups
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            D = np.stack([np.nanmean(np.linalg.norm(P - P[:, m, None], axis=2), 0)
                          for m in range(M)])
        part = [set(np.flatnonzero(S[m] <= rigid * s0)) for m in range(M)]
        overlap = vis.T.astype(int) @ vis.astype(int)
        cand = []
        for a in range(M):
            for b in range(a + 1, M):
                if overlap[a, b] or not part[a] & part[b]:
                    continue
                shared = part[a] & part[b]
                if all(abs(D[a, q] - D[b, q]) <= match * s0 for q in shared):
                    cand.append((a, b))
        # only unambiguous pairs: neither marker matches any other
        count = np.bincount(np.array(cand, int).ravel(), minlength=M) if cand else None
        cand = [(a, b) for a, b in cand if count[a] == 1 and count[b] == 1]
        if not cand:
            return groups
        a, b = cand[0]
        groups[a] = groups[a] + groups[b]
        del groups[b]
    return groups


CONTINUITY_JOINS = True  # step 7b: markers left as two ids are joined by motion continuity
JOINS_AFTER_EXCHANGES = True  # step 9: and again where step 8 exchanged (figure 4881)


def _join_by_continuity(X, groups, n_min, max_step=np.inf) -> list:
    """Step 7b (module docstring): while there are more markers than ``n_min``, two
    markers that never share a frame are joined when joining them costs at most
    ``CONTINUITY_MARGIN`` in step 8's continuity cost (``_continuity_cost``: the changes of
    fragment the join makes) and every other join of either costs at least that much more;
    the cheapest such join first, none that crosses a gap faster than ``max_step`` per
    frame (``_paced``)."""
    vis = ~np.isnan(X[..., 0])
    span = _spans(vis, groups)
    cost = _continuity_cost(X, vis)
    while len(groups) > n_min:
        seen = np.stack([vis[:, g].any(1) for g in groups], 1)
        overlap = seen.T.astype(int) @ seen.astype(int)
        M = len(groups)
        own = [cost(g) for g in groups]
        C = np.full((M, M), np.inf)
        for a in range(M):
            for b in range(a + 1, M):
                if not overlap[a, b] and _paced(X, span, groups[a] + groups[b], max_step):
                    C[a, b] = C[b, a] = cost(groups[a] + groups[b]) - own[a] - own[b]
        best = None
        for a in range(M):
            b = int(np.argmin(C[a]))
            if not C[a, b] <= CONTINUITY_MARGIN:
                continue
            rest = np.r_[np.delete(C[a], b), np.delete(C[b], a)]
            if (rest >= C[a, b] + CONTINUITY_MARGIN).all() and (best is None
                                                                 or C[a, b] < best[0]):
                best = (C[a, b], min(a, b), max(a, b))
        if best is None:
            return groups
        _, a, b = best
        groups[a] = groups[a] + groups[b]
        del groups[b]
    return groups


SPLIT_JOINS = True  # step 10: a marker holding two others' pieces is split and joined


def _split_joins(X, groups, n_min, min_frames, max_step=np.inf, rigid=3.0, one_body=1.5,
                 jump_margin=10.8, voter_frames=100) -> list:
    """Step 10 (module docstring): while there are more markers than ``n_min``, a marker
    whose earlier fragments join one other marker and whose later ones another is split
    and joined so, where that costs at most ``CONTINUITY_MARGIN`` in step 8's continuity
    cost (``_continuity_cost``), every moved fragment fits its new marker (``_takes``) and
    every other split join or plain join of the marker that fits costs at least that much
    more; the cheapest such marker first, none that crosses a gap faster than
    ``max_step`` per frame (``_paced``)."""
    vis = ~np.isnan(X[..., 0])
    span = _spans(vis, groups)
    cost = _continuity_cost(X, vis)
    while len(groups) > n_min:
        P = _tracks(X, groups)
        s0 = _pair_sd(P, min_frames)[1]
        if not s0 > 0:
            return groups
        sd_of = _fragment_sd(X, vis, P, min_frames)
        bound = jump_margin * s0 ** 2
        M = len(groups)
        seen = np.stack([vis[:, g].any(1) for g in groups], 1)
        own = [cost(g) for g in groups]

        def takes(part, b, a) -> bool:
            """every fragment of ``part`` (of marker a) fits marker b's fragments: no judge
            sees it at another distance and it is not off their body (no judge at all is
            no objection)."""
            return not any(
                _off_body(X, vis, P, sd_of, h, groups[b], [a, b], rigid * s0, one_body * s0,
                          bound, voter_frames)
                or not (_misfit(X, vis, P, sd_of, h, groups[b], [a, b], rigid * s0, bound,
                                voter_frames) <= bound).all()
                for h in part)

        best = None
        for a in range(M):
            g = sorted(groups[a], key=lambda f: span[f][0])
            if len(g) < 2:
                continue
            alts = [(cost(groups[a] + groups[b]) - own[a] - own[b], None) for b in range(M)
                    if b != a and not (seen[:, a] & seen[:, b]).any()
                    and _paced(X, span, groups[a] + groups[b], max_step)]
            for cut in range(1, len(g)):
                d = []
                for part in (g[:cut], g[cut:]):
                    s = vis[:, part].any(1)
                    d.append([(cost(groups[b] + part) - own[b], b) for b in range(M)
                              if b != a and not (s & seen[:, b]).any()
                              and _paced(X, span, groups[b] + part, max_step)])
                alts += [(c1 + c2 - own[a], (cut, b, c)) for c1, b in d[0] for c2, c in d[1]
                         if b != c]
            alts.sort(key=lambda x: x[0])

            def fits(move) -> bool:
                return move is None or (takes(g[:move[0]], move[1], a)
                                        and takes(g[move[0]:], move[2], a))
            for i, (c, move) in enumerate(alts):
                if c > CONTINUITY_MARGIN:
                    break
                if move is None or not fits(move):
                    continue
                if not any(x < c + CONTINUITY_MARGIN and fits(m)
                           for j, (x, m) in enumerate(alts) if j != i) and (
                        best is None or c < best[0]):
                    best = (c, a, g, move)
                break
        if best is None:
            return groups
        _, a, g, (cut, b, c) = best
        groups[b] = groups[b] + g[:cut]
        groups[c] = groups[c] + g[cut:]
        del groups[a]
    return groups


SPHERE_JOINS = True  # step 11: a marker left as two ids is joined where joint spheres judge
SPHERE_FIT_Z = 3.0      # ... the piece fits a marker's sphere within this x the sphere's rms
SPHERE_MISFIT_Z = 6.0   # ... and is off every other candidate's by at least this x its rms
SPHERE_POINTS = 5       # ... on at least this many of the piece's frames in the body


def _sphere_fit(y) -> tuple:
    """(centre, radius, rms residual) of points ``y`` (N, 3): Kasa's algebraic fit."""
    A = np.c_[2 * y, np.ones(len(y))]
    sol = np.linalg.lstsq(A, (y ** 2).sum(1), rcond=None)[0]
    c = sol[:3]
    r = float(np.sqrt(max(sol[3] + c @ c, 0.0)))
    return c, r, float(np.sqrt(np.mean((np.linalg.norm(y - c, axis=1) - r) ** 2)))


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
        common, _, frames = _one_body_frames(P, S, s0, body_sd, body_frames)
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
                if len(yb) < 50 or len(ya) < SPHERE_POINTS:
                    continue
                key = (body, b if len(points(body, b)) >= len(points(body, a)) else a)
                if key not in spheres:
                    spheres[key] = _sphere_fit(yb)
                c, r, rms = spheres[key]
                if not rms <= fit_rms * s0:
                    continue                 # not a neighbour across one joint
                res = np.linalg.norm(ya - c, axis=1) - r
                zs.append(float(np.sqrt(np.mean(res ** 2))) / max(rms, 1e-12))
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
                if not (lo <= SPHERE_FIT_Z and hi < SPHERE_MISFIT_Z):
                    continue
                rivals = [(a, c) for c in free[a] if c != b] + [(b, c) for c in free[b]
                                                                if c != a]
                if all(verdict[r][1] >= SPHERE_MISFIT_Z for r in rivals) and (
                        best is None or lo < best[0]):
                    best = (lo, a, b)
        if best is None:
            return groups
        _, a, b = best
        groups[a] = groups[a] + groups[b]
        del groups[b]
    return groups


def _regroup(X, res: MarkerSets, nxt: MarkerSets) -> MarkerSets:
    """``res`` after a merge pass on its tracks: ``nxt``'s tracks, each group the union of
    the fragments of the ``res`` markers it merged (in order of first sight)."""
    groups = tuple(tuple(sorted((f for g in grp for f in res.groups[g]),
                                key=lambda f: _first_seen(X, f))) for grp in nxt.groups)
    return MarkerSets(positions=nxt.positions, groups=groups, n_min=res.n_min,
                      dropped=res.dropped, distance=res.distance)


def _tracks(X, groups) -> np.ndarray:
    """(T, len(groups), 3): each group's fragment columns of X put together."""
    out = np.full((X.shape[0], len(groups), 3), np.nan)
    for g, fs in enumerate(groups):
        for f in fs:
            seen = ~np.isnan(X[:, f, 0])
            out[seen, g] = X[seen, f]
    return out


def _sd_to(P, q, min_frames) -> np.ndarray:
    """(M,) sd over common frames of the distance between q (T, 3) and each column of P
    (T, M, 3); NaN where they share fewer than ``min_frames`` frames."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        d = np.linalg.norm(P - q[:, None], axis=2)
        s = np.nanstd(d, axis=0)
    s[(~np.isnan(d)).sum(0) < min_frames] = np.nan
    return s


def _pair_sd(P, min_frames) -> tuple[np.ndarray, float]:
    """(M, M) distance sd between every two tracks of P (T, M, 3) (``_sd_to``; NaN on the
    diagonal) and s0, the measured sd of a rigid pair: the median of each track's smallest."""
    S = np.stack([_sd_to(P, P[:, m], min_frames) for m in range(P.shape[1])])
    np.fill_diagonal(S, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return S, float(np.nanmedian(np.nanmin(S, 1)))


def _exchange(X, groups, P, S, a, b, ga, gb, min_frames) -> None:
    """Give markers ``a`` and ``b`` the fragments ``ga`` and ``gb``, in place: their groups,
    their tracks in ``P`` and their rows and columns of the sd matrix ``S``."""
    groups[a], groups[b] = list(ga), list(gb)
    P[:, a], P[:, b] = _tracks(X, [ga, gb]).transpose(1, 0, 2)
    for m in (a, b):
        S[m] = S[:, m] = _sd_to(P, P[:, m], min_frames)
        S[m, m] = np.nan


def _turning(X, vis, ga, gb, ends=5) -> float:
    """Sum over the changes of fragment (in either marker, over their common frames) of the
    angle (rad) between the direction from marker a to marker b before and after: the mean
    direction over the last ``ends`` common frames before and the first ``ends`` after."""
    T = X.shape[0]
    ida, idb = np.full(T, -1), np.full(T, -1)
    for ids, g in ((ida, ga), (idb, gb)):
        for f in g:
            ids[vis[:, f]] = f
    t = np.flatnonzero((ida >= 0) & (idb >= 0))
    if t.size < 2:
        return 0.0
    u = X[t, idb[t]] - X[t, ida[t]]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    cut = np.flatnonzero((ida[t[1:]] != ida[t[:-1]]) | (idb[t[1:]] != idb[t[:-1]])) + 1
    bounds = np.r_[0, cut, t.size]
    total = 0.0
    for i in range(1, bounds.size - 1):
        lo, mid, hi = bounds[i - 1], bounds[i], bounds[i + 1]
        v0 = u[max(lo, mid - ends):mid].mean(0)
        v1 = u[mid:min(hi, mid + ends)].mean(0)
        c = v0 @ v1 / (np.linalg.norm(v0) * np.linalg.norm(v1))
        total += float(np.arccos(np.clip(c, -1.0, 1.0)))
    return total


def _best_by_turning(X, vis, ga0, gb0, alts, margin):
    """The alternative (ga, gb) whose direction turns least across fragment changes, if it
    turns at least ``margin`` (rad) less than (ga0, gb0); else None."""
    best, found = _turning(X, vis, ga0, gb0) - margin, None
    for ga, gb in alts:
        c = _turning(X, vis, ga, gb)
        if c < best:
            best, found = c, (ga, gb)
    return found


def _jump_ss(X, vis, frags, Pq):
    """For the fragments ``frags`` and partner tracks ``Pq`` (T, Q, 3): a function of a
    list of them (one marker) giving its between-fragment sum of squares (Q,) (m^2) per
    partner: the sum over its fragments of their frames seen with the partner x (their mean
    distance to the partner over them - the marker's mean)^2. Zero for fragments at one
    constant distance to the partner; a piece of another marker at another distance adds its
    frames x the difference^2."""
    stats = {}
    for f in frags:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            d = np.linalg.norm(Pq[vis[:, f]] - X[vis[:, f], f][:, None], axis=2)
        n = (~np.isnan(d)).sum(0)
        s = np.nansum(d, 0)
        stats[f] = (n, s, s ** 2 / np.maximum(n, 1))      # n x mean^2

    def ss(g):
        n = sum(stats[f][0] for f in g)
        s = sum(stats[f][1] for f in g)
        return sum(stats[f][2] for f in g) - s ** 2 / np.maximum(n, 1)
    return ss


def _jumps(X, vis, ga0, gb0, alts, Pq, margin, per_marker=False):
    """Step 4's jump costs of two markers' fragments (ga0, gb0) and of their alternatives
    ``alts``: (now, costs (len(alts),)), each the sum over both markers and the partners of
    ``_jump_ss``, over the partners only that sit at constant distances from the fragments
    in some assignment (the least cost over (ga0, gb0) and the alternatives <= ``margin``;
    a partner across a joint drifts, and its fragments' means fit no two markers). With
    ``per_marker`` that is asked of each partner and each of the two markers apart: a
    partner of one marker's segment is across a joint from the other marker, where it
    drifts, and still tells where the first marker's pieces belong (figure 9533)."""
    ss = _jump_ss(X, vis, ga0 + gb0, Pq)
    if per_marker:
        now = np.stack([ss(ga0), ss(gb0)])                               # (2, Q)
        costs = np.array([np.stack([ss(ga), ss(gb)]) for ga, gb in alts]
                         ).reshape(len(alts), 2, -1)
        fits = np.minimum(now, costs.min(0, initial=np.inf)) <= margin  # (2, Q)
        return float(now[fits].sum()), costs[:, fits].sum(1)
    now = ss(ga0) + ss(gb0)
    costs = np.array([ss(ga) + ss(gb) for ga, gb in alts]).reshape(len(alts), -1)
    fits = np.minimum(now, costs.min(0, initial=np.inf)) <= margin
    return float(now[fits].sum()), costs[:, fits].sum(1)


def _best_by_jumps(X, vis, ga0, gb0, alts, Pq, margin):
    """The alternative (ga, gb) with the least jump cost (``_jumps``), if it is at least
    ``margin`` (m^2) below that of (ga0, gb0); else None."""
    now, costs = _jumps(X, vis, ga0, gb0, alts, Pq, margin)
    i = int(np.argmin(costs))
    return alts[i] if costs[i] <= now - margin else None


TURN_FALLBACK = True   # step 4: a pair moving as one body whose partners decide nothing turns


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
                                        jump_margin * s0 ** 2)
                    if ga is not None:
                        found = ga
                if found is None and TURN_FALLBACK and S[a, b] <= one_body * s0:
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


def _run_exchanges(frs, ga, free) -> list:
    """The alternatives of steps 4 and 4b: the fragments ``frs`` of two markers (in time
    order; those in ``ga`` are the first marker's) with the fragments of one run changing
    marker, as (ga', gb') lists, each kept when ``free(g)`` (no two of its fragments seen
    in one frame) holds for both."""
    lab = [f in ga for f in frs]
    out = []
    for i1 in range(len(frs)):
        for i2 in range(i1 + 1, len(frs) + 1 - (i1 == 0)):
            nl = [not x if i1 <= k < i2 else x for k, x in enumerate(lab)]
            na = [f for f, x in zip(frs, nl) if x]
            nb = [f for f, x in zip(frs, nl) if not x]
            if na and nb and free(na) and free(nb):
                out.append((na, nb))
    return out


def _spans(vis, groups) -> dict:
    """fragment -> (first, last) frame it is seen in, for every fragment of ``groups``."""
    out = {}
    for g in groups:
        for f in g:
            seen = np.flatnonzero(vis[:, f])
            out[f] = (int(seen[0]), int(seen[-1]))
    return out


def _cross_alternatives(span: dict, ga, gb):
    """``_run_exchanges`` of two markers' fragments, overlap judged on their spans
    (``span``: fragment -> (first, last) frame; cheaper than frame by frame)."""
    return _run_exchanges(
        sorted(ga + gb, key=lambda f: span[f][0]), ga,
        lambda g: all(span[f][1] < span[h][0] for f, h in zip(g[:-1], g[1:])))


def _too_fast(runs, max_step: float) -> bool:
    """Step 3's speed gate. ``runs``: (first frame, last frame, first position, last
    position, source) of one marker's runs, in time order and never overlapping: whether a
    run following one of another source starts farther from where that one ended than
    ``max_step`` (m) per frame of the gap between them."""
    return any(a[4] != b[4] and np.linalg.norm(b[2] - a[3]) > max_step * (b[0] - a[1])
               for a, b in zip(runs[:-1], runs[1:]))


def _paced(X, span: dict, g, max_step: float) -> bool:
    """No change of fragment in marker ``g`` (fragments never overlapping; ``span``:
    fragment -> (first, last) frame) crosses its gap faster than ``max_step`` (m) per frame:
    step 3's speed gate (``_too_fast``), kept by every later step that moves fragments."""
    if not np.isfinite(max_step) or len(g) < 2:
        return True
    return not _too_fast([(span[f][0], span[f][1], X[span[f][0], f], X[span[f][1], f], f)
                          for f in sorted(g, key=lambda f: span[f][0])], max_step)


KEPT_TRACK_VOTES = True    # step 4b: a marker without voters is judged by its kept track
KEPT_TRACK_JUDGES_VOTERS = False   # ... also where the piece moved in is a voter itself


MISFITS_ARE_BAD = True   # step 4b: a marker holding a misfit piece (step 4c's) is examined
LESS_OFF_BODY = True     # step 4b: nor a move off one body onto one it is further off
RIGID_SOMEWHERE = True   # step 4b: a voter's partner counts where rigid to some alternative (7429)
JUMPS_PER_MARKER = True  # step 4b's jump veto: a partner fits per marker, not per pair (9533)
NO_NEW_MISFITS = True    # step 4b: nor one that makes a fitting piece a misfit (figure 4430)


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

        def checked(g, old, excl):
            """every fragment moved into g shares >= min_frames frames with a partner of
            one of the voters g kept: nothing is put where no partner can judge it. Where
            g kept no voter (every fragment it kept is shorter than voter_frames) and no
            voter moves in, the partners of the track the kept fragments make together
            judge (``KEPT_TRACK_VOTES``; module docstring, step 4b)"""
            kept = [f for f in g if f in old]
            q = np.setdiff1d(np.concatenate([part[f] for f in kept if f in part]
                                            + [[]]), excl).astype(int)
            if (KEPT_TRACK_VOTES and kept and not any(f in part for f in kept)
                    and (KEPT_TRACK_JUDGES_VOTERS
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
                if LESS_OFF_BODY and there.max() > home.max():
                    # off both bodies, further off the new one (figure 4579)
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

        bad = [m for m, g in enumerate(groups) if any(
            part[f].size and np.nanmax(_sd_to(P[:, part[f]], P[:, m], min_frames)) > rigid * s0
            for f in g if f in part)]
        if MISFITS_ARE_BAD:
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
                if RIGID_SOMEWHERE:
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
                jumps, turns = None, False
                for na, nb in alts:
                    if not (checked(na, groups[a], ex) and checked(nb, groups[b], ex)):
                        continue
                    if not (_paced(X, span, na, max_step) and _paced(X, span, nb, max_step)):
                        continue
                    ta, tb = _tracks(X, [na, nb]).transpose(1, 0, 2)
                    gain = now - score(na, ta, q, keep) - score(nb, tb, q, keep)
                    if gain >= margin and (best is None or gain > best[0]):
                        # never an exchange that step 4's jump test would undo
                        if jumps is None:
                            js = strict(a, b)
                            jumps = _jumps(X, vis, groups[a], groups[b], alts, P[:, js],
                                           jump_margin * s0 ** 2, JUMPS_PER_MARKER)
                        now_j, alt_j = jumps
                        if alt_j[alts.index((na, nb))] >= now_j + jump_margin * s0 ** 2:
                            continue
                        if turns is False:
                            turns = turning_judged(a, b)
                        if turns is not None and (_turning(X, vis, na, nb)
                                                  >= turns + turn_margin):
                            continue
                        if body_veto and (displaced(groups[a], na, groups[b], ex)
                                          or displaced(groups[b], nb, groups[a], ex)):
                            continue
                        if NO_NEW_MISFITS and (misfit_made(groups[a], na, groups[b], ex)
                                               or misfit_made(groups[b], nb, groups[a], ex)):
                            continue
                        best = (gain, a, b, na, nb)
        if best is None:
            break
        _, a, b, na, nb = best
        groups[a], groups[b] = na, nb
    return groups


def _fragment_sd(X, vis, P, min_frames):
    """A cached ``sd_of(f)``: (M,) distance sd of fragment f to every track of P (T, M, 3),
    NaN where they are seen together for too few frames (``_sd_to``)."""
    cache: dict = {}

    def sd_of(f):
        if f not in cache:
            cache[f] = _sd_to(P[vis[:, f]], X[vis[:, f], f], min(min_frames, int(vis[:, f].sum())))
        return cache[f]
    return sd_of


def _rigid_to_all(sd_of, frags, rigid_sd) -> np.ndarray:
    """(M,) bool: the tracks rigid (sd <= ``rigid_sd``) to every fragment of ``frags`` they
    are seen with, and seen with at least one (``sd_of``: ``_fragment_sd``)."""
    sds = [sd_of(f) for f in frags]
    ok = np.ones(sds[0].shape, bool) if sds else np.zeros(0, bool)
    seen = np.zeros_like(ok)
    for sd in sds:
        ok &= np.isnan(sd) | (sd <= rigid_sd)
        seen |= ~np.isnan(sd)
    return ok & seen


def _misfit(X, vis, P, sd_of, f, kept, excl, rigid_sd, bound, partner_frames,
            with_frames=False, with_judges=False):
    """How far fragment ``f`` sits from where the fragments ``kept`` (one marker) are.
    Judges: the tracks of P (T, M, 3) (not in ``excl``) rigid to f and to each kept
    fragment they are seen with (``sd_of(h)``: (M,) distance sd of fragment h to every
    track, NaN where seen together for too few frames; rigid: <= ``rigid_sd``), seen with
    kept + [f] for >= ``partner_frames`` frames (rigid that long: a segment partner, as a
    voter's in step 4b; a track across a joint can be rigid to each of two short
    fragments yet drift between them, figure 87) and at one constant distance from the
    kept fragments (``_jump_ss`` <= ``bound``). Returns the ``_jump_ss`` (m^2)
    of kept + [f] on each judge (a piece of another marker sits at other distances; empty
    when no track judges); ``with_frames``: also the frames each judge is seen with f;
    ``with_judges``: also the judges' track indices."""
    none = ((np.zeros(0), np.zeros(0, int)) if with_frames or with_judges
            else np.zeros(0))
    if not kept:
        return none
    ok = (sd_of(f) <= rigid_sd) & _rigid_to_all(sd_of, kept, rigid_sd)
    ok[excl] = False
    js = np.flatnonzero(ok)
    if js.size == 0:
        return none
    frames = (vis[:, kept + [f]].any(1)[:, None] & ~np.isnan(P[:, js, 0])).sum(0)
    ss = _jump_ss(X, vis, kept + [f], P[:, js])
    use = (ss(kept) <= bound) & (frames >= partner_frames)
    if with_frames:
        return ss(kept + [f])[use], (vis[:, f][:, None] & ~np.isnan(P[:, js[use], 0])).sum(0)
    if with_judges:
        return ss(kept + [f])[use], js[use]
    return ss(kept + [f])[use]


def _one_body(vis, P, sd_of, kept, excl, body_sd, body_frames) -> np.ndarray:
    """(M,) bool: the tracks of P (T, M, 3), not in ``excl``, that move as one body with
    the fragments ``kept`` (one marker): distance sd <= ``body_sd`` to each of them they are
    seen with (``_rigid_to_all``), over >= ``body_frames`` frames in all."""
    body = _rigid_to_all(sd_of, kept, body_sd)
    body[excl] = False
    return body & ((vis[:, kept].any(1)[:, None] & ~np.isnan(P[:, :, 0])).sum(0)
                   >= body_frames)


def _body_sds(vis, P, sd_of, f, kept, excl, body_sd, body_frames) -> tuple:
    """(js, sd): the tracks moving as one body with the fragments ``kept`` (``_one_body``)
    that are seen with fragment ``f``, and f's distance sd to each (empty without kept)."""
    if not kept:
        return np.zeros(0, int), np.zeros(0)
    sd = sd_of(f)
    js = np.flatnonzero(_one_body(vis, P, sd_of, kept, excl, body_sd, body_frames)
                        & ~np.isnan(sd))
    return js, sd[js]


def _off_body(X, vis, P, sd_of, f, kept, excl, rigid_sd, body_sd, bound, body_frames) -> bool:
    """Fragment ``f`` cannot be the marker of the fragments ``kept``: a track of P (not in
    ``excl``) that moves as one body with them (sd <= ``body_sd`` to each it is seen with,
    over >= ``body_frames`` frames) is not rigid to f (sd > ``rigid_sd``) or sits at another
    distance from it (``_jump_ss`` of kept + [f] above that of kept by ``bound``)."""
    js, sd = _body_sds(vis, P, sd_of, f, kept, excl, body_sd, body_frames)
    if js.size == 0:
        return False
    if (sd > rigid_sd).any():
        return True
    ss = _jump_ss(X, vis, kept + [f], P[:, js])
    return bool((ss(kept + [f]) - ss(kept) > bound).any())


def _fits(costs, bound) -> bool:
    """``_misfit``'s costs say the fragment fits: some judge, and every one within
    ``bound``."""
    return bool(costs.size and costs.max() <= bound)


def _placed(costs_frames, bound) -> bool:
    """``_misfit``'s costs and frames (``with_frames``) place an unjudged piece: the judges
    within ``bound`` see it for >= ``UNJUDGED_EVIDENCE`` frames in all."""
    costs, frames = costs_frames
    return bool(frames[costs <= bound].sum() >= UNJUDGED_EVIDENCE)


UNJUDGED_MOVES = True   # step 4c: a piece no judge sees on its own marker moves where it fits
UNJUDGED_EVIDENCE = 20  # ... on judges that see it for this many frames in all


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
        moves = []
        for a, g in enumerate(groups):
            if len(g) < 2:
                continue
            for f in g:
                kept = [h for h in g if h != f]
                miss, judges = _misfit(X, vis, P, sd_of, f, kept, [a], rigid * s0, bound,
                                       voter_frames, with_judges=True)
                # judges that find f where its marker is (an off-body piece can have some)
                at_home = set(judges[miss <= bound].tolist())
                off = _off_body(X, vis, P, sd_of, f, kept, [a], rigid * s0, one_body * s0,
                                bound, voter_frames)
                unjudged = UNJUDGED_MOVES and miss.size == 0 and not off
                if not (miss.size and miss.min() > bound) and not off and not unjudged:
                    continue
                def fits_in(b):
                    if unjudged:
                        return _placed(_misfit(X, vis, P, sd_of, f, groups[b], [a, b],
                                               rigid * s0, bound, voter_frames,
                                               with_frames=True), bound)
                    if not _fits_on(X, vis, P, sd_of, f, groups[b], [a, b], rigid * s0,
                                    one_body * s0, bound, voter_frames):
                        return False
                    return _tells(X, vis, P, sd_of, f, groups[b], [a, b], rigid * s0, bound,
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
                elif (not to and off and ONLY_FREE_MARKER and not at_home
                      and (len(free) == 1 or ONE_UNJUDGED_FREE)
                      and (_body_sds(vis, P, sd_of, f, kept, [a], one_body * s0,
                                     voter_frames)[1] > rigid * s0).any()
                      and (open_ := open_free())
                      and (len(open_) == 1 or CONTINUITY_OFF_BODY and (
                          b := _continues_best(X, vis, groups, f, a, open_)) is not None)):
                    # off its marker's body (not rigid to a one-body track; no judge finds
                    # it there), and one marker only is free over its frames, with no track
                    # there to judge it (figure 4662) - or, of several free markers, the
                    # others all have a track that finds it off (ONE_UNJUDGED_FREE, figure
                    # 5221) - or, of several with none, the one that continues it best
                    # (CONTINUITY_OFF_BODY, figure 2738)
                    moves.append((key, f, a, open_[0] if len(open_) == 1 else b, None))
                elif not to and not unjudged and MISFIT_EXCHANGES:
                    swaps = _misfit_exchanges(X, vis, P, sd_of, span, groups, f, a, rigid * s0,
                                              one_body * s0, bound, voter_frames, max_step,
                                              at_home)
                    if len(swaps) == 1:
                        moves.append((key, f, a, swaps[0][0], swaps[0][1:]))
                    elif (CONTINUITY_OPEN and not swaps and not at_home and miss.size
                          and miss.min() > bound and (b := _continues_best(
                              X, vis, groups, f, a, open_free())) is not None):
                        # every judge at home finds it away, no marker fits it and no
                        # exchange takes it: the free marker with no track to find it off
                        # that continues its motion clearly best (figure 4462)
                        moves.append((key, f, a, b, None))
                    elif (BODY_FITS_FREE and not swaps and off and not at_home
                          and (b := _one_body_fits(X, vis, P, sd_of, f, groups, free, [a],
                                                   rigid * s0, one_body * s0, bound,
                                                   voter_frames)) is not None):
                        # off its marker's body, found there by no judge, taken by no
                        # marker or exchange: the one free marker whose one-body tracks
                        # all hold it as their own, every other free marker off one of
                        # its one-body tracks (figure 10847)
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


MISFIT_EXCHANGES = True  # step 4c: a misfit with no free marker to go to is exchanged
EXCHANGE_UNJUDGED = True  # step 4c: a misfit may be exchanged onto a marker where no
#                           track judges it, for a piece that fits (figure 4251)
ONLY_FREE_MARKER = True  # step 4c: a piece off its body that no judge places goes to the one
#                          marker free over its frames (figure 4662)
ONE_UNJUDGED_FREE = True  # ... or, of several free markers, to the one where no track
#                           finds it off (figure 5221)
CONTINUITY_OPEN = True   # step 4c: a misfit no marker takes goes to the free marker where
#                          nothing finds it off that continues it best (figure 4462)
CONTINUITY_OPEN_MARGIN = 2.0   # ... by this much in step 8's continuity cost over the next
ONE_OPEN = True          # ... or, the one such marker, where it continues it better (9778)
CONTINUITY_OFF_BODY = True   # ... also an off-body piece with several free markers where
#                              nothing finds it off (ONLY_FREE_MARKER's case; figure 2738)
BODY_FITS_FREE = True    # step 4c: an off-body piece no marker takes goes to the one free
#                          marker whose one-body tracks all hold it (figure 10847)
TELLING_JUDGES = True    # step 4c: a move needs a judge on the new marker that does not
#                          also find the piece on its own (figure 4083)


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


def _tells(X, vis, P, sd_of, f, kept, excl, rigid_sd, bound, partner_frames, at_home) -> bool:
    """A judge of fragment ``f`` on the marker of the fragments ``kept`` (``_misfit``) is
    not among ``at_home``, the judges that find f where it is (``TELLING_JUDGES``; figure
    4083: an off-body piece's own segment partner, as far from its true marker as from the
    one it would move to, was the only judge there). True without such judges at home."""
    if not (TELLING_JUDGES and at_home):
        return True
    _, there = _misfit(X, vis, P, sd_of, f, kept, excl, rigid_sd, bound, partner_frames,
                       with_judges=True)
    return not set(there.tolist()) <= at_home


def _continues_best(X, vis, groups, f, a, open_):
    """Step 4c's ``CONTINUITY_OPEN`` and ``CONTINUITY_OFF_BODY``: of the markers ``open_``
    (free over fragment ``f``'s frames, no track judging it there: ``_unjudged_on``), the
    one whose continuity cost (step 8's ``_continuity_cost``) f raises least, when that is
    less than taking f off its marker ``a`` lowers it and at least
    ``CONTINUITY_OPEN_MARGIN`` less than the next such marker's; else None (also with fewer
    than two such markers, unless ``ONE_OPEN``: then the one, when f raises its cost less
    than taking f off a lowers a's; figure 9778: marker 20's 13-frame first piece, 527 and
    1057 x the bound off both judges of marker 10 it sat on, one marker free, 1.34
    against 3.36). Figure 4462: marker 30's first 17 frames, rigid to markers 0, 2
    and 3 of the root segment while the chain between barely moved (but at other distances
    than marker 1), sat on marker 1; markers 29 and 30 were both free and unjudged, and f
    raised their costs by 3.78 and 1.61 (taking it off marker 1 lowered that by 2.49).
    Figure 2738: marker 0's first 23 frames, off the one-body track of marker 6 it sat on,
    no judge placing it; markers 0 and 1 free and unjudged, added costs 0.69 and 4.46
    (taking it off marker 6, 3.66)."""
    if len(open_) < (1 if ONE_OPEN else 2):
        return None
    cost = _continuity_cost(X, vis)
    gain = cost(groups[a]) - cost([h for h in groups[a] if h != f])   # f off its marker
    if len(open_) == 1:
        # one marker free and unjudged: it continues f better than its marker does
        # (``ONE_OPEN``; figure 9778)
        b = open_[0]
        return b if cost(groups[b] + [f]) - cost(groups[b]) < gain else None
    (best, b), (second, _) = sorted((cost(groups[b] + [f]) - cost(groups[b]), b)
                                    for b in open_)[:2]
    return b if best < gain and second - best >= CONTINUITY_OPEN_MARGIN else None


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
    own = (f,) if EXCHANGE_UNJUDGED else ()
    return [(b, na, nb) for b in range(len(groups)) if b != a
            for na, nb in _cross_alternatives(span, groups[a], groups[b])
            if f in nb and takes(na, groups[a], [a, b])
            and takes(nb, groups[b], [a, b], own if set(na) - set(groups[a]) else ())
            and _tells(X, vis, P, sd_of, f, [h for h in nb if h in groups[b]], [a, b],
                       rigid_sd, bound, partner_frames, at_home)]


def _unjudged_on(X, vis, P, sd_of, f, kept, excl, rigid_sd, body_sd, bound,
                 partner_frames) -> bool:
    """No track judges fragment ``f`` on the marker of the fragments ``kept``: no judge of
    ``_misfit`` and off no one-body track (``_off_body``)."""
    return (not _misfit(X, vis, P, sd_of, f, kept, excl, rigid_sd, bound, partner_frames).size
            and not _off_body(X, vis, P, sd_of, f, kept, excl, rigid_sd, body_sd, bound,
                              partner_frames))


def _fits_on(X, vis, P, sd_of, f, kept, excl, rigid_sd, body_sd, bound, partner_frames) -> bool:
    """Fragment ``f`` fits the marker of the fragments ``kept``: ``_fits`` of ``_misfit``
    (some judge, every one within ``bound``) and not ``_off_body``."""
    return (_fits(_misfit(X, vis, P, sd_of, f, kept, excl, rigid_sd, bound, partner_frames),
                  bound)
            and not _off_body(X, vis, P, sd_of, f, kept, excl, rigid_sd, body_sd, bound,
                              partner_frames))


def _first_seen(X, f) -> int:
    return int(np.flatnonzero(~np.isnan(X[:, f, 0]))[0])


def _gap(fa: np.ndarray, fb: np.ndarray) -> int:
    """Fewest frames between a frame of sorted ``fa`` and one of sorted ``fb``."""
    k = np.searchsorted(fb, fa)
    after = np.abs(fb[np.minimum(k, fb.size - 1)] - fa)
    before = np.abs(fb[np.maximum(k - 1, 0)] - fa)
    return int(np.minimum(after, before).min())


def _run_ends(frames: np.ndarray, x: np.ndarray, n: int):
    """Per contiguous run of sorted ``frames`` (positions ``x`` (len, 3)): (first frame,
    last frame, position and velocity per frame of a straight-line fit to its first ``n``
    frames at the first frame, the same for its last ``n`` frames at the last frame)."""
    cut = np.flatnonzero(np.diff(frames) > 1) + 1
    out = []
    for lo, hi in zip(np.r_[0, cut], np.r_[cut, frames.size]):
        ends = []
        for sl, t0 in ((slice(lo, min(hi, lo + n)), frames[lo]),
                       (slice(max(lo, hi - n), hi), frames[hi - 1])):
            t = frames[sl] - t0
            if t.size < 2:
                ends.append((x[sl].mean(0), np.full(3, np.nan)))
                continue
            A = np.stack([np.ones(t.size), t], 1)
            c = np.linalg.lstsq(A, x[sl], rcond=None)[0]
            ends.append((c[0], c[1]))
        out.append((int(frames[lo]), int(frames[hi - 1]), ends[0], ends[1]))
    return out


def _junctions(ra, rb):
    """(gap frames, miss m) at every change of column between two never-overlapping columns
    (runs from ``_run_ends``): the miss is the distance at the middle of the gap between the
    end of the run before, extrapolated forward at constant velocity, and the start of the
    run after, extrapolated backward."""
    runs = sorted([(r, 0) for r in ra] + [(r, 1) for r in rb], key=lambda q: q[0][0])
    out = []
    for (r0, s0), (r1, s1) in zip(runs[:-1], runs[1:]):
        if s0 == s1:
            continue
        t1, t2 = r0[1], r1[0]
        mid = 0.5 * (t1 + t2)
        (p0, v0), (p1, v1) = r0[3], r1[2]
        miss = float(np.linalg.norm(p0 + v0 * (mid - t1) - p1 - v1 * (mid - t2)))
        out.append((t2 - t1, miss))               # NaN: a run too short for a velocity
    return out


ORDER_SD_WEIGHT = 1.0  # step 3's order: the whole sd of the least rigid partner (5991)
LOOSE_BY_CONTINUITY = True  # step 3's loose passes: order by max(distance, scaled miss)
ACCEL_GAP_FRAMES = 10.0     # ... the miss divided by max(1, (gap / this)^2) (7107, 6555)


def _merge_pass(X, min_frames, max_distance_m, n_markers, samples, neighbours,
                partner_sd_weight=0.5, gap_weight_m=1e-4, continuity_m=0.0,
                continuity_frames=10, continuity_max_gap=45, max_gap=None,
                max_step=np.inf, order_sd_weight=None, loose=False) -> MarkerSets:
    """One merge: drop short fragments, pose-aligned distances, constrained linkage
    (``max_step``: no merge that crosses a gap faster than this per frame, m). The
    threshold is judged on distances floored at ``partner_sd_weight`` times the least
    rigid partner's sd, the joins are ordered by distances floored at ``order_sd_weight``
    (None: ``ORDER_SD_WEIGHT``) times it (module docstring, steps 2-3). A ``loose`` pass
    (``max_distance_m`` is then ``loose_distance_m``) orders its joins by the worse of that
    distance and the scaled continuity miss where ``LOOSE_BY_CONTINUITY`` (step 3)."""
    if order_sd_weight is None:
        order_sd_weight = ORDER_SD_WEIGHT
    T, F = X.shape[:2]
    vis = ~np.isnan(X).any(2)
    keep = np.flatnonzero(vis.sum(0) >= min_frames)
    dropped = tuple(int(f) for f in np.setdiff1d(np.arange(F), keep))
    D = np.full((F, F), np.nan)
    if keep.size == 0:
        return MarkerSets(positions=np.full((T, 0, 3), np.nan), groups=(), dropped=dropped,
                          n_min=0, distance=D)
    Xk, vk = X[:, keep], vis[:, keep]
    K = keep.size
    n_min = int(vk.sum(1).max())
    lower = max(n_min, int(n_markers) if n_markers is not None else 0)
    # rigidity of every fragment pair (sd of distance over common frames, >= min_frames)
    common = vk.T.astype(np.int64) @ vk.astype(np.int64)                   # (K, K) frames
    sd = np.full((K, K), np.inf)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for i in range(K):
            d = np.linalg.norm(Xk - Xk[:, i:i + 1], axis=2)
            sd[i] = np.nanstd(d, axis=0)
    sd[(common < min_frames) | np.isnan(sd)] = np.inf
    np.fill_diagonal(sd, np.inf)
    overlap = common > 0
    frames = [np.flatnonzero(vk[:, i]) for i in range(K)]
    samp = [_samples(f, samples) for f in frames]
    Dk = np.where(overlap, np.inf, np.nan)        # NaN: no common partners to align on
    Ok = Dk.copy()                                # the same, floored for the order
    for i in range(K):
        for j in range(i + 1, K):
            if overlap[i, j]:
                continue
            # partners rigid to both fragments (a short fragment finds everything rigid)
            both_sd = np.maximum(sd[i], sd[j])
            rank = np.argsort(both_sd, kind="stable")
            rank = rank[np.isfinite(both_sd[rank])]
            if rank.size < 3:
                continue
            a = np.repeat(samp[i], samp[j].size)
            b = np.tile(samp[j], samp[i].size)
            both = vk[a][:, rank] & vk[b][:, rank]                           # (P, R)
            enough = both.sum(1) >= 3
            if not enough.any():
                continue
            a, b, both = a[enough], b[enough], both[enough]
            # the first `neighbours` most rigid partners seen at a and at b
            pos = np.cumsum(both, 1)
            pick = both & (pos <= neighbours)
            nk = np.minimum(both.sum(1), neighbours)
            best = obest = np.inf
            for n in np.unique(nk):
                sel = nk == n
                cols = np.nonzero(pick[sel])[1].reshape(-1, n)
                src = Xk[b[sel, None], rank[cols]]
                dst = Xk[a[sel, None], rank[cols]]
                R, t = _kabsch_batch(src, dst)
                mj = np.einsum("bij,bj->bi", R, Xk[b[sel], j]) + t
                # an alignment is only as good as its least rigid partner
                least = both_sd[rank[cols]].max(1)
                miss = np.linalg.norm(mj - Xk[a[sel], i], axis=1)
                best = min(best, float(np.maximum(miss, least * partner_sd_weight).min()))
                obest = min(obest, float(np.maximum(miss, least * order_sd_weight).min()))
            Dk[i, j], Ok[i, j] = best, obest
    Dk = np.fmin(Dk, Dk.T)
    Ok = np.fmin(Ok, Ok.T)
    D[np.ix_(keep, keep)] = Dk
    # constrained single linkage
    cluster = list(range(K))
    members = {c: [c] for c in range(K)}
    seen = {c: vk[:, c].copy() for c in range(K)}
    iu, ju = np.triu_indices(K, 1)
    dist = Dk[iu, ju]
    odist = Ok[iu, ju]
    rescued = np.zeros(dist.size, bool)
    by_continuity = loose and LOOSE_BY_CONTINUITY
    scaled_miss = np.full(dist.size, np.nan)    # NaN: motion continuity does not judge
    if continuity_m > 0:
        # motion continuity: a pair whose ends meet within continuity_m across every change
        # of column (gaps of at most continuity_max_gap frames) is a candidate at that miss
        runs = [_run_ends(frames[i], Xk[frames[i], i], continuity_frames) for i in range(K)]
        for e in np.flatnonzero(~overlap[iu, ju]):
            jn = _junctions(runs[iu[e]], runs[ju[e]])
            if by_continuity and jn and all(g <= continuity_max_gap for g, m in jn):
                sm = [m / max(1.0, (g / ACCEL_GAP_FRAMES) ** 2) for g, m in jn
                      if np.isfinite(m)]
                if sm:
                    scaled_miss[e] = max(sm)
            if jn and all(g <= continuity_max_gap and m <= continuity_m for g, m in jn):
                miss = max(m for g, m in jn)
                dist[e], odist[e] = np.fmin(dist[e], miss), np.fmin(odist[e], miss)
                rescued[e] = True
    cand = np.flatnonzero((dist <= max_distance_m) | rescued)
    gap = np.array([_gap(frames[iu[e]], frames[ju[e]]) for e in cand], np.float64)
    if max_gap is not None:
        cand, gap = cand[gap <= max_gap], gap[gap <= max_gap]
    # a loose join is ordered by the worse of the distance and the scaled continuity miss
    # (np.fmax: the distance alone where continuity does not judge)
    key = np.fmax(odist[cand], scaled_miss[cand]) + gap_weight_m * gap
    # each cluster's runs (first frame, last frame, first position, last position)
    runs_of = {c: [(int(f[lo]), int(f[hi - 1]), Xk[f[lo], c], Xk[f[hi - 1], c])
                   for lo, hi in zip(np.r_[0, cut], np.r_[cut, f.size])]
               for c, f in enumerate(frames)
               for cut in [np.flatnonzero(np.diff(f) > 1) + 1]}

    def too_fast(ci, cj) -> bool:
        """the merged marker would jump a gap between the two clusters faster than
        max_step per frame"""
        runs = [r + (0,) for r in runs_of[ci]] + [r + (1,) for r in runs_of[cj]]
        return _too_fast(sorted(runs, key=lambda r: r[0]), max_step)

    for e in cand[np.argsort(key, kind="stable")]:
        if len(members) <= lower:
            break
        ci, cj = cluster[iu[e]], cluster[ju[e]]
        if ci == cj or (seen[ci] & seen[cj]).any():
            continue
        if np.isfinite(max_step) and too_fast(ci, cj):
            continue
        runs_of[ci] = runs_of[ci] + runs_of.pop(cj)
        for m in members[cj]:
            cluster[m] = ci
        members[ci] += members.pop(cj)
        seen[ci] |= seen.pop(cj)
    groups = sorted((sorted(ms, key=lambda m: frames[m][0]) for ms in members.values()),
                    key=lambda ms: frames[ms[0]][0])
    out = np.full((T, len(groups), 3), np.nan)
    for g, ms in enumerate(groups):
        for m in ms:
            out[vk[:, m], g] = Xk[vk[:, m], m]
    return MarkerSets(positions=out, groups=tuple(tuple(int(keep[m]) for m in ms)
                                                  for ms in groups),
                      dropped=dropped, n_min=n_min, distance=D)


def _bodies(one, S) -> list:
    """Sets (sorted tuples, >= 3) of tracks that all move as one body with each other
    (``one``: (M, M) bool): each track with its one-body partners taken in order of sd
    while they move as one body with every track taken so far."""
    out = set()
    for m in range(one.shape[0]):
        body = [m]
        for j in sorted(np.flatnonzero(one[m]), key=lambda j: S[m, j]):
            if one[j, body].all():
                body.append(int(j))
        if len(body) >= 3:
            out.add(tuple(sorted(body)))
    return sorted(out)


def _body_frame(P, body) -> tuple:
    """(frames, R, t): the frames all tracks of ``body`` are seen and, in each, the rigid
    motion y = R x + t taking world points into the body's frame (its tracks' positions in
    the first of those frames)."""
    fr = np.flatnonzero(~np.isnan(P[:, list(body), 0]).any(1))
    src = P[fr][:, list(body)]
    R, t = _kabsch_batch(src, np.broadcast_to(src[:1], src.shape))
    return fr, R, t


def _one_body_frames(P, S, s0, body_sd, body_frames) -> tuple:
    """(common, one, frames) of tracks P (T, M, 3) with pair sds S: the frames each pair is
    seen in together (M, M), the pairs moving as one body (sd <= ``body_sd`` x s0 over >=
    ``body_frames`` common frames), and the frame (``_body_frame``) of each body
    (``_bodies``) seen in >= ``body_frames`` frames. Steps 8 and 11."""
    seen = ~np.isnan(P[..., 0])
    common = seen.T.astype(np.int64) @ seen.astype(np.int64)
    with np.errstate(invalid="ignore"):
        one = (S <= body_sd * s0) & (common >= body_frames)
    frames = {b: _body_frame(P, b) for b in _bodies(one, S)}
    return common, one, {b: v for b, v in frames.items() if v[0].size >= body_frames}


VIRTUAL_JOINT_RMS = 5.0      # step 8: the joint a body's frame borrows fits within this x s0
VIRTUAL_MIN_LEVER_M = 0.02   # ... and lies this far off the line through its two tracks seen


def _fixed_point(fa, fb, min_frames=50) -> tuple | None:
    """(u, v, rms, frames) of the point fixed in two bodies' frames (``_body_frame``: u in
    the first's, v in the second's): the joint between them, linear least squares over the
    frames both are seen in (R_a^T (u - t_a) = R_b^T (v - t_b)); rms the world distance
    between the two images. None under ``min_frames`` common frames."""
    fra, Ra, ta = fa
    frb, Rb, tb = fb
    _, ia, ib = np.intersect1d(fra, frb, return_indices=True)
    if ia.size < min_frames:
        return None
    RaT, RbT = np.transpose(Ra[ia], (0, 2, 1)), np.transpose(Rb[ib], (0, 2, 1))
    A = np.concatenate([RaT, -RbT], 2).reshape(-1, 6)
    b = (np.einsum("bij,bj->bi", RaT, ta[ia])
         - np.einsum("bij,bj->bi", RbT, tb[ib])).reshape(-1)
    sol = np.linalg.lstsq(A, b, rcond=1e-6)[0]   # min-norm on a hinge's axis
    r = (A @ sol - b).reshape(-1, 3)
    return sol[:3], sol[3:], float(np.sqrt((r ** 2).sum(1).mean())), int(ia.size)


def _virtual_frames(P, frames, s0, joint_rms=VIRTUAL_JOINT_RMS,
                    min_lever=VIRTUAL_MIN_LEVER_M) -> dict:
    """Each body's frame (``_one_body_frames``' ``frames``) extended to the frames where
    only two or more of its tracks are seen, with the joint to its best-fitting
    neighbouring body (``_fixed_point``, rms <= ``joint_rms`` x s0, that body seen in
    full) as a third point: (frames, R, t) as ``_body_frame`` gives, for bodies that gain
    frames so. A third point within ``min_lever`` of the line through the two tracks
    seen leaves the roll about it free: those frames are left out. Step 8 (6245)."""
    out = {}
    for B, (frB, RB, tB) in frames.items():
        best = None
        for A, fa in frames.items():
            if set(A) & set(B):
                continue
            fp = _fixed_point(fa, frames[B])
            if fp is not None and fp[2] <= joint_rms * s0 and (best is None
                                                                or fp[2] < best[1][2]):
                best = (A, fp)
        if best is None:
            continue
        A, (u, v, _, _) = best
        frA, RA, tA = frames[A]
        ref = P[frB[0]][list(B)]               # B's tracks in B's frame
        Q = P[frA][:, list(B)]
        seen = ~np.isnan(Q[..., 0])
        extra = (seen.sum(1) >= 2) & ~seen.all(1)
        if not extra.any():
            continue
        c = np.einsum("bji,bj->bi", RA[extra], u - tA[extra])   # the joint in the world
        fr, R, t = [frB], [RB], [tB]
        for key in {tuple(r) for r in seen[extra]}:
            cols = np.flatnonzero(key)
            d = ref[cols[1]] - ref[cols[0]]
            w = v - ref[cols[0]]
            if np.linalg.norm(np.cross(d, w)) / np.linalg.norm(d) < min_lever:
                continue
            rows = (seen[extra] == key).all(1)
            src = np.concatenate([Q[extra][rows][:, cols], c[rows][:, None]], 1)
            dst = np.broadcast_to(np.vstack([ref[cols], v]), src.shape)
            Rk, tk = _kabsch_batch(src, dst)
            fr.append(frA[extra][rows])
            R.append(Rk)
            t.append(tk)
        if len(fr) > 1:
            fr = np.concatenate(fr)
            o = np.argsort(fr, kind="stable")
            out[B] = (fr[o], np.concatenate(R)[o], np.concatenate(t)[o])
    return out


def _points_in(frames, Y):
    """A function (body, column) -> the points of column ``Y[:, column]`` seen in the frames
    of ``body`` (a key of ``frames``, as ``_one_body_frames`` gives), in the body's frame;
    each computed once."""
    cache = {}

    def points(body, c):
        if (body, c) not in cache:
            fr, R, t = frames[body]
            x = Y[fr, c]
            ok = ~np.isnan(x[:, 0])
            cache[body, c] = np.einsum("bij,bj->bi", R[ok], x[ok]) + t[ok]
        return cache[body, c]
    return points


def _common_sphere(Ys) -> list:
    """Residuals |y - c| - r_i of each point set in ``Ys`` about one centre c with a radius
    per set (Kasa's algebraic fit, shared centre)."""
    n = len(Ys)
    A = np.zeros((sum(len(y) for y in Ys), 3 + n))
    A[:, :3] = 2 * np.concatenate(Ys)
    i = 0
    for k, y in enumerate(Ys):
        A[i:i + len(y), 3 + k] = 1.0
        i += len(y)
    b = np.concatenate([(y ** 2).sum(1) for y in Ys])
    sol = np.linalg.lstsq(A, b, rcond=None)[0]
    c = sol[:3]
    return [np.linalg.norm(y - c, axis=1) - np.sqrt(max(sol[3 + k] + c @ c, 0.0))
            for k, y in enumerate(Ys)]


def _sphere_verdict(pts, ga, gb, na, nb, moved):
    """(sum of squares kept, exchanged, mean square of the moved pieces kept, exchanged,
    points) of two markers' fragments ``pts`` (fragment -> points in a body's frame) fitted
    on one common sphere centre, as ``ga``/``gb`` (current) and ``na``/``nb`` (exchanged);
    None where a marker has < 50 points or the moved pieces < 5."""
    out = []
    for x, y in ((ga, gb), (na, nb)):
        ya = [pts[f] for f in x]
        yb = [pts[f] for f in y]
        if sum(map(len, ya)) < 50 or sum(map(len, yb)) < 50:
            return None
        ra, rb = _common_sphere([np.concatenate(ya), np.concatenate(yb)])
        res = np.r_[ra, rb]
        m = np.concatenate([np.full(len(pts[f]), f in moved) for f in list(x) + list(y)])
        out.append((float(res @ res), float(res[m] @ res[m]), int(m.sum()), res.size))
    (sk, pk, nd, n), (sm, pm, _, _) = out
    if nd < 5:
        return None
    return sk, sm, pk / nd, pm / nd, n


VIRTUAL_FRAMES = True  # step 8: spheres also in frames where a body shows two tracks (6245)
VIRTUAL_FIT_RMS = 2.0  # ... judging there within this x s0 rms (true neighbours: 91 % <= 2)
CONTINUITY_EXCHANGES = True  # step 8: exchanges no sphere or direction finds, by continuity
CONTESTED_DIRECTIONS = True  # ... a direction veto needs no body for the exchange (8759)
STEP8_JUMPS = True  # step 8 makes no exchange that step 4's jump test would undo (4455)
CONTINUITY_MARGIN = 4.0      # steps 7b and 10: the most a join may cost in continuity
CONTINUITY_EXCHANGE_MARGIN = 2.0   # step 8: the least gain in the continuity cost (1304)
CONTINUITY_MM_PER_FRAME = (0.6, 0.009)   # a junction's typical miss: a x gap + b x gap^2 (mm)


def _continuity_cost(X, vis):
    """``cost(g)``: the motion-continuity cost of one marker's fragments ``g``: over each
    change from one fragment to the next (in time order), log(1 + (miss / m)^2), the miss
    that of step 3 (``_junctions``: constant-velocity lines fitted to the 10 frames each
    side, met at mid-gap) and m the typical miss of one marker across that gap,
    a x gap + b x gap^2 mm (``CONTINUITY_MM_PER_FRAME``: step 3's medians, 2 mm at 1-5
    frames to 36 mm at 31-45). A piece of another marker misses at both its ends."""
    ends = {}
    a_mm, b_mm = CONTINUITY_MM_PER_FRAME

    def end(f):
        if f not in ends:
            fr = np.flatnonzero(vis[:, f])
            r = _run_ends(fr, X[fr, f], 10)
            ends[f] = (int(fr[0]), r[0], r[-1])
        return ends[f]

    def cost(g) -> float:
        g = sorted(g, key=lambda f: end(f)[0])
        c = 0.0
        for f0, f1 in zip(g[:-1], g[1:]):
            (gap, miss), = _junctions([end(f0)[2]], [end(f1)[1]])
            if np.isfinite(miss):
                c += float(np.log1p((miss * 1e3 / (a_mm * gap + b_mm * gap ** 2)) ** 2))
        return c
    return cost


def _direction_spread(ends, frame) -> float:
    """Mean resultant length (0-1) of the unit direction from the first to the second of
    two markers' tracks ``ends`` (T, 2, 3) in a body's ``frame`` (``_body_frame``), over the
    frames both are seen with the body; NaN under ``DIRECTION_FRAMES`` such frames."""
    fr, R, _ = frame
    d = np.einsum("bij,bj->bi", R, ends[fr, 1] - ends[fr, 0])
    d = d[~np.isnan(d[:, 0])]
    if len(d) < DIRECTION_FRAMES:
        return float("nan")
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return float(np.linalg.norm(d.mean(0)))


def _sphere_exchanges(X, groups, min_frames, body_sd=1.5, body_frames=100, fit_rms=1.5,
                      min_misfit=2.0, max_rounds=3, direction_margin=DIRECTION_MARGIN,
                      max_step=np.inf, rigid=3.0, jump_margin=10.8) -> tuple[list, bool]:
    """Step 8 (module docstring): exchanges between two markers moving as one body judged
    by the sphere each keeps about its joint in the frame of a neighbouring body, then by
    how their direction stays within a joint's range in that frame
    (``direction_margin``). None that step 4's jump test would undo (``STEP8_JUMPS``:
    raising ``_jumps`` on the tracks rigid to every fragment of both markers by
    ``jump_margin`` x s0 squared). Returns the groups and whether any changed."""
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

        best = turn = cont = None
        sd_of = _fragment_sd(X, vis, P, min_frames) if STEP8_JUMPS else None
        for a, b in zip(*np.nonzero(np.triu(one, 1))):
            ga, gb = groups[a], groups[b]
            if len(ga) + len(gb) < 3:
                continue
            undone = set()             # alternatives step 4's jump test would undo
            if STEP8_JUMPS:
                alts = _cross_alternatives(span, ga, gb)
                js = _rigid_to_all(sd_of, ga + gb, rigid * s0)
                js[[a, b]] = False
                js = np.flatnonzero(js)
                if alts and js.size:
                    now_j, alt_j = _jumps(X, vis, ga, gb, alts, P[:, js],
                                          jump_margin * s0 ** 2)
                    undone = {frozenset((frozenset(na), frozenset(nb)))
                              for (na, nb), c in zip(alts, alt_j)
                              if c >= now_j + jump_margin * s0 ** 2}
            done = set()
            kept = {}                     # body -> the current assignment's direction spread
            kept_ends = P[:, [a, b]]        # the current tracks (kept current by _exchange)
            smooth_now = None               # the current assignment's continuity cost
            for na, nb in _cross_alternatives(span, ga, gb):
                key = frozenset((frozenset(na), frozenset(nb)))
                if key in done or key in undone or not (_paced(X, span, na, max_step)
                                       and _paced(X, span, nb, max_step)):
                    continue
                done.add(key)
                moved = (set(ga) - set(na)) | (set(gb) - set(nb))
                rest = set(ga + gb) - moved
                if (sum(span[f][1] - span[f][0] for f in moved)
                        > sum(span[f][1] - span[f][0] for f in rest)):
                    moved = rest           # the smaller side is the exchanged piece
                gain, veto = 0.0, False
                spread = []               # (kept, exchanged) direction spread per body
                ends = _tracks(X, [na, nb])
                for body in frames:
                    if a in body or b in body:
                        continue
                    pts = {f: points(body, f) for f in ga + gb}
                    v = _sphere_verdict(pts, ga, gb, na, nb, moved)
                    gate = fit_rms
                    if v is None and VIRTUAL_FRAMES:
                        # too few points with the body seen in full: with two of its
                        # tracks and its joint to a neighbour as the third point
                        if virtual is None:
                            virtual = _virtual_frames(P, frames, s0)
                            points_v = _points_in(virtual, X)
                        if body in virtual:
                            v = _sphere_verdict({f: points_v(body, f) for f in ga + gb},
                                                ga, gb, na, nb, moved)
                            gate = VIRTUAL_FIT_RMS
                    if body not in kept:
                        kept[body] = _direction_spread(kept_ends, frames[body])
                    if not DIRECTION_SEES_MOVED or (sum(len(pts[f]) for f in moved)
                                                    >= DIRECTION_MOVED_FRAMES):
                        spread.append((kept[body], _direction_spread(ends, frames[body])))
                    if v is None:
                        continue
                    sk, sm, pk, pm, n = v
                    var = min(sk, sm) / (n - 5)
                    if not var <= (gate * s0) ** 2 * n / (n - 5):
                        continue                 # not a neighbour across one joint
                    kp, mv = np.sqrt(pk / var), np.sqrt(pm / var)
                    if kp >= min_misfit and kp >= min_misfit * mv:
                        gain = max(gain, (sk - sm) / var)
                    if mv >= min_misfit and mv >= min_misfit * kp:
                        veto = True
                if gain > 0 and not veto and (best is None or gain > best[0]):
                    best = (gain, a, b, na, nb)
                spread = np.array([r for r in spread if np.isfinite(r).all()]).reshape(-1, 2)
                if not veto and spread.size:
                    # the body that holds their direction tightest (their neighbour)
                    rk, rx = spread[np.argmax(spread.max(1))]
                    if (rx - rk >= direction_margin
                            and not (spread[:, 0] - spread[:, 1] >= direction_margin).any()
                            and (turn is None or rx - rk > turn[0])):
                        turn = (rx - rk, a, b, na, nb)
                if CONTINUITY_EXCHANGES and not veto and not (
                        spread.size and (spread[:, 0] - spread[:, 1] >= direction_margin).any()
                        and not (CONTESTED_DIRECTIONS and (
                            spread[:, 1] - spread[:, 0] >= direction_margin).any())):
                    if smooth_now is None:
                        smooth_now = continuity(ga) + continuity(gb)
                    smooth = smooth_now - continuity(na) - continuity(nb)
                    if (smooth >= CONTINUITY_EXCHANGE_MARGIN
                            and (cont is None or smooth > cont[0])):
                        cont = (smooth, a, b, na, nb)
        if best is None:
            best = turn
        if best is None:
            best = cont
        if best is None:
            break
        _exchange(X, groups, P, S, *best[1:], min_frames)
        changed = True
    return groups, changed

"""Every switch and threshold of the marker-set repairs, in one place.

The steps read them here at call time (``rules.NAME``), so a test or a screen
(``benchmarks/screen_markersets.py --set/--compare``) that sets
``skeleton.markersets.rules.NAME`` changes the merge everywhere. A flag's comment names
the step, the rule and the figure it was chosen on; the step modules' docstrings give the
measurements.
"""

DIRECTION_MARGIN = 0.1  # step 8: the least gain in the mean resultant length of two markers'
                        # direction, in the frame of the body that holds it tightest, for an
                        # exchange (``spheres``);        1 mm noise on markers >= 20 mm apart
                        # costs ~0.005
DIRECTION_FRAMES = 50   # ... over at least this many frames both are seen with the body
DIRECTION_SEES_MOVED = True   # step 8: a body judges the direction only where it sees the
DIRECTION_MOVED_FRAMES = 5    # ... moved pieces for at least this many frames

TWO_OF_FOUR = True   # step 7 also takes two rigid pairs of ids that never share a frame
ONE_SPLIT = True     # step 7 takes the one split where the fragments split only one way
PARTNER_SPLITS = True   # ... and judges ids with a segment partner too, by turns and jumps

CONTINUITY_JOINS = True  # step 7b: markers left as two ids are joined by motion continuity
CHAIN_JOINS = True  # ... and a marker left as three or more, where their joins are each
#                     other's only rivals (figure 22748)
PAIR_JOINS = True  # ... and two markers each left as two ids, where the joins are each
#                    other's rivals but one pairing of the four is clear (figure 26100)
RANGE_JOINS = True  # ... and an id whose cheapest join has rivals within the margin, where
#                     the distance ranges to other tracks rule every rival out (26928)
RANGE_OFF_Z = 5.0   # ... a track finds the id this x its distance sd outside a rival's range
RANGE_FIT_Z = 1.5   # ... and within this x of the join's range
RANGE_VOTES = 1     # ... on at least this many tracks (2 until stop 78; 29501: 1 against 0)
RANGE_RATIO = 2     # ... and this x those finding the reverse (26929: 15 against 1)
RANGE_FRAMES = 100  # ... the range measured over at least this many frames
JOINS_AFTER_EXCHANGES = True  # step 9: and again where step 8 exchanged (figure 4881)

SPLIT_JOINS = True  # step 10: a marker holding two others' pieces is split and joined

SPHERE_JOINS = True  # step 11: a marker left as two ids is joined where joint spheres judge
SPHERE_FIT_Z = 3.0      # ... the piece fits a marker's sphere within this x the sphere's rms
SPHERE_MISFIT_Z = 6.0   # ... and is off every other candidate's by at least this x its rms
SPHERE_POINTS = 5       # ... on at least this many of the piece's frames in the body
SPHERE_JOINS_PAIRS = True  # ... judging in two-track bodies' frames too (``_pair_frames``,
#                            the lent body seen in part; ``VIRTUAL_FIT_RMS``), figure 14980

JUMPS_SEEN_TWICE = True  # step 4's jumps: a partner fits only where it sees two fragments
#                          of one marker (figure 16029)
JUMPS_OWN_NOISE = True   # ... each partner in units of its own within-fragment noise
#                          variance, s0^2 at least: a partner across a joint drifts (31380)
TURN_FALLBACK = True   # step 4: a pair moving as one body whose partners decide nothing turns

KEPT_TRACK_VOTES = True    # step 4b: a marker without voters is judged by its kept track
KEPT_TRACK_JUDGES_VOTERS = False   # ... also where the piece moved in is a voter itself
CLEAR_VOTER_MOVES = True   # ... or where that move gains the margin over every other split
#                            of the pair's fragments (figure 10199; figure 313's was not clear)

MISFITS_ARE_BAD = True   # step 4b: a marker holding a misfit piece (step 4c's) is examined
LESS_OFF_BODY = True     # step 4b: nor a move off one body onto one it is further off
MEDIAN_OFF_BODY = True   # ... further off by the median sd to the one-body tracks (13314)
RIGID_SOMEWHERE = True   # step 4b: a voter's partner counts where rigid to some alternative (7429)
JUMPS_PER_MARKER = True  # step 4b's jump veto: a partner fits per marker, not per pair (9533)
BODY_CONFIRMS = True     # step 4b: an exchange gaining less than the margin, by at least
BODY_CONFIRMS_FRACTION = 0.5   # this x the margin, where every moved piece leaves a body it
#                                is off for one it moves as one with (figure 3464)
NO_NEW_MISFITS = True    # step 4b: nor one that makes a fitting piece a misfit (figure 4430)
PIECES_BREAK_TIES = True  # step 4b: of exchanges within the margin of the best, one that puts
#                           the pieces they differ on where a judge fits them (21448)

UNJUDGED_MOVES = True   # step 4c: a piece no judge sees on its own marker moves where it fits
UNJUDGED_EVIDENCE = 20  # ... on judges that see it for this many frames in all
UNJUDGED_CONTINUES = True  # ... or, with fewer, to the marker where judges fit it that
#                            continues its motion better than its own (figure 24267)

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
ONE_OPEN_CLEAR = True    # ... by CONTINUITY_OPEN_MARGIN at least (25854: 2.19 vs 3.17 stays)
CONTINUITY_OFF_BODY = True   # ... also an off-body piece with several free markers where
#                              nothing finds it off (ONLY_FREE_MARKER's case; figure 2738)
BODY_FITS_FREE = True    # step 4c: an off-body piece no marker takes goes to the one free
#                          marker whose one-body tracks all hold it (figure 10847)
SPHERE_OFF_BODY = True   # step 4c: an off-body piece no marker, exchange or body takes, with
#                          several free markers where nothing finds it off, goes to the one
#                          whose joint sphere it lies on, the others' off (figure 12527)
SPLIT_BODY_STAYS = True  # step 4c: an off-body piece every judge at home fits stays where a
#                          one-body track there holds it too (figure 11934)
DRIFT_JUDGES = True   # steps 4c and 10: on the marker a piece would move to, a judge that
#                       drifts across a joint allows for its drift (figures 12450, 12460)
HOME_DRIFT = True     # step 4c: on the piece's own marker too (figure 31380)
TELLING_JUDGES = True    # step 4c: a move needs a judge on the new marker that does not
#                          also find the piece on its own (figure 4083)
HOME_MAJORITY_STAYS = True  # step 4c: an off-body piece most of whose judges at home fit it
#                             (two at least) moves only where as many judges fit it (22706)
NOVEL_POSE_ASIDE = True  # steps 4c (at home) and 12 (every marker's mates): a track that
#                          finds a piece off is set aside where it is at a pose to one that
#                          fits it never seen over the marker's other frames (33057)
NOVEL_POSE_SD = 3.0      # ... the two not rigid there (distance sd above this x s0), the
#                          piece's mean distance out of their range by more than this

ORDER_SD_WEIGHT = 1.0  # step 3's order: the whole sd of the least rigid partner (5991)
LOOSE_BY_CONTINUITY = True  # step 3's loose passes: order by max(distance, scaled miss)
ACCEL_GAP_FRAMES = 10.0     # ... the miss divided by max(1, (gap / this)^2) (7107, 6555)

VIRTUAL_JOINT_RMS = 5.0      # step 8: the joint a body's frame borrows fits within this x s0
VIRTUAL_MIN_LEVER_M = 0.02   # ... and lies this far off the line through its two tracks seen

VIRTUAL_FRAMES = True  # step 8: spheres also in frames where a body shows two tracks (6245)
VIRTUAL_FIT_RMS = 2.0  # ... judging there within this x s0 rms (true neighbours: 91 % <= 2)
CONTINUITY_EXCHANGES = True  # step 8: exchanges no sphere or direction finds, by continuity
CONTESTED_DIRECTIONS = True  # ... a direction veto needs no body for the exchange (8759)
STEP8_JUMPS = True  # step 8 makes no exchange that step 4's jump test would undo (4455)
PAIR_FRAMES = True  # step 8: last, spheres in a two-track body's frame with its joint to a
#                     body of three or more as the third point (figure 12020)
PAIR_JOINT_RMS = 2.0   # ... that joint fitting within this x s0 (7375: 4.57, three joints off)
PAIR_EVERY_LENDER = True  # ... a frame per body whose joint fits, not the best one's only
PAIR_OVER_JUMPS = True    # ... also judging exchanges step 4's jumps would undo (14892)
PAIR_OUTWEIGHS_JUMPS = True  # ... where its gain is above their jump cost in s0^2 (14892:
#                              689 against 99; 21752: 887 against about 481,000)
PAIR_OUTWEIGHS_BODIES = True  # ... and above the drop step 8's own bodies' spheres lose by
#                               it, summed (24196: 56.3 against 155.4)
PAIR_FIT_RMS = 2.5   # ... judging within this x s0 rms, not VIRTUAL_FIT_RMS (17442: 2.13;
#                      true neighbours in these frames: 74 % <= 2, 83 % <= 2.5)
AGREEING_SPHERES = True  # step 8: last, an exchange that two or more bodies across one
#                          joint prefer and none opposes, where no sphere decides (10034)
AGREEING_SPHERES_GAIN = 10.0   # ... each of two by at least this drop in the residual sum of
#                                squares / its variance (2159 wrong ones, 0-184: never two > 0)
AGREED_DIRECTIONS = True  # ... none where a body holds the two's direction tighter as
#                           merged by DIRECTION_MARGIN (18946: hinge spheres alike, 0.98 -> 0.16)
CONTINUITY_MARGIN = 4.0      # steps 7b and 10: the most a join may cost in continuity
CONTINUITY_EXCHANGE_MARGIN = 2.0   # step 8: the least gain in the continuity cost (1304)
CONTINUITY_MM_PER_FRAME = (0.6, 0.009)   # a junction's typical miss: a x gap + b x gap^2 (mm)

MODEL_CHECK = True      # step 12: every piece judged once more on its marker's one-body
#                         mates (robust distance sds), ``model``; figures 14715, 13925
MODEL_PAIR_FRAMES = 50  # ... a mate's distance measured over at least this many frames
MODEL_BODY_SD = 1.5     # ... a one-body mate: robust distance sd within this x s0
MODEL_MIN_FRAMES = 5    # ... a mate judges a piece it is seen with this many frames
MODEL_OFF_Z = 3.0       # ... off: the judging mates' median rms miss beyond this x the sd
MODEL_FIT_Z = 2.0       # ... fits: their median within this x
MODEL_FAR_Z = 6.0       # ... and none beyond this x
MODEL_FAR_OUTVOTED = 3  # ... unless this many mates find it within MODEL_FIT_Z (18401)
MODEL_EVIDENCE = 10     # ... seen by them for this many frames in all
MODEL_STRONGER = True   # ... a piece fitting one mate moves where it fits several (12669)
MODEL_STRONG_MATES = 2  # ... that many
MODEL_ROUNDS = 20       # ... one change a round
MODEL_ROTATIONS = True  # ... three pieces moved round three markers where no exchange fits (17802)
ROTATION_MOVERS = True  # ... judged without the three moving pieces on the mates' tracks (29639)
MODEL_NEAR_MATES = True  # ... a mate vetoes a fit only where it finds the marker's own
#                          frames nearest the piece within MODEL_FIT_Z (17888)
MODEL_UNSURE = True      # ... a piece one mate judges, fitting or not, moves where it fits
#                          several (17888: 2.8 on its one mate)
MODEL_HALF_FITS = True   # ... an off piece fits where half its mates find it within
#                          MODEL_FIT_Z, MODEL_STRONG_MATES at least (18074: 0.9, 1.3, 3.7, 5.1)
MODEL_JOINS = True       # ... after step 12 moved pieces, ids merged again as after step 8
MODEL_STRONGER_EXCHANGES = True  # ... a piece fitting one mate is exchanged where it fits
#                                  several, the pieces there fitting its marker, not theirs (18401)
MODEL_STRONGER_CLEAR = True  # ... only where those mates find it clearly (their pooled rms z
#                              within MODEL_CLEAR_Z) or better than its one mate does (20213)
MODEL_CLEAR_Z = 1.5     # ... (pieces on their right marker with two or more mates within
#                         MODEL_FIT_Z: 11 of 10,568 beyond it, the largest 1.64; 20213's 1.64)
MODEL_CONTINUITY = True  # ... a piece that is not off moves only where the continuity cost
#                          (step 7b's) rises less than CONTINUITY_MARGIN (26461: 3.50 to 10.99)
MODEL_UNJUDGED_BACK = True  # ... an off piece's exchange takes back a piece no mate judges
#                             where it is, fitting its new marker, continuity not rising (26494)
MODEL_OFF_OPEN = True  # ... an off piece no marker fits moves to the one free marker where no
#                        mate judges it, continuity not rising (26901)
OPEN_MOVE_NO_RISE = True  # ... of several such markers, the one where continuity does not
#                           rise (41134: -1.39 on its own marker, +0.46 on its partner)
MODEL_RANGE_MOVES = True  # ... a piece no mate judges moves to the one free marker whose
#                           distance ranges it keeps where its own rule it out (step 7b's
#                           RANGE_ values), continuity not rising (26623)
MODEL_UNFIT_MOVES = True  # ... a piece neither off nor fitting (median z), a mate beyond
#                           MODEL_FAR_Z, moves where several fit it clearly (25141: 37, 2.8, 1.2)
UNJUDGED_FIT_MOVES = True  # ... a piece no mate judges moves to the one free marker where its
#                           mates fit it, no track's range rules that marker out, continuity
#                           rising by less than CONTINUITY_MARGIN (45450: 1.00 x, rise 0.17)
OFF_EXCHANGE_UNFIT_BACK = True  # ... an off piece's exchange takes back a piece that does not
#                           fit where it is and fits the off piece's marker (45688: 2.26, 1.04)
CONTRAST_EXCHANGES = True  # ... two overlapping pieces, each fitting at home on the median but
#                            a mate finding it beyond MODEL_OFF_Z, are exchanged where every
#                            mate fits each on the other's marker, continuity not rising
#                            (46734: 6.01 and 5.28 at home, at most 1.36 exchanged, -6.21)
SPHERE_CHECK = True     # step 12b: two pieces exchanged where joint spheres decide, then
#                         step 12 again (``spheres._sphere_check``; figure 12175)
SPHERE_MOVES = True     # ... and a piece moved onto the one marker never seen with it
#                         whose sphere it lies on, where they decide alike (figure 34087;
#                         off at stop 81: it made held-out 39328 wrong, which
#                         MOVES_KEEP_MODEL prevents)
MOVES_KEEP_MODEL = True  # ... no move where step 12's rigid model fits the piece at home
#                          or finds it off on the new marker (39328: 0.90 and 0.84 at
#                          home, 89.6 on the new marker)
OFF_FAR_CONTRAST = True  # ... an off piece's destination: a mate beyond MODEL_FAR_Z vetoes only
#                          where it finds it as far off as the nearest mate at home (42256)
VETO_NEEDS_CONTRAST = True  # ... a fit at home vetoes only where the new marker's mates do
#                             not fit the piece too (41236: one mate, equally far from both
#                             markers, 1.01 at home and 0.77 on the new marker)
LENDERS_ONCE = True     # ... a two-track body's frames with different lenders agree
#                         once, not once per lender (figure 37858)
NEIGHBOUR_CONTINUITY = True  # step 12c: a piece moves to its one-body partner never seen
#                              with it where motion continuity in the frame of a body across
#                              one joint decides (``neighbour``; 26684, 39284, 39416)
NEIGHBOUR_CONTINUITY_MARGIN = 1.0  # ... the cost falling by at least this in every such body
NEIGHBOUR_BEST_MARGIN = True  # ... by the margin in the best body, and at all in every other
#                               (a larger body seen in part, figure 41236)
NEIGHBOUR_FIT_RMS = 2.0  # ... a body across one joint: both markers' spheres within this x s0
NEIGHBOUR_UNJUDGED = True  # ... and where no body judges it, nor a mate of either marker,
#                            nor the distance ranges, the world's cost falling by at least
NEIGHBOUR_WORLD_MARGIN = 0.5  # ... this (28220: 0.67)

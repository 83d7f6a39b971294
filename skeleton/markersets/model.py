"""Step 12 of the marker-set merge: a last check of every piece against the rigid model.

Steps 4-11 judge one kind of mistake each, with the sds of whole tracks; a piece they all
miss stays on a wrong id. Step 12 (``_model_check``, ``rules.MODEL_CHECK``) looks at the
merged markers once more as a model: for each marker, its one-body mates (tracks whose
distance to it has a robust sd, 1.4826 x the median absolute deviation over their common
frames, within ``MODEL_BODY_SD`` x s0, s0 the median of each track's smallest such sd) and
the distance to each (the median). A piece (one fragment of a marker of two or more) is
judged on the mates and distances its marker has without it: its rms miss of each mate's
distance over the frames they share, in units of that pair's robust sd (at least s0).
It is *off* where every mate seen with it for ``MODEL_MIN_FRAMES`` or more frames finds
it more than ``MODEL_OFF_Z`` off, and it *fits* a marker where every such mate finds it
within ``MODEL_FIT_Z`` and they see it for ``MODEL_EVIDENCE`` frames in all.

- An off piece moves to the one marker, free over its frames (and paced: step 3's speed
  gate), that it fits; where no marker is free, to the one marker it fits whose pieces over
  its frames are off there and fit its own marker (an exchange).
- Where such an exchange fails only because the one piece coming back does not fit the
  off piece's marker, three pieces may move round three markers (``MODEL_ROTATIONS``, stop
  66, ``_rotations``): that piece goes to the marker it fits without that marker's one
  piece over its frames, and that piece, not fitting there, to the first marker, which
  takes it. Held-out figure 17802: the first pieces of markers 6, 22 and 42 sat on 22, 42
  and 6 (a three-cycle: every exchange of two leaves one piece where it misses).
- A piece that fits its marker on one mate only moves to the one free marker it fits on
  ``MODEL_STRONG_MATES`` or more (``MODEL_STRONGER``): a marker of a 2-marker segment
  keeps one distance, a sphere a piece of another segment may cross.

One change per round, the piece furthest off first; at most ``MODEL_ROUNDS`` rounds.
Figures (known wrong after steps 1-11 at stop 62; first run at stops 60-62): 14715, marker
24's last 13 frames on marker 18 of another 2-marker segment, 31.7 x off its one mate there
and fitting marker 24's (1.2); 13925, the last pieces of marker 10 (2-marker segment) and
marker 22 exchanged; 13725, the late pieces of markers 6 and 12 (two 2-marker sibling
segments) exchanged, in two rounds; 12669, marker 7's first 14 frames on marker 1 (2-marker
segment), fitting its mate (a sphere) and fitting marker 7's two mates seen then. Screens
(stop 63, ``benchmarks/screen_markersets.py FIGS OUT --cache ... --compare
MODEL_CHECK=False``): held out, first runs 15000-15749 (full merges), 750/750 right, step
12 acting on none; from the step-4 cache, 14000-14999 right but for 14892 and 14980 (left
below), acting on 14715 only, and 0-91, 92/92, acting on none; at 2 mm noise (``/tmp``
driver, figures 20000-20029, full merges) acting on none. On the 9 real recordings the
merged groups are the same with and without it. Still wrong after it: 12175 (the first
pieces of the two markers of a 2-marker segment and of its 2-marker child exchanged
pairwise: each piece fits its swapped mate; step 4b made the first move, the two pairs'
distances being 179.1 and 179.4 mm; since stop 65 step 12b exchanges one pair on the
joint spheres, ``spheres._sphere_check``, and this step, keeping those pieces
(``fixed``), the other), 14892 (two markers of a 3-marker segment 33 mm
apart, 199 and 202 mm from the third, exchanged end pieces: no distance tells them; step
4's jumps made the exchange on a child segment's marker 50 mm from the joint, 1.55 and
2.19 x s0 from one body with the two, while the third marker missed the jumps' bound by
21.9 to 21.2 mm^2; since stop 65 step 8's two-track bodies exchange them back,
``PAIR_EVERY_LENDER`` and ``PAIR_OVER_JUMPS``) and 14980 (an 11-frame first piece no mate
sees, left an id of its own; since stop 64 step 11 joins it, ``SPHERE_JOINS_PAIRS``).
Held-out figure 17888 (first run at stop 66): marker 1's first 29 frames sat on marker 17
(3-marker segment), 2.8 x off the one mate that sees them there (under ``MODEL_OFF_Z``), and
on marker 1 one of its three mates (marker 5, of a hinge child, 39.4 mm away and one body
with it over marker 1's other frames) finds them 26.4 x off, past ``MODEL_FAR_Z``; marker
17's own first 36 frames were left an id of their own. Since stop 67:

- A mate has a say in whether a piece fits a marker only where it finds the marker's own
  frames nearest the piece (as many as it sees the piece in; in the marker's other
  fragments not off it, since another marker's piece there is no measure) within
  ``MODEL_FIT_Z`` (``MODEL_NEAR_MATES``; ``judge(.., fit=True)``): a mate one body with the
  marker by chance (a hinge neighbour) drifts over time, and a piece at the end of a track
  meets it where it has drifted. Such a mate still counts where a piece is judged off.
  17888's marker 5 finds marker 1's own 29 frames nearest the piece 5.5 x off; the other
  two mates find the piece 1.1 and 0.9 x. (Counting those mates nowhere, not even for off,
  left figure 13725's two markers mixed: a piece judged beside another marker's piece.)
- A piece one mate judges, fitting it or not (but not off), moves where ``MODEL_STRONG_
  MATES`` fit it, free over its frames (``MODEL_UNSURE``; 17888: 2.8 x on its one mate).
- After step 12 moved pieces, ids are merged again as after step 8 (step 3's linkage,
  then step 7b's continuity; ``MODEL_JOINS``): 17888's marker 17, left as two ids.
- An off piece fits where half its mates, ``MODEL_STRONG_MATES`` at least, find it within
  ``MODEL_FIT_Z`` (none beyond ``MODEL_FAR_Z``), in place of the median
  (``MODEL_HALF_FITS``). Held-out figure 18074 (stop 66): marker 17's first 28 frames sat on
  marker 15 (both of 4-marker hinge segment 4), off its three mates there (5.3, 12.6, 22.4
  x); on marker 17 its segment mates find it 0.9 and 1.3 x, two markers of the hinge parent
  (robust sds 1.43 and 1.17 x s0) 3.7 and 5.1 x: a median of 2.5. Those two fit marker 17's
  own nearest frames (0.9, 1.2 x), so ``MODEL_NEAR_MATES`` keeps them.
- A mate beyond ``MODEL_FAR_Z`` does not veto a fit where ``MODEL_FAR_OUTVOTED`` mates
  find the piece within ``MODEL_FIT_Z``, and a piece fitting one mate is exchanged where it
  fits several, each piece coming back not fitting there (judged without the others) and
  fitting its marker (``MODEL_STRONGER_EXCHANGES``). Held-out figure 18401 (stop 67):
  marker 18's last 140 frames (4-marker hinge segment 5) sat on marker 3 (2-marker segment
  1, its parent), fitting its one mate (marker 4, one body with marker 18 by chance, 1.4
  x); on marker 18 its three segment mates find it 1.0, 0.9 and 1.0 x, marker 4 7.1 x;
  marker 3's two pieces there fit marker 4 (0.8, 0.9 x).

Since stop 69 a piece that is not off moves (or is exchanged) where several mates fit it
only if they fit it clearly: the rms z of those within ``MODEL_FIT_Z``, pooled over their
frames (``_pooled``), within ``MODEL_CLEAR_Z`` or within the z of its one mate at home
(``MODEL_STRONGER_CLEAR``). Held-out figure 20213 (stop 68): marker 8's last 12 frames
(2-marker segment 3) fit its one mate at 0.86; marker 38 (4-marker hinge child segment 14,
134.7 mm away, free over those frames) has two mates finding it 1.55 and 1.73 over 12 frames
each (pooled 1.64), and ``MODEL_STRONGER`` moved it there. No bound on the pooled z alone
tells such a move: pieces on their right marker with two or more mates within
``MODEL_FIT_Z`` (10,568 in step 12's first round on 146 cached figures, a ``/tmp`` logger)
pool to 0.99 in the median, 11 beyond 1.5, the largest 1.64 (22 frames). What tells it is
the one mate at home finding the piece better; a right move is kept from its marker only
where its new mates pool beyond 1.5 (0.1 % of right pieces) and the wrong home fits better
still. 12669's, 17888's and 18401's moves pool to 0.95, 1.01 and 0.97.

Since stop 75 a piece neither off nor fitting its marker (the median z of its mates between
``MODEL_FIT_Z`` and ``MODEL_OFF_Z``, also without mates that miss the marker's own nearest
frames), with two mates or more and one of them beyond ``MODEL_FAR_Z``, moves as a piece one
mate judges does: where ``MODEL_STRONG_MATES`` fit it, clearly (pooled within
``MODEL_CLEAR_Z``) (``MODEL_UNFIT_MOVES``). Held-out figure 25141 (stop 74): marker 11's
first 16 frames (3-marker segment 3) sat on marker 8 (3-marker sibling segment 2); marker
8's mates find them 37.0 (segment partner 9), 2.8 (segment partner 7) and 1.2 x (marker 14
of the hinge child segment, one body with marker 8 by chance, which also kept step 4c from
moving the piece); on marker 11, free over those frames, its segment mates 10 and 12 find
them 1.02 and 0.82 x.

Since stop 76:

- A piece that is not off its marker (``MODEL_STRONGER``, ``MODEL_UNSURE``,
  ``MODEL_UNFIT_MOVES``) does not move, nor is it exchanged, where the move raises the two
  markers' continuity cost (step 7b's ``_continuity_cost``) by ``CONTINUITY_MARGIN`` or more
  (``MODEL_CONTINUITY``). Held-out figure 26461 (stop 75): marker 32's frames 45-84 (3-marker
  segment 10) fit their one judge at home, segment mate 34, at 1.05 x; on segment mate 33,
  hidden over 45-96, marker 34 finds them 0.98 x (32 and 33 are 30.5 and 29.6 mm from it)
  and marker 39 of the hinge child, one body with 33 but not with 32 (robust sds 1.35 and
  1.69 x s0), 1.36 x, so ``MODEL_STRONGER`` moved them. Marker 33 was last seen at frame 44,
  20 mm from where the piece starts: the move raises the cost from 3.50 to 10.99. The moves
  of 12669, 17888, 25141, 13925 and 13725 lower it; 18401's raises it by 1.44.
- An off piece's exchange takes back a piece that no mate of its marker judges where it
  is, where no mate of the off piece's marker finds it beyond ``MODEL_FIT_Z`` and the
  exchange does not raise the two markers' continuity cost (``MODEL_UNJUDGED_BACK``,
  ``_unjudged_back``). Held-out figure 26494 (stop 75): marker 22's first 68 frames
  (2-marker segment 8) sat on marker 2 (2-marker segment 1, its parent), 45.6 x off marker
  2's partner and 0.96 x on marker 22's mate; marker 2's frames 42-61, inside them, sat on
  marker 22, where no mate sees them, and marker 2's partner finds them 0.94 x over 5
  frames, under ``MODEL_EVIDENCE``. The exchange lowers the cost from 2.54 to 1.26.
- An off piece that no marker fits moves to the one marker free over its frames (and
  paced) where no mate judges it, where the move does not raise the two markers'
  continuity cost (``MODEL_OFF_OPEN``, ``_open_move``). Held-out figure 26901 (stop 76):
  marker 51's last 20 frames (2-marker segment 15, hidden from frame 348 with its partner)
  sat at the end of marker 31 (its 4-marker parent segment's), whose mates find them 5.04,
  1.66 and 3.99 x; the move lowers the cost from 2.38 to 0.83.

Since stop 77 a piece that no mate of its marker judges moves to the one marker free over
its frames (and paced) where the distance ranges other tracks keep to that marker hold it
and those they keep to its own marker (without it) rule it out - step 7b's
``RANGE_JOINS`` test, ``_range_prefers`` - where the move does not raise the two markers'
continuity cost (``MODEL_RANGE_MOVES``, ``_range_move``). A marker across a joint from a
track keeps its distance to it between bounds the joint sets. Held-out figure 26623 (stop
76): marker 15's last 23 frames (2-marker segment 6, both markers hidden before them) sat
at the end of its partner 16; two markers of the child segment find them in marker 15's
ranges and 7.6 and 8.3 x their sd outside marker 16's; the move lowers the continuity cost
by 1.56.

Since stop 78 a rotation (``MODEL_ROTATIONS``) is judged without the three pieces it moves
on the mates' tracks (``ROTATION_MOVERS``): a mate holding another of the rotated pieces
over the frames judged misplaces the piece by that piece's error. Held-out figure 29639
(stop 77): the last pieces of markers 15, 47 and 49 (47 and 49 on one 2-marker segment)
sat on 47, 49 and 15; marker 15's piece is 19.4 and 20.7 x off marker 47's mates and fits
marker 15's (1.2 x), but marker 49's piece, coming back from marker 15, missed marker 49's
mates by 0.97 and 6.76 x - the second mate held marker 15's piece over those frames.
Without it the mates find it 0.97 and 0.98 x.

Since stop 80 a mate that misses a piece (beyond ``MODEL_FIT_Z``) is set aside where a mate
that fits it is, over the piece's frames, at a pose to it not seen over the marker's own
frames (``NOVEL_POSE_ASIDE``, ``judges._unseen_pose``: the two not rigid there, distance sd
above ``NOVEL_POSE_SD`` x s0, and the piece's mean distance out of their range by more than
that). A marker near a joint axis keeps its distance to markers across the joint over the
angles it was seen at, not over new ones. Held-out figure 33057 (stop 79): marker 1's
first 10 frames (2-marker root segment) were judged 0.98 and 5.66 x by two mates (median
3.32: off) and moved to marker 10 of a child segment; the 5.66 mate is across a hinge from
the fitting one, at 200.3-203.4 mm from it over the piece against 137.1-191.8 mm before.

Since stop 84 a mate beyond ``MODEL_FAR_Z`` does not veto an off piece's destination where
it finds the piece less far off than the nearest mate at home does (``OFF_FAR_CONTRAST``):
the piece is off where it is, and a mate that finds it less off elsewhere is no reason to
keep it there. Held-out figure 42256 (stop 83): marker 4's last 15 frames (3-marker segment
1) sat at the end of marker 30 (3-marker sibling segment 9), 11.2 x off its one judging
mate there. On marker 4, free over those frames, its two segment mates find them 1.06 and
0.70 x; three markers of the child segment 12, one body with marker 4 near their joint,
find them 7.8, 5.2 and 6.1 x off (each beyond every distance it kept to marker 4 before:
marker 39 at 92.8 mm against at most 86.8), and the one ``MODEL_NEAR_MATES`` keeps (6.07 x)
vetoed the fit, two mates within being fewer than ``MODEL_FAR_OUTVOTED``. The veto stands
where the far mate finds the piece at least as far off as home does.

Since stop 86:

- A piece that no mate of its marker judges, where the distance ranges do not move it
  (``MODEL_RANGE_MOVES``), moves to the one marker free over its frames (and paced) where
  its mates fit it, where no track keeps it inside its own marker's range and outside that
  marker's, and where the move raises the two markers' continuity cost by less than
  ``CONTINUITY_MARGIN`` (``UNJUDGED_FIT_MOVES``, ``_unjudged_fit_move``). Held-out figure
  45450 (stop 85): marker 18's last 13 frames (2-marker segment 6) sat at the end of
  marker 9 (its 2-marker parent segment's), whose partner is hidden from frame 386; on
  marker 18, free over them, partner 19 finds them 1.00 x over 13 frames; the cost rises
  by 0.17.
- An off piece's exchange also takes back a piece that does not fit where it is (judged
  without the other pieces coming back) and fits the off piece's marker without it, as
  ``MODEL_STRONGER_EXCHANGES`` does for a piece that is not off
  (``OFF_EXCHANGE_UNFIT_BACK``, ``_unfit_back``). Held-out figure 45688 (stop 85): the
  linkage exchanged the first pieces of markers 30 (2-marker hinge segment 10, frames
  0-11) and 32 (3-marker segment 11, frames 0-22); marker 32's is 15.7 x off marker 30's
  one mate and fits marker 32's (0.84 x); marker 30's is 2.26 x on marker 32's one mate,
  neither off nor fitting, and 1.04 x on marker 30's. The exchange lowers the continuity
  cost by 1.69.

Since stop 87 two overlapping pieces of two markers, each not off where it is but with one
of two or more judging mates finding it beyond ``MODEL_OFF_Z`` (``_contrasted``), are
exchanged where every mate of the other marker fits each (two or more, each within
``MODEL_FIT_Z``: ``_all_fit``) and the exchange does not raise the two markers' continuity
cost (``CONTRAST_EXCHANGES``, ``_contrast_exchange``): two markers of one segment at nearly
the same distances to their mates keep one telling mate. Held-out figure 46734 (stop 86):
step 8's ``PAIR_FRAMES`` exchanged the end pieces of markers 2 (frames 386-399) and 3
(375-399) of the 4-marker root segment; marker 3's piece is 1.17, 0.90 and 6.01 x on
marker 2's mates and 1.10 and 1.36 x on marker 3's, marker 2's 1.21, 0.90 and 5.28 x on
marker 3's and 1.03 and 1.30 x on marker 2's; the exchange lowers the cost by 6.21.

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

import warnings

import numpy as np
from scipy.ndimage import distance_transform_edt

from . import rules
from .continuity import _continuity_cost
from .judges import _unseen_pose
from .tracks import _paced, _range_prefers, _range_votes, _range_z, _spans, _tracks


def _robust(d: np.ndarray, min_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(median, 1.4826 x median absolute deviation) of each column of d (T, M), NaN where
    a column has fewer than ``min_frames`` finite values (by sorting: NaN sorts last;
    np.nanmedian is many times slower on these small arrays)."""
    def med(a):
        a = np.sort(a, axis=0)
        n = np.isfinite(a).sum(0)
        lo, hi = np.maximum((n - 1) // 2, 0), np.maximum(n // 2, 0)
        cols = np.arange(a.shape[1])
        return 0.5 * (a[lo, cols] + a[hi, cols]), n
    m, n = med(d)
    mad = 1.4826 * med(np.abs(d - m))[0]
    few = n < min_frames
    m[few] = np.nan
    mad[few] = np.nan
    return m, mad


class _Model:
    """The tracks of ``groups`` and what judges a piece on them (the module docstring)."""

    def __init__(self, X, vis, groups):
        self.X, self.vis, self.groups = X, vis, groups
        self.P = _tracks(X, groups)
        self._memo = {}
        self.cost = _continuity_cost(X, vis)
        n = len(groups)
        sd = np.full((n, n), np.nan)
        for i in range(n):
            d = np.linalg.norm(self.P - self.P[:, i:i + 1], axis=2)
            sd[i] = _robust(d, rules.MODEL_PAIR_FRAMES)[1]
            sd[i, i] = np.nan
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            self.s0 = float(np.nanmedian(np.nanmin(sd, 1)))

    def _judged(self, h, k, without) -> list[tuple[float, int]]:
        """``judge(h, k, without)``, kept for the model's life."""
        key = (h, k, tuple(sorted(without)))
        if key not in self._memo:
            self._memo[key] = self.judge(h, k, without)
        return self._memo[key]

    def judge(self, f, k, without=(), fit=False) -> list[tuple[float, int]]:
        """(z, frames) for each one-body mate of marker ``k`` seen with fragment ``f``:
        the mates and their distances measured on k's fragments other than ``f`` and
        ``without``, over frames where none of those is seen. With ``fit`` (a verdict
        whether f fits k, ``MODEL_NEAR_MATES``) without the mates that miss k's own frames
        nearest f: such a mate may find a piece off, but it does not veto a fit."""
        X, vis, P = self.X, self.vis, self.P
        frf = vis[:, f]
        Pk = _tracks(X, [[h for h in self.groups[k] if h != f and h not in without]])[:, 0]
        own = ~np.isnan(Pk[:, 0]) & ~frf
        if not own.any():
            return []
        seen = (~np.isnan(P[frf, :, 0])).sum(0) >= rules.MODEL_MIN_FRAMES
        others = [j for j in np.flatnonzero(seen) if j != k]
        if not others:
            return []
        d_rest = np.linalg.norm(P[own][:, others] - Pk[own][:, None], axis=2)
        c, s = _robust(d_rest, rules.MODEL_PAIR_FRAMES)
        body = np.isfinite(s) & (s <= rules.MODEL_BODY_SD * self.s0)
        near_check = fit and rules.MODEL_NEAR_MATES
        if near_check:
            home = own.copy()
            for h in self.groups[k]:
                if h != f and h not in without and _off(self._judged(h, k, tuple(without))):
                    home &= ~vis[:, h]
            # each own frame's distance in frames from the piece's nearest frame
            gap = distance_transform_edt(~frf)
        out = []
        for col in np.flatnonzero(body):
            j = others[col]
            if f in self.groups[j]:
                continue
            # the mate's track over f's frames, without fragments that are leaving it
            t = frf & ~np.isnan(P[:, j, 0])
            for h in without:
                if h in self.groups[j]:
                    t &= ~vis[:, h]
            n = int(t.sum())
            if n < rules.MODEL_MIN_FRAMES:
                continue
            unit = max(s[col], self.s0)
            miss = np.linalg.norm(X[t, f] - P[t, j], axis=1) - c[col]
            z = float(np.sqrt(np.mean(miss ** 2)) / unit)
            if near_check:
                # the mate on the marker's own n frames nearest the piece, in k's other
                # fragments not off k (another marker's piece there is no measure): a
                # mate whose distance drifts there cannot judge a piece beside them
                both = np.flatnonzero(home & ~np.isnan(P[:, j, 0]))
                near = both[np.argsort(gap[both], kind="stable")[:n]]
                d_near = np.linalg.norm(P[near, j] - Pk[near], axis=1) - c[col]
                if len(near) and np.sqrt(np.mean(d_near ** 2)) / unit > rules.MODEL_FIT_Z:
                    continue
            out.append((z, n, j, t))
        if rules.NOVEL_POSE_ASIDE:
            # a mate that finds f off at a pose to a mate that fits it never seen over the
            # marker's own frames is across a joint from that mate (figure 33057)
            margin = rules.NOVEL_POSE_SD * self.s0
            fit_ = [(j, t) for z, _, j, t in out if z <= rules.MODEL_FIT_Z]
            out = [o for o in out if o[0] <= rules.MODEL_FIT_Z or not any(
                _unseen_pose(np.linalg.norm(P[:, o[2]] - P[:, h], axis=1), own, t & o[3],
                             margin, rules.MODEL_PAIR_FRAMES) for h, t in fit_)]
        return [(z, n) for z, n, _, _ in out]


def _off(js) -> bool:
    """Off its marker: the median z of the judging mates beyond ``MODEL_OFF_Z``."""
    return bool(js) and _median_z(js) > rules.MODEL_OFF_Z


def _fits(js, half=False, far_below=None) -> bool:
    """Fits a marker: the median z within ``MODEL_FIT_Z``, none beyond ``MODEL_FAR_Z``, and
    ``MODEL_EVIDENCE`` frames seen with the mates in all (a mate beyond is outvoted where
    ``MODEL_FAR_OUTVOTED`` mates find it within ``MODEL_FIT_Z``, or, with ``far_below``, where
    it finds it below that z: an off piece's z at home, ``OFF_FAR_CONTRAST``). With ``half``
    (an off piece's destination, ``MODEL_HALF_FITS``): half the mates within,
    ``MODEL_STRONG_MATES`` at least, in place of the median."""
    if not js or sum(n for _, n in js) < rules.MODEL_EVIDENCE:
        return False
    zs = [z for z, _ in js]
    within = sum(z <= rules.MODEL_FIT_Z for z in zs)
    if (max(zs) > rules.MODEL_FAR_Z and within < rules.MODEL_FAR_OUTVOTED
            and (far_below is None or max(zs) >= far_below)):
        return False
    if half and rules.MODEL_HALF_FITS:
        return 2 * within >= len(zs) and within >= min(len(zs), rules.MODEL_STRONG_MATES)
    return float(np.median(zs)) <= rules.MODEL_FIT_Z


def _against_model(model, f, home, new) -> bool:
    """Moving fragment ``f`` from marker ``home`` to marker ``new`` goes against the rigid
    model: the mates at home fit it, or the new marker's find it off (the moves of steps
    12b and 12c: ``MOVES_KEEP_MODEL``, ``NEIGHBOUR_CONTINUITY``). A fit at home that the
    new marker's mates share tells the two apart no more than the move's own evidence
    does (``VETO_NEEDS_CONTRAST``)."""
    js_new = model.judge(f, new)
    if _off(js_new):
        return True
    if not _fits(model.judge(f, home)):
        return False
    return not (rules.VETO_NEEDS_CONTRAST and _fits(js_new))


def _median_z(js) -> float:
    """The median z of the judging mates (0 where none judges)."""
    return float(np.median([z for z, _ in js])) if js else 0.0


def _takes(js) -> bool:
    """A marker takes back an exchanged piece: it fits, or no mate judges it there."""
    return not js or _fits(js)


def _clash(vis, groups, k, f, without=()) -> list:
    """The fragments of marker ``k`` (other than ``without``) seen in a frame of ``f``."""
    return [h for h in groups[k] if h not in without and (vis[:, h] & vis[:, f]).any()]


def _model_check(X, groups, max_step, fixed=()) -> list:
    """Step 12 (the module docstring) on the fragment ``groups``; returns new groups. The
    fragments ``fixed`` stay on their markers (step 12b's exchanges, ``SPHERE_CHECK``)."""
    vis = ~np.isnan(X[..., 0])
    groups = [list(g) for g in groups]
    span = _spans(vis, groups)
    for _ in range(rules.MODEL_ROUNDS):
        model = _Model(X, vis, groups)
        changes = []
        for a, g in enumerate(groups):
            if len(g) < 2:
                continue
            for f in g:
                if f in fixed:
                    continue
                home = model.judge(f, a)
                off = _off(home)
                # one mate judges it and it is not off: fitting (an off piece cannot fit
                # its one mate), or, with MODEL_UNSURE, either way
                weak = rules.MODEL_STRONGER and len(home) == 1 and not off and (
                    rules.MODEL_UNSURE or _fits(model.judge(f, a, fit=True)))
                # neither off nor fitting, one mate finding it beyond MODEL_FAR_Z: it
                # moves where several mates fit it clearly (``MODEL_UNFIT_MOVES``, 25141)
                unfit = (rules.MODEL_UNFIT_MOVES and not off and not weak and len(home) >= 2
                         and max(z for z, _ in home) > rules.MODEL_FAR_Z
                         and _median_z(model.judge(f, a, fit=True)) > rules.MODEL_FIT_Z)
                if not (off or weak or unfit):
                    if rules.CONTRAST_EXCHANGES and _contrasted(home):
                        change = _contrast_exchange(model, vis, span, groups, f, a, max_step,
                                                    fixed)
                        if change is not None:
                            changes.append((0.0, change))
                    if rules.MODEL_RANGE_MOVES and not home:
                        change = _range_move(model, vis, span, groups, f, a, max_step)
                        if change is None and rules.UNJUDGED_FIT_MOVES:
                            change = _unjudged_fit_move(model, vis, span, groups, f, a,
                                                        max_step)
                        if change is not None:
                            changes.append((0.0, change))
                    continue
                change = _destination(model, vis, span, groups, f, a, off, max_step, fixed,
                                      home_z=home[0][0] if weak else 0.0 if unfit else None,
                                      off_z=min(z for z, _ in home) if off else None)
                if change is None and off and rules.MODEL_OFF_OPEN:
                    change = _open_move(model, vis, span, groups, f, a, max_step)
                if change is not None:
                    score = min(z for z, _ in home) if off else 0.0
                    changes.append((score, change))
        if not changes:
            break
        changes.sort(key=lambda c: -c[0])
        groups = changes[0][1]
    return groups


def _pooled(js) -> float:
    """The rms z, over their frames, of the mates that find a piece within ``MODEL_FIT_Z``."""
    fit = [(z, n) for z, n in js if z <= rules.MODEL_FIT_Z]
    return float(np.sqrt(sum(n * z * z for z, n in fit) / sum(n for _, n in fit)))


def _destination(model, vis, span, groups, f, a, off, max_step, fixed=(), home_z=None,
                 off_z=None):
    """The new groups after fragment ``f`` of marker ``a`` moves (or is exchanged) to the one
    marker that takes it, or None. ``home_z``: the z of the one mate that judges a piece
    that is not off (``MODEL_STRONGER``); ``off_z``: the least z of the mates that find a
    piece off at home (``OFF_FAR_CONTRAST``)."""
    X = model.X
    found = []
    for b in range(len(groups)):
        if b == a:
            continue
        clash = _clash(vis, groups, b, f)
        if set(clash) & set(fixed):
            continue
        js = model.judge(f, b, without=clash, fit=True)
        if off:
            if not _fits(js, half=True, far_below=off_z if rules.OFF_FAR_CONTRAST else None):
                continue
        elif len(js) < rules.MODEL_STRONG_MATES or not _fits(js):
            continue
        elif rules.MODEL_STRONGER_CLEAR and _pooled(js) > max(home_z, rules.MODEL_CLEAR_Z):
            # mates that find it less clearly than its one mate at home do not outvote it
            continue
        elif clash and not (rules.MODEL_STRONGER_EXCHANGES and all(
                _unfit_back(model, f, a, b, h, clash) for h in clash)):
            # a piece fitting one mate: an exchange only where each piece coming back
            # does not fit b (without the others) and fits a
            continue
        new_a = [h for h in groups[a] if h != f] + clash
        new_b = [h for h in groups[b] if h not in clash] + [f]
        if clash:
            # an exchange: each piece coming back is off b and fits a without f
            if off and not all(_off(model.judge(h, b))
                               and _takes(model.judge(h, a, without=(f,), fit=True))
                               or _unjudged_back(model, groups, f, a, b, h, new_a, new_b)
                               or (rules.OFF_EXCHANGE_UNFIT_BACK
                                   and _unfit_back(model, f, a, b, h, clash))
                               for h in clash):
                if rules.MODEL_ROTATIONS and len(clash) == 1:
                    found += _rotations(model, vis, span, groups, f, a, b, clash[0],
                                        max_step, fixed)
                continue
            if any((vis[:, h1] & vis[:, h2]).any() for h1 in new_a for h2 in new_a
                   if h1 < h2):
                continue
        if not (_paced(X, span, new_a, max_step) and _paced(X, span, new_b, max_step)):
            continue
        if not off and rules.MODEL_CONTINUITY and (
                _rise(model, groups, a, b, new_a, new_b) >= rules.CONTINUITY_MARGIN):
            # a piece its mates do not find off does not move where it breaks the motion
            # of both markers by the margin (``MODEL_CONTINUITY``, 26461)
            continue
        found.append({a: new_a, b: new_b})
    if len(found) != 1:
        return None
    out = [list(g) for g in groups]
    for m, g in found[0].items():
        out[m] = g
    return [g for g in out if g]


def _open_move(model, vis, span, groups, f, a, max_step):
    """``MODEL_OFF_OPEN``: the new groups after a piece ``f`` off its marker ``a`` that no
    marker fits moves to the one marker free over its frames (and paced) where no mate
    judges it, where that does not raise the two markers' continuity cost; or None.
    Held-out figure 26901 (stop 76): marker 51's last 20 frames (2-marker segment 15)
    sat at the end of marker 31 (4-marker parent segment 8), whose segment mates find them
    5.04, 1.66 and 3.99 x (off: the median beyond ``MODEL_OFF_Z``); marker 51, hidden from
    frame 348 with its partner, is the one free marker, and nothing judges the piece there;
    the move lowers the continuity cost from 2.38 to 0.83. With ``OPEN_MOVE_NO_RISE``,
    the one such marker where the continuity cost does not rise: held-out 41134 (stop 83),
    marker 34's last 14 frames (2-marker leaf segment 11) sat at the end of marker 11
    (2-marker parent segment 3), whose mate finds them 46.3 x off; marker 34 and its
    partner 33 are both free there and unjudged, and the move raises the cost by 0.46 on
    marker 33 and lowers it by 1.39 on marker 34."""
    found = [m for m in _free_moves(model, vis, span, groups, f, a, max_step)
             if not model.judge(f, m[0])]
    if rules.OPEN_MOVE_NO_RISE and len(found) > 1:
        found = [m for m in found if _rise(model, groups, a, *m) <= 0]
    return _one_free_move(model, groups, a, found)


def _range_move(model, vis, span, groups, f, a, max_step):
    """``MODEL_RANGE_MOVES``: the new groups after a piece ``f`` that no mate of its marker
    ``a`` judges moves to the one marker free over its frames (and paced) whose distance
    ranges to other tracks the piece keeps where a's (without f) rule it out (step 7b's
    ``_range_z`` and ``_range_prefers``), and where the move does not raise the two
    markers' continuity cost; or None. Held-out figure 26623 (stop 76): marker 15's last
    23 frames (2-marker segment 6, both markers hidden before them) sat at the end of its
    partner 16; no mate judges them on either marker, and the continuity cost (4.30 where
    they are, 2.74 on marker 15) is within the margin. Two tracks of the child segment find
    them within ``RANGE_FIT_Z`` of marker 15's ranges and beyond ``RANGE_OFF_Z`` outside
    marker 16's (truth: 0 against 7.6 and 8.3 x the sd), none the reverse."""
    P, i = _with_piece(model, vis, f, a)
    z_home = _range_z(P, i, a, (a, i))
    return _one_free_move(model, groups, a, [
        m for m in _free_moves(model, vis, span, groups, f, a, max_step)
        if _range_prefers(_range_z(P, i, m[0], (a, m[0], i)), z_home)])


def _unjudged_fit_move(model, vis, span, groups, f, a, max_step):
    """``UNJUDGED_FIT_MOVES``: the new groups after a piece ``f`` that no mate of its marker
    ``a`` judges moves to the one marker free over its frames (and paced) where its mates
    fit it (``_fits``), where no track keeps the piece inside a's distance range and
    outside that marker's (``_range_votes``) and the move raises the two markers'
    continuity cost by less than ``CONTINUITY_MARGIN`` (as ``MODEL_CONTINUITY`` lets a
    piece that is not off move); or None. Held-out figure 45450 (stop 85): marker 18's
    last 13 frames (387-399; 2-marker segment 6) sat at the end of marker 9 (2-marker
    parent segment 3), whose partner is hidden from frame 386; on marker 18, free over
    those frames, its partner 19 finds them 1.00 x over 13 frames, no range votes either
    way, and the move raises the continuity cost by 0.17."""
    found = [m for m in _free_moves(model, vis, span, groups, f, a, max_step)
             if _fits(model.judge(f, m[0], fit=True))]
    if len(found) != 1:
        return None
    b, new_a, new_b = found[0]
    P, i = _with_piece(model, vis, f, a)
    z_home = _range_z(P, i, a, (a, i))
    if _range_votes(_range_z(P, i, b, (a, b, i)), z_home)[1]:
        return None
    if _rise(model, groups, a, b, new_a, new_b) >= rules.CONTINUITY_MARGIN:
        return None
    return _moved(groups, a, b, new_a, new_b)


def _unfit_back(model, f, a, b, h, clash) -> bool:
    """``MODEL_STRONGER_EXCHANGES`` and ``OFF_EXCHANGE_UNFIT_BACK``: piece ``h`` of marker
    ``b``, over the frames of the (off, for the second) piece ``f`` of marker ``a``, goes
    back to ``a`` in an exchange where it does not fit ``b`` (without the other pieces
    coming back) and fits ``a`` without f. For an off piece, held-out figure 45688 (stop
    85): the first pieces of markers 30 (frames 0-11; 2-marker hinge segment 10) and 32
    (frames 0-22; 3-marker segment 11) were exchanged from the linkage on; marker 32's
    piece is 15.66 x off marker 30's one mate and fits marker 32's (0.84 x), and marker
    30's piece is 2.26 x on marker 32's one mate (not off) and 1.04 x on marker 30's."""
    return (not _fits(model.judge(h, b, without=[x for x in clash if x != h], fit=True))
            and _fits(model.judge(h, a, without=(f,), fit=True)))


def _contrasted(js) -> bool:
    """Two mates or more judge a piece and one finds it beyond ``MODEL_OFF_Z``
    (``CONTRAST_EXCHANGES``; a piece that is not off, so the median fits or nearly)."""
    return len(js) >= rules.MODEL_STRONG_MATES and max(z for z, _ in js) > rules.MODEL_OFF_Z


def _all_fit(js) -> bool:
    """``MODEL_STRONG_MATES`` mates or more judge a piece, each within ``MODEL_FIT_Z``, over
    ``MODEL_EVIDENCE`` frames in all."""
    return (len(js) >= rules.MODEL_STRONG_MATES and _fits(js)
            and all(z <= rules.MODEL_FIT_Z for z, _ in js))


def _contrast_exchange(model, vis, span, groups, f, a, max_step, fixed=()):
    """``CONTRAST_EXCHANGES``: the new groups after piece ``f`` of marker ``a`` (not off,
    one mate finding it beyond ``MODEL_OFF_Z``: ``_contrasted``) is exchanged with the one
    piece ``h`` of the one marker ``b`` over its frames, where h is so judged on b too,
    every mate of b (without h) fits f and every mate of a (without f) fits h (``_all_fit``),
    and the exchange does not raise the two markers' continuity cost; or None. Two markers
    of one segment at nearly the same distances to their mates keep one telling mate.
    Held-out figure 46734 (stop 86): step 8's ``PAIR_FRAMES`` exchanged the end pieces of
    markers 2 (frames 386-399) and 3 (375-399) of the 4-marker root segment; marker 3's
    piece is 1.17, 0.90 and 6.01 x on marker 2's mates and 1.10 and 1.36 x on marker 3's,
    marker 2's 1.21, 0.90 and 5.28 x on marker 3's and 1.03 and 1.30 x on marker 2's; the
    exchange lowers the continuity cost by 6.21."""
    found = []
    for b in range(len(groups)):
        if b == a:
            continue
        clash = _clash(vis, groups, b, f)
        if len(clash) != 1 or clash[0] in fixed:
            continue
        h = clash[0]
        if _clash(vis, groups, a, h, without=(f,)):
            continue
        js_h = model._judged(h, b, ())   # h's own verdict at home, as the round judged it
        if _off(js_h) or not _contrasted(js_h):
            continue
        if not (_all_fit(model.judge(f, b, without=(h,), fit=True))
                and _all_fit(model.judge(h, a, without=(f,), fit=True))):
            continue
        new_a = [x for x in groups[a] if x != f] + [h]
        new_b = [x for x in groups[b] if x != h] + [f]
        if not (_paced(model.X, span, new_a, max_step) and _paced(model.X, span, new_b, max_step)):
            continue
        if _rise(model, groups, a, b, new_a, new_b) > 0:
            continue
        found.append((b, new_a, new_b))
    if len(found) != 1:
        return None
    return _moved(groups, a, *found[0])


def _with_piece(model, vis, f, a):
    """The model's tracks with marker ``a`` blank over fragment ``f``'s frames and ``f``
    as a track of its own, and that track's index (the distance ranges' input)."""
    P = model.P.copy()
    P[vis[:, f], a] = np.nan
    y = np.full((len(P), 1, 3), np.nan)
    y[vis[:, f], 0] = model.X[vis[:, f], f]
    P = np.concatenate([P, y], 1)
    return P, P.shape[1] - 1


def _free_moves(model, vis, span, groups, f, a, max_step):
    """(b, a's new fragments, b's) for each marker ``b`` free over the frames of ``a``'s
    fragment ``f`` where a without f and b with it are paced (``_paced``)."""
    for b in range(len(groups)):
        if b == a or _clash(vis, groups, b, f):
            continue
        new_a = [h for h in groups[a] if h != f]
        new_b = groups[b] + [f]
        if _paced(model.X, span, new_a, max_step) and _paced(model.X, span, new_b, max_step):
            yield b, new_a, new_b


def _one_free_move(model, groups, a, found):
    """The new groups after the one move of ``found`` (``_free_moves``' items), where it is
    one and does not raise the two markers' continuity cost; or None."""
    if len(found) != 1:
        return None
    b, new_a, new_b = found[0]
    if _rise(model, groups, a, b, new_a, new_b) > 0:
        return None
    return _moved(groups, a, b, new_a, new_b)


def _moved(groups, a, b, new_a, new_b) -> list:
    """``groups`` with markers ``a`` and ``b`` holding fragments ``new_a`` and ``new_b``
    (an id left empty dropped)."""
    out = [list(g) for g in groups]
    out[a], out[b] = new_a, new_b
    return [g for g in out if g]


def _rise(model, groups, a, b, new_a, new_b) -> float:
    """How much markers ``a`` and ``b`` taking fragments ``new_a`` and ``new_b`` raise
    their continuity cost (step 7b's, ``_continuity_cost``); below 0 where it falls."""
    return ((model.cost(new_a) + model.cost(new_b))
            - (model.cost(groups[a]) + model.cost(groups[b])))


def _unjudged_back(model, groups, f, a, b, h, new_a, new_b) -> bool:
    """``MODEL_UNJUDGED_BACK``: piece ``h`` of marker ``b``, over the frames of the off
    piece ``f`` of marker ``a``, goes back to ``a`` in an exchange where no mate of ``b``
    judges it there, no mate of ``a`` (without f) finds it beyond ``MODEL_FIT_Z``, and the
    exchange (to ``new_a`` and ``new_b``) does not raise the two markers' continuity cost.
    Held-out figure 26494 (stop
    76): marker 22's first 68 frames sat on marker 2 (its parent segment's), 45.6 x off
    marker 2's segment mate there and 0.96 x on marker 22's; marker 2's 20 frames inside
    them sat on marker 22, where no mate sees them, and marker 2's mate finds them 0.94 x
    over 5 frames (under ``MODEL_EVIDENCE``); the exchange lowers the continuity cost from
    2.54 to 1.26."""
    if not rules.MODEL_UNJUDGED_BACK or model.judge(h, b):
        return False
    if any(z > rules.MODEL_FIT_Z for z, _ in model.judge(h, a, without=(f,), fit=True)):
        return False
    return _rise(model, groups, a, b, new_a, new_b) <= 0


def _rotations(model, vis, span, groups, f, a, b, h, max_step, fixed=()) -> list:
    """Three pieces moved round three markers (``MODEL_ROTATIONS``): ``f``, off its marker
    ``a``, fits ``b``, whose piece ``h`` over f's frames is off ``b`` but not taken by
    ``a``; h goes to the marker ``c`` it fits without c's one piece ``r`` over h's frames,
    and r, not fitting c, to ``a``, which takes it without f. Each such rotation, overlap-free
    and paced, as {marker: its new fragments}. Held-out figure 17802 (first run at stop 66):
    the first pieces of markers 6, 22 and 42 sat on 22, 42 and 6; marker 42's piece lies
    145.6 x off marker 6's one mate and fits marker 42's two (0.8, 0.9), marker 42's other
    id holds marker 22's piece (27.1 and 8.4 x off), which fits marker 22's mate (1.0), and
    marker 6's piece on marker 22 misses its mate by 2.7 and fits marker 6's (1.0); no
    exchange of two moves every piece where it fits."""
    if h in fixed or not _off(model.judge(h, b)):
        return []
    out = []
    for c in range(len(groups)):
        if c in (a, b):
            continue
        clash = _clash(vis, groups, c, h)
        if len(clash) != 1 or clash[0] in fixed:
            continue
        r = clash[0]
        # the mates' tracks without the pieces the rotation moves (``ROTATION_MOVERS``)
        movers = rules.ROTATION_MOVERS
        if (not _fits(model.judge(h, c, without=[r, f] if movers else clash, fit=True))
                or _fits(model.judge(r, c, without=(f, h) if movers else (), fit=True))
                or not _takes(model.judge(r, a, without=(f, h) if movers else (f,), fit=True))):
            continue
        new = {a: [x for x in groups[a] if x != f] + [r],
               b: [x for x in groups[b] if x != h] + [f],
               c: [x for x in groups[c] if x != r] + [h]}
        if any((vis[:, x] & vis[:, y]).any() for g in new.values() for x in g for y in g
               if x < y):
            continue
        if all(_paced(model.X, span, g, max_step) for g in new.values()):
            out.append(new)
    return out

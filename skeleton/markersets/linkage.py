"""Steps 1-3 of the marker-set merge: drop, pose-aligned distances, constrained linkage.

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

The partner floor and the gap order, measured with bench_skeleton_outputs.py's figures
(1 mm noise, 1-3 gaps of 3-40 frames per marker, 5 ghosts, 400 frames): figures 0-39 (on
which the weights were chosen) 32/40 merged exactly without either, 33/40 with the floor,
34/40 with both; figures 40-79 (held out) 29/40, 32/40, 33/40 (physical figures, markers
>= 20 mm apart: 17/22, 17/22, 19/22). Gap weights 0.05 and 0.15 mm per frame did worse on
figures 0-39 (33/40 and 32/40).

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
miss by more than 10 mm or across more than 45 frames) and 119 (two markers of a segment
exchanged, not repaired). The
rescue alone also left one marker as two ids in figures 23, 41 and 51 (changed alignments
put the pieces above ``max_distance_m``); the loose pass of step 5 joins them, and alone
(``continuity_m=0``) changes no figure (109 of 120). Merge time x1.07 of steps 1-3 alone
in the same run (218 s for 120 figures; HEAD 196 s in a separate run).

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

import warnings

import numpy as np

from . import rules
from .continuity import _junctions, _run_ends
from .tracks import _gap, _kabsch_batch, _samples, _too_fast
from .types import MarkerSets


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
        order_sd_weight = rules.ORDER_SD_WEIGHT
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
    by_continuity = loose and rules.LOOSE_BY_CONTINUITY
    scaled_miss = np.full(dist.size, np.nan)    # NaN: motion continuity does not judge
    if continuity_m > 0:
        # motion continuity: a pair whose ends meet within continuity_m across every change
        # of column (gaps of at most continuity_max_gap frames) is a candidate at that miss
        runs = [_run_ends(frames[i], Xk[frames[i], i], continuity_frames) for i in range(K)]
        for e in np.flatnonzero(~overlap[iu, ju]):
            jn = _junctions(runs[iu[e]], runs[ju[e]])
            if by_continuity and jn and all(g <= continuity_max_gap for g, m in jn):
                sm = [m / max(1.0, (g / rules.ACCEL_GAP_FRAMES) ** 2) for g, m in jn
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

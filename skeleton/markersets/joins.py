"""Steps 5, 6, 7b, 9 and 10 of the marker-set merge: ids of one marker joined.

Steps 5 and 9 run the linkage (``linkage._merge_pass``) again from the package's
``_repairs``; steps 6, 7b and 10 are here.

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
7b. join by continuity (``_join_by_continuity``, ``CONTINUITY_JOINS``): while there are
   still more markers than the bound, two markers that never share a frame are joined
   when the join costs at most ``CONTINUITY_MARGIN`` (4) in step 8's continuity cost (the
   changes of fragment it makes) and every other join of either costs at least 4 more,
   the cheapest first. An end piece of a 2-marker segment's marker whose partner is
   hidden across the gap has no pose to align on and no partner to join by (figure 339:
   marker 39's last 62 frames, 37 frames after the rest, its partner seen in 8 of them:
   1.93, the next join 7.96; 1371: marker 33's last 10 frames, 1.12 against 7.80).
   A marker left as three or more ids has no such join: its ids' rivals are each other.
   Where no join is clear, the ids linked by joins within the margin are joined all at
   once when every two of them could join, each one's joins outside cost the margin more
   than its cheapest inside, the whole join costs at most the margin per join and it
   leaves no fewer markers than the bound (``CHAIN_JOINS``, stop 72, ``_chain``; held-out
   figure 22748: marker 16 of a 2-marker segment left as ids over frames 0-320, 346-356
   and 373-399, joins 1.50, 2.45 and 3.12 among them, the next 14.14).
   Two markers each left as two ids, hidden over nearly the same frames, give four ids
   whose joins are each other's rivals. Where no chain is joined either, the ids linked by
   joins within the margin (an even number, at most 8) are joined two by two where one
   pairing of them all is cheaper by the margin than every other, each of its joins costs
   at most the margin and each id's joins outside cost the margin more than its join in
   it (``PAIR_JOINS``, stop 76, ``_pairing``; held-out figure 26100: markers 33 and 34 of a
   2-marker hinge segment, joins 1.70 and 1.02, crossed 2.55 and 7.65: pairings 2.72
   against 10.20).
   An end piece of a 2-marker segment's marker, both markers hidden before it, can join
   the marker and its partner within the margin of each other. Where nothing above is
   joined, an id whose cheapest join has rivals within the margin on its side only is
   joined where the distance ranges other tracks keep to each candidate rule every rival
   out: at least ``RANGE_VOTES`` (1; 2 until stop 78) tracks, and ``RANGE_RATIO`` (2) times
   those finding the reverse, find the id within ``RANGE_FIT_Z`` (1.5) x the distance's sd of the join's range and
   ``RANGE_OFF_Z`` (5) x outside the rival's (``RANGE_JOINS``, stop 77, ``_range_join``).
   A marker across a joint from a track keeps its distance to it between bounds the joint
   sets. Held-out figures 26928 (marker 35's last 15 frames: joins 2.11 and 4.62 to its
   partner; 4 tracks against none) and 26929 (marker 9's last 15: 2.60, 5.36 and 5.99;
   15 tracks against 1 for the partner, 18 against none for marker 7). Since stop 78 one
   track against none joins: held-out figure 29501 (marker 13's last 10 frames: joins 1.97
   and 3.65 to its partner 12; 0.98 x in 13's range and 6.72 x outside 12's on the one
   track, none the reverse).
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
   off marker 26's body. A judge that drifts across a joint (rigid to the marker's
   fragments, but not one body with them) allows for its drift there
   (``DRIFT_JUDGES``, ``judges._drift_allowance``; held-out figure 12460, stop 61: two
   short pieces of markers 49 and 10 left as one id, the split join costing 1.40 against
   the next at 6.19, but on marker 10 a track of the next segment at distance sd 2.88 x
   s0 over 370 frames found marker 10's last 12 frames 13.8 x the bound off; with the
   allowance 0.16, while marker 10's segment partner fits it at 0.08).


Step 6 (stop 17, designed on figure 166): figures 0-279 274 -> 275 of 280 (fixed 166),
held out 280-399 114 -> 115 of 120 (fixed 292, a split marker too), none lost; still
failing 28, 93, 157, 186, 221; 339, 341, 371, 372, 379. Merge time x1.35 of steps 1-3
alone over figures 0-399 (``bench_markersets.py 0 200`` and ``200 400``, both x1.35).

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

import warnings

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from . import rules
from .continuity import _continuity_cost
from .judges import _misfit, _off_body
from .tracks import _fragment_sd, _paced, _pair_sd, _range_prefers, _range_z, _spans, _tracks


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
            if not C[a, b] <= rules.CONTINUITY_MARGIN:
                continue
            rest = np.r_[np.delete(C[a], b), np.delete(C[b], a)]
            if (rest >= C[a, b] + rules.CONTINUITY_MARGIN).all() and (best is None
                                                                 or C[a, b] < best[0]):
                best = (C[a, b], min(a, b), max(a, b))
        if best is None and rules.CHAIN_JOINS:
            chain = _chain(C, cost, groups, own, M - n_min)
            if chain is not None:
                first = min(chain)
                groups[first] = [h for i in sorted(chain) for h in groups[i]]
                groups = [g for i, g in enumerate(groups) if i == first or i not in chain]
                continue
        if best is None and rules.PAIR_JOINS:
            pairs = _pairing(C, M - n_min)
            if pairs is not None:
                for a, b in pairs:
                    groups[a] = groups[a] + groups[b]
                gone = {b for _, b in pairs}
                groups = [g for i, g in enumerate(groups) if i not in gone]
                continue
        if best is None and rules.RANGE_JOINS:
            pair = _range_join(_tracks(X, groups), C)
            if pair is not None:
                best = (None,) + pair
        if best is None:
            return groups
        _, a, b = best
        groups[a] = groups[a] + groups[b]
        del groups[b]
    return groups


def _range_join(P, C):
    """Step 7b's ``RANGE_JOINS``: an id ``a`` whose cheapest join ``b`` costs at most
    ``CONTINUITY_MARGIN`` but has rivals within the margin of it (only among a's joins:
    no other id joins b nearly as cheaply) is joined to b where, for each rival c, the
    tracks that find a within ``RANGE_FIT_Z`` of b's distance range to them and at least
    ``RANGE_OFF_Z`` outside c's (``_range_z``) outnumber the reverse (``_range_prefers``). The
    cheapest such join, as (a, b) with a < b, or None. Held-out figure 26928 (stop 76):
    marker 35's last 15 frames (2-marker segment, both markers hidden before them) were
    an id of their own; the join to marker 35 costs 2.11, to its partner 34 4.62, but the
    parent segment's marker 14 is 368-376 mm from them, inside 35's range (345-414 mm) and
    186 mm outside 34's (131-184 mm, sd 16.7)."""
    margin = rules.CONTINUITY_MARGIN
    best = None
    for a in range(len(C)):
        b = int(np.argmin(C[a]))
        if not C[a, b] <= margin or (best is not None and C[a, b] >= best[0]):
            continue
        if (np.delete(C[b], a) < C[a, b] + margin).any():
            continue
        rivals = [c for c in np.flatnonzero(C[a] < C[a, b] + margin) if c != b]
        if not rivals:
            continue
        zb = _range_z(P, a, b, (a, b))
        if all(_range_prefers(zb, _range_z(P, a, c, (a, b, c))) for c in rivals):
            best = (C[a, b], min(a, b), max(a, b))
    return None if best is None else best[1:]


def _matchings(K, C):
    """Every way to pair all of the ids ``K`` two by two with joins of finite cost in
    ``C``: lists of (a, b) with a < b."""
    if not K:
        yield []
        return
    a, rest = K[0], K[1:]
    for i, b in enumerate(rest):
        if np.isfinite(C[a, b]):
            for m in _matchings(rest[:i] + rest[i + 1:], C):
                yield [(min(a, b), max(a, b))] + m


def _pairing(C, spare, most=8):
    """Step 7b's ``PAIR_JOINS``: two markers each left as two ids, hidden over nearly the
    same frames, give four ids whose joins are each other's rivals: each right join has a
    crossed one within the margin, so no join is clear. The ids linked by joins of at most
    ``CONTINUITY_MARGIN`` (``C``, the join costs; an even number of them, at most ``most``
    and no more than twice ``spare``, the markers above the bound) are joined two by two
    where one pairing of them all is cheapest by the margin over every other, each of its
    joins costs at most the margin, and every join of an id with an id outside costs at
    least the margin more than its join in the pairing. Returns the pairs (a, b), a < b,
    or None. Held-out figure 26100 (stop 76): markers 33 and 34 of a 2-marker hinge
    segment, each left as two ids, joins 1.70 and 1.02, the crossed ones 2.55 and 7.65:
    pairings 2.72 against 10.20."""
    margin = rules.CONTINUITY_MARGIN
    n, label = connected_components(csr_matrix(C <= margin), directed=False)
    best = None
    for c in range(n):
        K = [int(i) for i in np.flatnonzero(label == c)]
        if len(K) < 4 or len(K) % 2 or len(K) > most or len(K) // 2 > spare:
            continue
        totals = sorted((sum(C[a, b] for a, b in m), m) for m in _matchings(K, C))
        if not totals:
            continue
        total, pairs = totals[0]
        if len(totals) > 1 and not totals[1][0] >= total + margin:
            continue
        if not all(C[a, b] <= margin for a, b in pairs):
            continue
        out = np.delete(C[K], K, axis=1)
        near = {a: C[a, b] for p in pairs for a, b in (p, p[::-1])}
        if not all((out[i] >= near[a] + margin).all() for i, a in enumerate(K)):
            continue
        if best is None or total < best[0]:
            best = (total, pairs)
    return None if best is None else best[1]


def _chain(C, cost, groups, own, spare):
    """Step 7b's ``CHAIN_JOINS``: a marker left as three or more ids has no join that
    every other join of its ids exceeds by the margin - its ids' other joins are each
    other. The ids linked by joins of at most ``CONTINUITY_MARGIN`` (``C``, the join costs)
    are one marker where every two of them can join (share no frame, paced: finite ``C``),
    every join of one of them with an id outside costs at least the margin more than its
    cheapest join inside, joining all of them costs at most the margin per join, and no more
    than ``spare`` ids (markers above the bound) go. Returns the indices of the ids of the
    cheapest such chain, or None. Figure 22748 (held out, stop 71): marker 16 of a
    2-marker segment left as ids over frames 0-320, 346-356 and 373-399, joins 1.50, 2.45
    and 3.12 among them, the next 14.14."""
    margin = rules.CONTINUITY_MARGIN
    n, label = connected_components(csr_matrix(C <= margin), directed=False)
    best = None
    for c in range(n):
        K = np.flatnonzero(label == c)
        if len(K) < 3 or len(K) - 1 > spare:
            continue
        sub = C[np.ix_(K, K)]
        self_ = np.eye(len(K), dtype=bool)
        if not np.isfinite(sub[~self_]).all():
            continue
        near = np.where(self_, np.inf, sub).min(1)
        out = np.delete(C[K], K, axis=1)
        if not (out >= near[:, None] + margin).all():
            continue
        joined = cost([h for i in K for h in groups[i]]) - sum(own[i] for i in K)
        if joined <= margin * (len(K) - 1) and (best is None or near.min() < best[0]):
            best = (near.min(), K)
    return None if best is None else {int(i) for i in best[1]}


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
            drift = (s0, one_body * s0) if rules.DRIFT_JUDGES else None
            return not any(
                _off_body(X, vis, P, sd_of, h, groups[b], [a, b], rigid * s0, one_body * s0,
                          bound, voter_frames)
                or not (_misfit(X, vis, P, sd_of, h, groups[b], [a, b], rigid * s0, bound,
                                voter_frames, drift=drift) <= bound).all()
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
                if c > rules.CONTINUITY_MARGIN:
                    break
                if move is None or not fits(move):
                    continue
                if not any(x < c + rules.CONTINUITY_MARGIN and fits(m)
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

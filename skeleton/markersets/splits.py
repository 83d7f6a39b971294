"""Step 7 of the marker-set merge: two markers left as three (or four) ids.

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

import numpy as np

from . import rules
from .judges import _jump_ss, _turning
from .tracks import _pair_sd, _partner_frames, _sd_to, _tracks


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
        if rules.TWO_OF_FOUR:
            sets += _pairs_of_pairs(vis, groups, ok, bad)
        found = None
        for ids in sets:
            frs = [f for m in ids for f in groups[m]]
            splits = _colourings(X, vis, frs)
            if len(splits) < (1 if rules.ONE_SPLIT else 2):
                continue
            others = np.setdiff1d(np.arange(M), ids)
            seen, rigid = _partner_frames(X, vis, P, frs, others, min_frames,
                                          rigid_partner * s0)
            partners = others[(seen > 0) & (rigid >= rigid_share * seen)]
            if partners.size and not (rules.PARTNER_SPLITS and len(splits) > 1):
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

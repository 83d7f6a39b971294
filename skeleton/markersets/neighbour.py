"""Step 12c of the marker-set merge: motion continuity in a neighbouring body's frame.

Two markers of one segment, both hidden, come back as one piece: which of the two it is,
nothing rigid can tell where the segment shows one marker at a time (a 2-marker segment):
no mate is seen with the piece, and where the two are about equally far from their joint
their spheres about it are alike. What is left is motion continuity, and in the world a
marker's path carries the motion of every segment above it, so a junction's miss across a
gap of 20-40 frames is of the order of the markers' spacing (steps 3, 7b and 8 judge it
there, ``continuity._continuity_cost``). In the frame of the body the segment hangs from,
a marker only turns about the joint, and its path is much smoother.

``_neighbour_continuity`` (``NEIGHBOUR_CONTINUITY``): a piece ``f`` of marker ``b`` moves
to marker ``a`` that moves as one body with ``b`` and shares no frame with ``f``, where

- in the world, the continuity cost (step 7b's, both markers summed) falls by the move;
- in the frame of every neighbouring body (step 12b's bodies, ``_judging_frames``, holding
  neither marker and where both keep a joint sphere without ``f`` within the body's fit
  gate: the body is across one joint from them) that sees ``f`` for ``SPHERE_POINTS``
  frames, the same cost, computed on the markers' positions in that frame, falls: by at
  least ``NEIGHBOUR_CONTINUITY_MARGIN`` in the best such body, at all in every other
  (``NEIGHBOUR_BEST_MARGIN``; stop 82 asked the margin of every body, which left 41236,
  where a third, larger body seen in part finds a fall of 0.52 beside 2.56 and 2.34);
- step 12's rigid model does not find ``f`` off on ``a``, nor fit it on ``b`` where a's
  mates do not fit it too (``model._against_model``, ``VETO_NEEDS_CONTRAST``); the move
  is paced (step 3's speed gate).

Where no body judges a move (``NEIGHBOUR_UNJUDGED``), nor a mate of either marker seen
with ``f`` (step 12's rigid model), nor a track whose distance range holds ``f`` for one
marker and not the other (``tracks._range_votes``, either way), the world is the only
witness left: the move is made where the world's cost falls by at least
``NEIGHBOUR_WORLD_MARGIN`` (0.5), paced. 28220 (stop 77): marker 35's last 24 frames on its
partner 34, a 2-marker leaf whose parent, grandparent and sibling have two markers each;
the cost falls by 0.67.

The largest fall in a body moves first, then the largest world fall of the moves no body
judges; one move a round, at most ``MODEL_ROUNDS`` rounds.
Figures (all wrong on stop 81's code; a leaf segment whose markers are all hidden near
the end, one coming back, that end piece on a partner): 26684 (2-marker segment, markers
10 and 11, the parent two markers, judged in its two-track frame), 39284 (markers 33 and
34), 39416 (3-marker segment, markers 46 and 47), 41236 (4-marker segment, markers 41
and 42; stop 83's two rules above). The margin and the screens are in
docs/figures-skeleton.md.

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

import numpy as np

from . import rules
from .bodies import _one_body_frames, _points_in, _sphere_fit
from .continuity import _continuity_cost
from .model import _against_model, _Model, _with_piece
from .spheres import _judging_frames
from .tracks import _paced, _pair_sd, _range_votes, _range_z, _spans, _tracks


def _candidates(X, groups, min_frames=10, body_sd=1.5, body_frames=100, fit_rms=None,
                unjudged=False):
    """Each move step 12c weighs, where some body judges it (with ``unjudged`` also where
    none does, the list of bodies empty): (a, f, b, world fall,
    [(body, fall in its frame, the larger of the two spheres' rms / s0)]), the falls
    negative where the cost falls (``_neighbour_continuity``); the bodies those across
    one joint from both markers that see ``f``: their spheres fit within the body's gate
    (``_judging_frames``' with ``fit_rms``, ``NEIGHBOUR_FIT_RMS`` x s0 by default)."""
    fit_rms = rules.NEIGHBOUR_FIT_RMS if fit_rms is None else fit_rms
    vis = ~np.isnan(X[..., 0])
    P = _tracks(X, groups)
    S, s0 = _pair_sd(P, min_frames)
    if not s0 > 0:
        return []
    _, one, full = _one_body_frames(P, S, s0, body_sd, body_frames)
    if not full:
        return []
    frames, gate, lent = _judging_frames(P, one, full, s0, fit_rms)
    points = _points_in(frames, X)
    world = _continuity_cost(X, vis)
    costs = {}

    def frame_cost(body):
        # the continuity cost in the body's frame (every column moved into it)
        if body not in costs:
            fr, R, t = frames[body]
            Y = np.full_like(X, np.nan)
            Y[fr] = np.einsum("tij,tfj->tfi", R, X[fr]) + t[:, None]
            costs[body] = (_continuity_cost(Y, ~np.isnan(Y[..., 0])), ~np.isnan(Y[..., 0]))
        return costs[body]

    def sphere_rms(body, m, f):
        # marker m's joint sphere in body without f: its rms / s0 (inf: too few points)
        rest = [points(body, h) for h in groups[m] if h != f]
        if sum(map(len, rest)) < 50:
            return np.inf
        return _sphere_fit(np.concatenate(rest))[2] / s0

    def fall(cost, a, b, f):
        ga, gb = list(groups[a]), list(groups[b])
        nb = [h for h in gb if h != f]
        return cost(ga + [f]) + cost(nb) - cost(ga) - cost(gb)

    out = []
    for b, gb in enumerate(groups):
        if len(gb) < 2:
            continue
        for a in np.flatnonzero(one[b]):
            a = int(a)
            for f in gb:
                if vis[:, groups[a]][vis[:, f]].any():
                    continue
                judged = []
                for body in frames:
                    if any(m in body or m in lent.get(body, ()) for m in (a, b)):
                        continue
                    if len(points(body, f)) < rules.SPHERE_POINTS:
                        continue
                    rms = max(sphere_rms(body, a, f), sphere_rms(body, b, f))
                    if not rms <= max(gate[body], fit_rms):
                        continue
                    cost, seen = frame_cost(body)
                    if not all(seen[:, h].sum() >= 2 for h in list(groups[a]) + list(gb)):
                        continue
                    judged.append((body, fall(cost, a, b, f), rms))
                if judged or unjudged:
                    out.append((a, f, b, fall(world, a, b, f), judged))
    return out


def _neighbour_continuity(X, groups, max_step=np.inf, min_frames=10) -> list | None:
    """Step 12c (module docstring): groups after one move, or None."""
    vis = ~np.isnan(X[..., 0])
    span = _spans(vis, groups)
    model = None
    found, alone = [], []
    for a, f, b, w, judged in _candidates(X, groups, min_frames,
                                          unjudged=rules.NEIGHBOUR_UNJUDGED):
        if not w < 0:
            continue
        if not judged:
            if w <= -rules.NEIGHBOUR_WORLD_MARGIN:
                alone.append((w, a, f, b))
            continue
        falls = [d for _, d, _ in judged]
        if rules.NEIGHBOUR_BEST_MARGIN:
            if not (max(falls) < 0 and min(falls) <= -rules.NEIGHBOUR_CONTINUITY_MARGIN):
                continue
        elif not max(falls) <= -rules.NEIGHBOUR_CONTINUITY_MARGIN:
            continue
        found.append((min(d for _, d, _ in judged), a, f, b))
    for by_body, (_, a, f, b) in [(True, m) for m in sorted(found)] + \
            [(False, m) for m in sorted(alone)]:
        if model is None:
            model = _Model(X, vis, groups)
        if by_body and _against_model(model, f, b, a):
            continue
        if not by_body and not _unjudged(model, vis, f, b, a):
            continue
        new_a = list(groups[a]) + [f]
        new_b = [h for h in groups[b] if h != f]
        if not (_paced(X, span, new_a, max_step) and _paced(X, span, new_b, max_step)):
            continue
        out = [list(g) for g in groups]
        out[a], out[b] = new_a, new_b
        return out
    return None


def _unjudged(model, vis, f, home, new) -> bool:
    """Nothing but the world's continuity tells marker ``home``'s piece ``f`` from marker
    ``new`` (``NEIGHBOUR_UNJUDGED``): no mate of either marker is seen with it (step 12's
    rigid model) and no track finds it in one marker's distance range and outside the
    other's (``_range_votes``, either way)."""
    if model.judge(f, home) or model.judge(f, new):
        return False
    P, i = _with_piece(model, vis, f, home)
    z_home = _range_z(P, i, home, (home, i))
    z_new = _range_z(P, i, new, (home, new, i))
    return _range_votes(z_new, z_home) == (0, 0)

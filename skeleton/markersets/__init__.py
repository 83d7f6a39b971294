"""Marker identity: merge trajectory fragments into physical markers (the thesis' Marker Sets).

``merge_fragments(trajectories (T, F, 3), min_frames=10, max_distance_m=0.012,
n_markers=None, rng=None) -> MarkerSets``. A tracker starts a new id whenever it loses a
marker (occlusion), so one physical marker arrives as several fragments, each a column with
NaN outside its life. Following the thesis (000, section 3.3, after Kirk, O'Brien & Forsyth
2005), steps 1-3 drop too-short fragments, measure pose-aligned distances between fragments
that never share a frame and merge them by constrained single linkage; steps 4-11 repair
what one minimum distance per gap decides wrong, and step 12 checks every piece once more
against the rigid model (its marker's one-body mates), step 12b against the joint spheres,
and step 12c by motion continuity in a neighbouring body's frame.
One module per step; each module's docstring gives its rule, the figures it was designed
on and what it measured:

- ``linkage`` (steps 1-3): dropping, pose-aligned distances, motion continuity, the
  constrained linkage and its loose pass (``_merge_pass``);
- ``swaps`` (step 4): runs exchanged between two markers of one segment, judged by the
  jumps of their partners' distances (``_repair_swaps``, which runs 4b and 4c too);
- ``cross`` (step 4b): exchanges between any two markers, judged by voting fragments
  (``_repair_cross``);
- ``misfits`` (step 4c): a piece off its marker on every judge moves to the marker it fits
  (``_move_misfits``);
- ``joins`` (steps 5, 6, 7b, 9, 10): markers left as two ids joined by partners, by motion
  continuity, and by splitting a marker holding two others' pieces;
- ``splits`` (step 7): two markers of a 2-marker segment left as three ids;
- ``spheres`` (steps 8, 11 and 12b): the sphere each marker keeps about its joint in a
  neighbouring body's frame, its direction and its continuity, for exchanges and joins
  (12b, after step 12: two pieces exchanged, or one moved, where the spheres decide,
  ``_sphere_check``);
- ``model`` (step 12): a piece off its marker's one-body mates (robust distance
  statistics) moves or is exchanged to the one marker it fits (``_model_check``);
- ``neighbour`` (step 12c): a piece moves to its one-body partner where motion continuity
  in the frame of a body across one joint decides, or, where nothing else judges the
  piece, continuity in the world (``_neighbour_continuity``);
- ``tracks``, ``judges``, ``continuity``, ``bodies``: what the steps share (tracks and
  their distance sds, the jump and misfit judges, run ends and junction misses, body
  frames and joint spheres); ``rules``: every rule's switch and threshold, one place
  (tests and ``benchmarks/screen_markersets.py`` set them there); ``types``: ``MarkerSets``.

The figures named below and in the step modules are ``bench_markersets.py``'s (seed
1000 + k, 400 frames, 1 mm noise, 1-3 gaps of 3-39 frames per marker, 5 ghosts);
docs/figures-skeleton.md holds the record of every screen.

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

import warnings

import numpy as np

# the steps, and helpers that tests and benchmarks reach by this name
from . import rules
from .bodies import _body_frame, _fixed_point, _sphere_fit, _virtual_frames
from .continuity import _junctions, _run_ends
from .cross import _repair_cross
from .joins import _join_by_continuity, _join_by_partners, _split_joins
from .linkage import _merge_pass
from .misfits import _move_misfits
from .model import _model_check
from .neighbour import _neighbour_continuity
from .spheres import _join_by_spheres, _sphere_check, _sphere_exchanges
from .splits import _two_of_three
from .swaps import _repair_swaps
from .tracks import _first_seen, _pair_sd, _tracks
from .types import MarkerSets


__all__ = ["MarkerSets", "merge_fragments"]


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
    ``repair_swaps`` then runs steps 4, 4b, 4c, 5, 6, 7, 7b, 8, 9, 10, 11, 12, 12b and 12c (the
    step modules; ``swap_margin``: the least gain in the rigidity cost for which fragments
    change marker).
    ``continuity_m`` (10 mm; 0 turns it off): the largest miss of the motion-continuity
    extrapolations across a gap for which a pair beyond ``max_distance_m`` still merges
    (``linkage``'s docstring, step 3).
    ``defer_gap`` (60 frames; None turns it off): the longest gap merged before longer
    gaps are judged (``linkage``'s docstring, step 3).
    ``speed_gate`` (1.5; None turns it off): no merge whose marker would cross a gap faster
    than this x the fastest frame-to-frame step of any fragment (``linkage``'s docstring, step 3).
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
    """Steps 4-12c (the step modules) on the linkage's markers ``res``."""
    def merge_and_join(res, joins):
        # a step that moved pieces can leave a marker as two ids: merged within
        # max_distance_m, then (``joins``) joined by motion continuity as in step 7b
        res = merge_again(res, False)
        if joins and res.n_markers > n_min:
            groups = _join_by_continuity(X, [list(g) for g in res.groups], n_min, max_step)
            if len(groups) < res.n_markers:
                res = _with_groups(X, res, groups)
        return res

    res = _with_groups(X, res, _repair_swaps(X, [list(g) for g in res.groups],
                                             min_frames, swap_margin, max_step=max_step))
    # a marker left as two ids beside a swap (the swap made them overlap) can merge now
    res = merge_again(res, True)
    groups = _join_by_partners(X, [list(g) for g in res.groups], min_frames, n_min)
    groups = _two_of_three(X, groups, min_frames, n_min)
    if rules.CONTINUITY_JOINS:
        groups = _join_by_continuity(X, groups, n_min, max_step)
    groups, exchanged = _sphere_exchanges(X, groups, min_frames, max_step=max_step)
    if len(groups) < res.n_markers or exchanged:
        res = _with_groups(X, res, groups)
    if exchanged:
        # step 8 can leave a marker as two ids likewise (joins: 4881)
        res = merge_and_join(res, rules.JOINS_AFTER_EXCHANGES)
    if rules.SPLIT_JOINS and res.n_markers > n_min:
        groups = _split_joins(X, [list(g) for g in res.groups], n_min, min_frames,
                              max_step=max_step)
        if len(groups) < res.n_markers:
            res = _with_groups(X, res, groups)
    if rules.SPHERE_JOINS and res.n_markers > n_min:
        groups = _join_by_spheres(X, [list(g) for g in res.groups], n_min, min_frames,
                                  max_step=max_step)
        if len(groups) < res.n_markers:
            res = _with_groups(X, res, groups)
    if rules.MODEL_CHECK:
        groups = _model_check(X, [list(g) for g in res.groups], max_step)
        seen = {_state(groups)}
        fixed = set()
        for _ in range(rules.MODEL_ROUNDS if rules.SPHERE_CHECK else 0):
            # step 12b: an exchange (or move) the joint spheres decide, its pieces then
            # kept by step 12
            new = _sphere_check(X, groups, max_step, min_frames)
            if new is None:
                break
            fixed |= {f for g, g0 in zip(new, groups) for f in set(g) - set(g0)}
            new = _model_check(X, new, max_step, fixed)
            if _state(new) in seen:
                break
            seen.add(_state(new))
            groups = new
        if [sorted(g) for g in groups] != [sorted(g) for g in res.groups]:
            res = _with_groups(X, res, groups)
            if rules.MODEL_JOINS and res.n_markers > n_min:
                # a piece moved off a marker can leave that marker's own piece free to join
                res = merge_and_join(res, True)
    if rules.NEIGHBOUR_CONTINUITY:
        # step 12c: a piece moved to its one-body partner by continuity in a neighbour's frame
        groups, moved = [list(g) for g in res.groups], False
        for _ in range(rules.MODEL_ROUNDS):
            new = _neighbour_continuity(X, groups, max_step, min_frames)
            if new is None:
                break
            groups, moved = new, True
        if moved:
            res = _with_groups(X, res, groups)
    return res


def _state(groups) -> frozenset:
    """The partition ``groups`` as a set of fragment sets (order-free)."""
    return frozenset(frozenset(g) for g in groups)


def _repairs_from(X, groups, min_frames: int = 10, max_distance_m: float = 0.012,
                  n_markers=None, samples: int = 12, neighbours: int = 3, max_passes: int = 4,
                  loose_distance_m: float = 0.1, swap_margin: float = 1.0,
                  continuity_m: float = 0.01, speed_gate=1.5) -> MarkerSets:
    """Steps 4-12 of ``merge_fragments`` (its defaults) resumed from the linkage's fragment
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


def _with_groups(X, res: MarkerSets, groups) -> MarkerSets:
    """``res`` with new fragment groups (each in order of first sight, the groups too) and
    their tracks."""
    groups = sorted((sorted(g, key=lambda f: _first_seen(X, f)) for g in groups),
                    key=lambda g: _first_seen(X, g[0]))
    return MarkerSets(positions=_tracks(X, groups), groups=tuple(tuple(g) for g in groups),
                      n_min=res.n_min, dropped=res.dropped, distance=res.distance)


def _regroup(X, res: MarkerSets, nxt: MarkerSets) -> MarkerSets:
    """``res`` after a merge pass on its tracks: ``nxt``'s tracks, each group the union of
    the fragments of the ``res`` markers it merged (in order of first sight)."""
    groups = tuple(tuple(sorted((f for g in grp for f in res.groups[g]),
                                key=lambda f: _first_seen(X, f))) for grp in nxt.groups)
    return MarkerSets(positions=nxt.positions, groups=groups, n_min=res.n_min,
                      dropped=res.dropped, distance=res.distance)

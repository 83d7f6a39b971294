"""The judges the repair steps share: turning, jumps and misfits.

``_turning``: how far the direction between two markers turns across their fragment
changes. ``_jump_ss`` / ``_jumps``: the jumps of a partner's distance at a marker's
fragment changes (step 4). ``_misfit`` / ``_off_body`` / ``_fits_on``: whether a piece sits
at its marker's distances from the tracks rigid to it (steps 4b and 4c).

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

import warnings

import numpy as np

from . import rules
from .tracks import _rigid_to_all


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
        nm2 = s ** 2 / np.maximum(n, 1)                   # n x mean^2
        # n, sum, n x mean^2, within-fragment sum of squares about its mean
        stats[f] = (n, s, nm2, np.nansum(d ** 2, 0) - nm2)

    def ss(g):
        n = sum(stats[f][0] for f in g)
        s = sum(stats[f][1] for f in g)
        return sum(stats[f][2] for f in g) - s ** 2 / np.maximum(n, 1)
    ss.judges = lambda g: sum((stats[f][0] > 0).astype(int) for f in g) >= 2

    def noise():
        # (Q,) pooled within-fragment distance variance per partner (NaN where unseen)
        dof = sum(np.maximum(stats[f][0] - 1, 0) for f in frags)
        with np.errstate(invalid="ignore", divide="ignore"):
            return sum(stats[f][3] for f in frags) / np.where(dof > 0, dof, np.nan)
    ss.noise = noise
    return ss


def _jumps(X, vis, ga0, gb0, alts, Pq, margin, per_marker=False, seen_twice=False,
           s0=None):
    """Step 4's jump costs of two markers' fragments (ga0, gb0) and of their alternatives
    ``alts``: (now, costs (len(alts),)), each the sum over both markers and the partners of
    ``_jump_ss``, over the partners only that sit at constant distances from the fragments
    in some assignment (the least cost over (ga0, gb0) and the alternatives <= ``margin``;
    a partner across a joint drifts, and its fragments' means fit no two markers). With
    ``per_marker`` that is asked of each partner and each of the two markers apart: a
    partner of one marker's segment is across a joint from the other marker, where it
    drifts, and still tells where the first marker's pieces belong (figure 9533). With
    ``seen_twice`` a partner fits an assignment only where it is seen with two or more
    fragments of one of its markers (``JUMPS_SEEN_TWICE``): one it sees a single fragment
    of in each marker fits there at no cost, whatever it is (figure 16029). With ``s0``
    each partner's costs are scaled by s0^2 / its pooled within-fragment distance variance
    (s0^2 at least; ``JUMPS_OWN_NOISE``): a partner across a joint drifts, and the same
    jump there tells less (figure 31380: 2.25 mm sd against s0 1.37 mm)."""
    ss = _jump_ss(X, vis, ga0 + gb0, Pq)
    if s0 is not None:
        raw = ss
        var = raw.noise()
        with np.errstate(invalid="ignore"):
            w = np.where(np.isfinite(var), s0 ** 2 / np.maximum(var, s0 ** 2), 1.0)

        def ss(g):
            return raw(g) * w
        ss.judges = raw.judges
    if per_marker:
        now = np.stack([ss(ga0), ss(gb0)])                               # (2, Q)
        costs = np.array([np.stack([ss(ga), ss(gb)]) for ga, gb in alts]
                         ).reshape(len(alts), 2, -1)
        fits = np.minimum(now, costs.min(0, initial=np.inf)) <= margin  # (2, Q)
        return float(now[fits].sum()), costs[:, fits].sum(1)
    now = ss(ga0) + ss(gb0)
    costs = np.array([ss(ga) + ss(gb) for ga, gb in alts]).reshape(len(alts), -1)
    if seen_twice:
        judged = np.array([ss.judges(ga) | ss.judges(gb) for ga, gb in alts]
                          ).reshape(costs.shape)
        fits = np.minimum(np.where(ss.judges(ga0) | ss.judges(gb0), now, np.inf),
                          np.where(judged, costs, np.inf).min(0, initial=np.inf)) <= margin
    else:
        fits = np.minimum(now, costs.min(0, initial=np.inf)) <= margin
    return float(now[fits].sum()), costs[:, fits].sum(1)


def _best_by_jumps(X, vis, ga0, gb0, alts, Pq, margin, s0=None):
    """The alternative (ga, gb) with the least jump cost (``_jumps``), if it is at least
    ``margin`` (m^2) below that of (ga0, gb0); else None. ``s0``: the partners in units of
    their own noise (``JUMPS_OWN_NOISE``)."""
    now, costs = _jumps(X, vis, ga0, gb0, alts, Pq, margin,
                        seen_twice=rules.JUMPS_SEEN_TWICE,
                        s0=s0 if rules.JUMPS_OWN_NOISE else None)
    i = int(np.argmin(costs))
    return alts[i] if costs[i] <= now - margin else None


def _misfit(X, vis, P, sd_of, f, kept, excl, rigid_sd, bound, partner_frames,
            with_frames=False, with_judges=False, drift=None):
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
    ``with_judges``: also the judges' track indices. ``drift`` (s0, body_sd): each judge's
    cost is divided by its drift allowance (``_drift_allowance``)."""
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
    cost = ss(kept + [f])
    if drift is not None:
        cost = cost / _drift_allowance(vis, P, sd_of, f, kept, js, *drift)
    if with_frames:
        return cost[use], (vis[:, f][:, None] & ~np.isnan(P[:, js[use], 0])).sum(0)
    if with_judges:
        return cost[use], js[use]
    return cost[use]


def _drift_allowance(vis, P, sd_of, f, kept, js, s0, body_sd) -> np.ndarray:
    """(len(js),): how much larger a judge's ``_jump_ss`` of fragment ``f`` may be where the
    judge drifts (``DRIFT_JUDGES``; figures 12460 and 12450). A judge across a joint that barely
    moves is rigid to a marker within ``rigid_sd`` yet wanders about its mean distance by
    drift^2 = sd^2 - ``body_sd``^2 (sd: its largest distance sd to the fragments ``kept``;
    none for a judge of one body with them). A piece of n frames then sits off that mean by
    a variance of s0^2 / n + drift^2, not s0^2 / n, so its n x offset^2 (the ``_jump_ss`` it
    adds) is scaled by 1 + n x drift^2 / s0^2 before it meets the bound."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sd = np.nanmax(np.stack([sd_of(h)[js] for h in kept]), 0)
    drift2 = np.maximum(np.nan_to_num(sd) ** 2 - body_sd ** 2, 0.0)
    n = (vis[:, f][:, None] & ~np.isnan(P[:, js, 0])).sum(0)
    return 1.0 + n * drift2 / s0 ** 2


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


def _off_tracks(X, vis, P, sd_of, f, kept, excl, rigid_sd, body_sd, bound,
                body_frames) -> np.ndarray:
    """The tracks of P (not in ``excl``) that move as one body with the fragments ``kept``
    (one marker; sd <= ``body_sd`` to each they are seen with, over >= ``body_frames``
    frames) and find fragment ``f`` off it: not rigid to f (sd > ``rigid_sd``) or at
    another distance from it (``_jump_ss`` of kept + [f] above that of kept by ``bound``)."""
    js, sd = _body_sds(vis, P, sd_of, f, kept, excl, body_sd, body_frames)
    off = sd > rigid_sd
    rest = js[~off]
    if rest.size:                # the jump sums only where the sd leaves it open
        ss = _jump_ss(X, vis, kept + [f], P[:, rest])
        off[~off] = ss(kept + [f]) - ss(kept) > bound
    return js[off]


def _off_body(X, vis, P, sd_of, f, kept, excl, rigid_sd, body_sd, bound, body_frames) -> bool:
    """Fragment ``f`` cannot be the marker of the fragments ``kept``: a track that moves as
    one body with them finds it off (``_off_tracks``)."""
    return bool(_off_tracks(X, vis, P, sd_of, f, kept, excl, rigid_sd, body_sd, bound,
                            body_frames).size)


def _unseen_pose(d, kept_frames, piece_frames, margin, pair_frames) -> bool:
    """Two tracks' distance ``d`` (T,) over a piece's frames (``piece_frames``) is at a
    pose not seen over a marker's other frames (``kept_frames``): there they are not rigid
    (distance sd above ``margin``, over >= ``pair_frames`` frames), and over the piece its
    mean lies outside their range by more than ``margin`` (``NOVEL_POSE_ASIDE``)."""
    seen = ~np.isnan(d)
    k, p = d[kept_frames & seen], d[piece_frames & seen]
    if k.size < pair_frames or p.size == 0 or k.std() <= margin:
        return False
    return bool(p.mean() > k.max() + margin or p.mean() < k.min() - margin)


def _novel_pose(vis, P, f, kept, fit, others, margin, pair_frames) -> list:
    """The tracks of ``others`` (indices into P) at a pose to a judge of ``fit`` (tracks
    that find fragment ``f`` on the marker of the fragments ``kept``) over f's frames not
    seen over the kept frames (``_unseen_pose``; figure 33057). Such a track is across a
    joint from that judge, at an angle where its distance to f's marker was never
    measured."""
    kv, fv = vis[:, kept].any(1), vis[:, f]
    return [int(j) for j in others
            if any(_unseen_pose(np.linalg.norm(P[:, j] - P[:, h], axis=1), kv, fv, margin,
                                pair_frames) for h in fit)]


def _fits(costs, bound) -> bool:
    """``_misfit``'s costs say the fragment fits: some judge, and every one within
    ``bound``."""
    return bool(costs.size and costs.max() <= bound)


def _placed(costs_frames, bound) -> bool:
    """``_misfit``'s costs and frames (``with_frames``) place an unjudged piece: the judges
    within ``bound`` see it for >= ``UNJUDGED_EVIDENCE`` frames in all."""
    costs, frames = costs_frames
    return bool(frames[costs <= bound].sum() >= rules.UNJUDGED_EVIDENCE)


def _tells(X, vis, P, sd_of, f, kept, excl, rigid_sd, bound, partner_frames, at_home) -> bool:
    """A judge of fragment ``f`` on the marker of the fragments ``kept`` (``_misfit``) is
    not among ``at_home``, the judges that find f where it is (``TELLING_JUDGES``; figure
    4083: an off-body piece's own segment partner, as far from its true marker as from the
    one it would move to, was the only judge there). True without such judges at home."""
    if not (rules.TELLING_JUDGES and at_home):
        return True
    _, there = _misfit(X, vis, P, sd_of, f, kept, excl, rigid_sd, bound, partner_frames,
                       with_judges=True)
    return not set(there.tolist()) <= at_home


def _unjudged_on(X, vis, P, sd_of, f, kept, excl, rigid_sd, body_sd, bound,
                 partner_frames) -> bool:
    """No track judges fragment ``f`` on the marker of the fragments ``kept``: no judge of
    ``_misfit`` and off no one-body track (``_off_body``)."""
    return (not _misfit(X, vis, P, sd_of, f, kept, excl, rigid_sd, bound, partner_frames).size
            and not _off_body(X, vis, P, sd_of, f, kept, excl, rigid_sd, body_sd, bound,
                              partner_frames))


def _fits_on(X, vis, P, sd_of, f, kept, excl, rigid_sd, body_sd, bound, partner_frames,
             drift=None) -> bool:
    """Fragment ``f`` fits the marker of the fragments ``kept``: ``_fits`` of ``_misfit``
    (some judge, every one within ``bound``; ``drift``: ``_misfit``'s) and not
    ``_off_body``."""
    return (_fits(_misfit(X, vis, P, sd_of, f, kept, excl, rigid_sd, bound, partner_frames,
                          drift=drift), bound)
            and not _off_body(X, vis, P, sd_of, f, kept, excl, rigid_sd, body_sd, bound,
                              partner_frames))

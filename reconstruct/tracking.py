"""Temporal correspondence: unlabelled 3D point clouds -> marker trajectories.

Each live track predicts its next position (constant velocity, or constant acceleration once
it has three consecutive samples); the points of the next frame are assigned to the
predictions by an optimal assignment (``scipy.optimize.linear_sum_assignment``) restricted
to a gate that widens with the time since the track was last seen. An unmatched track leaves
a gap (NaN) and keeps predicting; after more than ``max_gap_frames`` missing frames it ends,
so a marker reappearing later gets a new id: a trajectory is broken rather than swapped.
Unmatched points start new tracks.

Ambiguity: when two markers come close (their blobs merge into one point, or two points fit
one prediction nearly equally well), no assignment can be trusted. A matched pair
(track r with a velocity, point c) is ambiguous when another live track's prediction is within
``ambiguity_margin_m`` of being as close to c, or another point is within that margin of
being as close to r's prediction. Every track involved ends there and the points start new
tracks: the trajectories are broken rather than swapped. Likewise when a track vanishes
within ``merge_radius_m`` of another track's new point (the two markers' blobs merged, so
that point may be either marker), both tracks end.

Deferred decision (re-linking): a track ended by such a guard, or by one bad point, is often
continued unambiguously a few frames later. After the forward pass, a track A ending at frame
e is joined to a track B starting at s (1 <= s - e <= ``relink_max_gap`` + 1) when, over a
multi-frame window, B's first samples lie within ``relink_tol_m`` of A's extrapolation (a
quadratic fit of A's last samples, robust to one outlier) and A's last samples within it of
B's back-extrapolation, and every other track with samples in either window is farther by
at least ``relink_margin_m``, in both directions. Otherwise the gap stays (gaps rather than
swaps).
Conventions: docs/conventions.md [arrays] ((T, M, 3), NaN gaps), [units], [time].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from reconstruct.types import MarkerCloudSequence, Trajectories

__all__ = ["TrackingConfig", "track"]

_MODELS = ("velocity", "acceleration")
_BIG = 1e9


@dataclass(frozen=True, kw_only=True)
class TrackingConfig:
    """Parameters of :func:`track`.

    Attributes:
        model: "velocity" (constant velocity) or "acceleration" (constant acceleration when a
            track has >= 3 consecutive samples, else constant velocity).
        base_gate_m: gate around a prediction, m (noise + model error at one frame).
        max_accel_mps2: acceleration the gate allows for, m/s^2 (the gate grows by
            a dt^2 k (k + 1) / 2 after k frames, the constant-velocity prediction error).
        max_speed_mps: speed the gate allows for a track with no velocity yet, m/s.
        max_gate_m: the gate never exceeds this (a marker moving off its prediction by more
            is broken off as a new trajectory rather than risk taking a neighbour's point).
        max_gap_frames: a track missing for more frames ends (the marker gets a new id).
        min_length: tracks with fewer samples are dropped (1 keeps every track).
        ambiguity_margin_m: a competing track or point closer than the assigned distance plus
            this margin makes the assignment ambiguous: the tracks end (None: off).
        merge_radius_m: a track that vanishes within this distance of another track's new
            point ends, and so does the other (the two markers' blobs have merged; None: off).
        relink_max_gap: after tracking, join a track ending at frame e to one starting at
            most this many missing frames later when the join is unambiguous (None: off).
        relink_tol_m: a join needs the median distance between each track's samples and the
            other track's extrapolation (forward and backward) below this.
        relink_margin_m: every other track near either window must be farther than the
            joined one by at least this margin, else no join.
        relink_fit_frames: samples (up to) of each track fitted by a quadratic in time; a
            track with fewer than 3 samples is never joined.
        relink_check_frames: frames past the gap (or before it) whose samples are compared.
    """

    model: str = "velocity"
    base_gate_m: float = 0.006
    max_accel_mps2: float = 60.0
    max_speed_mps: float = 3.0
    max_gate_m: float = 0.03
    max_gap_frames: int = 5
    min_length: int = 1
    ambiguity_margin_m: float | None = 0.004
    merge_radius_m: float | None = 0.025
    relink_max_gap: int | None = 3
    relink_tol_m: float = 0.006
    relink_margin_m: float = 0.008
    relink_fit_frames: int = 8
    relink_check_frames: int = 5

    def __post_init__(self):
        if self.model not in _MODELS:
            raise ValueError(f"model={self.model!r}, expected one of {_MODELS}")
        for name in ("base_gate_m", "max_accel_mps2", "max_speed_mps", "max_gate_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}={getattr(self, name)}, expected > 0")
        if self.max_gap_frames < 0:
            raise ValueError(f"max_gap_frames={self.max_gap_frames}, expected >= 0")
        if self.min_length < 1:
            raise ValueError(f"min_length={self.min_length}, expected >= 1")
        if self.merge_radius_m is not None and not self.merge_radius_m > 0:
            raise ValueError(f"merge_radius_m={self.merge_radius_m}, expected > 0 or None")
        if self.ambiguity_margin_m is not None and not self.ambiguity_margin_m >= 0:
            raise ValueError(f"ambiguity_margin_m={self.ambiguity_margin_m}, expected >= 0 "
                             "or None")
        if self.relink_max_gap is not None and self.relink_max_gap < 0:
            raise ValueError(f"relink_max_gap={self.relink_max_gap}, expected >= 0 or None")
        for name in ("relink_tol_m", "relink_margin_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}={getattr(self, name)}, expected > 0")
        if self.relink_fit_frames < 3:
            raise ValueError(f"relink_fit_frames={self.relink_fit_frames}, expected >= 3")
        if self.relink_check_frames < 1:
            raise ValueError(f"relink_check_frames={self.relink_check_frames}, expected >= 1")


def _drop_merged(pred, pts, res_px, missed, r, c, radius, jump=0.0015, resid_px=0.3):
    """A track seen last frame that finds no point now, next to another track's new point
    (closer than ``radius``), has likely merged into it (one blob, one point for two
    markers): that point's identity is unknown, so both tracks end.
    Returns (r, c) kept and the tracks to end."""
    vanish = np.ones(len(pred), bool)
    vanish[r] = False
    vanish &= missed == 0
    if not vanish.any():
        return r, c, np.zeros(0, np.int64)
    v = np.flatnonzero(vanish)
    d = np.linalg.norm(pred[v][:, None, :] - pts[c][None, :, :], axis=2)   # (V, K)
    hit = d < radius
    if not hit.any():
        return r, c, np.zeros(0, np.int64)
    # the other track is affected only if its point shows the merge: off its prediction or
    # with a large ray error (a blob shared with the vanished marker)
    shows = (np.linalg.norm(pts[c] - pred[r], axis=1) > jump) | (res_px[c] > resid_px)
    hit &= shows[None, :]
    if not hit.any():
        return r, c, np.zeros(0, np.int64)
    gone = hit.any(axis=0)
    ended = np.concatenate([v[hit.any(axis=1)], r[gone]])
    return r[~gone], c[~gone], ended


def _drop_ambiguous(cost, r, c, margin, established):
    """Remove ambiguous pairs from the assignment ``r -> c`` (gated ``cost``, _BIG outside).

    Only ``established`` tracks (with a velocity) are tested: a track without one predicts
    its last position, equally far from every neighbour moving the same way, so its
    second sample is left to the optimal assignment.
    Returns (r, c) kept and the indices of every track involved in an ambiguity (matched or
    not), which the caller ends.
    """
    d = cost[r, c]
    lim = (d + margin)[:, None]
    comp_tr = cost[:, c].T < lim                      # (K, n_tracks): tracks near point c
    comp_tr[np.arange(r.size), r] = False
    comp_pt = cost[r] < lim                           # (K, n_pts): points near track r
    comp_pt[np.arange(r.size), c] = False
    amb = (comp_tr.any(axis=1) | comp_pt.any(axis=1)) & established[r]
    if not amb.any():
        return r, c, np.zeros(0, np.int64)
    ended = set(r[amb].tolist())
    ended.update(np.flatnonzero(comp_tr[amb].any(axis=0)).tolist())
    ended_arr = np.array(sorted(ended), np.int64)
    keep = ~np.isin(r, ended_arr)
    return r[keep], c[keep], ended_arr


def _fit(t, p, outlier_m=0.0015):
    """Quadratic (linear for 3 samples) least-squares fit of ``p`` (n, 3) over frames ``t``.
    When a sample is off by more than ``outlier_m`` (and n >= 5), the fit leaving out the one
    sample that gives the smallest worst residual is used instead (an end sample has too much
    leverage to show up as the largest residual of the full fit).
    Returns a function of frames -> (k, 3)."""
    t0 = t.mean()

    def solve(keep):
        deg = 2 if keep.sum() >= 4 else 1
        V = np.vander(t[keep] - t0, deg + 1)
        coef = np.linalg.lstsq(V, p[keep], rcond=None)[0]
        return deg, coef, np.linalg.norm(V @ coef - p[keep], axis=1).max()

    every = np.ones(t.size, bool)
    deg, coef, worst = solve(every)
    if worst > outlier_m and t.size >= 5:
        fits = [solve(every & (np.arange(t.size) != i)) for i in range(t.size)]
        deg, coef, _ = min(fits, key=lambda x: x[2])
    return lambda tq: np.vander(np.asarray(tq, float) - t0, deg + 1) @ coef


def _window_dist(tt, ii, pp, f, lo, hi, n):
    """Median distance (n,) of each track's samples in frames ``lo..hi-1`` to the fit ``f``
    (inf for tracks with no sample there); samples ``tt, ii, pp`` sorted by frame."""
    a, b = np.searchsorted(tt, [lo, hi])
    out = np.full(n, np.inf)
    if a == b:
        return out
    d = np.linalg.norm(pp[a:b] - f(tt[a:b]), axis=1)
    ids = ii[a:b]
    for k in np.unique(ids):
        out[k] = np.median(d[ids == k])
    return out


def _relink(tt, ii, pp, n, T, cfg):
    """Root track (n,) of each of the ``n`` tracks after joining unambiguous continuations
    (module docstring); samples: frames ``tt``, track ids ``ii``, points ``pp`` (sorted by
    frame)."""
    cnt = np.bincount(ii, minlength=n)
    order = np.lexsort((tt, ii))                      # by track, then frame
    start = np.searchsorted(ii[order], np.arange(n + 1))
    first = np.full(n, T)
    last = np.full(n, -1)
    first[cnt > 0] = tt[order[start[:-1][cnt > 0]]]
    last[cnt > 0] = tt[order[start[1:][cnt > 0] - 1]]
    W, nf, nc = cfg.relink_max_gap, cfg.relink_fit_frames, cfg.relink_check_frames
    tol, margin = cfg.relink_tol_m, cfg.relink_margin_m
    ok = cnt >= 3
    fits = {}

    def fit(k, end):
        if (k, end) not in fits:
            rows = order[start[k]:start[k + 1]]
            rows = rows[-nf:] if end else rows[:nf]
            fits[k, end] = _fit(tt[rows].astype(np.float64), pp[rows])
        return fits[k, end]

    pairs = []
    for a in np.flatnonzero(ok & (last < T - 1)):
        e = last[a]
        for b in np.flatnonzero(ok & (first > e) & (first <= e + W + 1)):
            s = first[b]
            # B's first frames against A's extrapolation, A's last frames against B's
            da = _window_dist(tt, ii, pp, fit(a, True), s, s + nc, n)
            db = _window_dist(tt, ii, pp, fit(b, False), e - nc + 1, e + 1, n)
            dab, dba = da[b], db[a]
            if not (dab < tol and dba < tol):
                continue
            da[[a, b]] = db[[a, b]] = np.inf
            # every other track near either window must be clearly farther
            if da.min() < dab + margin or db.min() < dba + margin:
                continue
            pairs.append((dab + dba, a, b))
    root = np.arange(n)
    nxt = {}
    used_a, used_b = set(), set()
    for _, a, b in sorted(pairs):
        if a in used_a or b in used_b:
            continue
        used_a.add(a)
        used_b.add(b)
        nxt[a] = b
    for a in sorted(set(nxt) - set(nxt.values()), key=lambda k: first[k]):
        k = a
        while k in nxt:
            k = nxt[k]
            root[k] = a
    return root


def track(clouds: MarkerCloudSequence, cfg: TrackingConfig | None = None,
          rate_hz: float | None = None) -> Trajectories:
    """Link the point clouds of consecutive frames into trajectories ``T1, T2, ...``.

    Frames missing from ``clouds`` (a jump in frame index) count as frames with no points.
    """
    cfg = cfg or TrackingConfig()
    rate = rate_hz or clouds.rate_hz
    if not rate or rate <= 0:
        raise ValueError(f"rate_hz={rate!r}: the frame rate is needed for tracking gates")
    dt = 1.0 / rate
    if len(clouds) == 0:
        return Trajectories(positions=np.zeros((0, 0, 3)), rate_hz=rate, labels=())
    frames = clouds.frames
    f0 = int(frames[0])
    T = int(frames[-1]) - f0 + 1
    # live track state
    ids = np.zeros(0, np.int64)
    last = np.zeros((0, 3))        # last observed position
    vel = np.zeros((0, 3))         # per frame
    acc = np.zeros((0, 3))         # per frame^2
    n_consec = np.zeros(0, np.int64)
    missed = np.zeros(0, np.int64)  # frames since last seen (0 = seen in the previous frame)
    rec_t, rec_id, rec_p, rec_r = [], [], [], []
    next_id = 0
    by_frame = {c.frame: c for c in clouds}
    for t in range(T):
        cl = by_frame.get(f0 + t)
        pts = cl.points if cl is not None else np.zeros((0, 3))
        res = cl.residual_mm if cl is not None else np.zeros(0)
        res_px = cl.residual_px if cl is not None else np.zeros(0)
        k = (missed + 1).astype(np.float64)
        pred = last.copy()
        hv = n_consec >= 2
        pred[hv] += vel[hv] * k[hv, None]
        if cfg.model == "acceleration":
            ha = n_consec >= 3
            # velocity is a backward difference (the velocity half a frame ago): exact for
            # constant acceleration with the k (k + 1) / 2 factor
            pred[ha] += 0.5 * acc[ha] * (k[ha] * (k[ha] + 1))[:, None]
        # constant-velocity prediction error under acceleration a: a dt^2 k (k + 1) / 2
        gate = np.where(hv, cfg.base_gate_m + 0.5 * cfg.max_accel_mps2 * dt ** 2 * k * (k + 1),
                        cfg.base_gate_m + cfg.max_speed_mps * k * dt)
        gate = np.minimum(gate, cfg.max_gate_m)
        matched_tr = np.zeros(len(ids), bool)
        matched_pt = np.zeros(len(pts), bool)
        if len(ids) and len(pts):
            d = np.linalg.norm(pred[:, None, :] - pts[None, :, :], axis=2)
            cost = np.where(d < gate[:, None], d, _BIG)
            r, c = linear_sum_assignment(cost)
            ok = cost[r, c] < _BIG
            r, c = r[ok], c[ok]
            if cfg.ambiguity_margin_m is not None and r.size:
                r, c, ended = _drop_ambiguous(cost, r, c, cfg.ambiguity_margin_m, hv)
                missed[ended] = cfg.max_gap_frames + 1      # ends below
            if cfg.merge_radius_m is not None and r.size:
                r, c, ended = _drop_merged(pred, pts, res_px, missed, r, c,
                                             cfg.merge_radius_m)
                missed[ended] = cfg.max_gap_frames + 1
            newp = pts[c]
            consec = missed[r] == 0
            kr = (missed[r] + 1).astype(np.float64)
            v_diff = (newp - last[r]) / kr[:, None]
            # after a gap the difference spans several frames (a poor velocity): keep the
            # model's own velocity propagated over the gap when it has one
            use_acc = n_consec[r] >= (3 if cfg.model == "acceleration" else 10**9)
            v_prop = vel[r] + np.where(use_acc[:, None], acc[r] * kr[:, None], 0.0)
            had_v = n_consec[r] >= 2
            v_new = np.where((consec | ~had_v)[:, None], v_diff, v_prop)
            acc[r] = np.where((consec & had_v)[:, None], v_new - vel[r], acc[r])
            vel[r] = v_new
            n_consec[r] = np.where(consec, n_consec[r] + 1, np.maximum(n_consec[r], 2))
            last[r] = newp
            missed[r] = 0
            matched_tr[r] = True
            matched_pt[c] = True
            rec_t.append(np.full(len(r), t))
            rec_id.append(ids[r])
            rec_p.append(newp)
            rec_r.append(res[c])
        missed[~matched_tr] = np.minimum(missed[~matched_tr] + 1, cfg.max_gap_frames + 1)
        alive = missed <= cfg.max_gap_frames
        ids, last, vel, acc, n_consec, missed = (a[alive] for a in
                                                 (ids, last, vel, acc, n_consec, missed))
        new = np.flatnonzero(~matched_pt)
        if new.size:
            nid = np.arange(next_id, next_id + new.size)
            next_id += new.size
            ids = np.concatenate([ids, nid])
            last = np.concatenate([last, pts[new]])
            vel = np.concatenate([vel, np.zeros((new.size, 3))])
            acc = np.concatenate([acc, np.zeros((new.size, 3))])
            n_consec = np.concatenate([n_consec, np.ones(new.size, np.int64)])
            missed = np.concatenate([missed, np.zeros(new.size, np.int64)])
            rec_t.append(np.full(new.size, t))
            rec_id.append(nid)
            rec_p.append(pts[new])
            rec_r.append(res[new])
    if not rec_t:
        return Trajectories(positions=np.zeros((T, 0, 3)), rate_hz=rate, labels=(),
                            first_frame=f0)
    tt = np.concatenate(rec_t)
    ii = np.concatenate(rec_id)
    pp = np.concatenate(rec_p)
    rr = np.concatenate(rec_r)
    if cfg.relink_max_gap is not None and next_id > 1:
        ii = _relink(tt, ii, pp, next_id, T, cfg)[ii]
    length = np.bincount(ii, minlength=next_id)
    keep_ids = np.flatnonzero(length >= cfg.min_length)
    remap = np.full(next_id, -1)
    remap[keep_ids] = np.arange(keep_ids.size)
    M = keep_ids.size
    pos = np.full((T, M, 3), np.nan)
    resid = np.full((T, M), np.nan)
    m = remap[ii]
    ok = m >= 0
    pos[tt[ok], m[ok]] = pp[ok]
    resid[tt[ok], m[ok]] = rr[ok]
    return Trajectories(positions=pos, rate_hz=rate, labels=tuple(f"T{i + 1}" for i in range(M)),
                        first_frame=f0, residual_mm=resid)

"""Body frames and joint spheres (steps 8 and 11): one-body groups of tracks, their Kabsch
frames, frames extended with a borrowed joint, sphere fits and their verdicts.

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

import numpy as np

from . import rules
from .tracks import _kabsch_batch


def _sphere_fit(y) -> tuple:
    """(centre, radius, rms residual) of points ``y`` (N, 3): Kasa's algebraic fit."""
    A = np.c_[2 * y, np.ones(len(y))]
    sol = np.linalg.lstsq(A, (y ** 2).sum(1), rcond=None)[0]
    c = sol[:3]
    r = float(np.sqrt(max(sol[3] + c @ c, 0.0)))
    return c, r, float(np.sqrt(np.mean((np.linalg.norm(y - c, axis=1) - r) ** 2)))


def _sphere_z(y, sphere) -> float:
    """How far points ``y`` (N, 3) lie off ``sphere`` (``_sphere_fit``'s centre, radius,
    rms): the rms of their radius residuals in units of the sphere's own rms (steps 4c and
    11)."""
    c, r, rms = sphere
    res = np.linalg.norm(y - c, axis=1) - r
    return float(np.sqrt(np.mean(res ** 2))) / max(rms, 1e-12)


def _in_frame_order(fr, R, t) -> tuple:
    """(frames, R, t) of a body's frame pieces (lists of arrays) joined and sorted by frame,
    as ``_body_frame`` gives them."""
    fr = np.concatenate(fr)
    o = np.argsort(fr, kind="stable")
    return fr[o], np.concatenate(R)[o], np.concatenate(t)[o]


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


def _virtual_frames(P, frames, s0, joint_rms=rules.VIRTUAL_JOINT_RMS,
                    min_lever=rules.VIRTUAL_MIN_LEVER_M) -> dict:
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
            out[B] = _in_frame_order(fr, R, t)
    return out


def _pair_frames(P, one, frames, s0, joint_rms=None, min_lever=rules.VIRTUAL_MIN_LEVER_M,
                 min_frames=50, every_lender=False) -> tuple[dict, dict]:
    """Frames of two-track bodies (``PAIR_FRAMES``, step 8): each pair of tracks moving as
    one body (``one``) that no body of ``frames`` (three or more tracks) holds, with its
    joint to the body it fits best as the third point: in that body's frame the two tracks
    keep spheres about one centre (``_common_sphere``, rms <= ``joint_rms`` x s0 over >=
    ``min_frames`` frames; ``PAIR_JOINT_RMS``), >= ``min_lever`` off the line through them.
    Returns ({(i, j): (frames, R, t)} as ``_body_frame`` gives, over the frames both tracks
    and that body are seen; {(i, j): the body lent}). Figure 12020 (held out at stop 60): a
    2-marker leaf segment under a 2-marker segment, whose parent has three markers; its
    joint fits at 1.61 x s0. On the final groups of figures 7375 and 12020 (14 such pairs,
    all one segment's), the best joint to a body one joint away fitted at 0.85-2.39 x s0
    (9 pairs); for the 5 pairs with no such body the best fitted at 1.24 (a sibling), 4.57,
    6.57, 8.44 and 11.58. At the first gate, ``VIRTUAL_JOINT_RMS`` (5), figure 7375's
    2-marker segment 12 borrowed the 4.57 joint from a body three joints away, and its
    frame then exchanged two pieces wrongly (2.21 residual sds, just over the 2).
    ``every_lender``: a frame per body that fits within the gate, keyed (i, j, *that body's
    tracks), not the best one's only (step 11, ``SPHERE_JOINS_PAIRS``: figure 16029, where
    the best lender is hidden over the piece to judge)."""
    joint_rms = rules.PAIR_JOINT_RMS if joint_rms is None else joint_rms
    out, lent = {}, {}
    held = {frozenset((x, y)) for B in frames for x in B for y in B if x != y}
    for i, j in zip(*np.nonzero(np.triu(one, 1))):
        i, j = int(i), int(j)
        if frozenset((i, j)) in held:
            continue
        fitting = []
        for A, (frA, RA, tA) in frames.items():
            if i in A or j in A:
                continue
            ok = ~np.isnan(P[frA][:, [i, j], 0]).any(1)
            if ok.sum() < min_frames:
                continue
            fr, R, t = frA[ok], RA[ok], tA[ok]
            Y = [np.einsum("bij,bj->bi", R, P[fr, m]) + t for m in (i, j)]
            u, res = _common_centre(Y)
            rms = float(np.sqrt(np.mean(np.concatenate(res) ** 2)))
            if rms <= joint_rms * s0:
                fitting.append((rms, A, fr, R, t, u))
        fitting.sort(key=lambda c: c[0])
        for _, A, fr, R, t, u in (fitting if every_lender else fitting[:1]):
            c = np.einsum("bji,bj->bi", R, u - t)          # the joint in the world
            src = np.stack([P[fr, i], P[fr, j], c], 1)
            d = src[:, 1] - src[:, 0]
            lever = np.linalg.norm(np.cross(d, src[:, 2] - src[:, 0]), axis=1) / (
                np.linalg.norm(d, axis=1))
            if not np.median(lever) >= min_lever:
                continue
            Rk, tk = _kabsch_batch(src, np.broadcast_to(src[:1], src.shape))
            key = (i, j, *A) if every_lender else (i, j)
            out[key] = (fr, Rk, tk)
            lent[key] = A
    return out, lent


def _partial_frames(P, frames) -> dict:
    """Each body's frame (``_one_body_frames``' ``frames``) extended to the frames where
    three or more of its tracks, not all, are seen (a body of four or more): Kabsch of
    those onto their positions in the body's frame; (frames, R, t) as ``_body_frame``
    gives, for the bodies that gain frames so (``SPHERE_OFF_BODY``)."""
    out = {}
    for B, (frB, RB, tB) in frames.items():
        if len(B) < 4:
            continue
        ref = P[frB[0]][list(B)]
        seen = ~np.isnan(P[:, list(B), 0])
        extra = np.flatnonzero((seen.sum(1) >= 3) & ~seen.all(1))
        if not extra.size:
            continue
        fr, R, t = [frB], [RB], [tB]
        for key in {tuple(r) for r in seen[extra]}:
            cols = np.flatnonzero(key)
            rows = extra[(seen[extra] == key).all(1)]
            src = P[rows][:, [B[c] for c in cols]]
            Rk, tk = _kabsch_batch(src, np.broadcast_to(ref[cols], src.shape))
            fr.append(rows)
            R.append(Rk)
            t.append(tk)
        out[B] = _in_frame_order(fr, R, t)
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
    return _common_centre(Ys)[1]


def _common_centre(Ys) -> tuple:
    """(c, residuals) of ``_common_sphere``."""
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
    return c, [np.linalg.norm(y - c, axis=1) - np.sqrt(max(sol[3 + k] + c @ c, 0.0))
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


def _sphere_pick(X, P, S, s0, f, a, candidates, body_sd=1.5, body_frames=100,
                 fit_rms=1.5):
    """The one marker of ``candidates`` (track indices of P (T, M, 3), pair sds S) whose
    joint sphere fragment ``f`` of X (now on track ``a``) lies on, every other candidate's
    being off (``SPHERE_OFF_BODY``, step 4c): in the frame of each body (``_one_body_frames``;
    ``_partial_frames`` where it shows three or more of its tracks) holding neither ``a``
    nor the candidate, where it sees f in >= ``SPHERE_POINTS`` frames
    (else in its frame extended with a borrowed joint, ``_virtual_frames``, judging within
    ``VIRTUAL_FIT_RMS``), the candidate's track keeps a sphere (Kasa fit of >= 50 points,
    rms <= ``fit_rms`` x s0: a neighbour across one joint) and f's radius residuals have
    an rms of z x the sphere's. The pick lies within ``SPHERE_FIT_Z`` on some body and
    under ``SPHERE_MISFIT_Z`` on all; every other candidate >= ``SPHERE_MISFIT_Z`` on some
    body. None otherwise. Step 11's test, applied to a piece and the markers it could go to.
    Figure 12527 (held out at stop 60): marker 50's last 19 frames, 2-marker segment 16,
    both markers hidden then, sat on marker 23 of another segment; markers 49 and 50 were
    free with no track to judge the piece on either, their spheres about the joint with
    4-marker segment 13 of radii 208 and 241 mm."""
    _, _, full = _one_body_frames(P, S, s0, body_sd, body_frames)
    frames = {**full, **_partial_frames(P, full)}
    virtual = pts_xv = pts_pv = None
    pts_x, pts_p = _points_in(frames, X), _points_in(frames, P)
    z = {b: [] for b in candidates}
    for body in frames:
        if a in body:
            continue
        y, pp, gate = pts_x(body, f), pts_p, fit_rms
        if len(y) < rules.SPHERE_POINTS and rules.VIRTUAL_FRAMES:
            if virtual is None:
                virtual = _virtual_frames(P, full, s0)
                pts_xv, pts_pv = _points_in(virtual, X), _points_in(virtual, P)
            if body in virtual:
                y, pp, gate = pts_xv(body, f), pts_pv, rules.VIRTUAL_FIT_RMS
        if len(y) < rules.SPHERE_POINTS:
            continue
        for b in candidates:
            if b in body:
                continue
            yb = pp(body, b)
            if len(yb) < 50:
                continue
            sphere = _sphere_fit(yb)
            if not sphere[2] <= gate * s0:
                continue
            z[b].append(_sphere_z(y, sphere))
    on = [b for b in candidates if z[b] and min(z[b]) <= rules.SPHERE_FIT_Z
          and max(z[b]) < rules.SPHERE_MISFIT_Z]
    if len(on) == 1 and all(z[b] and max(z[b]) >= rules.SPHERE_MISFIT_Z
                            for b in candidates if b != on[0]):
        return on[0]
    return None


def _direction_spread(ends, frame) -> float:
    """Mean resultant length (0-1) of the unit direction from the first to the second of
    two markers' tracks ``ends`` (T, 2, 3) in a body's ``frame`` (``_body_frame``), over the
    frames both are seen with the body; NaN under ``DIRECTION_FRAMES`` such frames."""
    fr, R, _ = frame
    d = np.einsum("bij,bj->bi", R, ends[fr, 1] - ends[fr, 0])
    d = d[~np.isnan(d[:, 0])]
    if len(d) < rules.DIRECTION_FRAMES:
        return float("nan")
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return float(np.linalg.norm(d.mean(0)))

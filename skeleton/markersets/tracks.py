"""Tracks and the sds of their distances, shared by the marker-set steps.

A track is the (T, 3) positions of a set of fragments (NaN where none is seen); the sd of
the distance between two tracks over their common frames measures rigidity (s0: the median
sd of pairs moving as one body, ``_pair_sd``). Also: exchanges of runs between two markers,
the speed gate on a gap (``_paced``), the distance ranges steps 7b and 12 judge pieces
by (``_range_z``, ``_range_prefers``), and the Kabsch fit the pose alignment and body
frames use.

Conventions: docs/conventions.md [arrays] (NaN gaps), [errors].
"""
from __future__ import annotations

import warnings

import numpy as np

from . import rules


def _kabsch_batch(src, dst):
    """(R, t) per batch with dst ~ R src + t, src/dst (B, K, 3)."""
    cs, cd = src.mean(1), dst.mean(1)
    H = np.einsum("bki,bkj->bij", dst - cd[:, None], src - cs[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    U[:, :, 2] *= d[:, None]
    R = U @ Vt
    return R, cd - np.einsum("bij,bj->bi", R, cs)


def _samples(frames: np.ndarray, n: int) -> np.ndarray:
    """Up to n frames of a fragment: both ends (nearest the gaps) and evenly in between."""
    if frames.size <= n:
        return frames
    k = max(1, n // 4)
    mid = frames[np.linspace(k, frames.size - 1 - k, n - 2 * k).astype(int)]
    return np.unique(np.concatenate([frames[:k], mid, frames[-k:]]))


def _partner_frames(X, vis, P, frs, others, min_frames, rigid_sd) -> tuple:
    """For the tracks ``others`` (columns of ``P``): the frames each is seen with the
    fragments ``frs``, and of those the frames of fragments it is rigid to (distance sd <=
    ``rigid_sd``): a segment partner of the fragments (step 4) is rigid over most of them."""
    seen, rigid = np.zeros(others.size), np.zeros(others.size)
    for f in frs:
        Pf = P[vis[:, f]][:, others]
        sf = _sd_to(Pf, X[vis[:, f], f], min(min_frames, int(vis[:, f].sum())))
        n = (~np.isnan(Pf[..., 0])).sum(0)
        ok = ~np.isnan(sf)
        seen[ok] += n[ok]
        rigid[ok] += n[ok] * (sf[ok] <= rigid_sd)
    return seen, rigid


def _tracks(X, groups) -> np.ndarray:
    """(T, len(groups), 3): each group's fragment columns of X put together."""
    out = np.full((X.shape[0], len(groups), 3), np.nan)
    for g, fs in enumerate(groups):
        for f in fs:
            seen = ~np.isnan(X[:, f, 0])
            out[seen, g] = X[seen, f]
    return out


def _sd_to(P, q, min_frames) -> np.ndarray:
    """(M,) sd over common frames of the distance between q (T, 3) and each column of P
    (T, M, 3); NaN where they share fewer than ``min_frames`` frames."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        d = np.linalg.norm(P - q[:, None], axis=2)
        s = np.nanstd(d, axis=0)
    s[(~np.isnan(d)).sum(0) < min_frames] = np.nan
    return s


def _pair_sd(P, min_frames) -> tuple[np.ndarray, float]:
    """(M, M) distance sd between every two tracks of P (T, M, 3) (``_sd_to``; NaN on the
    diagonal) and s0, the measured sd of a rigid pair: the median of each track's smallest."""
    S = np.stack([_sd_to(P, P[:, m], min_frames) for m in range(P.shape[1])])
    np.fill_diagonal(S, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return S, float(np.nanmedian(np.nanmin(S, 1)))


def _exchange(X, groups, P, S, a, b, ga, gb, min_frames) -> None:
    """Give markers ``a`` and ``b`` the fragments ``ga`` and ``gb``, in place: their groups,
    their tracks in ``P`` and their rows and columns of the sd matrix ``S``."""
    groups[a], groups[b] = list(ga), list(gb)
    P[:, a], P[:, b] = _tracks(X, [ga, gb]).transpose(1, 0, 2)
    for m in (a, b):
        S[m] = S[:, m] = _sd_to(P, P[:, m], min_frames)
        S[m, m] = np.nan


def _run_exchanges(frs, ga, free) -> list:
    """The alternatives of steps 4 and 4b: the fragments ``frs`` of two markers (in time
    order; those in ``ga`` are the first marker's) with the fragments of one run changing
    marker, as (ga', gb') lists, each kept when ``free(g)`` (no two of its fragments seen
    in one frame) holds for both."""
    lab = [f in ga for f in frs]
    out = []
    for i1 in range(len(frs)):
        for i2 in range(i1 + 1, len(frs) + 1 - (i1 == 0)):
            nl = [not x if i1 <= k < i2 else x for k, x in enumerate(lab)]
            na = [f for f, x in zip(frs, nl) if x]
            nb = [f for f, x in zip(frs, nl) if not x]
            if na and nb and free(na) and free(nb):
                out.append((na, nb))
    return out


def _spans(vis, groups) -> dict:
    """fragment -> (first, last) frame it is seen in, for every fragment of ``groups``."""
    out = {}
    for g in groups:
        for f in g:
            seen = np.flatnonzero(vis[:, f])
            out[f] = (int(seen[0]), int(seen[-1]))
    return out


def _cross_alternatives(span: dict, ga, gb):
    """``_run_exchanges`` of two markers' fragments, overlap judged on their spans
    (``span``: fragment -> (first, last) frame; cheaper than frame by frame)."""
    return _run_exchanges(
        sorted(ga + gb, key=lambda f: span[f][0]), ga,
        lambda g: all(span[f][1] < span[h][0] for f, h in zip(g[:-1], g[1:])))


def _too_fast(runs, max_step: float) -> bool:
    """Step 3's speed gate. ``runs``: (first frame, last frame, first position, last
    position, source) of one marker's runs, in time order and never overlapping: whether a
    run following one of another source starts farther from where that one ended than
    ``max_step`` (m) per frame of the gap between them."""
    return any(a[4] != b[4] and np.linalg.norm(b[2] - a[3]) > max_step * (b[0] - a[1])
               for a, b in zip(runs[:-1], runs[1:]))


def _paced(X, span: dict, g, max_step: float) -> bool:
    """No change of fragment in marker ``g`` (fragments never overlapping; ``span``:
    fragment -> (first, last) frame) crosses its gap faster than ``max_step`` (m) per frame:
    step 3's speed gate (``_too_fast``), kept by every later step that moves fragments."""
    if not np.isfinite(max_step) or len(g) < 2:
        return True
    return not _too_fast([(span[f][0], span[f][1], X[span[f][0], f], X[span[f][1], f], f)
                          for f in sorted(g, key=lambda f: span[f][0])], max_step)


def _fragment_sd(X, vis, P, min_frames):
    """A cached ``sd_of(f)``: (M,) distance sd of fragment f to every track of P (T, M, 3),
    NaN where they are seen together for too few frames (``_sd_to``)."""
    cache: dict = {}

    def sd_of(f):
        if f not in cache:
            cache[f] = _sd_to(P[vis[:, f]], X[vis[:, f], f], min(min_frames, int(vis[:, f].sum())))
        return cache[f]
    return sd_of


def _rigid_to_all(sd_of, frags, rigid_sd) -> np.ndarray:
    """(M,) bool: the tracks rigid (sd <= ``rigid_sd``) to every fragment of ``frags`` they
    are seen with, and seen with at least one (``sd_of``: ``_fragment_sd``)."""
    sds = [sd_of(f) for f in frags]
    ok = np.ones(sds[0].shape, bool) if sds else np.zeros(0, bool)
    seen = np.zeros_like(ok)
    for sd in sds:
        ok &= np.isnan(sd) | (sd <= rigid_sd)
        seen |= ~np.isnan(sd)
    return ok & seen


def _first_seen(X, f) -> int:
    return int(np.flatnonzero(~np.isnan(X[:, f, 0]))[0])


def _gap(fa: np.ndarray, fb: np.ndarray) -> int:
    """Fewest frames between a frame of sorted ``fa`` and one of sorted ``fb``."""
    k = np.searchsorted(fb, fa)
    after = np.abs(fb[np.minimum(k, fb.size - 1)] - fa)
    before = np.abs(fb[np.maximum(k - 1, 0)] - fa)
    return int(np.minimum(after, before).min())


def _range_z(P, a, k, skip) -> np.ndarray:
    """Per track t of ``P`` (not in ``skip``): how far the track ``a`` lies outside the
    range of distances from t that track ``k`` keeps, in units of that distance's sd: the
    median over a's frames of the miss beyond the 1st-99th percentile. The range needs
    ``RANGE_FRAMES`` frames of k with t, the verdict ``SPHERE_POINTS`` frames of a with t;
    NaN where either is short. A marker across a joint from t keeps its distance between
    bounds the joint sets (``RANGE_JOINS``)."""
    z = np.full(P.shape[1], np.nan)
    for t in range(P.shape[1]):
        if t in skip:
            continue
        dk = np.linalg.norm(P[:, k] - P[:, t], axis=1)
        dk = dk[np.isfinite(dk)]
        da = np.linalg.norm(P[:, a] - P[:, t], axis=1)
        da = da[np.isfinite(da)]
        if len(dk) < rules.RANGE_FRAMES or len(da) < rules.SPHERE_POINTS:
            continue
        sd = dk.std()
        if not sd > 0:
            continue
        lo, hi = np.percentile(dk, [1, 99])
        z[t] = np.median(np.maximum(0.0, np.maximum(lo - da, da - hi))) / sd
    return z


def _range_prefers(zb, zc) -> bool:
    """The tracks that find the piece in b's range (``RANGE_FIT_Z``) and off c's
    (``RANGE_OFF_Z``) number at least ``RANGE_RATIO`` times those that find the reverse,
    and at least ``RANGE_VOTES``. Far tracks can find the right marker off: a pose not
    seen before moves the ends of the distance's range (held-out figure 26929: marker 9's
    last 15 frames against its partner 8, 15 tracks for 9 and 1 for 8). One track with
    none against decides (held-out figure 29501, stop 77: marker 13's last 10 frames,
    against its partner 12, 0.98 x in 13's range and 6.72 x outside 12's)."""
    n_b, n_c = _range_votes(zb, zc)
    return n_b >= rules.RANGE_VOTES and n_b >= rules.RANGE_RATIO * n_c


def _range_votes(zb, zc) -> tuple[int, int]:
    """(tracks finding the piece in b's range and off c's, tracks finding the reverse):
    within ``RANGE_FIT_Z`` of one marker's range and ``RANGE_OFF_Z`` outside the other's."""
    with np.errstate(invalid="ignore"):
        fit_b, off_b = zb <= rules.RANGE_FIT_Z, zb >= rules.RANGE_OFF_Z
        fit_c, off_c = zc <= rules.RANGE_FIT_Z, zc >= rules.RANGE_OFF_Z
    return int((fit_b & off_c).sum()), int((fit_c & off_b).sum())

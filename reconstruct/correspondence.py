"""Spatial correspondence: which undistorted blobs of C views are images of the same marker.

Per frame:

1. **Epipolar gating.** For every camera pair (i, j) the essential matrix (normalised
   coordinates) gives the epipolar line of each blob of i in j; blob pairs closer than
   ``gate_px`` to each other's lines (in both images) are seeds.
2. **Candidate enumeration.** Each seed is triangulated and projected into the other cameras;
   the nearest blob within ``gate_px`` of the projection joins the candidate. Identical blob
   sets found from different seeds are merged.
3. **Minimum reprojection error.** Every candidate is triangulated (DLT + refinement, one bad
   ray rejected: ``reconstruct.triangulation``); candidates with a ray error above
   ``max_error_px`` are dropped.
4. **Greedy acceptance.** Candidates are taken best first (most cameras, then smallest RMS
   error); a candidate is accepted only if none of its blobs is used already, so each blob is
   used at most once. A second round repeats 1-4 on the blobs left over.
5. **Ghost removal.** A point supported by two cameras only is dropped when its rays meet at
   less than ``min_angle_deg``, when one of its blobs lies within ``gate_px`` of the projection
   of a better (>= 3-camera) point (the blob is explained already), or outside ``bounds``.
6. **Merged blobs** (when blob areas are given). Two markers close in an image make one
   blob, whose centroid lies between them and biases any point using it. A blob's size
   ``sqrt(area) * depth / f`` estimates the marker diameter (up to a constant); a blob larger
   than ``merged_size_ratio`` times the frame's median is taken as merged. Its ray is removed
   and the point re-triangulated from the others; a point left with fewer than
   ``min_cameras`` unmerged rays is dropped (the marker has no blob of its own there).

Conventions: docs/conventions.md [pixels], [frames], [arrays]. Works for any C >= 2.
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from scipy.spatial import cKDTree

from reconstruct.triangulation import RigArrays, triangulate_normalized
from reconstruct.types import PointCloud

__all__ = ["CorrespondenceConfig", "EpipolarGeometry", "epipolar_geometry", "match_frame"]


@dataclass(frozen=True, kw_only=True)
class CorrespondenceConfig:
    """Parameters of :func:`match_frame` (pixels are undistorted pixels of the camera).

    Attributes:
        gate_px: epipolar and reprojection gate for joining a blob to a candidate.
        max_error_px: largest ray error a reconstructed point may keep.
        bad_ray_px: a ray with a larger error is rejected if >= 2 others remain.
        min_cameras: fewest cameras a point needs (>= 2).
        min_angle_deg: smallest ray angle of a 2-camera point.
        bounds: None or ((xmin, ymin, zmin), (xmax, ymax, zmax)) m; points outside are dropped.
        rounds: matching rounds (later rounds use the blobs left over).
        merged_size_ratio: blob-size ratio above which a blob counts as merged (step 6;
            None: off). Two equal discs merged have sqrt(2) = 1.41.
    """

    gate_px: float = 1.5
    max_error_px: float = 1.5
    bad_ray_px: float = 0.75
    min_cameras: int = 2
    min_angle_deg: float = 5.0
    bounds: tuple | None = None
    rounds: int = 2
    merged_size_ratio: float | None = 1.25

    def __post_init__(self):
        for name in ("gate_px", "max_error_px", "bad_ray_px"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}={getattr(self, name)}, expected > 0")
        if self.min_cameras < 2:
            raise ValueError(f"min_cameras={self.min_cameras}, expected >= 2")
        if self.rounds < 1:
            raise ValueError(f"rounds={self.rounds}, expected >= 1")
        if self.merged_size_ratio is not None and not self.merged_size_ratio > 1:
            raise ValueError(f"merged_size_ratio={self.merged_size_ratio}, expected > 1 "
                             "or None")
        if self.bounds is not None:
            b = np.asarray(self.bounds, dtype=np.float64)
            if b.shape != (2, 3) or np.any(b[0] >= b[1]):
                raise ValueError(f"bounds={self.bounds!r}, expected ((lo x,y,z), (hi x,y,z))")


@dataclass(frozen=True, kw_only=True)
class EpipolarGeometry:
    """Camera geometry and the essential matrices of all pairs.

    Attributes:
        geo: stacked rig arrays.
        pairs: (P, 2) camera index pairs i < j.
        E: (P, 3, 3) with ``x_j^T E x_i = 0`` for normalised homogeneous ``x``.
    """

    geo: RigArrays
    pairs: np.ndarray
    E: np.ndarray


def _skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def epipolar_geometry(geo: RigArrays) -> EpipolarGeometry:
    C = geo.n_cameras
    if C < 2:
        raise ValueError(f"correspondence needs >= 2 cameras, got {C}")
    pairs = np.array([(i, j) for i in range(C) for j in range(i + 1, C)], dtype=np.int64)
    E = []
    for i, j in pairs:
        R_ji = geo.R[j] @ geo.R[i].T
        t_ji = geo.t[j] - R_ji @ geo.t[i]
        E.append(_skew(t_ji) @ R_ji)
    return EpipolarGeometry(geo=geo, pairs=pairs, E=np.array(E))


def _homog(x):
    return np.concatenate([x, np.ones((len(x), 1))], axis=1)


def _seeds(blobs, epi: EpipolarGeometry, gate_px, avail):
    """Seed blob pairs passing the epipolar gate: arrays (cam_i, blob_i, cam_j, blob_j)."""
    out = []
    f = epi.geo.f
    for p, (i, j) in enumerate(epi.pairs):
        ai, aj = np.flatnonzero(avail[i]), np.flatnonzero(avail[j])
        if not ai.size or not aj.size:
            continue
        xi, xj = _homog(blobs[i][ai]), _homog(blobs[j][aj])
        E = epi.E[p]
        lj = xi @ E.T                      # lines in j: (Ni, 3)
        li = xj @ E                        # lines in i: (Nj, 3)
        num = xj @ lj.T                    # (Nj, Ni) = x_j . (E x_i)
        dj = np.abs(num) / np.hypot(lj[:, 0], lj[:, 1])[None, :] * f[j]
        di = np.abs(num) / np.hypot(li[:, 0], li[:, 1])[:, None] * f[i]
        bj, bi = np.nonzero((dj < gate_px) & (di < gate_px))
        if bi.size:
            out.append(np.stack([np.full(bi.size, i), ai[bi], np.full(bi.size, j), aj[bj]], 1))
    return np.concatenate(out) if out else np.zeros((0, 4), np.int64)


def _extend(X, seeds, trees, geo: RigArrays, gate_px):
    """(K, C) blob index per camera for each seed point: the seed blobs plus the nearest
    available blob within ``gate_px`` of the projection in every other camera."""
    K, C = len(X), geo.n_cameras
    obs = np.full((K, C), -1, np.int64)
    pc = np.einsum("cij,kj->kci", geo.R, X) + geo.t[None]
    z = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = pc[..., :2] / z[..., None]
    for c in range(C):
        tree, idx = trees[c]
        if tree is None:
            continue
        front = np.flatnonzero(z[:, c] > 0)
        d, j = tree.query(uv[front, c], k=1, distance_upper_bound=gate_px / geo.f[c])
        hit = np.isfinite(d)
        obs[front[hit], c] = idx[j[hit]]
    r = np.arange(K)
    obs[r, seeds[:, 0]] = seeds[:, 1]
    obs[r, seeds[:, 2]] = seeds[:, 3]
    return obs


def _midpoints(seeds, blobs, geo: RigArrays):
    """Two-ray midpoint triangulation of seed pairs, (K, 3)."""
    def rays(cams, idx):
        x = _gather(blobs, cams, idx)
        d = np.concatenate([x, np.ones((len(x), 1))], axis=1)
        d = np.einsum("kji,kj->ki", geo.R[cams], d)                     # R.T @ d
        return geo.centres[cams], d / np.linalg.norm(d, axis=1, keepdims=True)

    o1, d1 = rays(seeds[:, 0], seeds[:, 1])
    o2, d2 = rays(seeds[:, 2], seeds[:, 3])
    w = o1 - o2
    b = np.sum(d1 * d2, axis=1)
    dd = np.sum(d1 * w, axis=1)
    e = np.sum(d2 * w, axis=1)
    den = 1 - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (b * e - dd) / den
        u = (e - b * dd) / den
    X = (o1 + s[:, None] * d1 + o2 + u[:, None] * d2) / 2
    X[(den < 1e-12) | (s <= 0) | (u <= 0)] = np.nan
    return X


def _ray_angle_deg(X, cams, geo: RigArrays):
    """Largest angle between the rays of each point (N,) from its cameras (N, C) bool."""
    d = X[:, None, :] - geo.centres[None]
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    cos = np.einsum("nai,nbi->nab", d, d)
    m = cams[:, :, None] & cams[:, None, :]
    cos = np.where(m, cos, 1.0)
    return np.degrees(np.arccos(np.clip(cos.min(axis=(1, 2)), -1, 1)))


def _one_round(blobs, epi: EpipolarGeometry, cfg: CorrespondenceConfig, avail):
    geo = epi.geo
    C = geo.n_cameras
    seeds = _seeds(blobs, epi, cfg.gate_px, avail)
    if not len(seeds):
        return []
    X = _midpoints(seeds, blobs, geo)
    good = np.all(np.isfinite(X), axis=1)
    if not good.any():
        return []
    trees = []
    for c in range(C):
        idx = np.flatnonzero(avail[c])
        trees.append((cKDTree(blobs[c][idx]), idx) if idx.size else (None, idx))
    obs = _extend(X[good], seeds[good], trees, geo, cfg.gate_px)
    obs = np.unique(obs, axis=0)
    obs = obs[(obs >= 0).sum(axis=1) >= cfg.min_cameras]
    if not len(obs):
        return []
    xy = np.full((C, len(obs), 2), np.nan)
    for c in range(C):
        m = obs[:, c] >= 0
        xy[c, m] = blobs[c][obs[m, c]]
    res = triangulate_normalized(xy, geo, bad_ray_px=cfg.bad_ray_px)
    used = res.used
    n_used = used.sum(axis=1)
    worst = np.nanmax(np.where(used, res.ray_error_px, 0.0), axis=1)
    keep = res.ok & (n_used >= cfg.min_cameras) & (worst <= cfg.max_error_px)
    idx = np.flatnonzero(keep)
    # Greedy acceptance, best first: a heap keyed by (-cameras, RMS error). A candidate that
    # shares some blobs with an accepted point loses them and, if it keeps >= min_cameras,
    # is re-triangulated and pushed back (e.g. a marker whose merged blob went to a
    # neighbour keeps its other views). Blob ids are c * stride + b in a set.
    stride = max(len(b) for b in blobs) + 1
    offs = stride * np.arange(C)
    o_all = np.where(used[idx], obs[idx], -1)
    keys_all = np.where(o_all >= 0, o_all + offs[None], -1).tolist()
    heap = [(-int(n_used[k]), float(res.residual_px[k]), i, k, [x for x in keys_all[i] if x >= 0])
            for i, k in enumerate(idx.tolist())]
    heapq.heapify(heap)
    tie = len(heap)
    extra = {}           # re-triangulated candidates: tie -> (point, residual_mm, obs row)
    taken: set[int] = set()
    accepted = []
    while heap:
        n_neg, rms, i, k, ks = heapq.heappop(heap)
        free = [x for x in ks if x not in taken]
        if len(free) == len(ks):
            taken.update(ks)
            if i in extra:
                X, rmm, o = extra[i]
            else:
                X, rmm, o = res.points[k], float(res.residual_mm[k]), o_all[i]
            accepted.append((X, rms, rmm, o))
            continue
        if len(free) < cfg.min_cameras:
            continue
        o2 = np.full(C, -1, np.int64)
        fa = np.array(free)
        o2[fa // stride] = fa % stride
        xy = np.full((C, 1, 2), np.nan)
        for c in np.flatnonzero(o2 >= 0):
            xy[c, 0] = blobs[c][o2[c]]
        r = triangulate_normalized(xy, geo, bad_ray_px=cfg.bad_ray_px)
        nu = int(r.used[0].sum())
        if (not r.ok[0] or nu < cfg.min_cameras
                or np.nanmax(np.where(r.used[0], r.ray_error_px[0], 0.0)) > cfg.max_error_px):
            continue
        o2 = np.where(r.used[0], o2, -1)
        tie += 1
        extra[tie] = (r.points[0], float(r.residual_mm[0]), o2)
        heapq.heappush(heap, (-nu, float(r.residual_px[0]), tie, -1,
                              (o2 + offs)[o2 >= 0].tolist()))
    for item in accepted:
        o = item[3]
        for c in np.flatnonzero(o >= 0):
            avail[c][o[c]] = False
    return accepted


def _gather(blobs, cams, idx):
    out = np.empty((len(cams), 2))
    for c in np.unique(cams):
        m = cams == c
        out[m] = blobs[c][idx[m]]
    return out


def match_frame(blobs_norm, epi: EpipolarGeometry, cfg: CorrespondenceConfig | None = None,
                frame: int = 0, areas=None) -> PointCloud:
    """Reconstruct the markers of one frame from per-camera undistorted blobs.

    Args:
        blobs_norm: C arrays ``(N_c, 2)`` of normalised image coordinates
            (``Camera.pixel_to_normalized`` of the blob centroids), in rig camera order.
        epi: :func:`epipolar_geometry` of the rig.
        cfg: parameters.
        frame: frame index stored in the cloud.
        areas: None or C arrays ``(N_c,)`` of blob areas in px (enables step 6).
    Returns:
        a :class:`PointCloud`; ``obs`` indexes ``blobs_norm[c]``.
    """
    cfg = cfg or CorrespondenceConfig()
    geo = epi.geo
    C = geo.n_cameras
    if len(blobs_norm) != C:
        raise ValueError(f"{len(blobs_norm)} blob arrays for a {C}-camera rig")
    blobs = []
    for c, b in enumerate(blobs_norm):
        b = np.asarray(b, dtype=np.float64)
        if b.size == 0:
            b = b.reshape(0, 2)
        if b.ndim != 2 or b.shape[1] != 2:
            raise ValueError(f"blobs_norm[{c}].shape={b.shape}, expected (N, 2)")
        blobs.append(b)
    avail = [np.all(np.isfinite(b), axis=1) for b in blobs]
    acc = []
    for _ in range(cfg.rounds):
        new = _one_round(blobs, epi, cfg, avail)
        if not new:
            break
        acc.extend(new)
    if not acc:
        return PointCloud.empty(frame, C)
    X = np.array([a[0] for a in acc])
    rp = np.array([a[1] for a in acc])
    rm = np.array([a[2] for a in acc])
    obs = np.array([a[3] for a in acc])
    cams = obs >= 0
    keep = _not_ghost(X, cams, obs, blobs, geo, cfg)
    if areas is not None and cfg.merged_size_ratio is not None:
        X, rp, rm, obs, keep = _drop_merged_rays(X, rp, rm, obs, keep, blobs, areas, geo, cfg)
        cams = obs >= 0
    return PointCloud(frame=frame, points=X[keep], residual_px=rp[keep], residual_mm=rm[keep],
                      cameras=cams[keep], obs=obs[keep])


def _drop_merged_rays(X, rp, rm, obs, keep, blobs, areas, geo: RigArrays,
                      cfg: CorrespondenceConfig):
    """Step 6: remove rays of merged blobs; re-triangulate or drop the points they touch."""
    if len(areas) != len(blobs):
        raise ValueError(f"{len(areas)} area arrays for {len(blobs)} cameras")
    cams = obs >= 0
    k_idx, c_idx = np.nonzero(cams & keep[:, None])
    if k_idx.size < 5:
        return X, rp, rm, obs, keep
    z = np.einsum("ki,ki->k", geo.R[c_idx, 2], X[k_idx]) + geo.t[c_idx, 2]
    lens = np.array([len(x) for x in areas])
    offs = np.concatenate([[0], np.cumsum(lens)[:-1]])
    a = np.concatenate([np.asarray(x, np.float64).reshape(-1) for x in areas])[
        offs[c_idx] + obs[k_idx, c_idx]]
    size = np.sqrt(a) * z / geo.f[c_idx]
    ok = np.isfinite(size) & (size > 0)
    if ok.sum() < 5:
        return X, rp, rm, obs, keep
    merged = ok & (size > cfg.merged_size_ratio * np.median(size[ok]))
    if not merged.any():
        return X, rp, rm, obs, keep
    X, rp, rm, obs, keep = X.copy(), rp.copy(), rm.copy(), obs.copy(), keep.copy()
    C = geo.n_cameras
    ks = np.unique(k_idx[merged])
    o = obs[ks].copy()
    o[np.searchsorted(ks, k_idx[merged]), c_idx[merged]] = -1
    enough = (o >= 0).sum(axis=1) >= cfg.min_cameras
    keep[ks[~enough]] = False
    ks, o = ks[enough], o[enough]
    if not ks.size:
        return X, rp, rm, obs, keep
    xy = np.full((C, ks.size, 2), np.nan)
    for c in range(C):
        m = o[:, c] >= 0
        xy[c, m] = blobs[c][o[m, c]]
    r = triangulate_normalized(xy, geo, bad_ray_px=cfg.bad_ray_px)
    worst = np.nanmax(np.where(r.used, r.ray_error_px, 0.0), axis=1)
    good = r.ok & (r.used.sum(axis=1) >= cfg.min_cameras) & (worst <= cfg.max_error_px)
    keep[ks[~good]] = False
    g = ks[good]
    X[g], rp[g], rm[g] = r.points[good], r.residual_px[good], r.residual_mm[good]
    obs[g] = np.where(r.used[good], o[good], -1)
    return X, rp, rm, obs, keep


def _not_ghost(X, cams, obs, blobs, geo: RigArrays, cfg: CorrespondenceConfig):
    n = cams.sum(axis=1)
    keep = np.ones(len(X), bool)
    if cfg.bounds is not None:
        lo, hi = np.asarray(cfg.bounds, dtype=np.float64)
        keep &= np.all((X >= lo) & (X <= hi), axis=1)
    two = np.flatnonzero(n == 2)
    if not two.size:
        return keep
    keep[two] &= _ray_angle_deg(X[two], cams[two], geo) >= cfg.min_angle_deg
    strong = np.flatnonzero(n >= 3)
    if strong.size:
        pc = np.einsum("cij,kj->kci", geo.R, X[strong]) + geo.t[None]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = pc[..., :2] / pc[..., 2:3]                           # (S, C, 2)
        for k in two:
            for c in np.flatnonzero(cams[k]):
                b = blobs[c][obs[k, c]]
                d = np.linalg.norm(uv[:, c] - b, axis=1) * geo.f[c]
                if np.any((d < cfg.gate_px) & (pc[:, c, 2] > 0)):
                    keep[k] = False
                    break
    return keep

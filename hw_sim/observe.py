"""Object-mode observation: what each camera of a rig reports (blob centroids) for a scene.

The fast path of the simulator: no images are rendered; every visible marker becomes one 2D
detection at its true (distorted) pixel plus Gaussian noise, in a random order per camera
and frame (cameras do not know marker ids), with optional spurious blobs (reflections) and
merged blobs (two markers closer than their blob size in an image become one centroid).

Public API::

    observe(rig, scene, rng=None, *, noise_px=0.05, spurious_per_frame=0.0, occlusion=True,
            min_blob_px=1.0, merge_blobs=True, merge_factor=1.0) -> Observation
    visibility(rig, positions (T, M, 3), diameters_m (M,), *, occluder_segments=None,
               occluder_radii_m=None, min_blob_px=0.0, near_m=0.05) -> Visibility
    segment_distance(p0, p1, q0, q1) -> distances      # broadcasting, (..., 3) -> (...)

A marker is visible from a camera when it is present (finite), in front of the camera
(depth > ``near_m``), its centre projects inside the image, its blob is at least
``min_blob_px`` wide, and (``occlusion``) the line of sight from the camera centre to the
marker, stopped one marker diameter short of it, passes no occluder capsule closer than its
radius. Ground truth comes with every output: row ids, noise-free pixels, visibility,
occlusion, merges and 3D positions.
Conventions: docs/conventions.md [pixels], [arrays], [camera-order], [errors].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.camera import Rig
from capture.detections import Detections2D
from hw_sim.scenes import MarkerScene

__all__ = ["observe", "visibility", "segment_distance", "Observation", "Visibility"]

_CHUNK_ELEMENTS = 250_000  # (frames x cameras x markers x segments) per occlusion chunk


def _ro(a):
    a = np.asarray(a)
    a.setflags(write=False)
    return a


def segment_distance(p0, p1, q0, q1) -> np.ndarray:
    """Shortest distance between segments ``p0-p1`` and ``q0-q1`` (broadcast over ``...``).

    Closest points of two segments (Ericson, Real-Time Collision Detection 5.1.9), clamped
    to the segments; handles degenerate (zero-length) segments.
    """
    p0, p1, q0, q1 = (np.asarray(a, dtype=np.float64) for a in (p0, p1, q0, q1))
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a = np.einsum("...i,...i->...", d1, d1)
    e = np.einsum("...i,...i->...", d2, d2)
    f = np.einsum("...i,...i->...", d2, r)
    c = np.einsum("...i,...i->...", d1, r)
    b = np.einsum("...i,...i->...", d1, d2)
    a, e, f, c, b = np.broadcast_arrays(a, e, f, c, b)
    eps = 1e-18
    a_ok = a > eps
    e_ok = e > eps
    safe_a = np.where(a_ok, a, 1.0)
    safe_e = np.where(e_ok, e, 1.0)
    denom = a * e - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > eps * np.maximum(a * e, eps),
                     np.clip((b * f - c * e) / np.where(denom > 0, denom, 1.0), 0.0, 1.0), 0.0)
        t = (b * s + f) / safe_e
        s = np.where(t < 0, np.clip(-c / safe_a, 0.0, 1.0),
                     np.where(t > 1, np.clip((b - c) / safe_a, 0.0, 1.0), s))
        t = np.clip(t, 0.0, 1.0)
    # degenerate cases
    t = np.where(e_ok, t, 0.0)
    s = np.where(e_ok, s, np.clip(-c / safe_a, 0.0, 1.0))
    s = np.where(a_ok, s, 0.0)
    t = np.where(a_ok, t, np.clip(f / safe_e, 0.0, 1.0))
    t = np.where(a_ok | e_ok, t, 0.0)
    cp = p0 + s[..., None] * d1
    cq = q0 + t[..., None] * d2
    return np.linalg.norm(cp - cq, axis=-1)


@dataclass(frozen=True, kw_only=True)
class Visibility:
    """Per frame, camera and marker ([arrays]: T frames, C cameras, M markers).

    Attributes:
        projections: (T, C, M, 2) noise-free distorted pixels [pixels]; NaN for absent
            markers and markers behind the camera.
        diameter_px: (T, C, M) blob diameter in px (marker diameter * fx / depth).
        in_view: (T, C, M) bool: present, in front, centre inside the image, blob
            >= ``min_blob_px``.
        occluded: (T, C, M) bool: in view but hidden by an occluder capsule.
        visible: (T, C, M) bool: ``in_view & ~occluded``.
    """

    projections: np.ndarray
    diameter_px: np.ndarray
    in_view: np.ndarray
    occluded: np.ndarray
    visible: np.ndarray


def _occluded(centre, pts, trim, segs, radii) -> np.ndarray:
    """(F, M) bool for one camera: sight line centre->pts[f, m] (stopped ``trim[m]`` short)
    hits a capsule ``segs[f, s]`` of radius ``radii[s]``."""
    F, M, _ = pts.shape
    S = segs.shape[1]
    v = pts - centre
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        end = pts - v / n * trim[None, :, None]
    out = np.zeros((F, M), dtype=bool)
    mid = segs.mean(axis=2)                                           # (F, S, 3)
    reach = np.linalg.norm(segs[:, :, 1] - segs[:, :, 0], axis=-1) / 2 + radii  # (F, S)
    step = max(1, _CHUNK_ELEMENTS // max(M * S, 1))
    for f0 in range(0, F, step):
        sl = slice(f0, f0 + step)
        # cheap pre-test: sight line within reach of the capsule's bounding sphere
        d1 = end[sl] - centre                                         # (f, M, 3)
        w = mid[sl][:, None, :, :] - centre                           # (f, 1, S, 3)
        with np.errstate(invalid="ignore", divide="ignore"):
            tpar = np.clip(np.einsum("fmi,fmsi->fms", d1, w)
                           / np.einsum("fmi,fmi->fm", d1, d1)[..., None], 0.0, 1.0)
            gap = np.linalg.norm(tpar[..., None] * d1[:, :, None, :] - w, axis=-1)
            cand = gap < reach[sl][:, None, :]                        # (f, M, S)
        ff, mm, ss = np.nonzero(cand)
        if not ff.size:
            continue
        seg = segs[sl][ff, ss]                                        # (K, 2, 3)
        d = segment_distance(centre, end[sl][ff, mm], seg[:, 0], seg[:, 1])
        hit = d < radii[ss]
        out[f0 + ff[hit], mm[hit]] = True
    return out


def visibility(rig: Rig, positions, diameters_m, *, occluder_segments=None,
               occluder_radii_m=None, min_blob_px: float = 0.0,
               near_m: float = 0.05) -> Visibility:
    """Projections and visibility of markers ``positions`` (T, M, 3) in every rig camera."""
    P = np.asarray(positions, dtype=np.float64)
    if P.ndim == 2 and P.shape[1] == 3:
        P = P[None]
    if P.ndim != 3 or P.shape[2] != 3:
        raise ValueError(f"positions.shape={np.shape(positions)}, expected (T, M, 3)")
    T, M, _ = P.shape
    diam = np.broadcast_to(np.asarray(diameters_m, dtype=np.float64), (M,))
    segs = None
    if occluder_segments is not None:
        segs = np.asarray(occluder_segments, dtype=np.float64)
        if segs.ndim == 3:
            segs = segs[None]
        if segs.shape[0] != T or segs.shape[2:] != (2, 3):
            raise ValueError(f"occluder_segments.shape={segs.shape}, expected ({T}, S, 2, 3)")
        radii = np.asarray(occluder_radii_m, dtype=np.float64).reshape(-1)
        if radii.shape != (segs.shape[1],):
            raise ValueError(f"occluder_radii_m.shape={radii.shape}, "
                             f"expected ({segs.shape[1]},)")
    C = len(rig)
    flat = P.reshape(-1, 3)
    proj = np.empty((T, C, M, 2))
    dpx = np.empty((T, C, M))
    in_view = np.empty((T, C, M), dtype=bool)
    occl = np.zeros((T, C, M), dtype=bool)
    present = np.all(np.isfinite(P), axis=-1)
    for ci, cam in enumerate(rig):
        z = cam.depth(flat).reshape(T, M)
        uv = cam.project(flat).reshape(T, M, 2)
        with np.errstate(invalid="ignore", divide="ignore"):
            front = present & (z > near_m)
            size = diam[None, :] * cam.K[0, 0] / z
        uv[~front] = np.nan
        proj[:, ci] = uv
        dpx[:, ci] = np.where(front, size, np.nan)
        with np.errstate(invalid="ignore"):
            iv = front & cam.in_image(uv.reshape(-1, 2)).reshape(T, M) & (size >= min_blob_px)
        in_view[:, ci] = iv
        if segs is not None and segs.shape[1] and iv.any():
            occl[:, ci] = iv & _occluded(cam.center, P, diam, segs, radii)
    return Visibility(projections=_ro(proj), diameter_px=_ro(dpx), in_view=_ro(in_view),
                      occluded=_ro(occl), visible=_ro(in_view & ~occl))


@dataclass(frozen=True, kw_only=True)
class Observation:
    """Object-mode detections of a scene with full ground truth.

    Attributes:
        detections: the 2D table the cameras report (raw distorted px, shuffled per
            camera/frame; frames 0..T-1; ``area_px`` = imaged disc area, summed for merged
            blobs).
        marker_id: (K,) int64 true marker index of each detection row; -1 = spurious.
        true_xy: (K, 2) noise-free pixel of each row (for a merged blob: the area-weighted
            mean of its members; for a spurious blob: its own position).
        merged_row: (K,) bool: the row is a merge of two or more markers.
        positions: (T, M, 3) true marker positions, m (NaN = absent).
        projections, diameter_px, visible, occluded: as in ``Visibility`` (T, C, M[, 2]).
        merged: (T, C, M) bool: the marker's blob merged with another one in that image.
        labels: (M,) marker names.
        noise_px: the noise standard deviation injected per coordinate.
    """

    detections: Detections2D
    marker_id: np.ndarray
    true_xy: np.ndarray
    merged_row: np.ndarray
    positions: np.ndarray
    projections: np.ndarray
    diameter_px: np.ndarray
    visible: np.ndarray
    occluded: np.ndarray
    merged: np.ndarray
    labels: tuple[str, ...]
    noise_px: float

    def __post_init__(self):
        K = len(self.detections)
        for name in ("marker_id", "merged_row"):
            if np.shape(getattr(self, name)) != (K,):
                raise ValueError(f"{name}.shape={np.shape(getattr(self, name))}, expected ({K},)")
        if np.shape(self.true_xy) != (K, 2):
            raise ValueError(f"true_xy.shape={np.shape(self.true_xy)}, expected ({K}, 2)")
        T, M, _ = np.shape(self.positions)
        C = self.detections.n_cameras
        for name in ("visible", "occluded", "merged", "diameter_px"):
            if np.shape(getattr(self, name)) != (T, C, M):
                raise ValueError(f"{name}.shape={np.shape(getattr(self, name))}, "
                                 f"expected ({T}, {C}, {M})")

    def labelled_xy(self) -> np.ndarray:
        """(T, C, M, 2) the noisy detection of each marker (known correspondence), NaN where
        the marker was not detected as a blob of its own (not visible, or merged)."""
        T, C, M = self.visible.shape
        out = np.full((T, C, M, 2), np.nan)
        ok = (self.marker_id >= 0) & ~self.merged_row
        d = self.detections
        out[d.frame[ok], d.camera[ok], self.marker_id[ok]] = d.xy[ok]
        return out


def _merge_labels(vis: Visibility, factor: float) -> np.ndarray | None:
    """Merge groups of visible blobs, one label per (t, c, m) node (flattened), or None.

    Two visible blobs of one image merge when their centres are closer than ``factor`` times
    the sum of their radii; groups are the connected components of that relation.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    T, C, M = vis.visible.shape
    if M < 2:
        return None
    iu, ju = np.triu_indices(M, 1)
    step = max(1, 2_000_000 // max(C * M * M, 1))
    src, dst = [], []
    for t0 in range(0, T, step):
        sl = slice(t0, t0 + step)
        v = vis.visible[sl]
        xy = vis.projections[sl]
        r = vis.diameter_px[sl] / 2
        d2 = np.sum((xy[..., iu, :] - xy[..., ju, :]) ** 2, axis=-1)
        lim = factor * (r[..., iu] + r[..., ju])
        with np.errstate(invalid="ignore"):
            close = v[..., iu] & v[..., ju] & (d2 < lim ** 2)
        tt, cc, pp = np.nonzero(close)
        base = ((tt + t0) * C + cc) * M
        src.append(base + iu[pp])
        dst.append(base + ju[pp])
    src, dst = np.concatenate(src), np.concatenate(dst)
    if not src.size:
        return None
    n = T * C * M
    g = coo_matrix((np.ones(src.size, np.int8), (src, dst)), shape=(n, n))
    _, lab = connected_components(g, directed=False)
    return lab


def observe(rig: Rig, scene: MarkerScene, rng=None, *, noise_px: float = 0.05,
            spurious_per_frame: float = 0.0, occlusion: bool = True, min_blob_px: float = 1.0,
            merge_blobs: bool = True, merge_factor: float = 1.0) -> Observation:
    """Simulate object-mode cameras: 2D blob centroids of ``scene`` seen by ``rig``.

    Args:
        noise_px: standard deviation of the Gaussian centroid noise per coordinate (px).
        spurious_per_frame: mean number (Poisson) of spurious blobs per camera and frame,
            uniform over the image; their ``marker_id`` is -1.
        occlusion: hide markers behind the scene's occluder capsules.
        min_blob_px: markers whose blob is smaller than this (far away) are not reported.
        merge_blobs: report markers whose blobs overlap in an image (centre distance
            < ``merge_factor`` * sum of blob radii) as one area-weighted centroid.
        rng: ``numpy.random.Generator`` or int seed.
    """
    if not isinstance(scene, MarkerScene):
        raise TypeError(f"scene must be a MarkerScene, got {type(scene).__name__}")
    if noise_px < 0 or spurious_per_frame < 0:
        raise ValueError(f"noise_px={noise_px}, spurious_per_frame={spurious_per_frame}: "
                         "expected >= 0")
    g = np.random.default_rng(rng)
    segs = scene.occluder_segments if occlusion else None
    vis = visibility(rig, scene.positions, scene.marker_diameter_m, occluder_segments=segs,
                     occluder_radii_m=scene.occluder_radii_m if occlusion else None,
                     min_blob_px=min_blob_px)
    T, C, M = vis.visible.shape
    merged = np.zeros((T, C, M), dtype=bool)
    t_idx, c_idx, m_idx = np.nonzero(vis.visible)
    rows_f = [t_idx]
    rows_c = [c_idx]
    rows_id = [m_idx.astype(np.int64)]
    rows_xy = [vis.projections[t_idx, c_idx, m_idx]]
    rows_merged = [np.zeros(len(t_idx), dtype=bool)]
    rows_area = [np.pi / 4 * vis.diameter_px[t_idx, c_idx, m_idx] ** 2]
    lab = _merge_labels(vis, merge_factor) if merge_blobs and len(t_idx) else None
    if lab is not None:
        node_lab = lab[(t_idx * C + c_idx) * M + m_idx]
        size = np.bincount(node_lab)
        in_group = size[node_lab] >= 2
        merged[t_idx[in_group], c_idx[in_group], m_idx[in_group]] = True
        gl = node_lab[in_group]
        w = (vis.diameter_px[t_idx, c_idx, m_idx][in_group] / 2) ** 2  # blob area weights
        xy_g = rows_xy[0][in_group]
        uniq, inv = np.unique(gl, return_inverse=True)
        wsum = np.bincount(inv, w)
        mxy = np.stack([np.bincount(inv, w * xy_g[:, 0]), np.bincount(inv, w * xy_g[:, 1])],
                       axis=1) / wsum[:, None]
        order = np.lexsort((-w, inv))              # per group, the largest blob first
        first = order[np.r_[True, inv[order][1:] != inv[order][:-1]]]
        for a_ in (rows_f, rows_c, rows_id, rows_xy, rows_merged, rows_area):
            a_[0] = a_[0][~in_group]
        rows_f.append(t_idx[in_group][first])
        rows_c.append(c_idx[in_group][first])
        rows_id.append(m_idx[in_group][first].astype(np.int64))
        rows_xy.append(mxy)
        rows_merged.append(np.ones(len(uniq), dtype=bool))
        rows_area.append(np.pi * wsum)
    true_xy = np.concatenate(rows_xy) if rows_xy else np.zeros((0, 2))
    noisy = true_xy + g.normal(0.0, noise_px, true_xy.shape) if noise_px > 0 else true_xy.copy()
    if spurious_per_frame > 0:
        n_sp = g.poisson(spurious_per_frame, (T, C))
        tt, cc = np.nonzero(n_sp)
        reps = n_sp[tt, cc]
        tt, cc = np.repeat(tt, reps), np.repeat(cc, reps)
        sizes = np.array([rig[int(c)].size for c in cc], dtype=np.float64).reshape(-1, 2)
        sp = g.uniform(0.0, 1.0, (len(tt), 2)) * sizes - 0.5  # anywhere on the sensor
        rows_f.append(tt)
        rows_c.append(cc)
        rows_id.append(np.full(len(tt), -1, np.int64))
        true_xy = np.concatenate([true_xy, sp])
        noisy = np.concatenate([noisy, sp])
        rows_merged.append(np.zeros(len(tt), dtype=bool))
        rows_area.append(g.uniform(2.0, 30.0, len(tt)))  # reflections of assorted sizes
    f = np.concatenate(rows_f).astype(np.int64)
    c = np.concatenate(rows_c).astype(np.int64)
    ids = np.concatenate(rows_id)
    mr = np.concatenate(rows_merged)
    area = np.concatenate(rows_area)
    order = np.lexsort((g.random(len(f)), c, f))  # shuffled within each (frame, camera)
    f, c, ids, mr, true_xy, noisy, area = (a[order] for a in (f, c, ids, mr, true_xy, noisy,
                                                              area))
    det = Detections2D(frame=f, camera=c, xy=noisy, camera_names=tuple(rig.names),
                       rate_hz=scene.rate_hz, area_px=area)
    return Observation(detections=det, marker_id=_ro(ids), true_xy=_ro(true_xy),
                       merged_row=_ro(mr), positions=scene.positions,
                       projections=vis.projections, diameter_px=vis.diameter_px,
                       visible=vis.visible, occluded=vis.occluded, merged=_ro(merged),
                       labels=scene.labels, noise_px=float(noise_px))

"""3D positions of a few static markers (an L-frame, floor markers) from unlabelled blobs.

For world alignment after wand calibration: each camera's blobs over all frames are clustered
(``cluster_px``); clusters present in at least ``min_fraction`` of the camera's frames are its
static markers (spurious blobs come and go). Markers are matched across cameras greedily:
every pair of clusters from two cameras is triangulated and reprojected into all cameras; the
candidate seen (within ``gate_px``) by the most cameras, then with the smallest error, is
accepted and its blobs are used up. Points are refined by maximum likelihood in px
(``calibration.points.refine_points``). Conventions: docs/conventions.md [pixels], [frames],
[units].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from calibration.init_extrinsics import triangulate
from calibration.points import refine_points
from capture.detections import Detections2D


@dataclass(frozen=True, kw_only=True)
class StaticPoints:
    """points: (N, 3) m; xy: (C, N, 2) the clusters (px) each point was triangulated from,
    NaN where unseen; rms_px: (N,) reprojection RMS (2D norm)."""

    points: np.ndarray
    xy: np.ndarray
    rms_px: np.ndarray

    def __post_init__(self):
        N = np.shape(self.points)[0]
        if np.shape(self.points) != (N, 3):
            raise ValueError(f"points.shape={np.shape(self.points)}, expected (N, 3)")
        if np.shape(self.xy)[1:] != (N, 2) or np.shape(self.rms_px) != (N,):
            raise ValueError(f"xy.shape={np.shape(self.xy)}, rms_px.shape="
                             f"{np.shape(self.rms_px)}: expected (C, {N}, 2), ({N},)")


def camera_clusters(xy: np.ndarray, frame: np.ndarray, *, cluster_px: float = 2.0,
                    min_fraction: float = 0.5) -> np.ndarray:
    """Mean pixel (K, 2) of each blob cluster present in >= min_fraction of the frames."""
    if len(xy) == 0:
        return np.zeros((0, 2))
    pairs = cKDTree(xy).query_pairs(cluster_px, output_type="ndarray")
    n = len(xy)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, lab = connected_components(g, directed=False)
    n_frames = len(np.unique(frame))
    out = []
    for k in range(lab.max() + 1):
        sel = lab == k
        if len(np.unique(frame[sel])) >= min_fraction * n_frames:
            out.append(xy[sel].mean(axis=0))
    return np.array(out).reshape(-1, 2)


def static_points(det: Detections2D, cameras, *, cluster_px: float = 2.0, gate_px: float = 2.0,
                  min_views: int | None = None, min_fraction: float = 0.5) -> StaticPoints:
    """Triangulate the static markers of ``det`` with calibrated ``cameras`` (list or Rig).

    min_views: cameras that must see a point (default 3, or 2 for a 2-camera rig).
    """
    cams = list(cameras)
    C = len(cams)
    if det.n_cameras != C:
        raise ValueError(f"detections have {det.n_cameras} cameras, the rig {C}")
    if min_views is None:
        min_views = 3 if C >= 3 else 2
    px = [camera_clusters(det.xy[det.camera == c], det.frame[det.camera == c],
                          cluster_px=cluster_px, min_fraction=min_fraction) for c in range(C)]
    nrm = [cams[c].pixel_to_normalized(px[c]) if len(px[c]) else px[c] for c in range(C)]
    trees = [cKDTree(p) if len(p) else None for p in px]
    R = np.stack([c.R for c in cams])
    t = np.stack([c.t for c in cams])
    cands = []   # (-support, error, {camera: cluster index})
    for a in range(C):
        for b in range(a + 1, C):
            if not len(px[a]) or not len(px[b]):
                continue
            ia, ib = np.meshgrid(np.arange(len(px[a])), np.arange(len(px[b])), indexing="ij")
            ia, ib = ia.ravel(), ib.ravel()
            obs = np.full((C, len(ia), 2), np.nan)
            obs[a], obs[b] = nrm[a][ia], nrm[b][ib]
            X = triangulate(obs, R, t, np.ones(C, bool))
            for k in range(len(ia)):
                if not np.all(np.isfinite(X[k])):
                    continue
                members, err = {}, []
                for c in range(C):
                    if trees[c] is None or cams[c].depth(X[k:k + 1])[0] <= 0:
                        continue
                    p = cams[c].project(X[k:k + 1])[0]
                    d, j = trees[c].query(p)
                    if d <= gate_px:
                        members[c] = int(j)
                        err.append(d)
                if a in members and b in members and len(members) >= min_views:
                    cands.append((-len(members), float(np.mean(err)), members))
    cands.sort(key=lambda c: (c[0], c[1]))
    used = [set() for _ in range(C)]
    groups = []
    for _, _, members in cands:
        if any(j in used[c] for c, j in members.items()):
            continue
        for c, j in members.items():
            used[c].add(j)
        groups.append(members)
    xy = np.full((C, len(groups), 2), np.nan)
    for n, members in enumerate(groups):
        for c, j in members.items():
            xy[c, n] = px[c][j]
    nxy = np.full_like(xy, np.nan)
    for c in range(C):
        ok = np.isfinite(xy[c, :, 0])
        if ok.any():
            nxy[c, ok] = cams[c].pixel_to_normalized(xy[c, ok])
    X = refine_points(cams, xy, triangulate(nxy, R, t, np.ones(C, bool))) if groups else \
        np.zeros((0, 3))
    rms = np.zeros(len(groups))
    for n in range(len(groups)):
        e = [np.sum((cams[c].project(X[n:n + 1])[0] - xy[c, n]) ** 2) for c in range(C)
             if np.isfinite(xy[c, n, 0])]
        rms[n] = np.sqrt(np.mean(e))
    return StaticPoints(points=X, xy=xy, rms_px=rms)

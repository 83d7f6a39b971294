"""Initial camera poses from wand / point observations, no prior pose knowledge.

The first pair is camera 0 (the gauge, identity pose, docs/conventions.md [frames]) and its
strongest neighbour in the maximum spanning tree of shared-observation counts
(``scipy.sparse.csgraph`` on negated weights); its relative pose comes from the essential
matrix (``cv2.findEssentialMat`` RANSAC on normalised coordinates + ``cv2.recoverPose``).
Every further camera is added incrementally, the one seeing the most points triangulated by
the cameras placed so far first, by ``cv2.solvePnPRansac`` against those points, which keeps
one common scale along the chain.
Metric scale: the median triangulated wand length equals the wand's (none in single-point
mode: the root-to-first-neighbour baseline is 1).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import minimum_spanning_tree

from calibration.camera import Camera, rotation_from_rodrigues


@dataclass(frozen=True, kw_only=True)
class InitialPoses:
    """R: (C, 3, 3), t: (C, 3) cam_from_world; ok / reason for degenerate input."""

    R: np.ndarray
    t: np.ndarray
    ok: bool
    reason: str = ""


def normalized(xy: np.ndarray, cameras: list[Camera]) -> np.ndarray:
    """(C, T, M, 2) px -> normalised image coordinates with each camera's intrinsics."""
    out = np.full_like(xy, np.nan)
    for c, cam in enumerate(cameras):
        v = xy[c].reshape(-1, 2)
        ok = np.all(np.isfinite(v), axis=1)
        o = out[c].reshape(-1, 2)
        o[ok] = cam.pixel_to_normalized(v[ok])
        out[c] = o.reshape(xy[c].shape)
    return out


def triangulate(nxy: np.ndarray, R: np.ndarray, t: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Linear multi-view DLT. nxy (C, N, 2) normalised, NaN unseen; use (C,) bool -> (N, 3)."""
    C, N, _ = nxy.shape
    P = np.concatenate([R, t[:, :, None]], axis=2)  # (C, 3, 4)
    seen = np.all(np.isfinite(nxy), axis=2) & use[:, None]
    x = np.where(seen[..., None], nxy, 0.0)
    rows = np.concatenate([x[..., 0:1] * P[:, None, 2] - P[:, None, 0],
                           x[..., 1:2] * P[:, None, 2] - P[:, None, 1]], axis=0)  # (2C, N, 4)
    w = np.concatenate([seen, seen], axis=0)[..., None]
    A = np.transpose(rows * w, (1, 0, 2))
    _, _, vt = np.linalg.svd(A)
    Xh = vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:4]
    X[seen.sum(axis=0) < 2] = np.nan
    return X


def _tree_order(seen: np.ndarray) -> list[tuple[int, int]]:
    """Breadth-first (parent, child) edges of the maximum spanning tree of shared counts."""
    S = seen.astype(np.int64)
    W = S @ S.T
    np.fill_diagonal(W, 0)
    C = len(W)
    mst = minimum_spanning_tree(csr_matrix(-W.astype(float))).toarray()
    adj = (mst != 0) | (mst.T != 0)
    edges, done, q = [], {0}, deque([0])
    while q:
        p = q.popleft()
        for ch in sorted(np.flatnonzero(adj[p]), key=lambda j: -W[p, j]):
            if int(ch) not in done:
                done.add(int(ch))
                edges.append((p, int(ch)))
                q.append(int(ch))
    if len(done) != C:
        return []
    return edges


def resolve_end_order(nxy: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Flip each camera's wand ends so they match the lowest-index camera seeing the wand.

    nxy (C, T, M, 2) normalised; the choice minimises the algebraic epipolar error of the ends.
    Returns the reordered array.
    """
    C, T, M, _ = nxy.shape
    out = nxy.copy()
    seen = np.all(np.isfinite(nxy[:, :, [0, -1]]), axis=(2, 3))  # (C, T)
    ref = np.argmax(seen, axis=0)
    for c in range(C):
        for r in range(C):
            if r >= c:
                break
            sel = seen[c] & (ref == r)
            if not np.any(sel):
                continue
            Rr = R[c] @ R[r].T
            tr = t[c] - Rr @ t[r]
            tx = np.array([[0, -tr[2], tr[1]], [tr[2], 0, -tr[0]], [-tr[1], tr[0], 0]])
            E = tx @ Rr
            h = lambda a: np.concatenate([a, np.ones(a.shape[:-1] + (1,))], axis=-1)
            a0, a1 = h(nxy[r, sel, 0]), h(nxy[r, sel, -1])
            b0, b1 = h(nxy[c, sel, 0]), h(nxy[c, sel, -1])
            e = lambda b, a: np.abs(np.einsum("ni,ij,nj->n", b, E, a))
            same = e(b0, a0) + e(b1, a1)
            flip = e(b1, a0) + e(b0, a1)
            idx = np.flatnonzero(sel)[flip < same]
            out[c, idx] = out[c, idx, ::-1]
    return out


def initial_poses(nxy: np.ndarray, *, spacing_m=None, symmetric: bool = False,
                  thresh_norm: float = 1e-3) -> tuple[InitialPoses, np.ndarray]:
    """Initial poses from normalised observations nxy (C, T, M, 2).

    Returns the poses and nxy with the wand ends in a consistent order across cameras.
    """
    C, T, M, _ = nxy.shape
    if M == 3:
        pt = nxy[:, :, 1]
    elif M == 2:   # image midpoint of the two ends: close to the wand centre's image (init only)
        pt = 0.5 * (nxy[:, :, 0] + nxy[:, :, 1])
    else:
        pt = nxy[:, :, 0]
    seen = np.all(np.isfinite(pt), axis=2)
    R = np.tile(np.eye(3), (C, 1, 1))
    t = np.zeros((C, 3))
    edges = _tree_order(seen)
    if not edges:
        return InitialPoses(R=R, t=t, ok=False,
                            reason="camera graph is not connected by shared observations"), nxy
    placed = np.zeros(C, bool)
    placed[0] = True
    p, c = edges[0]
    both = seen[p] & seen[c]
    if both.sum() < 8:
        return InitialPoses(R=R, t=t, ok=False,
                            reason=f"cameras {p},{c} share only {both.sum()} points"), nxy
    a, b = pt[p, both], pt[c, both]
    try:
        E, mask = cv2.findEssentialMat(a, b, np.eye(3), method=cv2.RANSAC, prob=0.9999,
                                       threshold=thresh_norm)
    except cv2.error:
        # OpenCV 5.1 raises on degenerate points where 5.0 returned no matrix
        E = None
    if E is None or E.shape != (3, 3):
        return InitialPoses(R=R, t=t, ok=False, reason=(
            f"essential matrix failed for cameras {p},{c}: no consistent pose from their "
            f"{int(both.sum())} shared wand observations (wrong intrinsics?)")), nxy
    _, Rpc, tpc, _ = cv2.recoverPose(E, a, b, np.eye(3), mask=mask)
    R[c], t[c] = Rpc, tpc.ravel()
    placed[c] = True
    while not placed.all():
        # next: the unplaced camera seeing the most points the placed cameras triangulate
        # (incremental order; the spanning tree only chose the first pair)
        X = triangulate(pt, R, t, placed)
        n_ok = np.where(placed, -1, (np.isfinite(X[:, 0])[None] & seen).sum(axis=1))
        c = int(np.argmax(n_ok))
        ok = np.isfinite(X[:, 0]) & seen[c]
        if ok.sum() < 6:
            return InitialPoses(R=R, t=t, ok=False,
                                reason=f"camera {c}: only {ok.sum()} points for PnP"), nxy
        res, rvec, tvec, inl = cv2.solvePnPRansac(
            X[ok], pt[c, ok], np.eye(3), None, reprojectionError=thresh_norm * 3,
            iterationsCount=200, confidence=0.9999, flags=cv2.SOLVEPNP_EPNP)
        if not res:
            return InitialPoses(R=R, t=t, ok=False, reason=f"camera {c}: PnP failed"), nxy
        i = inl.ravel()
        _, rvec, tvec = cv2.solvePnP(X[ok][i], pt[c, ok][i], np.eye(3), None, rvec, tvec,
                                     useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        R[c], t[c] = rotation_from_rodrigues(rvec.ravel()), tvec.ravel()
        placed[c] = True
    if symmetric and M >= 2:
        nxy = resolve_end_order(nxy, R, t)
    if spacing_m is not None and M >= 2:
        use = np.ones(C, bool)
        X0 = triangulate(nxy[:, :, 0], R, t, use)
        X1 = triangulate(nxy[:, :, -1], R, t, use)
        L = np.linalg.norm(X1 - X0, axis=1)
        L = L[np.isfinite(L)]
        if L.size == 0:
            return InitialPoses(R=R, t=t, ok=False, reason="no wand triangulated"), nxy
        t = t * ((spacing_m[-1] - spacing_m[0]) / np.median(L))
    return InitialPoses(R=R, t=t, ok=True), nxy

"""Markers -> rigid segments: pairwise-distance-variance affinity and spectral clustering.

``segment_markers(trajectories (T, M, 3), n_segments=None, rng=None) -> Segmentation``.
Markers on one rigid body keep constant mutual distances, so the standard deviation of
their distance over time is ~0 (noise). The affinity uses local scaling (Zelnik-Manor &
Perona): ``A_ij = exp(-sd_ij^2 / (s_i s_j))``. K is chosen by the largest eigengap of the
normalised Laplacian unless given. Conventions: docs/conventions.md [arrays] (NaN gaps).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from sklearn.cluster import SpectralClustering

__all__ = ["Segmentation", "distance_sd", "segment_markers"]

# Local scale s_i = sd to the marker's LOCAL_SCALE_K-th nearest neighbour, floored. Every
# segment carries >= 2 markers, so a small k keeps s_i at the noise level of its own segment
# (k = 3 let two-marker segments take a between-segment scale and merge with a neighbour);
# the floor stands for the noise level (noise-free data gives sd = 0; real data 1.4-7 mm).
# Measured (benchmarks/bench_skeleton.py figures, 600 frames): k=2, 3 mm -> automatic K
# right on 50/50 noise-free and 50/50 with 1 mm noise (k=3, 1 mm: 42/50 and 22/50).
SCALE_FLOOR_M = 3e-3
LOCAL_SCALE_K = 2


@dataclass(frozen=True, kw_only=True)
class Segmentation:
    """labels (M,) segment of each marker; n_segments; eigengap_k (the automatic choice);
    eigenvalues (first few of the normalised Laplacian); distance_sd (M, M) m."""

    labels: np.ndarray
    n_segments: int
    eigengap_k: int
    eigenvalues: np.ndarray
    distance_sd: np.ndarray


def distance_sd(traj: np.ndarray) -> np.ndarray:
    """(M, M) standard deviation over frames of each marker-pair distance (NaN-aware)."""
    traj = np.asarray(traj, np.float64)
    if traj.ndim != 3 or traj.shape[2] != 3:
        raise ValueError(f"trajectories.shape={traj.shape}, expected (T, M, 3)")
    d = np.linalg.norm(traj[:, :, None] - traj[:, None], axis=-1)
    with np.errstate(all="ignore"):
        sd = np.nanstd(d, axis=0)
    sd[np.isnan(sd)] = np.nanmax(sd) if np.isfinite(sd).any() else 1.0
    np.fill_diagonal(sd, 0.0)
    return sd


def segment_markers(traj: np.ndarray, n_segments: int | None = None, rng=None) -> Segmentation:
    sd = distance_sd(traj)
    M = sd.shape[0]
    k = min(LOCAL_SCALE_K, M - 1)
    s = np.maximum(np.sort(sd, axis=1)[:, k], SCALE_FLOOR_M)
    A = np.exp(-sd**2 / np.outer(s, s))
    deg = A.sum(1)
    L = np.eye(M) - A / np.sqrt(np.outer(deg, deg))
    ev = np.linalg.eigvalsh(L)
    kmax = max(2, M // 2 + 1)
    gaps = np.diff(ev[: kmax + 1])
    k_auto = int(np.argmax(gaps[1:]) + 2) if gaps.size > 1 else 1
    K = k_auto if n_segments is None else int(n_segments)
    if not 1 <= K <= M:
        raise ValueError(f"n_segments={n_segments!r}, expected 1..{M}")
    seed = rng if isinstance(rng, (int, np.integer)) else (
        int(np.random.default_rng(rng).integers(2**31)))
    if K == 1:
        labels = np.zeros(M, np.int64)
    else:
        with warnings.catch_warnings():   # well-separated segments: disconnected graph
            warnings.filterwarnings("ignore", message="Graph is not fully connected")
            labels = SpectralClustering(n_clusters=K, affinity="precomputed", random_state=seed,
                                        assign_labels="cluster_qr").fit(A).labels_
    # relabel in order of first marker
    _, first = np.unique(labels, return_index=True)
    order = np.argsort(first)
    remap = np.empty(K, np.int64)
    remap[labels[np.sort(first)]] = np.arange(K)
    return Segmentation(labels=remap[labels], n_segments=K, eigengap_k=k_auto,
                        eigenvalues=ev[: kmax + 1], distance_sd=sd)

"""Markers -> rigid segments: pairwise-distance-variance affinity, spectral clustering, rigidity.

``segment_markers(trajectories (T, M, 3), n_segments=None, rng=None) -> Segmentation``.
Markers on one rigid body keep constant mutual distances, so the standard deviation of
their distance over time is at the noise level. Every scale is measured in units of that
level, estimated from the data itself (``noise_sd``): the median over markers of the SD to
the marker's nearest-SD neighbour (every segment carries >= 2 markers, so that neighbour is
normally on the same segment). Nothing assumes a noise level in millimetres.

1. Affinity with local scaling (Zelnik-Manor & Perona): ``A_ij = exp(-sd_ij^2 / (s_i s_j))``,
   ``s_i`` the SD to the marker's 2nd-nearest neighbour, floored at 1.5x the noise level.
2. K by the largest eigengap of the normalised Laplacian unless given; spectral clustering.
3. Rigidity (automatic K only): a cluster holding a pair whose distance SD exceeds 4x the
   noise level is not one rigid body; it is split in two (complete linkage) until every
   cluster is rigid, single markers split off too. Then two clusters rigid to each other
   (every pair across them within 1.5x the noise level, 0.1 mm at least) are merged, closest
   first (stop 12: over seed sets 1000-12000 and six noise conditions, 3,600 segmentations,
   this changed one: noise-free seed 12045, a 4-marker segment the spectral step had cut in
   two, now right), and a single marker still alone joins the cluster it is most rigid with
   (step 5). Until stop 18 a split that left one marker alone was not made: three 2-marker
   segments spread by the spectral step over two 3-marker clusters stayed wrong (seed
   48012, 1 mm: K = 19 of 20). Low-passed as the pipeline segments, seed sets 1000-3000,
   7000-9000 and 46000-51000, noise-free, 1 mm, 1 mm + gaps, 2 mm and 3 mm (3,000
   segmentations; /tmp script, the conditions of ``_count``): 12 -> 7 wrong (fixed 48012
   at 1 and 2 mm, 46038 at 3 mm, 48032 and 7001 with gaps), none lost.
4. Each marker moves to the cluster with the smallest mean squared distance SD to its members
   (fixes markers near a joint that the affinity attached to the neighbouring segment).
5. A marker left alone joins the cluster it is most rigid with (automatic K only).
6. Rigidity decides the count (automatic K only, stop 30). A segment is a rigid body, so when
   steps 3-5 still leave a cluster that is not rigid (a marker folded back in step 5), the
   count rises from the eigengap's: K + 1, K + 2, ... up to M / 2 are clustered afresh
   (spectral, rigid merge, reassignment; no split) and the first whose clusters all hold
   >= 2 markers and are rigid is taken; where none is, the one with the smallest largest
   within-cluster SD, if smaller than step 5's. Markers near a joint look rigid to both
   neighbours, and the one-marker-at-a-time split of step 3 cuts such a cluster at the wrong
   place: on CMU's 85_12 the eigengap (9) and steps 3-5 gave {pelvis + RTHI} (7.9x the
   noise level) and {RKNE RSHN RANK}; 13 clusters give {RTHI RKNE}, {RSHN RANK}, all within
   2.9x. On 85_02 (eigengap 11): 15 segments, no leg cluster above 3.5x (the forearm and
   hand clusters at 4.5x and 4.6x). Both tennis copies: 14, the same partition with and
   without gaps. Simulated figures whose steps 3-5 leave every cluster rigid do not change:
   the segmentation screens below (``tests.skeleton.test_segments``) gave the same counts
   and wrong seeds before and after; the count never rose on 2,300 benchmark figures at 0 and
   1 mm. With hw_sim's soft-tissue artefacts (markers sliding +-2-3 mm per axis on their
   bones, 1 mm noise; random trees 0-99) it rose in 1 (2 mm) and 4 (3 mm) figures, each
   then right, none right without it.

Measured (figures as benchmarks/bench_skeleton.py: random_tree(5..20 segments, 2-4 markers),
600 frames; right = same K and same partition as the truth; command:
``.venv/bin/python -m tests.skeleton.test_segments 1000 2000 3000``). Figures right out of 50,
before (fixed 3 mm scale floor, no rigidity step, commit 4aeaeb6) / after. Seeds 1000..1049
are the set the former constants were tuned on, 2000..2049 held out (the present constants
were chosen on both), 3000..3049 looked at once, after the constants were fixed:

    noise          1000..1049   2000..2049   3000..3049
    none           50 / 50      45 / 50      50 / 50
    1 mm           50 / 50      45 / 49      50 / 50
    1 mm + gaps    49 / 50      45 / 49      50 / 50
    0.5 mm         50 / 50      45 / 50      50 / 50
    2 mm           46 / 49      39 / 42      45 / 47
    3 mm           35 / 38      34 / 37      37 / 37

The pipeline (skeleton.pipeline) segments noisy data after its 6 Hz low-pass: distance
changes across a joint follow the slow motion, white marker noise is broadband. Right out of
50 per set, raw / low-passed, on figures since hw_sim's 20 mm marker spacing (70ca108;
``.venv/bin/python -m tests.skeleton.test_segments 1000 2000 3000 7000 8000 9000``, stop 12;
7000-9000 first run then):

    noise          1000     2000     3000     7000     8000     9000
    none           50       50       50       50       50       50    (not filtered)
    0.5 mm         50/50    50/50    50/50    50/50    50/50    50/50
    1 mm           50/50    50/50    50/50    50/50    48/50    50/50
    1 mm + gaps    50/50    50/50    50/50    50/49    48/50    50/50
    2 mm           48/50    44/50    46/50    46/50    46/49    47/49
    3 mm           38/50    36/49    40/50    37/50    41/48    38/49

The real 4-2-3 arm's distance SDs are slow soft-tissue motion, which the filter keeps: its
noise level (2.52 / 2.49 mm), largest within-segment SD (2.76x / 2.80x) and smallest
cross-segment SD (1.70x / 1.72x the level) barely move.

Remaining failures on raw data are segment pairs whose every cross distance varies by less
than ~2x the noise (seed 2003: two segments, all cross SDs <= 2.6 mm at 1 mm noise, 2.1 mm
noise-free, so a rigidity threshold loose enough for the real arm recording cannot split
them); the
2-3 mm failures have not been analysed one by one. Conventions: docs/conventions.md [arrays]
(NaN gaps).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform
from sklearn.cluster import SpectralClustering

__all__ = ["Segmentation", "distance_sd", "noise_sd", "segment_markers"]

# Local scale s_i = sd to the marker's LOCAL_SCALE_K-th nearest neighbour: k = 2 keeps s_i at
# the noise level of its own segment for segments of >= 3 markers (k = 3 let two-marker
# segments take a between-segment scale and merge with a neighbour). The floor is
# SCALE_NOISE_FACTOR x the measured noise level (a fixed 3 mm floor blurred 1.4 mm within-
# segment SDs with 2-3 mm between-segment SDs near joints: 45/50 on held-out seeds); 1.25-1.75
# give the same counts (seeds 1000/2000, noise-free and 1 mm), 1.0 and 2.0 do not (1 mm:
# 46 and 47 of 50 on 1000 and 2000 with 1.0; 50 and 47 with 2.0). SCALE_FLOOR_M only keeps
# noise-free data (sd = 0) finite: 1e-5..1e-3 m give the same counts.
LOCAL_SCALE_K = 2
SCALE_NOISE_FACTOR = 1.5
SCALE_FLOOR_M = 1e-4
# A cluster is rigid when every pair's distance SD is <= RIGID_FACTOR x the noise level.
# Synthetic within-segment pairs reach 1.14x (1 mm noise), the real 4-2-3 arm recording 2.8x
# (soft tissue: 7.0 mm against a 2.5 mm level); 3x..6x give the same counts (seeds 1000/2000,
# noise-free and 1 mm; split and reassignment matter at 2-3 mm: without both, 39 and 34 of
# 50 instead of 42 and 37 on 2000..2049). No merge at this level: at 1 mm noise three
# held-out segment pairs have a union that looks rigid (2003, 2008, 2028: 1.8x, 3.2x, 3.7x)
# and the spectral step separates those of 2008 and 2028 correctly; merging them would undo
# that (MERGE_FACTOR, below, stays under all three).
RIGID_FACTOR = 4.0
# Clusters whose union is rigid within MERGE_FACTOR x the noise level are one segment (the
# spectral step can cut a rigid segment in two on degenerate, noise-free data: seed 12045,
# a 4-marker segment as 2 + 2). Synthetic within-segment SDs reach 1.14x; the segment pairs
# below whose unions look rigid are at 1.8x-3.7x, so they stay apart.
MERGE_FACTOR = 1.5


@dataclass(frozen=True, kw_only=True)
class Segmentation:
    """labels (M,) segment of each marker (numbered by first marker); n_segments; eigengap_k
    (the eigengap's choice, before rigidity splits); eigenvalues (first few of the normalised
    Laplacian); distance_sd (M, M) m; noise_sd (m, the within-segment distance SD level)."""

    labels: np.ndarray
    n_segments: int
    eigengap_k: int
    eigenvalues: np.ndarray
    distance_sd: np.ndarray
    noise_sd: float = 0.0


def distance_sd(traj: np.ndarray) -> np.ndarray:
    """(M, M) standard deviation over frames of each marker-pair distance (NaN-aware: frames
    where either marker is missing are left out; a pair never seen together gets the largest
    SD)."""
    traj = np.asarray(traj, np.float64)
    if traj.ndim != 3 or traj.shape[2] != 3:
        raise ValueError(f"trajectories.shape={traj.shape}, expected (T, M, 3)")
    M = traj.shape[1]
    i, j = np.triu_indices(M, 1)
    d = np.linalg.norm(traj[:, i] - traj[:, j], axis=-1)          # (T, M(M-1)/2)
    seen = ~np.isnan(d)
    d = np.where(seen, d, 0.0)
    with np.errstate(all="ignore"):
        n = seen.sum(0)
        dev = np.where(seen, d - d.sum(0) / n, 0.0)
        pair_sd = np.sqrt((dev * dev).sum(0) / n)
    sd = np.zeros((M, M))
    sd[i, j] = sd[j, i] = pair_sd
    sd[np.isnan(sd)] = np.nanmax(sd) if np.isfinite(sd).any() else 1.0
    return sd


def noise_sd(sd: np.ndarray) -> float:
    """Within-segment distance SD level (m): median over markers of the SD to the nearest-SD
    other marker (~sqrt(2) x the per-coordinate noise for white noise)."""
    sd = np.asarray(sd, np.float64)
    if sd.ndim != 2 or sd.shape[0] != sd.shape[1] or sd.shape[0] < 2:
        raise ValueError(f"sd.shape={sd.shape}, expected (M, M) with M >= 2")
    return float(np.median(np.sort(sd, axis=1)[:, 1]))


def _split_nonrigid(sd: np.ndarray, labels: np.ndarray, tau: float) -> np.ndarray:
    """Split (complete linkage, in two) every cluster holding a pair with sd > tau, repeatedly,
    one-marker halves included: the spectral step can spread three 2-marker segments over two
    clusters ({a1, b1, b2} and {a2, c1, c2}; seed 48012, 1 mm), and only the split-off single
    markers, merged back rigid (``_merge_rigid``), rebuild a. A single marker rigid with nothing
    (a mis-merged trajectory, an outlier) is no segment: ``_fold_singletons`` puts it back."""
    labels = labels.copy()
    changed = True
    while changed:
        changed = False
        for c in range(labels.max() + 1):
            idx = np.flatnonzero(labels == c)
            sub = sd[np.ix_(idx, idx)]
            if idx.size < 2 or sub.max() <= tau:
                continue
            two = fcluster(linkage(squareform(sub, checks=False), "complete"), 2, "maxclust")
            labels[idx[two == 2]] = labels.max() + 1
            changed = True
    return labels


def _merge_rigid(sd: np.ndarray, labels: np.ndarray, tau: float) -> np.ndarray:
    """Merge, closest first, two clusters rigid to each other (every pair across them has
    sd <= tau), until no two are."""
    labels = labels.copy()
    while True:
        ids = np.unique(labels)
        best, pair = np.inf, None
        for i, a in enumerate(ids):
            for b in ids[i + 1:]:
                m = sd[np.ix_(labels == a, labels == b)].max()
                if m <= tau and m < best:
                    best, pair = m, (a, b)
        if pair is None:
            return labels
        labels[labels == pair[1]] = pair[0]


def _reassign(sd: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Move markers, best improvement first, to the cluster with the smallest mean squared
    distance SD to its other members; a cluster never drops below 2 markers."""
    labels = labels.copy()
    sd2 = sd**2
    rows = np.arange(labels.size)
    for _ in range(labels.size):
        onehot = np.eye(labels.max() + 1)[labels]
        others = onehot.sum(0)[None, :] - onehot
        with np.errstate(all="ignore"):
            cost = np.where(others > 0, (sd2 @ onehot) / others, np.inf)
        best = np.argmin(cost, 1)
        gain = cost[rows, labels] - cost[rows, best]
        gain[(onehot.sum(0)[labels] <= 2) | (best == labels)] = 0.0
        if not (gain > 0).any():
            break
        i = int(np.argmax(gain))
        labels[i] = best[i]
    return labels


def _fold_singletons(sd: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """A one-marker cluster (a marker rigid with nothing: a tracker's swap, a wrong
    marker-set merge) joins the cluster it is most rigid with (smallest mean squared
    distance SD): a segment needs >= 2 markers to be lined up at all."""
    labels = labels.copy()
    while True:
        n = np.bincount(labels)
        lone = np.flatnonzero(n == 1)
        if lone.size == 0 or (n > 0).sum() < 2:
            return labels
        i = int(np.flatnonzero(labels == lone[0])[0])
        cand = [c for c in np.flatnonzero(n > 0) if c != lone[0]]
        labels[i] = min(cand, key=lambda c: float(np.mean(sd[i, labels == c] ** 2)))


def _spectral(A: np.ndarray, K: int, seed: int) -> np.ndarray:
    """Spectral clustering of affinity ``A`` into ``K`` clusters (one cluster for K = 1)."""
    if K == 1:
        return np.zeros(A.shape[0], np.int64)
    with warnings.catch_warnings():   # well-separated segments: disconnected graph
        warnings.filterwarnings("ignore", message="Graph is not fully connected")
        labels = SpectralClustering(n_clusters=K, affinity="precomputed", random_state=seed,
                                    assign_labels="cluster_qr").fit(A).labels_
    return np.asarray(labels, np.int64)


def _worst_sd(sd: np.ndarray, labels: np.ndarray) -> float:
    """The largest distance SD between two markers of one cluster."""
    return max(float(sd[np.ix_(labels == c, labels == c)].max()) for c in np.unique(labels))


def _automatic(sd: np.ndarray, A: np.ndarray, k0: int, seed: int, noise: float) -> np.ndarray:
    """Labels for the automatic segment count (see the module docstring, steps 3-6)."""
    tau = max(RIGID_FACTOR * noise, SCALE_FLOOR_M)
    merge_tau = max(MERGE_FACTOR * noise, SCALE_FLOOR_M)
    labels = _split_nonrigid(sd, _spectral(A, k0, seed), tau)
    labels = _fold_singletons(sd, _reassign(sd, _merge_rigid(sd, labels, merge_tau)))
    best, score = labels, max(_worst_sd(sd, labels), tau)
    for K in range(k0 + 1, sd.shape[0] // 2 + 1):
        if score <= tau:
            break
        cand = _reassign(sd, _merge_rigid(sd, _spectral(A, K, seed), merge_tau))
        cand_score = max(_worst_sd(sd, cand), tau)
        if np.bincount(cand).min() >= 2 and cand_score < score:
            best, score = cand, cand_score
    return best


def segment_markers(traj: np.ndarray, n_segments: int | None = None, rng=None) -> Segmentation:
    sd = distance_sd(traj)
    M = sd.shape[0]
    if M < 2:
        raise ValueError(f"trajectories.shape={np.shape(traj)}, expected M >= 2 markers")
    noise = noise_sd(sd)
    k = min(LOCAL_SCALE_K, M - 1)
    s = np.maximum(np.sort(sd, axis=1)[:, k], max(SCALE_NOISE_FACTOR * noise, SCALE_FLOOR_M))
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
    if n_segments is None:
        labels = _automatic(sd, A, K, seed, noise)
    else:
        labels = _reassign(sd, _spectral(A, K, seed))
    # relabel in order of first marker (drops any emptied label)
    _, first = np.unique(labels, return_index=True)
    remap = np.full(labels.max() + 1, -1, np.int64)
    remap[labels[np.sort(first)]] = np.arange(first.size)
    return Segmentation(labels=remap[labels], n_segments=int(first.size), eigengap_k=k_auto,
                        eigenvalues=ev[: kmax + 1], distance_sd=sd, noise_sd=noise)

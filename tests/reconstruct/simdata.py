"""Simulated inputs and truth scoring shared by the reconstruction tests and benchmarks.

``moving_markers`` builds a ``hw_sim.scenes.MarkerScene`` of markers on smooth random
paths with moving capsule occluders (a stand-in when the articulated figure is not wanted);
``figure_scene`` is ``hw_sim.scenes.figure``.
"""
from __future__ import annotations

import numpy as np

from hw_sim.scenes import MarkerScene


#: issue 4's acceptance, shared by the reconstruction tests: reconstructable markers found,
#: spurious 3D points; the simulated cameras' blob-centroid noise
MIN_FOUND = 0.995
MAX_SPURIOUS = 0.002
NOISE_PX = 0.05
#: 0.05 px at ~5 m with f ~ 1200 px: ~0.2 mm per axis, 0.35 mm in 3D (0.26-0.27 mm measured)
RMS_3D_M = 0.00035

def moving_markers(n_markers=40, n_frames=240, rate_hz=120.0, rng=0, *, speed_mps=1.0,
                   min_separation_m=0.08, n_occluders=2) -> MarkerScene:
    """Markers oscillating smoothly (peak speed ~``speed_mps``) in a 1.6 m box at the volume
    centre, kept ``min_separation_m`` apart at every frame, and vertical capsule occluders
    (radius 0.12 m) circling through the box."""
    g = np.random.default_rng(rng)
    t = np.arange(n_frames) / rate_hz
    paths = []
    for _ in range(200 * n_markers):
        if len(paths) == n_markers:
            break
        base = g.uniform([-0.8, -0.8, 0.4], [0.8, 0.8, 2.0])
        freq = g.uniform(0.3, 0.8, 3)
        amp = speed_mps / (2 * np.pi * freq) / np.sqrt(3)
        path = base + amp * np.sin(2 * np.pi * freq * t[:, None] + g.uniform(0, 2 * np.pi, 3))
        if all(np.linalg.norm(path - q, axis=1).min() >= min_separation_m for q in paths):
            paths.append(path)
    if len(paths) < n_markers:
        raise ValueError("could not place markers apart; lower n_markers or separation")
    P = np.stack(paths, axis=1)
    segs = np.zeros((n_frames, n_occluders, 2, 3))
    for s in range(n_occluders):
        a = 2 * np.pi * (0.25 + 0.2 * s) * t + s * np.pi
        r = 1.3 + 0.3 * s
        segs[:, s, 0] = np.stack([r * np.cos(a), r * np.sin(a), np.zeros_like(a)], 1)
        segs[:, s, 1] = np.stack([r * np.cos(a), r * np.sin(a), np.full_like(a, 2.2)], 1)
    return MarkerScene(positions=P, marker_diameter_m=np.full(n_markers, 0.014),
                       rate_hz=rate_hz, labels=tuple(f"M{i + 1}" for i in range(n_markers)),
                       occluder_segments=segs if n_occluders else None,
                       occluder_radii_m=np.full(n_occluders, 0.12) if n_occluders else None)


def figure_scene(n_frames=240, rate_hz=120.0, rng=0):
    """The articulated hw_sim figure (``hw_sim.scenes.figure``)."""
    from hw_sim.scenes import figure
    return figure(n_frames, rate_hz, rng)


def reconstructable(obs) -> np.ndarray:
    """(T, M) bool: the marker has its own (unmerged) blob in >= 2 cameras."""
    return ((obs.visible & ~obs.merged).sum(axis=1)) >= 2


def match_points(points, truth, tol_m):
    """Truth marker of each point (N,) (-1 when no truth marker within ``tol_m``)."""
    if not len(points):
        return np.zeros(0, np.int64)
    ok = np.all(np.isfinite(truth), axis=1)
    d = np.linalg.norm(points[:, None] - np.where(ok[:, None], truth, np.inf)[None], axis=2)
    j = np.argmin(d, axis=1)
    return np.where(d[np.arange(len(points)), j] < tol_m, j, -1)


def score_clouds(clouds, obs, tol_m=0.005):
    """Counts over all frames: reconstructable markers, found, points, spurious points (no
    truth marker within ``tol_m``, or a second point on one marker), 3D errors (m) of the
    points matched to truth."""
    need = reconstructable(obs)
    n_need = n_found = n_pts = n_spur = 0
    errs = []
    for cl in clouds.clouds:
        t = cl.frame
        truth = obs.positions[t]
        m = match_points(cl.points, truth, tol_m)
        n_pts += len(cl)
        n_spur += int(np.sum(m < 0)) + int(np.sum(m >= 0) - np.unique(m[m >= 0]).size)
        found = np.zeros(truth.shape[0], bool)
        found[m[m >= 0]] = True
        n_need += int(need[t].sum())
        n_found += int((need[t] & found).sum())
        errs.append(np.linalg.norm(cl.points[m >= 0] - truth[m[m >= 0]], axis=1))
    return dict(need=n_need, found=n_found, points=n_pts, spurious=n_spur,
                errors=np.concatenate(errs) if errs else np.zeros(0))


def score_tracks(traj, obs, max_gap_frames, tol_m=0.005):
    """Identity swaps (tracks whose samples belong to > 1 truth marker), and per marker the
    number of tracks against the number of reconstructable runs (runs separated by at most
    ``max_gap_frames`` missing frames count as one)."""
    T, M = traj.positions.shape[:2]
    truth = obs.positions[traj.first_frame:traj.first_frame + T]
    owner = np.full((T, M), -1)
    for t in range(T):
        ok = np.all(np.isfinite(traj.positions[t]), axis=1)
        owner[t, ok] = match_points(traj.positions[t, ok], truth[t], tol_m)
    swaps = 0
    tracks_of = [set() for _ in range(truth.shape[1])]
    unmatched_samples = 0
    for m in range(M):
        ids = set(owner[:, m][owner[:, m] >= 0].tolist())
        unmatched_samples += int(np.sum((owner[:, m] < 0)
                                        & np.all(np.isfinite(traj.positions[:, m]), axis=1)))
        if len(ids) > 1:
            swaps += 1
        for i in ids:
            tracks_of[i].add(m)
    need = reconstructable(obs)[traj.first_frame:traj.first_frame + T]
    expected = np.zeros(truth.shape[1], np.int64)
    for i in range(truth.shape[1]):
        idx = np.flatnonzero(need[:, i])
        if idx.size:
            expected[i] = 1 + int(np.sum(np.diff(idx) > max_gap_frames + 1))
    actual = np.array([len(s) for s in tracks_of])
    return dict(swaps=swaps, expected=expected, actual=actual,
                unmatched_samples=unmatched_samples)


def score_identity(traj, obs, tol_m=0.005, resolve_m=0.028):
    """Identity swaps and trajectory breaks of ``traj`` against truth.

    A sample belongs to the nearest true marker within ``tol_m``; it is *resolved* when every
    other true marker is at least ``resolve_m`` (default two 14 mm marker diameters) from
    that marker, so the two cannot share blobs.

    - ``swaps``: trajectories holding resolved samples of two or more true markers.
    - ``swaps_any``: trajectories holding samples (resolved or not) of two or more markers.
    - ``breaks``: for each true marker, each change of trajectory between consecutive samples
      of that marker (its samples in time order, from whatever trajectory).
    - ``breaks_at_occlusion``: breaks where, in some frame from the last sample of the old
      trajectory to the first of the new one (inclusive), the marker has its own blob in
      fewer than 2 cameras (``reconstructable`` is False): the break coincides with a true
      occlusion (or merge).
    - ``unjustified``: the other breaks, as (marker, frame of the old sample, frame of the new).
    """
    T, M = traj.positions.shape[:2]
    f0 = traj.first_frame
    truth = obs.positions[f0:f0 + T]
    need = reconstructable(obs)[f0:f0 + T]
    owner = np.full((T, M), -1)
    resolved = np.zeros((T, M), bool)
    for t in range(T):
        ok = np.flatnonzero(np.all(np.isfinite(traj.positions[t]), axis=1))
        if not ok.size:
            continue
        m = match_points(traj.positions[t, ok], truth[t], tol_m)
        owner[t, ok] = m
        tr = truth[t]
        d = np.linalg.norm(tr[:, None] - tr[None], axis=2)
        np.fill_diagonal(d, np.inf)
        near = np.nanmin(np.where(np.isfinite(d), d, np.inf), axis=1)      # (M_true,)
        has = m >= 0
        resolved[t, ok[has]] = near[m[has]] >= resolve_m
    swaps = swaps_any = 0
    for k in range(M):
        o = owner[:, k]
        swaps_any += len(set(o[o >= 0].tolist())) > 1
        swaps += len(set(o[resolved[:, k]].tolist())) > 1
    breaks = at_occl = 0
    unjust = []
    for i in range(truth.shape[1]):
        tt, kk = np.nonzero(owner == i)
        if not tt.size:
            continue
        order = np.lexsort((kk, tt))
        tt, kk = tt[order], kk[order]
        for j in np.flatnonzero(kk[1:] != kk[:-1]):
            a, b = tt[j], tt[j + 1]
            breaks += 1
            if not need[a:b + 1, i].all():
                at_occl += 1
            else:
                unjust.append((i, int(a + f0), int(b + f0)))
    return dict(swaps=swaps, swaps_any=swaps_any, breaks=breaks, breaks_at_occlusion=at_occl,
                unjustified=unjust)


def clean_point_errors(clouds, obs):
    """3D errors (m) of points whose every blob is an unmerged blob of one true marker."""
    det = obs.detections
    sl = det.frame_slices()
    errs = []
    for cl in clouds.clouds:
        if not len(cl) or cl.frame not in sl:
            continue
        s = sl[cl.frame]
        cams = det.camera[s]
        rows_of = [np.flatnonzero(cams == c) + s.start for c in range(cl.n_cameras)]
        for k in range(len(cl)):
            ids = [obs.marker_id[rows_of[c][cl.obs[k, c]]]
                   for c in np.flatnonzero(cl.cameras[k])]
            merged = [obs.merged_row[rows_of[c][cl.obs[k, c]]]
                      for c in np.flatnonzero(cl.cameras[k])]
            if len(set(ids)) == 1 and ids[0] >= 0 and not any(merged):
                errs.append(np.linalg.norm(cl.points[k] - obs.positions[cl.frame, ids[0]]))
    return np.array(errs)

"""Offline reprocessing of a simulated 8-camera, 120 Hz session on the hw_sim figure.

Input: the 2D detection table with blob areas (``--no-area``: without, as from a plain CSV).
Scene: ``hw_sim.scenes.figure`` (the articulated humanoid of ``hw_sim.articulated``: 45
markers on 15 segments whose capsules hide markers), ``hw_sim.rig.make_rig(8)`` with mild
distortion, ``hw_sim.observe.observe`` with occlusion on, 0.05 px centroid noise and
spurious blobs making 1% of all blobs (the Poisson rate per camera-frame is set from the
scene's mean visible blob count). Input is the 2D detection table: blob detection time is
NOT included (see benchmarks/bench_blobs.py for its cost per frame).

Prints: reconstruction (found / spurious / 3D RMS), tracking (identity swaps, trajectory
breaks against true occlusions: tests/reconstruct/simdata.score_identity), gap filling with
the figure's segment map (oracle labels: trajectories relabelled by truth), and the wall
time of ``reconstruct_sequence`` relative to the session duration with ``--workers``
workers, with a 1-worker run of the first 10 s as the baseline for the parallel speed-up.
Run: .venv/bin/python benchmarks/bench_reconstruct.py [--seconds 60] [--workers 2]
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from capture.detections import Detections2D  # noqa: E402
from hw_sim.articulated import humanoid  # noqa: E402
from hw_sim.observe import observe  # noqa: E402
from hw_sim.rig import make_rig  # noqa: E402
from hw_sim.scenes import figure  # noqa: E402
from reconstruct.pipeline import (ReconstructionConfig, postprocess,  # noqa: E402
                                  reconstruct_sequence)
from reconstruct.tracking import track  # noqa: E402
from reconstruct.types import Trajectories  # noqa: E402
from tests.reconstruct.simdata import (clean_point_errors, match_points,  # noqa: E402
                                       score_clouds, score_identity)

RATE_HZ = 120.0
NOISE_PX = 0.05
SPURIOUS_FRACTION = 0.01
DIST = (-0.05, 0.01, 0.0, 0.0, 0.0)


def spurious_rate(rig, scene, fraction, rng):
    """Spurious blobs per camera-frame making ``fraction`` of all blobs."""
    probe = observe(rig, scene, rng=rng, noise_px=0.0)
    per_cam_frame = len(probe.detections) / (scene.n_frames * len(rig))
    return fraction / (1 - fraction) * per_cam_frame


def cpu_s() -> float:
    """CPU seconds of this process and its finished children (the worker processes)."""
    me = resource.getrusage(resource.RUSAGE_SELF)
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + ch.ru_utime + ch.ru_stime


def oracle_labelled(traj, obs, tol_m=0.005):
    """(T, M_true, 3) tracked samples relabelled by their true marker (gaps NaN)."""
    T = traj.n_frames
    truth = obs.positions[traj.first_frame:traj.first_frame + T]
    out = np.full(truth.shape, np.nan)
    for t in range(T):
        ok = np.flatnonzero(np.all(np.isfinite(traj.positions[t]), axis=1))
        m = match_points(traj.positions[t, ok], truth[t], tol_m)
        out[t, m[m >= 0]] = traj.positions[t, ok[m >= 0]]
    return out, truth


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-area", action="store_true",
                    help="drop the blob areas (as from a plain frame,camera,x,y CSV): no "
                         "merged-blob test in the correspondence")
    a = ap.parse_args()
    T = int(a.seconds * RATE_HZ)
    rig = make_rig(8, dist=DIST, rng=a.seed)
    scene = figure(T, RATE_HZ, a.seed + 1)
    fig = humanoid(np.random.default_rng(a.seed + 1))          # the same figure (same rng)
    if tuple(fig.marker_names) != scene.labels:
        raise RuntimeError("humanoid(rng) no longer reproduces figure()'s markers")
    rate = spurious_rate(rig, scene, SPURIOUS_FRACTION, a.seed + 3)
    obs = observe(rig, scene, rng=a.seed + 2, noise_px=NOISE_PX, spurious_per_frame=rate)
    det = obs.detections
    if a.no_area:
        det = Detections2D(frame=det.frame, camera=det.camera, xy=det.xy,
                           camera_names=det.camera_names, rate_hz=det.rate_hz)
    print(f"input: 2D detections {'WITHOUT' if a.no_area else 'with'} blob areas")
    print(f"scene: hw_sim figure, {scene.n_markers} markers on {fig.n_segments} segments, "
          f"{T} frames ({a.seconds:g} s at {RATE_HZ:g} Hz), 8 cameras, {len(det)} blobs, "
          f"spurious blobs {(obs.marker_id < 0).mean():.2%} ({rate:.3f}/camera-frame), "
          f"occluded {obs.occluded.sum() / obs.visible.shape[0] / 8:.1f} of "
          f"{scene.n_markers} markers per camera-frame, merged blobs "
          f"{obs.merged_row.mean():.2%} of rows; noise {NOISE_PX} px")
    cfg = ReconstructionConfig()
    load0 = os.getloadavg()[0]
    c0 = cpu_s()
    t0 = time.perf_counter()
    clouds, traj = reconstruct_sequence(det, rig, cfg, workers=a.workers)
    wall = time.perf_counter() - t0
    cpu = cpu_s() - c0
    t0 = time.perf_counter()
    track(clouds, cfg.tracking)
    wall_track = time.perf_counter() - t0
    s = score_clouds(clouds, obs)
    e = s.pop("errors")
    ce = clean_point_errors(clouds, obs)
    print(f"reconstructed {s['found']}/{s['need']} = {s['found'] / s['need']:.4%} of markers "
          f"seen (own blob) by >= 2 cameras; spurious 3D points {s['spurious']}/{s['points']} "
          f"= {s['spurious'] / s['points']:.4%} (> 5 mm from every true marker)")
    print(f"3D error vs truth: RMS {1000 * np.sqrt(np.mean(e ** 2)):.3f} mm, median "
          f"{1000 * np.median(e):.3f} mm over all points within 5 mm of a marker; RMS "
          f"{1000 * np.sqrt(np.mean(ce ** 2)):.3f} mm over the {ce.size} points built only "
          f"from unmerged blobs of one marker")
    st = score_identity(traj, obs)
    un = st.pop("unjustified")
    print(f"tracking: {traj.n_markers} trajectories; identity swaps {st['swaps']} (resolved "
          f"samples: no other marker within 28 mm), {st['swaps_any']} counting unresolved "
          f"samples; breaks {st['breaks']}, at a true occlusion {st['breaks_at_occlusion']}, "
          f"elsewhere {len(un)}")
    if un:
        P = obs.positions
        near = []
        for i, f_a, f_b in un:
            d = np.linalg.norm(P[f_a:f_b + 1] - P[f_a:f_b + 1, i:i + 1], axis=2)
            d[:, i] = np.inf
            near.append(1000 * d.min())
        near = np.array(near)
        print(f"  breaks elsewhere: {int(np.sum(near < 28))} with another marker within 28 mm "
              f"(closest {near.min():.1f} mm), {int(np.sum(near >= 28))} not; first: {un[:6]}")
    # gap filling with the segment map, on oracle-labelled trajectories
    lab, truth = oracle_labelled(traj, obs)
    labels = scene.labels
    segs = [[labels[m] for m in np.flatnonzero(fig.marker_segment == k)]
            for k in range(fig.n_segments)]
    base = Trajectories(positions=lab, rate_hz=RATE_HZ, labels=labels)
    for name, c, sg in (("spline <= 10 frames", ReconstructionConfig(fill_max_gap=10), None),
                        ("rigid (segments)", ReconstructionConfig(), segs),
                        ("rigid + spline <= 10", ReconstructionConfig(fill_max_gap=10), segs)):
        f = postprocess(base, c, sg)
        fe = np.linalg.norm(f.positions[f.filled] - truth[f.filled], axis=1)
        n_gap = int((~base.present()).sum())
        print(f"gap fill {name}: filled {f.filled.sum()} of {n_gap} missing samples, error vs "
              f"truth RMS {1000 * np.sqrt(np.mean(fe ** 2)):.2f} mm, 95th pct "
              f"{1000 * np.percentile(fe, 95):.2f} mm" if fe.size else
              f"gap fill {name}: nothing filled")
    print(f"wall time {wall:.1f} s with {a.workers} workers = {wall / a.seconds:.3f} x the "
          f"session duration ({T / wall:.0f} frames/s; load average before {load0:.2f} on "
          f"{os.cpu_count()} cores); 2D detections in, blob detection not included")
    print(f"CPU time {cpu:.1f} s = {cpu / a.seconds:.3f} CPU-s per session second: on "
          f"{a.workers} unshared cores >= {cpu / a.workers / a.seconds:.3f} x the session "
          f"duration; tracking (serial) {wall_track:.1f} s of the wall time")
    sub = det.frame < int(min(10.0, a.seconds) * RATE_HZ)
    d10 = Detections2D(frame=det.frame[sub], camera=det.camera[sub], xy=det.xy[sub],
                       camera_names=det.camera_names, rate_hz=RATE_HZ,
                       area_px=None if det.area_px is None else det.area_px[sub])
    n10 = int(sub.sum() and det.frame[sub].max() + 1)
    t0 = time.perf_counter()
    reconstruct_sequence(d10, rig, cfg, workers=1)
    w1 = time.perf_counter() - t0
    print(f"baseline 1 worker: {n10 / w1:.0f} frames/s; parallel speed-up "
          f"{(T / wall) / (n10 / w1):.2f}x")


if __name__ == "__main__":
    main()

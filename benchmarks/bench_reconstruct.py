"""Offline reprocessing of a simulated 8-camera, 120 Hz session: accuracy and wall time.

Scene: the hw_sim articulated figure when ``hw_sim.articulated`` is present, else
``moving_markers`` (40 markers on smooth paths, capsule occluders); occlusion on, 0.05 px
noise, ~1% spurious blobs. Reports reconstruction (found / spurious / 3D RMS), tracking
(identity swaps, trajectory breaks against true occlusions) and the wall time of
``reconstruct_sequence`` relative to the session duration with 2 workers, with a 1-worker
run of the first 10 s as the baseline for the parallel speed-up.
Run: .venv/bin/python benchmarks/bench_reconstruct.py [--seconds 60] [--workers 2]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from capture.detections import Detections2D  # noqa: E402
from hw_sim.observe import observe  # noqa: E402
from hw_sim.rig import make_rig  # noqa: E402
from reconstruct.pipeline import ReconstructionConfig, reconstruct_sequence  # noqa: E402
from tests.reconstruct.simdata import (figure_scene, moving_markers, score_clouds,  # noqa: E402
                                       score_tracks)

RATE_HZ = 120.0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    T = int(a.seconds * RATE_HZ)
    rig = make_rig(8, dist=(-0.05, 0.01, 0, 0, 0), rng=a.seed)
    scene = figure_scene(T, RATE_HZ, rng=a.seed + 1)
    name = "hw_sim figure"
    if scene is None:
        scene = moving_markers(40, T, RATE_HZ, rng=a.seed + 1, speed_mps=1.5)
        name = "moving_markers (figure not available)"
    obs = observe(rig, scene, rng=a.seed + 2, noise_px=0.05, spurious_per_frame=0.35)
    det = obs.detections
    print(f"scene: {name}, {scene.n_markers} markers, {T} frames ({a.seconds:g} s at "
          f"{RATE_HZ:g} Hz), {len(det)} blobs, spurious blobs {(obs.marker_id < 0).mean():.2%},"
          f" occluded {obs.occluded.mean():.1%} of marker-camera-frames")
    cfg = ReconstructionConfig()
    t0 = time.perf_counter()
    clouds, traj = reconstruct_sequence(det, rig, cfg, workers=a.workers)
    wall = time.perf_counter() - t0
    s = score_clouds(clouds, obs)
    e = s.pop("errors")
    st = score_tracks(traj, obs, cfg.tracking.max_gap_frames)
    print(f"reconstructed {s['found']}/{s['need']} = {s['found'] / s['need']:.4%} of markers "
          f"seen by >= 2 cameras; spurious 3D points {s['spurious']}/{s['points']} = "
          f"{s['spurious'] / s['points']:.4%}; 3D RMS {1000 * np.sqrt(np.mean(e ** 2)):.3f} mm")
    broken = int(np.sum(st["actual"] != st["expected"]))
    print(f"tracking: {traj.n_markers} trajectories, identity swaps {st['swaps']}, markers "
          f"whose trajectory count differs from their true visibility runs: {broken} "
          f"(tracks {st['actual'].sum()} vs runs {st['expected'].sum()}), samples on no "
          f"true marker {st['unmatched_samples']}")
    print(f"wall time {wall:.1f} s with {a.workers} workers = {wall / a.seconds:.2f} x the "
          f"session duration ({T / wall:.0f} frames/s)")
    sub = det.frame < int(min(10.0, a.seconds) * RATE_HZ)
    d10 = Detections2D(frame=det.frame[sub], camera=det.camera[sub], xy=det.xy[sub],
                       camera_names=det.camera_names, rate_hz=RATE_HZ)
    n10 = int(sub.sum() and det.frame[sub].max() + 1)
    t0 = time.perf_counter()
    reconstruct_sequence(d10, rig, cfg, workers=1)
    w1 = time.perf_counter() - t0
    print(f"baseline 1 worker: {n10 / w1:.0f} frames/s; parallel speed-up "
          f"{(T / wall) / (n10 / w1):.2f}x")


if __name__ == "__main__":
    main()

"""Wand calibration benchmark: accuracy vs hw_sim truth and solve time, 8/12/16 cameras.

Baseline in the same run: the initial poses (essential matrix + PnP chain, before bundle
adjustment) -- accuracy ratio bundle/initial is printed.
Usage: .venv/bin/python benchmarks/bench_calibration.py [n_frames] [cams,...]
"""
import sys
import time

import numpy as np

from calibration.camera import Camera
from calibration.init_extrinsics import initial_poses, normalized
from calibration.wand import calibrate_wand
from calibration.wand_detect import detect_wand
from hw_sim.observe import observe
from hw_sim.rig import make_rig
from hw_sim.scenes import wand


def errors(Rs, ts, truth):
    R0, t0 = truth[0].R, truth[0].t
    dc, da = [], []
    for R, t, ct in zip(Rs, ts, truth):
        Rw, tw = R @ R0, R @ t0 + t
        dc.append(np.linalg.norm(-Rw.T @ tw - ct.center) * 1000)
        dR = Rw @ ct.R.T
        da.append(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    return max(dc), max(da)


def main():
    T = int(sys.argv[1]) if len(sys.argv) > 1 else 2000
    cams = [int(c) for c in sys.argv[2].split(",")] if len(sys.argv) > 2 else [8, 12, 16]
    noise = 0.05
    for C in cams:
        rig = make_rig(C, rng=1)
        ob = observe(rig, wand(T, rng=2), rng=3, noise_px=noise)
        init = [Camera(name=c.name, size=c.size, K=c.K, dist=c.dist) for c in rig]
        t0 = time.perf_counter()
        res = calibrate_wand(ob.detections, initial_intrinsics=init)
        dt = time.perf_counter() - t0
        obs = detect_wand(ob.detections, init, (0, 250, 500))
        ip, _ = initial_poses(normalized(obs.xy, init), spacing_m=obs.spacing_m, symmetric=True)
        c0, a0 = errors(ip.R, ip.t, rig)
        c1, a1 = errors([c.R for c in res.rig], [c.t for c in res.rig], rig)
        r = res.report
        print(f"{C:2d} cams {T} frames noise {noise} px: solve {dt:.1f} s | centre max "
              f"{c1:.3f} mm (initial {c0:.2f}, ratio {c1 / c0:.3f}) | angle max {a1:.4f} deg "
              f"(initial {a0:.3f}) | wand {r.wand_mean_mm:.3f} mm SD {r.wand_sd_mm:.3f} mm | "
              f"rms/coord {np.max(r.rms_px) / np.sqrt(2):.4f} px (noise {noise})", flush=True)


if __name__ == "__main__":
    main()

"""Wand calibration benchmark: accuracy vs hw_sim truth, solve time, and the wand-SD budget.

Per rig size (8/12/16 cameras, 2,000 frames, 0.05 px blob noise, no pose prior):
- solve time with the analytic sparse Jacobian, and the same calibration with the numeric
  (finite-difference, ``jac_sparsity``) Jacobian measured in the same run: ratio numeric/analytic;
  for 8 cameras (all sizes with --old-all) also the previous path (numeric Jacobian, threaded
  BLAS, strict ftol in every round);
- camera centre / orientation errors vs truth (initial poses before bundle adjustment as the
  accuracy baseline);
- wand length SD as the report gives it (ML triangulation with the estimated calibration),
  the first-order floor from the noise alone, the SD with the TRUE calibration on the same
  noisy detections (pure triangulation noise), and the SD with the estimated calibration on
  the exact (noise-free) projections (pure calibration error).
Last row: 8 cameras with ~2 spurious blobs per image, the recovery pass off vs on.
Usage: .venv/bin/python benchmarks/bench_calibration.py [n_frames] [cams,...] [--no-numeric]
       [--no-clutter] [--old-all]
"""
import sys
import time

import numpy as np

from calibration.camera import Camera
from calibration.init_extrinsics import initial_poses, normalized, triangulate
from calibration.points import refine_points
from calibration.wand import calibrate_wand
from calibration.wand_detect import detect_wand
from hw_sim.observe import observe
from hw_sim.rig import make_rig
from hw_sim.scenes import wand


# the bundle settings before the analytic Jacobian (commit 5fadf77): numeric Jacobian, BLAS
# threads left at the library default, ftol 1e-8 in the outlier rounds too
OLD_PATH = dict(ftol_outlier_rounds=1e-8, blas_threads=None)


def errors(Rs, ts, truth):
    R0, t0 = truth[0].R, truth[0].t
    dc, da = [], []
    for R, t, ct in zip(Rs, ts, truth):
        Rw, tw = R @ R0, R @ t0 + t
        dc.append(np.linalg.norm(-Rw.T @ tw - ct.center) * 1000)
        dR = Rw @ ct.R.T
        da.append(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    return max(dc), max(da)


def wand_sd_mm(xy, cams):
    """SD (mm) of the end-to-end length triangulated (DLT + ML) from xy (C, T, M, 2)."""
    n = normalized(xy, cams)
    R = np.stack([c.R for c in cams])
    t = np.stack([c.t for c in cams])
    use = np.ones(len(cams), bool)
    ends = [refine_points(cams, xy[:, :, m], triangulate(n[:, :, m], R, t, use))
            for m in (0, -1)]
    L = np.linalg.norm(ends[1] - ends[0], axis=1) * 1000
    return float(np.nanstd(L, ddof=1))


def main():
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    numeric = "--no-numeric" not in sys.argv
    T = int(args[0]) if args else 2000
    cams = [int(c) for c in args[1].split(",")] if len(args) > 1 else [8, 12, 16]
    noise = 0.05
    for C in [c for c in cams if c > 0]:   # "0" runs only the clutter row
        rig = make_rig(C, rng=1)
        ob = observe(rig, wand(T, rng=2), rng=3, noise_px=noise)
        init = [Camera(name=c.name, size=c.size, K=c.K, dist=c.dist) for c in rig]
        t0 = time.perf_counter()
        res = calibrate_wand(ob.detections, initial_intrinsics=init)
        dt = time.perf_counter() - t0
        line = f"{C:2d} cams {T} frames noise {noise} px: solve {dt:.1f} s (analytic Jacobian)"
        if numeric:
            t0 = time.perf_counter()
            resn = calibrate_wand(ob.detections, initial_intrinsics=init, jacobian="numeric")
            dtn = time.perf_counter() - t0
            cn, an = errors([c.R for c in resn.rig], [c.t for c in resn.rig], rig)
            line += (f", numeric-Jacobian baseline {dtn:.1f} s, ratio numeric/analytic "
                     f"{dtn / dt:.2f} (numeric result: centre {cn:.3f} mm, angle {an:.4f} deg)")
        if numeric and (C == 8 or "--old-all" in sys.argv):
            t0 = time.perf_counter()
            calibrate_wand(ob.detections, initial_intrinsics=init, jacobian="numeric",
                           bundle_options=OLD_PATH)
            dto = time.perf_counter() - t0
            line += (f"\n   previous path (numeric Jacobian, threaded BLAS, ftol 1e-8 in every "
                     f"round) {dto:.1f} s, ratio previous/analytic {dto / dt:.1f}")
        print(line, flush=True)
        obs = detect_wand(ob.detections, init, (0, 250, 500))
        ip, _ = initial_poses(normalized(obs.xy, init), spacing_m=obs.spacing_m, symmetric=True)
        c0, a0 = errors(ip.R, ip.t, rig)
        c1, a1 = errors([c.R for c in res.rig], [c.t for c in res.rig], rig)
        r = res.report
        print(f"   centre max {c1:.3f} mm (initial {c0:.2f}, ratio {c1 / c0:.4f}) | angle max "
              f"{a1:.4f} deg (initial {a0:.3f}) | rms/coord {np.max(r.rms_px) / np.sqrt(2):.4f}"
              f" px, noise estimate {r.noise_px:.4f} px (injected {noise})", flush=True)
        # the wand-SD budget: camera-frames seeing all three markers, known correspondence
        lab = np.transpose(ob.labelled_xy(), (1, 0, 2, 3))
        tru = np.transpose(ob.projections, (1, 0, 2, 3))
        full = np.all(np.isfinite(lab), axis=(2, 3))[..., None, None]
        sd_noise = wand_sd_mm(np.where(full, lab, np.nan), list(rig))
        sd_cal = wand_sd_mm(np.where(full, tru, np.nan), list(res.rig))
        print(f"   wand {r.wand_mean_mm:.3f} mm SD {r.wand_sd_mm:.3f} mm (report) | floor from "
              f"noise {r.wand_sd_floor_mm:.3f} mm | SD with TRUE calibration {sd_noise:.3f} mm | "
              f"SD of exact projections with the estimated calibration {sd_cal:.5f} mm",
              flush=True)


def clutter_row(T, noise, spurious=2.0):
    """8 cameras, 3-marker wand, ~2 spurious blobs per image: recovery pass off vs on."""
    rig = make_rig(8, rng=1)
    ob = observe(rig, wand(T, rng=2), rng=3, noise_px=noise, spurious_per_frame=spurious)
    init = [Camera(name=c.name, size=c.size, K=c.K, dist=c.dist) for c in rig]
    for gate in (None, 2.0):
        t0 = time.perf_counter()
        res = calibrate_wand(ob.detections, initial_intrinsics=init, recover_gate_px=gate)
        dt = time.perf_counter() - t0
        c1, a1 = errors([c.R for c in res.rig], [c.t for c in res.rig], rig)
        r = res.report
        print(f" 8 cams, {spurious:g} spurious blobs/image, recovery "
              f"{'off' if gate is None else f'{gate:g} px'}: solve {dt:.1f} s | centre max "
              f"{c1:.3f} mm | angle max {a1:.4f} deg | observations/camera {r.n_obs.mean():.0f}"
              f" | wand SD {r.wand_sd_mm:.3f} mm (floor {r.wand_sd_floor_mm:.3f})", flush=True)


if __name__ == "__main__":
    main()
    if "--no-clutter" not in sys.argv:
        clutter_row(int(next((a for a in sys.argv[1:] if a.isdigit()), 2000)), 0.05)

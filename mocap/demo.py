"""The end-to-end demo on the simulated rig (app layer: wiring only, no algorithm).

Stages, each the code a lab would run on its own data:

1. ``hw_sim`` builds an 8-camera rig (1280x1024) around a 4 x 4 x 2.5 m volume.
2. A 500 mm three-marker wand is waved through the volume; the cameras report blob
   centroids (object mode, 0.05 px noise) and ``calibration.wand.calibrate_wand`` solves the
   extrinsics from those 2D detections alone (intrinsics as from a prior intrinsic
   calibration). An L-frame on the floor, reconstructed with the new calibration and
   identified by its geometry, sets the world origin, axes and floor
   (``calibration.static_markers`` + ``calibration.world.align_world``).
3. The articulated figure (45 markers, 15 body segments that hide markers) is rendered as
   8-bit IR frames with sensor noise; ``reconstruct.blobs`` finds the sub-pixel centroids
   (compared with the rendered truth: mean blob error, px).
4. ``reconstruct.pipeline.reconstruct_sequence`` triangulates, tracks, fills and filters
   with the *wand* calibration; 3D points are compared with the true marker positions.
5. The trajectories are written as C3D and TRC (``reconstruct.marker_files``).
6. ``skeleton.app.run_skeleton`` solves a skeleton from the unlabelled trajectories (no
   predefined model) and writes BVH and a skeleton JSON.

Conventions: docs/conventions.md.
"""
from __future__ import annotations

import os
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from calibration.rig_io import save_rig
from calibration.wand import calibrate_wand
from calibration.static_markers import static_points
from calibration.world import align_world
from capture.detections import Detections2D
from hw_sim.observe import observe
from hw_sim.render import render_scene
from hw_sim.rig import make_rig
from hw_sim.scenes import MarkerScene, figure, wand
from reconstruct.blobs import BlobConfig, detect_frames
from reconstruct.marker_files import MarkerData, write_markers
from skeleton.app import run_skeleton, write_outputs
from reconstruct.pipeline import ReconstructionConfig, reconstruct_sequence

__all__ = ["DemoConfig", "DemoResult", "run_demo", "L_FRAME_M"]

#: L-frame marker positions in the world frame (m): origin, x arm 0.5 m, y arm 0.3 m, and a
#: fourth marker on the x arm that makes the point set asymmetric (identification by shape).
#: A reconstructed point counts as a marker when within this distance of it (m): an order of
#: magnitude above the expected error, below the closest marker spacing on the figure.
MATCH_GATE_M = 0.005

L_FRAME_M = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.3, 0.0]])


@dataclass(frozen=True, kw_only=True)
class DemoConfig:
    """Demo settings. ``figure_frames`` at ``rate_hz`` sets the length of the take."""

    n_cameras: int = 8
    rate_hz: float = 120.0
    figure_frames: int = 240
    wand_frames: int = 1500
    wand_mm: tuple[float, ...] = (0.0, 250.0, 500.0)
    noise_px: float = 0.05
    seed: int = 0
    workers: int | None = None

    def __post_init__(self):
        if self.n_cameras < 2:
            raise ValueError(f"n_cameras={self.n_cameras}, expected >= 2")
        # the skeleton needs motion: below ~100 frames (0.8 s) the figure barely moves
        if self.figure_frames < 100 or self.wand_frames < 100:
            raise ValueError(f"figure_frames={self.figure_frames} (>= 100), "
                             f"wand_frames={self.wand_frames} (>= 100)")
        if self.workers is not None and not 1 <= self.workers <= 64:
            raise ValueError(f"workers={self.workers}, expected 1..64")


@dataclass(frozen=True, kw_only=True)
class DemoResult:
    """What the demo measured, and where it wrote its files."""

    n_cameras: int
    n_frames: int
    n_markers: int
    blob_error_px: float            # mean distance detected centroid -> rendered truth
    blob_recall: float              # visible markers found as blobs
    calib_centre_error_mm: float    # max camera-centre error of the wand calibration
    calib_reproj_px: float
    lframe_rms_mm: float
    reconstructed_fraction: float   # marker-frames seen by >= 2 cameras that were reconstructed
    spurious_fraction: float        # reconstructed points matching no true marker
    rms_3d_mm: float                # reconstructed points vs truth (one-to-one, 5 mm gate)
    n_trajectories: int
    n_segments: int                 # skeleton segments found (the figure has 15)
    marker_deviation_mm: float      # mean measured-to-fitted marker distance (thesis table)
    joint_error_mm: float           # median distance of solved joints to the nearest true joint
    files: dict = field(default_factory=dict)
    stage_s: dict = field(default_factory=dict)
    wall_s: float = 0.0

    def table(self) -> str:
        rows = [("cameras", f"{self.n_cameras}"),
                ("frames", f"{self.n_frames}"),
                ("markers", f"{self.n_markers}"),
                ("mean blob error", f"{self.blob_error_px:.4f} px "
                                    f"({100 * self.blob_recall:.1f}% of visible blobs found)"),
                ("calibration (wand)", f"reprojection {self.calib_reproj_px:.3f} px, "
                                       f"max camera-centre error {self.calib_centre_error_mm:.2f} mm"),
                ("L-frame fit", f"{self.lframe_rms_mm:.2f} mm RMS"),
                ("reconstructed", f"{100 * self.reconstructed_fraction:.2f}% of markers in >= 2 views, "
                                  f"{100 * self.spurious_fraction:.2f}% spurious points"),
                ("3D RMS error vs truth", f"{self.rms_3d_mm:.3f} mm"),
                ("trajectories", f"{self.n_trajectories}"),
                ("skeleton", f"{self.n_segments} segments (truth 15), marker deviation "
                             f"{self.marker_deviation_mm:.2f} mm, joint centres "
                             f"{self.joint_error_mm:.1f} mm from the nearest true joint (median)"),
                ("wall time", f"{self.wall_s:.1f} s (" + ", ".join(
                    f"{k} {v:.1f}" for k, v in self.stage_s.items()) + ")")]
        w = max(len(k) for k, _ in rows)
        lines = [f"{k:<{w}}  {v}" for k, v in rows]
        lines += [f"{'wrote':<{w}}  {p}" for p in self.files.values()]
        return "\n".join(lines)


def _render_detect(args):
    """Worker: render frames ``idx`` of the scene, detect blobs, score them against truth."""
    rig, scene, idx, seed, cfg = args
    fi, ci, pts, ar = [], [], [], []
    err_sum, n_match, n_vis = 0.0, 0, 0
    for t in idx:
        sf = render_scene(rig, scene, int(t), rng=np.random.default_rng([seed, int(t)]))
        for c, b in enumerate(detect_frames(list(sf.images), cfg)):
            fi.append(np.full(len(b), int(t), np.int64))
            ci.append(np.full(len(b), c, np.int64))
            pts.append(b.xy)
            ar.append(b.area_px)
            truth = sf.xy[c][sf.visible[c]]
            n_vis += len(truth)
            if len(truth) and len(b):
                d, _ = cKDTree(b.xy).query(truth, distance_upper_bound=1.0)
                ok = np.isfinite(d)
                err_sum += float(d[ok].sum())
                n_match += int(ok.sum())
    return (np.concatenate(fi), np.concatenate(ci), np.concatenate(pts),
            np.concatenate(ar), err_sum, n_match, n_vis)


def _centre_error_mm(a, b) -> float:
    return 1000 * max(float(np.linalg.norm(ca.center - cb.center)) for ca, cb in zip(a, b))


def run_demo(out_dir, config: DemoConfig | None = None,
             progress: Callable[[str], None] | None = None) -> DemoResult:
    """Run the whole simulated pipeline; write ``rig.toml``, ``markers.c3d``/``.trc``,
    ``skeleton.bvh``/``.json``."""
    cfg = config or DemoConfig()
    say = progress or (lambda s: None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    g = np.random.default_rng(cfg.seed)
    seeds = g.integers(2**31, size=8)
    workers = cfg.workers or min(os.cpu_count() or 1, 4)
    t_start = time.perf_counter()
    stage = {}

    # 1-2. rig and wand calibration from 2D detections alone
    t0 = time.perf_counter()
    true_rig = make_rig(cfg.n_cameras, rng=seeds[0])
    say(f"wand: {cfg.wand_frames} frames, {cfg.n_cameras} cameras")
    wscene = wand(cfg.wand_frames, spacing_mm=cfg.wand_mm, rate_hz=cfg.rate_hz, rng=seeds[1])
    wobs = observe(true_rig, wscene, rng=seeds[2], noise_px=cfg.noise_px)
    cal = calibrate_wand(wobs.detections, initial_intrinsics=true_rig, wand_mm=cfg.wand_mm,
                         progress=lambda s: say(f"  {s}"))
    if not cal.ok:
        raise RuntimeError(f"wand calibration failed: {cal.reason}")
    # world frame from an L-frame lying on the floor at the origin
    lscene = MarkerScene(positions=np.repeat(L_FRAME_M[None], 30, axis=0),
                         marker_diameter_m=np.full(len(L_FRAME_M), 0.014),
                         rate_hz=cfg.rate_hz, labels=("origin", "x_end", "y_end", "x_mid"))
    lobs = observe(true_rig, lscene, rng=seeds[3], noise_px=cfg.noise_px)
    sp = static_points(lobs.detections, cal.rig)
    world = align_world(cal.rig, sp.points, L_FRAME_M)
    if not world.ok:
        raise RuntimeError(f"world alignment failed: {world.reason}")
    rig, lrms = world.rig, world.rms_m
    rig_path = out / "rig.toml"
    save_rig(rig, rig_path)
    cal_err = _centre_error_mm(rig, true_rig)
    reproj = float(np.sqrt(np.nanmean(np.asarray(cal.residual_px) ** 2))) \
        if cal.residual_px is not None else float("nan")
    stage["calibration"] = time.perf_counter() - t0
    say(f"calibrated: max camera-centre error {cal_err:.2f} mm")

    # 3. render the figure as IR frames and detect blobs
    t0 = time.perf_counter()
    scene = figure(cfg.figure_frames, cfg.rate_hz, rng=seeds[4])
    T = cfg.figure_frames
    chunks = np.array_split(np.arange(T), max(1, min(T, 4 * workers)))
    jobs = [(true_rig, scene, ch, int(seeds[5]), BlobConfig()) for ch in chunks]
    parts = []
    say(f"rendering and detecting {T} frames x {cfg.n_cameras} cameras on {workers} workers")
    if workers > 1:
        with ProcessPoolExecutor(workers) as ex:
            for i, p in enumerate(ex.map(_render_detect, jobs)):
                parts.append(p)
                say(f"  frames {100 * (i + 1) // len(jobs)}%")
    else:
        parts = [_render_detect(j) for j in jobs]
    det = Detections2D(frame=np.concatenate([p[0] for p in parts]),
                       camera=np.concatenate([p[1] for p in parts]),
                       xy=np.concatenate([p[2] for p in parts]),
                       camera_names=rig.names, rate_hz=cfg.rate_hz,
                       area_px=np.concatenate([p[3] for p in parts]).astype(np.float64))
    n_match = sum(p[5] for p in parts)
    blob_err = sum(p[4] for p in parts) / max(n_match, 1)
    recall = n_match / max(sum(p[6] for p in parts), 1)
    stage["frames+blobs"] = time.perf_counter() - t0

    # 4. reconstruction with the wand calibration
    t0 = time.perf_counter()
    say("reconstructing")
    clouds, traj = reconstruct_sequence(det, rig, ReconstructionConfig(fill_max_gap=10),
                                        workers=workers)
    truth = scene.positions
    seen2 = _seen_by_two(true_rig, scene)
    errs, n_rec, n_pts, n_spur = [], 0, 0, 0
    for c in clouds.clouds:
        t = c.frame
        n_pts += len(c.points)
        want = np.flatnonzero(seen2[t])
        d = _match_one_to_one(c.points, truth[t], want, gate_m=MATCH_GATE_M)
        n_rec += int(np.isfinite(d).sum())
        errs.append(d[np.isfinite(d)])
        n_spur += len(c.points) - _n_matched_any(c.points, truth[t], MATCH_GATE_M)
    errs = np.concatenate(errs) if errs else np.zeros(0)
    frac = n_rec / max(int(seen2.sum()), 1)
    spurious = n_spur / max(n_pts, 1)
    rms = 1000 * float(np.sqrt(np.mean(errs ** 2))) if errs.size else float("nan")
    stage["reconstruction"] = time.perf_counter() - t0

    # 5. marker files
    md = MarkerData(positions=traj.positions, labels=traj.labels, rate_hz=traj.rate_hz,
                    residual_mm=traj.residual_mm, first_frame=traj.first_frame + 1)
    files = {"calibration": rig_path}
    for suffix in (".c3d", ".trc"):
        p = out / f"markers{suffix}"
        write_markers(md, p)
        files[suffix] = p
    # 6. skeleton without a predefined model, from the reconstructed trajectories
    t0 = time.perf_counter()
    say("skeleton")
    sk = run_skeleton(md, rng=int(seeds[6]), progress=lambda m: say(f"  {m}"))
    for p in write_outputs(sk, out / "skeleton.bvh", out / "skeleton.json"):
        files[p.suffix] = p
    joint_err = _joint_error_mm(sk.result.joint_centres, scene.joint_centres)
    stage["skeleton"] = time.perf_counter() - t0
    return DemoResult(n_cameras=cfg.n_cameras, n_frames=T, n_markers=truth.shape[1],
                      blob_error_px=blob_err, blob_recall=recall,
                      calib_centre_error_mm=cal_err, calib_reproj_px=reproj,
                      lframe_rms_mm=1000 * lrms, reconstructed_fraction=frac,
                      spurious_fraction=spurious, rms_3d_mm=rms,
                      n_trajectories=traj.positions.shape[1],
                      n_segments=int(sk.result.n_segments),
                      marker_deviation_mm=1000 * float(sk.deviation.overall_mean_m),
                      joint_error_mm=joint_err, files=files, stage_s=stage,
                      wall_s=time.perf_counter() - t_start)


def _joint_error_mm(solved, truth) -> float:
    """Median over solved joints of the median distance (mm) to the true joint that lies
    closest to it over the take; NaN when there is no truth or no joint."""
    if truth is None:
        return float("nan")
    S = np.asarray(solved)                                    # (T, S, 3), NaN for the root
    G = np.asarray(truth)                                     # (T, J, 3)
    d = np.linalg.norm(S[:, :, None] - G[:, None], axis=3)    # (T, S, J)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)      # the root joint is all-NaN
        med = np.nanmedian(np.where(np.isfinite(d), d, np.nan), axis=0)   # (S, J)
    best = np.nanmin(np.where(np.isfinite(med), med, np.inf), axis=1)
    best = best[np.isfinite(best)]
    return 1000 * float(np.median(best)) if best.size else float("nan")


def _match_one_to_one(points, truth, want, gate_m) -> np.ndarray:
    """Distance (m) from each wanted true marker to its own reconstructed point (one-to-one
    assignment, ``linear_sum_assignment``), NaN when none lies within ``gate_m``."""
    out = np.full(len(want), np.nan)
    if len(want) == 0 or len(points) == 0:
        return out
    D = np.linalg.norm(truth[want][:, None] - points[None], axis=2)
    D = np.where(np.isfinite(D), D, 1e3)
    r, c = linear_sum_assignment(np.minimum(D, 1e3))
    ok = D[r, c] <= gate_m
    out[r[ok]] = D[r[ok], c[ok]]
    return out


def _n_matched_any(points, truth, gate_m) -> int:
    """Reconstructed points lying within ``gate_m`` of some true marker."""
    t = truth[np.all(np.isfinite(truth), axis=1)]
    if len(points) == 0 or len(t) == 0:
        return 0
    d, _ = cKDTree(t).query(points, distance_upper_bound=gate_m)
    return int(np.isfinite(d).sum())


def _seen_by_two(rig, scene) -> np.ndarray:
    """(T, M) True where a marker is visible (in view, not occluded) in >= 2 cameras."""
    from hw_sim.observe import visibility

    v = visibility(rig, scene.positions, scene.marker_diameter_m,
                   occluder_segments=scene.occluder_segments,
                   occluder_radii_m=scene.occluder_radii_m, min_blob_px=1.0)
    return np.asarray(v.visible).sum(axis=1) >= 2

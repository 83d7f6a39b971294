"""Offline reconstruction of a recording or a 2D observation file into a marker file.

The library side of ``mocap reconstruct``: read the calibration, read the 2D detections (a
recording folder's recorded detections, blob detection over its frames, or a
``frame,camera,x,y`` CSV), run :func:`reconstruct.pipeline.reconstruct_sequence`, write
C3D / TRC / CSV (``reconstruct.marker_files``) and return a summary.
Conventions: docs/conventions.md [pixels], [camera-order], [units], [time].
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from calibration.camera import Rig
from capture.detections import Detections2D, read_detections_csv
from reconstruct.marker_files import MarkerData, write_markers
from reconstruct.pipeline import ReconstructionConfig, reconstruct_sequence
from reconstruct.types import MarkerCloudSequence, Trajectories

__all__ = ["OUTPUT_SUFFIXES", "ReconstructJob", "ReconstructSummary", "load_detections",
           "run_reconstruct"]

OUTPUT_SUFFIXES = (".c3d", ".trc", ".csv")

#: progress callback: (stage name, done, total)
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True, kw_only=True)
class ReconstructJob:
    """What ``mocap reconstruct`` does.

    Attributes:
        input: a recording folder (``capture.replay.is_recording``) or a 2D CSV
            ``frame,camera,x,y`` (camera = name or index in the calibration file).
        calibration: calibration TOML (``calibration.rig_io``). None: the recording's own
            calibration (recording folders only).
        output: marker file; its suffix (.c3d, .trc, .csv) chooses the format.
        config: reconstruction parameters.
        rate_hz: frame rate when the input does not carry one (None: the input's).
        workers: worker processes (None: all cores).
        blob_config: ``reconstruct.blobs.BlobConfig`` for recordings of frames (None: default).
    """

    input: Path
    calibration: Path | None
    output: Path
    config: ReconstructionConfig = field(default_factory=ReconstructionConfig)
    rate_hz: float | None = None
    workers: int | None = None
    blob_config: object | None = None

    def __post_init__(self):
        for name in ("input", "output"):
            object.__setattr__(self, name, Path(getattr(self, name)))
        if self.calibration is not None:
            object.__setattr__(self, "calibration", Path(self.calibration))
        if self.output.suffix.lower() not in OUTPUT_SUFFIXES:
            raise ValueError(f"output {str(self.output)!r}: unknown suffix "
                             f"{self.output.suffix!r}, expected one of {OUTPUT_SUFFIXES}")
        if self.rate_hz is not None and not self.rate_hz > 0:
            raise ValueError(f"rate_hz={self.rate_hz}, expected > 0")
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"workers={self.workers}, expected >= 1")


@dataclass(frozen=True, kw_only=True)
class ReconstructSummary:
    """What a run produced (``table()`` prints it)."""

    output: Path
    source: str                 # "csv", "recorded detections" or "blob detection"
    n_cameras: int
    n_frames: int
    rate_hz: float
    n_blobs: int
    n_points: int               # 3D points over all frames
    n_trajectories: int
    present_fraction: float     # trajectory samples present / (frames x trajectories)
    n_filled: int
    mean_residual_mm: float
    detect_s: float             # reading / blob detection
    reconstruct_s: float
    workers: int
    clouds: MarkerCloudSequence = field(repr=False)
    trajectories: Trajectories = field(repr=False)

    @property
    def duration_s(self) -> float:
        return self.n_frames / self.rate_hz

    def table(self) -> str:
        ratio = self.reconstruct_s / max(self.duration_s, 1e-9)
        rows = [
            ("output", str(self.output)),
            ("input", self.source),
            ("cameras", f"{self.n_cameras}"),
            ("frames", f"{self.n_frames} ({self.duration_s:.2f} s at {self.rate_hz:g} Hz)"),
            ("2D blobs", f"{self.n_blobs} ({self.n_blobs / max(self.n_frames, 1):.1f}/frame)"),
            ("3D points", f"{self.n_points} ({self.n_points / max(self.n_frames, 1):.1f}/frame)"),
            ("trajectories", f"{self.n_trajectories}"),
            ("samples present", f"{100 * self.present_fraction:.1f}%"),
            ("samples gap-filled", f"{self.n_filled}"),
            ("mean residual", f"{self.mean_residual_mm:.3f} mm"),
            ("time: detections", f"{self.detect_s:.2f} s"),
            ("time: reconstruction", f"{self.reconstruct_s:.2f} s with {self.workers} "
                                     f"worker(s) = {ratio:.2f} x session duration"),
        ]
        w = max(len(k) for k, _ in rows)
        return "\n".join(f"{k:<{w}}  {v}" for k, v in rows)


def _blob_detections(folder: Path, meta, config, progress: Progress | None) -> Detections2D:
    from capture.replay import recording_frames
    from reconstruct.blobs import BlobConfig, detections_from_frames

    if config is None:
        depth = 8
        s = next((x for x in meta.settings if x is not None), None)
        fmt = getattr(getattr(s, "pixel_format", None), "name", "") if s else ""
        if "16" in fmt:
            depth = 16
        elif "10" in fmt:
            depth = 10
        config = BlobConfig(bit_depth=depth)

    def frames():
        n = 0
        for fi, images in recording_frames(folder):
            # a camera missing from a frame set contributes no blobs that frame
            yield fi, [np.zeros((1, 1), np.uint8) if im is None else im for im in images]
            n += 1
            if progress and n % 25 == 0:
                progress("blob detection", n, 0)

    det = detections_from_frames(frames(), meta.camera_ids, config, rate_hz=meta.rate_hz)
    return det


def load_detections(path, rig: Rig | None = None, *, blob_config=None, rate_hz=None,
                    progress: Progress | None = None) -> tuple[Detections2D, str]:
    """The 2D detections of ``path`` and where they came from.

    A recording folder gives its recorded detections (``capture.replay
    .read_recording_detections``) or, for a recording of frames, the blobs found by
    ``reconstruct.blobs.detections_from_frames``. Any other path is read as a
    ``frame,camera,x,y`` CSV whose camera column holds names or indices of ``rig``.
    """
    from capture.replay import is_recording, load_metadata, read_recording_detections

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"input not found: {path}")
    if is_recording(path):
        meta = load_metadata(path)
        det = read_recording_detections(path)
        source = "recorded detections"
        if det is None:
            det = _blob_detections(path, meta, blob_config, progress)
            source = "blob detection"
    elif path.is_dir():
        raise ValueError(f"{path} is a folder but not a recording (no metadata.json)")
    else:
        det = read_detections_csv(path, camera_names=None if rig is None else rig.names,
                                  rate_hz=rate_hz)
        source = "csv"
    if rate_hz is not None:
        det = Detections2D(frame=det.frame, camera=det.camera, xy=det.xy,
                           camera_names=det.camera_names, rate_hz=rate_hz, area_px=det.area_px)
    if rig is not None:
        unknown = [n for n in det.camera_names if n not in rig.names]
        if unknown:
            raise ValueError(f"{path}: cameras {unknown} are not in the calibration "
                             f"(cameras {list(rig.names)})")
    return det, source


#: a recording's frames are mostly seen: detections spanning 100x more frames than they fill
#: (and more than 100 000) come from a bad frame number, not from occlusion
MAX_EMPTY_SPAN_RATIO = 100
MAX_EMPTY_SPAN_MIN = 100_000


def run_reconstruct(job: ReconstructJob, progress: Progress | None = None
                    ) -> ReconstructSummary:
    """Read, reconstruct, write ``job.output``; return the summary."""
    from calibration.rig_io import load_rig
    from capture.replay import is_recording, load_metadata

    if not job.input.exists():
        raise FileNotFoundError(f"input not found: {job.input}")
    cal = job.calibration
    if cal is None:
        if is_recording(job.input):
            cal = load_metadata(job.input).calibration_path
        if cal is None:
            raise ValueError(f"{job.input}: no --calibration given and the input names none")
    rig = load_rig(cal)
    t0 = time.perf_counter()
    det, source = load_detections(job.input, rig, blob_config=job.blob_config,
                                  rate_hz=job.rate_hz, progress=progress)
    detect_s = time.perf_counter() - t0
    if not det.rate_hz:
        raise ValueError(f"{job.input}: the frame rate is unknown; give it (--rate)")
    cut = job.config.filter_cutoff_hz
    if cut is not None and not cut < det.rate_hz / 2:
        raise ValueError(f"cutoff {cut:g} Hz: at {det.rate_hz:g} Hz the low-pass cutoff must "
                         f"be below {det.rate_hz / 2:g} Hz (Nyquist)")
    if len(det) == 0:
        raise ValueError(f"{job.input}: no 2D detections")
    frames = np.unique(det.frame)
    span = int(frames[-1] - frames[0] + 1)
    if span > MAX_EMPTY_SPAN_RATIO * frames.size and span > MAX_EMPTY_SPAN_MIN:
        raise ValueError(f"{job.input}: detections span frames {frames[0]}..{frames[-1]} "
                         f"({span} frames) but only {frames.size} frames hold any: a frame "
                         f"number is wrong (the trajectories would hold {span} rows)")
    workers = job.workers or (os.cpu_count() or 1)
    t0 = time.perf_counter()
    clouds, traj = reconstruct_sequence(
        det, rig, job.config, workers=workers,
        progress=(lambda d, n: progress("reconstruction", d, n)) if progress else None)
    reconstruct_s = time.perf_counter() - t0
    md = MarkerData(positions=traj.positions, labels=traj.labels, rate_hz=traj.rate_hz,
                    residual_mm=traj.residual_mm, first_frame=traj.first_frame + 1)
    job.output.parent.mkdir(parents=True, exist_ok=True)
    write_markers(md, job.output)
    present = traj.present()
    res = traj.residual_mm[np.isfinite(traj.residual_mm)]
    return ReconstructSummary(
        output=job.output, source=source, n_cameras=len(rig), n_frames=traj.n_frames,
        rate_hz=traj.rate_hz, n_blobs=len(det), n_points=sum(len(c) for c in clouds.clouds),
        n_trajectories=traj.n_markers,
        present_fraction=float(present.mean()) if present.size else 0.0,
        n_filled=int(traj.filled.sum()),
        mean_residual_mm=float(res.mean()) if res.size else float("nan"),
        detect_s=detect_s, reconstruct_s=reconstruct_s, workers=workers, clouds=clouds,
        trajectories=traj)

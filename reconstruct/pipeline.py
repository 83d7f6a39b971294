"""Offline reconstruction of a recording: 2D detections -> point clouds -> trajectories.

Stages: undistortion of every blob (``Camera.pixel_to_normalized``), per-frame spatial
correspondence and triangulation (``reconstruct.correspondence``, with its merged-blob test
when ``Detections2D.area_px`` is present; frames are independent and run in parallel chunks
on a ``ProcessPoolExecutor``), tracking (``reconstruct.tracking``),
then :func:`postprocess`: rigid-body gap filling from the other markers of the same segment
when a segment map is given, spline gap filling of short gaps (``reconstruct.gapfill``),
zero-phase Butterworth filtering (``reconstruct.filtering``) and rigidity flags
(``reconstruct.rigidity``, with a segment map).
Conventions: docs/conventions.md [camera-order], [arrays], [units].
"""
from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from calibration.camera import Rig
from capture.detections import Detections2D
from reconstruct.correspondence import (CorrespondenceConfig, EpipolarGeometry,
                                        epipolar_geometry, match_frame)
from reconstruct.filtering import butterworth_lowpass
from reconstruct.gapfill import fill_gaps_rigid, fill_gaps_spline
from reconstruct.rigidity import rigidity_flags
from reconstruct.tracking import TrackingConfig, track
from reconstruct.triangulation import rig_arrays
from reconstruct.types import MarkerCloudSequence, PointCloud, Trajectories

__all__ = ["ReconstructionConfig", "reconstruct_sequence", "reconstruct_clouds", "postprocess"]


@dataclass(frozen=True, kw_only=True)
class ReconstructionConfig:
    """Parameters of :func:`reconstruct_sequence`.

    Attributes:
        correspondence: spatial correspondence / triangulation parameters.
        tracking: tracking parameters.
        fill_max_gap: fill interior gaps of at most this many frames by cubic spline (0: off).
        filter_cutoff_hz: Butterworth low-pass cutoff (None: no filtering).
        filter_order: Butterworth order.
        chunk_frames: frames per parallel work item.
        rigidity_threshold_m: rigidity-test tolerance on marker distances within a segment.
    """

    correspondence: CorrespondenceConfig = field(default_factory=CorrespondenceConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    fill_max_gap: int = 0
    filter_cutoff_hz: float | None = None
    filter_order: int = 2
    chunk_frames: int = 240
    rigidity_threshold_m: float = 0.01

    def __post_init__(self):
        if self.fill_max_gap < 0:
            raise ValueError(f"fill_max_gap={self.fill_max_gap}, expected >= 0")
        if self.filter_cutoff_hz is not None and not self.filter_cutoff_hz > 0:
            raise ValueError(f"filter_cutoff_hz={self.filter_cutoff_hz}, expected > 0 or None")
        if self.chunk_frames < 1:
            raise ValueError(f"chunk_frames={self.chunk_frames}, expected >= 1")


def _match_chunk(epi: EpipolarGeometry, cfg: CorrespondenceConfig, frames, bounds, cams,
                 norm, n_cameras, area=None) -> list[PointCloud]:
    out = []
    for f, (a, b) in zip(frames, bounds):
        c = cams[a:b]
        xy = norm[a:b]
        blobs = [xy[c == k] for k in range(n_cameras)]
        areas = None if area is None else [area[a:b][c == k] for k in range(n_cameras)]
        out.append(match_frame(blobs, epi, cfg, frame=int(f), areas=areas))
    return out


def _camera_map(det: Detections2D, rig: Rig) -> np.ndarray:
    try:
        return np.array([rig.index(n) for n in det.camera_names], dtype=np.int64)
    except ValueError as e:
        raise ValueError(f"detections cameras {list(det.camera_names)} do not match the rig "
                         f"{rig.names}: {e}") from None


def reconstruct_clouds(detections: Detections2D, rig: Rig,
                       cfg: CorrespondenceConfig | None = None,
                       progress: Callable[[int, int], None] | None = None,
                       workers: int | None = None, chunk_frames: int = 240
                       ) -> MarkerCloudSequence:
    """Point clouds of every frame from the first to the last detected frame.

    ``progress(done_frames, total_frames)`` is called as chunks complete. ``workers`` processes
    (default ``os.cpu_count()``); 1 runs in this process.
    """
    if not isinstance(detections, Detections2D):
        raise TypeError(f"detections must be Detections2D, got {type(detections).__name__}")
    cfg = cfg or CorrespondenceConfig()
    C = len(rig)
    cmap = _camera_map(detections, rig)
    cam = cmap[detections.camera]
    norm = np.empty_like(detections.xy)
    for c in range(C):
        m = cam == c
        if m.any():
            norm[m] = rig[c].pixel_to_normalized(detections.xy[m])
    epi = epipolar_geometry(rig_arrays(rig))
    area = detections.area_px   # blob areas (merged-blob test of the correspondence), or None
    if len(detections) == 0:
        return MarkerCloudSequence(clouds=(), rate_hz=detections.rate_hz)
    sl = detections.frame_slices()
    frames = np.array(sorted(sl), dtype=np.int64)
    bounds = np.array([(sl[f].start, sl[f].stop) for f in frames], dtype=np.int64)
    total = len(frames)
    chunks = [slice(i, i + chunk_frames) for i in range(0, total, chunk_frames)]
    n_workers = (os.cpu_count() or 1) if workers is None else int(workers)
    if n_workers < 1:
        raise ValueError(f"workers={workers}, expected >= 1")

    def args(s):
        a, b = bounds[s][0, 0], bounds[s][-1, 1]
        return (epi, cfg, frames[s], bounds[s] - a, cam[a:b], norm[a:b], C,
                None if area is None else area[a:b])

    results: list[list[PointCloud]] = [None] * len(chunks)  # type: ignore[list-item]
    done = 0
    if n_workers == 1 or len(chunks) == 1:
        for i, s in enumerate(chunks):
            results[i] = _match_chunk(*args(s))
            done += len(results[i])
            if progress:
                progress(done, total)
    else:
        with ProcessPoolExecutor(max_workers=min(n_workers, len(chunks))) as ex:
            futs = {ex.submit(_match_chunk, *args(s)): i for i, s in enumerate(chunks)}
            for fut in as_completed(futs):
                i = futs[fut]
                results[i] = fut.result()
                done += len(results[i])
                if progress:
                    progress(done, total)
    by_frame = {pc.frame: pc for r in results for pc in r}
    clouds = tuple(by_frame.get(int(f)) or PointCloud.empty(int(f), C)
                   for f in range(int(frames[0]), int(frames[-1]) + 1))
    return MarkerCloudSequence(clouds=clouds, rate_hz=detections.rate_hz)


def _segment_indices(labels, segments) -> list[list[int]]:
    idx = {n: i for i, n in enumerate(labels)}
    out = []
    for seg in segments:
        if isinstance(seg, str):
            raise TypeError(f"segments must be sequences of labels, got the string {seg!r}")
        unknown = [n for n in seg if n not in idx]
        if unknown:
            raise ValueError(f"segment labels {unknown} are not trajectory labels")
        out.append([idx[n] for n in seg])
    return out


def postprocess(traj: Trajectories, config: ReconstructionConfig | None = None,
                segments=None) -> Trajectories:
    """Gap filling, filtering and rigidity flags of tracked trajectories.

    ``segments``: None, or groups of trajectory labels, one group per rigid segment (known
    once trajectories are labelled). With it, missing samples are first filled rigidly
    (``gapfill.fill_gaps_rigid``: Kabsch of >= 3 other markers of the segment, any gap
    length), then gaps of at most ``fill_max_gap`` frames by cubic spline, then the
    Butterworth filter; the rigidity test flags samples of the measured (unfilled) data.
    """
    config = config or ReconstructionConfig()
    if not traj.n_markers:
        return traj
    pos, filled = traj.positions, traj.filled
    flags = traj.rigidity_flag
    if segments is not None:
        groups = _segment_indices(traj.labels, segments)
        flags = rigidity_flags(pos, groups, config.rigidity_threshold_m)
        pos, filled = fill_gaps_rigid(pos, groups, filled=filled)
    if config.fill_max_gap > 0:
        pos, f2 = fill_gaps_spline(pos, config.fill_max_gap)
        filled = filled | f2
    if config.filter_cutoff_hz is not None:
        pos = butterworth_lowpass(pos, traj.rate_hz, config.filter_cutoff_hz,
                                  order=config.filter_order)
    if pos is traj.positions and flags is traj.rigidity_flag:
        return traj
    return traj.with_(positions=pos, filled=filled, rigidity_flag=flags)


def reconstruct_sequence(detections: Detections2D, rig: Rig,
                         config: ReconstructionConfig | None = None,
                         progress: Callable[[int, int], None] | None = None,
                         workers: int | None = None, rate_hz: float | None = None,
                         segments=None) -> tuple[MarkerCloudSequence, Trajectories]:
    """Reconstruct trajectories from the 2D detections of a calibrated rig.

    Returns (point clouds of every frame, trajectories ``T1..TM`` with NaN gaps and the
    ``filled`` mask of gap-filled samples). ``rate_hz`` overrides ``detections.rate_hz``.
    ``segments``: groups of trajectory labels per rigid segment, see :func:`postprocess`.
    """
    config = config or ReconstructionConfig()
    rate = rate_hz or detections.rate_hz
    if not rate:
        raise ValueError("detections carry no rate_hz; pass rate_hz=")
    clouds = reconstruct_clouds(detections, rig, config.correspondence, progress, workers,
                                config.chunk_frames)
    traj = track(clouds, config.tracking, rate_hz=rate)
    return clouds, postprocess(traj, config, segments)

"""2D detections: the flat table of blob centroids every camera produces per frame.

This is what a camera in "object mode" sends, what blob detection produces from frames, and
what wand calibration and reconstruction consume. Conventions: docs/conventions.md
[pixels], [arrays] (2D detections table), [camera-order].

CSV form: header ``frame,camera,x,y`` (raw pixel coordinates); ``camera`` is a camera name or
an index into ``camera_names``. Extra columns (e.g. ``area``) are ignored on read.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from .atomic import atomic_file

__all__ = ["Detections2D", "read_detections_csv", "write_detections_csv"]


@dataclass(frozen=True, kw_only=True)
class Detections2D:
    """Blob centroids of C cameras over frames, as a flat table sorted by (frame, camera).

    Attributes:
        frame: (K,) int64 frame index.
        camera: (K,) int64 camera index into ``camera_names``.
        xy: (K, 2) float64 raw (distorted) pixel coordinates [pixels].
        camera_names: ordered camera ids ([camera-order]).
        rate_hz: frame rate, or None when unknown.
        area_px: optional (K,) blob areas in px (NaN when unknown).
    """

    frame: np.ndarray
    camera: np.ndarray
    xy: np.ndarray
    camera_names: tuple[str, ...]
    rate_hz: float | None = None
    area_px: np.ndarray | None = field(default=None)

    def __post_init__(self):
        f = np.asarray(self.frame).reshape(-1)
        c = np.asarray(self.camera).reshape(-1)
        xy = np.asarray(self.xy, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ValueError(f"xy.shape={xy.shape}, expected (K, 2)")
        if f.shape[0] != xy.shape[0] or c.shape[0] != xy.shape[0]:
            raise ValueError(f"frame {f.shape}, camera {c.shape} and xy {xy.shape} lengths differ")
        if f.size and not np.issubdtype(f.dtype, np.integer):
            if not np.all(np.equal(np.mod(f, 1), 0)):
                raise ValueError("frame indices must be integers")
        if c.size and not np.issubdtype(c.dtype, np.integer):
            raise TypeError(f"camera indices must be integers, got dtype {c.dtype}")
        names = tuple(str(n) for n in self.camera_names)
        if not names:
            raise ValueError("camera_names is empty")
        if c.size and (c.min() < 0 or c.max() >= len(names)):
            raise ValueError(f"camera index out of range [0, {len(names)}): "
                             f"min={c.min()}, max={c.max()}")
        if not np.all(np.isfinite(xy)):
            raise ValueError("xy contains non-finite values; drop missing blobs instead")
        f = f.astype(np.int64)
        c = c.astype(np.int64)
        area = None if self.area_px is None else np.asarray(self.area_px, np.float64).reshape(-1)
        if area is not None and area.shape[0] != xy.shape[0]:
            raise ValueError(f"area_px {area.shape} does not match xy {xy.shape}")
        order = np.lexsort((c, f))
        if not np.all(order == np.arange(len(order))):
            f, c, xy = f[order], c[order], xy[order]
            area = None if area is None else area[order]
        for a in (f, c, xy) + (() if area is None else (area,)):
            a.setflags(write=False)
        object.__setattr__(self, "frame", f)
        object.__setattr__(self, "camera", c)
        object.__setattr__(self, "xy", xy)
        object.__setattr__(self, "camera_names", names)
        object.__setattr__(self, "area_px", area)
        if self.rate_hz is not None and not self.rate_hz > 0:
            raise ValueError(f"rate_hz={self.rate_hz}, expected > 0")

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    @property
    def n_cameras(self) -> int:
        return len(self.camera_names)

    @property
    def frames(self) -> np.ndarray:
        """Sorted unique frame indices present."""
        return np.unique(self.frame)

    def frame_slices(self) -> dict[int, slice]:
        """Map frame index -> slice of rows for that frame (rows are sorted by frame)."""
        if len(self) == 0:
            return {}
        starts = np.flatnonzero(np.r_[True, self.frame[1:] != self.frame[:-1]])
        ends = np.r_[starts[1:], len(self)]
        return {int(self.frame[s]): slice(int(s), int(e)) for s, e in zip(starts, ends)}

    def per_camera(self, rows: slice | np.ndarray | None = None) -> list[np.ndarray]:
        """Blob centroids split by camera: list of C arrays (N_c, 2), for the given rows."""
        cam = self.camera if rows is None else self.camera[rows]
        xy = self.xy if rows is None else self.xy[rows]
        return [xy[cam == i] for i in range(self.n_cameras)]

    @classmethod
    def from_per_frame(cls, frames: Sequence[Sequence[np.ndarray]], camera_names,
                       frame_indices=None, rate_hz=None) -> "Detections2D":
        """Build from ``frames[t][c] -> (N, 2)`` blob arrays."""
        fi, ci, pts = [], [], []
        idx = range(len(frames)) if frame_indices is None else frame_indices
        for t, per_cam in zip(idx, frames):
            for c, xy in enumerate(per_cam):
                xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
                fi.append(np.full(len(xy), t, np.int64))
                ci.append(np.full(len(xy), c, np.int64))
                pts.append(xy)
        if pts:
            return cls(frame=np.concatenate(fi), camera=np.concatenate(ci),
                       xy=np.concatenate(pts), camera_names=tuple(camera_names), rate_hz=rate_hz)
        return cls(frame=np.zeros(0, np.int64), camera=np.zeros(0, np.int64),
                   xy=np.zeros((0, 2)), camera_names=tuple(camera_names), rate_hz=rate_hz)


def write_detections_csv(det: Detections2D, path) -> Path:
    """Write ``frame,camera,x,y`` (and ``area_px`` when the detections carry blob areas)
    with camera names; rate and order in a leading comment."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, "w", newline="") as f:
        f.write(f"# cameras={','.join(det.camera_names)}")
        if det.rate_hz:
            f.write(f" rate_hz={det.rate_hz:g}")
        f.write("\n")
        w = csv.writer(f)
        names = det.camera_names
        if det.area_px is None:
            w.writerow(["frame", "camera", "x", "y"])
            for fr, c, (x, y) in zip(det.frame, det.camera, det.xy):
                w.writerow([int(fr), names[c], repr(float(x)), repr(float(y))])
        else:
            w.writerow(["frame", "camera", "x", "y", "area_px"])
            for fr, c, (x, y), a in zip(det.frame, det.camera, det.xy, det.area_px):
                w.writerow([int(fr), names[c], repr(float(x)), repr(float(y)), repr(float(a))])
    return path


def read_detections_csv(path, camera_names: Sequence[str] | None = None,
                        rate_hz: float | None = None) -> Detections2D:
    """Read a ``frame,camera,x,y`` CSV (an optional ``area_px`` column gives blob areas,
    which correspondence uses to spot merged blobs).

    ``camera`` entries may be names or integer indices. ``camera_names`` (e.g. the rig's order)
    wins; otherwise the ``# cameras=`` comment line, otherwise names in order of first
    appearance (integers are taken as indices).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"2D observation file not found: {path}")
    if not path.is_file():
        raise ValueError(f"{path}: not a file")
    header_names = None
    try:
        lines = path.read_text().splitlines()
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a text CSV ({e.reason} at byte {e.start})") from e
    data_lines = []
    for ln in lines:
        if ln.startswith("#"):
            for tok in ln[1:].split():
                if tok.startswith("cameras="):
                    header_names = tuple(tok[len("cameras="):].split(","))
                elif tok.startswith("rate_hz=") and rate_hz is None:
                    rate_hz = float(tok[len("rate_hz="):])
        elif ln.strip():
            data_lines.append(ln)
    if not data_lines:
        raise ValueError(f"{path}: empty file, expected a header 'frame,camera,x,y'")
    reader = csv.DictReader(data_lines)
    cols = [c.strip() for c in (reader.fieldnames or [])]
    need = {"frame", "camera", "x", "y"}
    if not need.issubset(cols):
        raise ValueError(f"{path}: columns {cols}, expected at least frame,camera,x,y")
    names = tuple(camera_names) if camera_names is not None else header_names
    has_area = "area_px" in cols
    fr, cam_raw, xy, area = [], [], [], []
    for lineno, row in enumerate(reader, start=2):
        row = {k.strip(): (v.strip() if isinstance(v, str) else v) for k, v in row.items()}
        try:
            f_i = int(row["frame"])
            x, y = float(row["x"]), float(row["y"])
            a = float(row["area_px"]) if has_area else np.nan
        except (TypeError, ValueError) as e:
            raise ValueError(f"{path}:{lineno}: bad row {row}: {e}") from e
        if f_i < 0:
            raise ValueError(f"{path}:{lineno}: frame {f_i} < 0")
        if not (np.isfinite(x) and np.isfinite(y)):
            continue  # a missing blob is simply absent
        fr.append(f_i)
        cam_raw.append(str(row["camera"]))
        xy.append((x, y))
        area.append(a)
    if names is None:
        seen: list[str] = []
        for c in cam_raw:
            if c not in seen:
                seen.append(c)
        if all(s.isdigit() for s in seen):
            n = max(int(s) for s in seen) + 1 if seen else 1
            names = tuple(f"cam_{i}" for i in range(n))
        else:
            names = tuple(seen)
    lookup = {n: i for i, n in enumerate(names)}
    cam = []
    for c in cam_raw:
        if c in lookup:
            cam.append(lookup[c])
        elif c.isdigit() and int(c) < len(names):
            cam.append(int(c))
        else:
            raise ValueError(f"{path}: unknown camera {c!r}; known cameras {list(names)}")
    return Detections2D(frame=np.asarray(fr, np.int64), camera=np.asarray(cam, np.int64),
                        xy=np.asarray(xy, np.float64).reshape(-1, 2), camera_names=names,
                        rate_hz=rate_hz,
                        area_px=np.asarray(area, np.float64) if has_area else None)

"""Marker files: C3D, TRC and CSV writing and reading of marker trajectories.

In memory: :class:`MarkerData` with positions ``(T, M, 3)`` in metres, NaN gaps
(docs/conventions.md [units], [arrays]). On disk: millimetres, as C3D and TRC users expect.

- C3D: written with the maintained ``c3d`` package as 32-bit floats (POINT:SCALE < 0),
  ``POINT:UNITS = "mm"``, ``POINT:RATE``, ``POINT:LABELS``; a gap is a point with residual -1
  (the C3D convention for an invalid sample), which independent readers (ezc3d, Mokka,
  Vicon Nexus) load as missing.
- TRC: the OpenSim / Motion Analysis text format (tab-separated, 5 header lines), gaps empty.
- CSV: ``frame,time_s,<label>_x,<label>_y,<label>_z,...`` in millimetres.
"""
from __future__ import annotations

import csv
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from capture.atomic import atomic_file, write_text_atomic

__all__ = ["MarkerData", "read_markers", "write_markers", "write_c3d", "read_c3d",
           "write_trc", "read_trc", "write_csv", "read_csv"]

_UNIT_TO_M = {"mm": 1e-3, "m": 1.0, "cm": 1e-2, "dm": 0.1}


@dataclass(frozen=True, kw_only=True)
class MarkerData:
    """Marker trajectories.

    Attributes:
        positions: (T, M, 3) metres, NaN where a marker is missing.
        labels: M marker names.
        rate_hz: frame rate.
        residual_mm: optional (T, M) reconstruction residual in mm (NaN where missing).
        first_frame: index of the first frame (C3D counts from 1).
    """

    positions: np.ndarray
    labels: tuple[str, ...]
    rate_hz: float
    residual_mm: np.ndarray | None = None
    first_frame: int = 1
    _meta: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        p = np.asarray(self.positions, dtype=np.float64)
        if p.ndim != 3 or p.shape[2] != 3:
            raise ValueError(f"positions.shape={p.shape}, expected (T, M, 3)")
        labels = tuple(str(s) for s in self.labels)
        if len(labels) != p.shape[1]:
            raise ValueError(f"{len(labels)} labels for {p.shape[1]} markers")
        if len(set(labels)) != len(labels):
            raise ValueError(f"duplicate marker labels: {sorted({l for l in labels if labels.count(l) > 1})}")
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ValueError(f"rate_hz={self.rate_hz}, expected > 0")
        # a marker is either fully present or fully missing in a frame
        p = p.copy()
        p[np.any(~np.isfinite(p), axis=2)] = np.nan
        res = None
        if self.residual_mm is not None:
            res = np.asarray(self.residual_mm, dtype=np.float64)
            if res.shape != p.shape[:2]:
                raise ValueError(f"residual_mm.shape={res.shape}, expected {p.shape[:2]}")
        object.__setattr__(self, "positions", p)
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "rate_hz", float(self.rate_hz))
        object.__setattr__(self, "residual_mm", res)

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    @property
    def n_markers(self) -> int:
        return self.positions.shape[1]


def default_labels(n: int) -> tuple[str, ...]:
    return tuple(f"M{i:03d}" for i in range(n))


# ---------------------------------------------------------------- C3D
def write_c3d(data: MarkerData, path) -> Path:
    """Write a C3D file (float storage, millimetres)."""
    import c3d

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    w = c3d.Writer(point_rate=float(data.rate_hz), analog_rate=0.0, point_scale=-1.0,
                   point_units="mm  ")
    mm = data.positions * 1000.0
    T, M, _ = mm.shape
    if T == 0:
        raise ValueError(f"{path}: no frames to write (a C3D file holds at least one)")
    missing = np.isnan(mm[..., 0])
    frames = []
    empty_analog = np.zeros((0, 0), dtype=np.float32)
    for t in range(T):
        pts = np.zeros((M, 5), dtype=np.float32)
        pts[:, :3] = np.where(missing[t][:, None], 0.0, mm[t])
        if data.residual_mm is not None:
            res = np.where(np.isfinite(data.residual_mm[t]), data.residual_mm[t], 0.0)
        else:
            res = np.zeros(M)
        pts[:, 3] = np.where(missing[t], -1.0, np.maximum(res, 0.0))
        frames.append((pts, empty_analog))
    w.add_frames(frames)
    _set_point_labels(w, list(data.labels))
    if data.first_frame != 1:
        w.set_start_frame(int(data.first_frame))
    with atomic_file(path, "wb") as h, warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="No analog data found")  # markers only
        w.write(h)
    return path


#: A C3D parameter dimension is one byte: labels go 255 at a time into POINT:LABELS,
#: POINT:LABELS2, POINT:LABELS3, ... (the C3D.org convention that Vicon, Qualisys and ezc3d
#: follow for large marker sets).
_LABELS_PER_PARAM = 255


def _set_point_labels(w, labels: list[str]) -> None:
    import c3d

    for k in range(0, max(len(labels), 1), _LABELS_PER_PARAM):
        chunk = labels[k:k + _LABELS_PER_PARAM]
        if not chunk:
            break
        text, size = c3d.Writer.pack_labels(chunk)
        suffix = "" if k == 0 else str(k // _LABELS_PER_PARAM + 1)
        w.point_group.add_str("LABELS" + suffix, "Point labels.", text, size, len(chunk))
        # the writer would add one DESCRIPTIONS of all markers (too long a dimension)
        w.point_group.add_str("DESCRIPTIONS" + suffix, "Point descriptions.",
                              " " * len(chunk), 1, len(chunk))


def _point_labels(r) -> list[str]:
    """POINT:LABELS followed by POINT:LABELS2, LABELS3, ... when present."""
    out = []
    for k in range(1, 1000):
        name = "POINT:LABELS" if k == 1 else f"POINT:LABELS{k}"
        try:
            p = r.get(name)
        except Exception:
            p = None
        if p is None:
            break
        out += [str(s).strip() for s in p.string_array]
    return out


def _input_file(path) -> Path:
    """``path`` as a Path, or a clear error: missing, or not a regular file."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"marker file not found: {path}")
    if not path.is_file():
        raise ValueError(f"{path}: not a file")
    return path


def _text_lines(path: Path) -> list[str]:
    try:
        return path.read_text().splitlines()
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a text marker file ({e.reason} at byte {e.start})") from e


def read_c3d(path) -> MarkerData:
    """Read a C3D file's point data (any encoding the ``c3d`` package reads) into metres."""
    import c3d

    path = _input_file(path)
    with open(path, "rb") as h:
        try:
            with warnings.catch_warnings():   # a marker-only file has no analog data: normal
                warnings.filterwarnings("ignore", message="No analog data found")
                r = c3d.Reader(h)
        except Exception as e:  # the library raises bare errors on a corrupt header
            raise ValueError(f"{path}: not a readable C3D file: {e}") from e
        units = "mm"
        try:
            units = r.get("POINT:UNITS").string_value.replace("\x00", "").strip().lower() or "mm"
        except Exception:
            pass
        scale = _UNIT_TO_M.get(units)
        if scale is None:
            raise ValueError(f"{path}: unknown POINT:UNITS {units!r}")
        labels = _point_labels(r)
        pos, res = [], []
        with warnings.catch_warnings():
            # the library warns and stops at an early end of file: counted below instead
            warnings.filterwarnings("ignore", message="reached end of file")
            for _, points, _analog in r.read_frames(copy=True):
                p = np.array(points[:, :3], dtype=np.float64)
                rr = np.array(points[:, 3], dtype=np.float64)
                bad = rr < 0
                p[bad] = np.nan
                rr = np.where(bad, np.nan, rr)
                pos.append(p)
                res.append(rr)
        short = r.frame_count - len(pos)
        if short > 1:
            raise ValueError(f"{path}: truncated C3D file: the header announces "
                             f"{r.frame_count} frames, the data ends after {len(pos)}")
        if short == 1:   # some exporters count one frame too many (last_frame inclusive)
            warnings.warn(f"{path}: the header announces {r.frame_count} frames, the data "
                          f"holds {len(pos)}: read {len(pos)}", stacklevel=2)
        rate = float(r.point_rate)
        first = int(r.first_frame)
    M = len(labels) if labels else (pos[0].shape[0] if pos else 0)
    positions = np.stack(pos) * scale if pos else np.zeros((0, M, 3))
    residual = np.stack(res) if res else None
    if not labels or len(labels) != positions.shape[1]:
        labels = list(default_labels(positions.shape[1]))
    # blank or repeated labels are made unique so that every marker keeps an identity
    seen: dict[str, int] = {}
    uniq = []
    for i, lab in enumerate(labels):
        lab = lab or f"M{i:03d}"
        if lab in seen:
            seen[lab] += 1
            lab = f"{lab}_{seen[lab]}"
        else:
            seen[lab] = 0
        uniq.append(lab)
    return MarkerData(positions=positions, labels=tuple(uniq), rate_hz=rate,
                      residual_mm=residual, first_frame=first)


# ---------------------------------------------------------------- TRC
def write_trc(data: MarkerData, path) -> Path:
    """Write a TRC file (OpenSim layout, millimetres, gaps as empty fields)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    T, M, _ = data.positions.shape
    mm = data.positions * 1000.0
    rate = data.rate_hz
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate:g}\t{rate:g}\t{T}\t{M}\tmm\t{rate:g}\t{data.first_frame}\t{T}",
        "Frame#\tTime\t" + "\t".join(f"{lab}\t\t" for lab in data.labels).rstrip("\t"),
        "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(M)),
        "",
    ]
    out = ["\n".join(lines)]
    for t in range(T):
        vals = []
        for m in range(M):
            if np.isnan(mm[t, m, 0]):
                vals.extend(["", "", ""])
            else:
                vals.extend(repr(float(v)) for v in mm[t, m])
        out.append(f"{t + data.first_frame}\t{t / rate:.6f}\t" + "\t".join(vals) + "\n")
    return write_text_atomic(path, "".join(out))


def read_trc(path) -> MarkerData:
    path = _input_file(path)
    lines = _text_lines(path)
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        raise ValueError(f"{path}: not a TRC file (first line {lines[0][:40] if lines else ''!r})")
    keys = lines[1].split("\t")
    vals = lines[2].split("\t")
    hdr = dict(zip([k.strip() for k in keys], [v.strip() for v in vals]))
    try:
        rate = float(hdr["DataRate"])
        n_markers = int(hdr["NumMarkers"])
        units = hdr.get("Units", "mm").lower()
        first = int(hdr.get("OrigDataStartFrame", "1") or 1)
    except (KeyError, ValueError) as e:
        raise ValueError(f"{path}: bad TRC header {hdr}: {e}") from e
    scale = _UNIT_TO_M.get(units)
    if scale is None:
        raise ValueError(f"{path}: unknown TRC units {units!r}")
    names = [s.strip() for s in lines[3].split("\t")[2:]]
    labels = [s for s in names if s][:n_markers]
    if len(labels) != n_markers:
        raise ValueError(f"{path}: header names {len(labels)} markers, NumMarkers={n_markers}")
    rows = []
    for ln in lines[5:]:
        if not ln.strip():
            continue
        parts = ln.split("\t")
        fields = parts[2:2 + 3 * n_markers]
        fields += [""] * (3 * n_markers - len(fields))
        rows.append([float(v) if v.strip() else np.nan for v in fields])
    pos = np.asarray(rows, dtype=np.float64).reshape(len(rows), n_markers, 3) * scale
    return MarkerData(positions=pos, labels=tuple(labels), rate_hz=rate, first_frame=first)


# ---------------------------------------------------------------- CSV
def write_csv(data: MarkerData, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    mm = data.positions * 1000.0
    with atomic_file(path, "w", newline="") as f:
        f.write(f"# units=mm rate_hz={data.rate_hz:g}\n")
        w = csv.writer(f)
        w.writerow(["frame", "time_s"] + [f"{lab}_{a}" for lab in data.labels for a in "xyz"])
        for t in range(data.n_frames):
            row = [t + data.first_frame, f"{t / data.rate_hz:.6f}"]
            row += ["" if np.isnan(v) else repr(float(v)) for v in mm[t].reshape(-1)]
            w.writerow(row)
    return path


def read_csv(path) -> MarkerData:
    path = _input_file(path)
    lines = _text_lines(path)
    rate, units = None, "mm"
    while lines and lines[0].startswith("#"):
        for tok in lines.pop(0)[1:].split():
            if tok.startswith("rate_hz="):
                rate = float(tok.split("=", 1)[1])
            elif tok.startswith("units="):
                units = tok.split("=", 1)[1]
    rows = list(csv.reader(lines))
    if not rows or rows[0][:2] != ["frame", "time_s"]:
        raise ValueError(f"{path}: expected a header starting frame,time_s")
    cols = rows[0][2:]
    if len(cols) % 3:
        raise ValueError(f"{path}: {len(cols)} coordinate columns, not a multiple of 3")
    labels = [c.rsplit("_", 1)[0] for c in cols[::3]]
    data = [[float(v) if v else np.nan for v in r[2:]] for r in rows[1:]]
    if rate is None:
        times = [float(r[1]) for r in rows[1:3]]
        if len(times) < 2 or times[1] <= times[0]:
            raise ValueError(f"{path}: no rate_hz comment and too few frames to infer the rate")
        rate = 1.0 / (times[1] - times[0])
    pos = np.asarray(data, dtype=np.float64).reshape(len(data), len(labels), 3) * _UNIT_TO_M[units]
    first = int(rows[1][0]) if len(rows) > 1 else 1
    return MarkerData(positions=pos, labels=tuple(labels), rate_hz=rate, first_frame=first)


# ---------------------------------------------------------------- dispatch
_WRITERS = {".c3d": write_c3d, ".trc": write_trc, ".csv": write_csv}
_READERS = {".c3d": read_c3d, ".trc": read_trc, ".csv": read_csv}


def write_markers(data: MarkerData, path) -> Path:
    """Write by suffix: ``.c3d``, ``.trc`` or ``.csv``."""
    suffix = Path(path).suffix.lower()
    if suffix not in _WRITERS:
        raise ValueError(f"unknown marker file type {suffix!r} for {path}; use .c3d, .trc or .csv")
    return _WRITERS[suffix](data, path)


def read_markers(path) -> MarkerData:
    """Read by suffix: ``.c3d``, ``.trc`` or ``.csv``."""
    suffix = Path(path).suffix.lower()
    if suffix not in _READERS:
        raise ValueError(f"unknown marker file type {suffix!r} for {path}; use .c3d, .trc or .csv")
    return _READERS[suffix](path)

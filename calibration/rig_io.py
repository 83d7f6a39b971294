"""Save and load a rig as a calibration TOML file (anipose / Pose2Sim layout).

Layout: docs/conventions.md [calibration-file]. Camera order is explicit
(``[metadata].order``) and never derived by sorting names.
"""
from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import tomli_w

from capture.atomic import atomic_file

from .camera import Camera, Rig, rodrigues_from_rotation, rotation_from_rodrigues

__all__ = ["save_rig", "load_rig", "CalibrationFileError"]

_REQUIRED = ("size", "matrix", "distortions", "rotation", "translation")


class CalibrationFileError(ValueError):
    """A calibration file is missing, malformed, or inconsistent; the message names the field."""


def _camera_table(cam: Camera) -> dict:
    return {
        "name": cam.name,
        "size": [float(cam.size[0]), float(cam.size[1])],
        "matrix": [[float(v) for v in row] for row in cam.K],
        "distortions": [float(v) for v in cam.dist],
        "rotation": [float(v) for v in rodrigues_from_rotation(cam.R)],
        "translation": [float(v) for v in cam.t],
        "fisheye": False,
    }


def save_rig(rig: Rig, path, *, metadata: dict | None = None) -> Path:
    """Write ``rig`` to ``path`` (TOML). ``metadata`` entries are added to ``[metadata]``."""
    if not isinstance(rig, Rig):
        raise TypeError(f"expected a Rig, got {type(rig).__name__}")
    path = Path(path)
    doc: dict = {}
    keys = []
    for i, cam in enumerate(rig.cameras):
        key = f"cam_{i + 1}" if cam.name in doc or cam.name == "metadata" else cam.name
        # keep section names simple TOML bare keys when possible
        key = key if key.replace("_", "").replace("-", "").isalnum() else f"cam_{i + 1}"
        if key in doc:
            key = f"cam_{i + 1}"
        doc[key] = _camera_table(cam)
        keys.append(key)
    meta = {"order": [c.name for c in rig.cameras], "units": "m",
            "conventions": "docs/conventions.md", "n_cameras": len(rig)}
    if metadata:
        for k, v in metadata.items():
            meta[str(k)] = v
    doc["metadata"] = meta
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, "wb") as f:
        tomli_w.dump(doc, f)
    return path


def _vec(table: dict, key: str, shape: tuple, where: str, sizes: tuple = ()) -> np.ndarray:
    """Numeric field ``key`` of exact ``shape``, or 1-D with a length in ``sizes``."""
    if key not in table:
        raise CalibrationFileError(f"{where}: missing field '{key}'")
    try:
        arr = np.asarray(table[key], dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise CalibrationFileError(f"{where}: field '{key}' is not numeric: {table[key]!r}") from e
    ok = arr.shape == shape or (arr.ndim == 1 and arr.size in sizes)
    if not ok:
        want = f"length {' or '.join(map(str, sizes))}" if sizes else f"shape {shape}"
        raise CalibrationFileError(f"{where}: field '{key}' has shape {arr.shape}, expected {want}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationFileError(f"{where}: field '{key}' contains non-finite values")
    return arr


def load_rig(path) -> Rig:
    """Read a calibration TOML file written by :func:`save_rig`, anipose or Pose2Sim."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"calibration file not found: {path}")
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise CalibrationFileError(f"{path}: malformed TOML: {e}") from e
    except IsADirectoryError as e:
        raise CalibrationFileError(f"{path}: a folder, expected a calibration TOML") from e
    meta = doc.get("metadata", {})
    sections = {k: v for k, v in doc.items() if k != "metadata" and isinstance(v, dict)}
    if not sections:
        raise CalibrationFileError(f"{path}: no camera tables found")
    by_name = {}
    for key, table in sections.items():
        name = str(table.get("name", key))
        if name in by_name:
            raise CalibrationFileError(f"{path}: camera name {name!r} appears twice")
        by_name[name] = (key, table)
    order = meta.get("order")
    if order is None:
        names = list(by_name)  # file (insertion) order, never sorted
    else:
        names = [str(n) for n in order]
        missing = [n for n in names if n not in by_name]
        extra = [n for n in by_name if n not in names]
        if missing or extra:
            raise CalibrationFileError(
                f"{path}: [metadata].order does not match the camera tables "
                f"(missing tables: {missing}, tables not in order: {extra})")
    cams = []
    for name in names:
        key, table = by_name[name]
        where = f"{path} [{key}]"
        if table.get("fisheye", False):
            raise CalibrationFileError(f"{where}: fisheye cameras are not supported")
        size = _vec(table, "size", (2,), where)
        K = _vec(table, "matrix", (3, 3), where)
        dist = _vec(table, "distortions", (5,), where, sizes=(4, 5))
        rvec = _vec(table, "rotation", (3,), where)
        t = _vec(table, "translation", (3,), where)
        try:
            cams.append(Camera(name=name, size=(int(round(size[0])), int(round(size[1]))), K=K,
                               dist=dist, R=rotation_from_rodrigues(rvec), t=t))
        except (ValueError, TypeError) as e:
            raise CalibrationFileError(f"{where}: {e}") from e
    return Rig(cameras=tuple(cams))

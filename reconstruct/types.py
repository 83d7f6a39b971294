"""Records passed between reconstruction stages.

2D detections (``capture.detections.Detections2D``) -> :class:`PointCloud` per frame (spatial
correspondence + triangulation) -> :class:`MarkerCloudSequence` -> :class:`Trajectories`
(tracking, gap filling, filtering, rigidity flags).
Conventions: docs/conventions.md [units], [arrays] (C cameras, N points, M markers,
T frames; NaN = missing).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

__all__ = ["PointCloud", "MarkerCloudSequence", "Trajectories"]


def _ro(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, kw_only=True)
class PointCloud:
    """The 3D points reconstructed in one frame.

    Attributes:
        frame: frame index.
        points: (N, 3) m, world frame.
        residual_px: (N,) RMS reprojection error of the contributing rays, px.
        residual_mm: (N,) mean distance of the point to its contributing rays, mm.
        cameras: (N, C) bool, the cameras whose blob contributed.
        obs: (N, C) int64, row of the contributing blob in that camera's blob list of the frame
            (the frame's rows of ``Detections2D`` for that camera, in table order); -1 = none.
    """

    frame: int
    points: np.ndarray
    residual_px: np.ndarray
    residual_mm: np.ndarray
    cameras: np.ndarray
    obs: np.ndarray

    def __post_init__(self):
        p = np.array(self.points, dtype=np.float64)   # copies: the caller's arrays stay writable
        if p.size == 0:
            p = p.reshape(0, 3)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points.shape={p.shape}, expected (N, 3)")
        N = p.shape[0]
        rp = np.array(self.residual_px, dtype=np.float64).reshape(-1)
        rm = np.array(self.residual_mm, dtype=np.float64).reshape(-1)
        if rp.shape != (N,) or rm.shape != (N,):
            raise ValueError(f"residual_px {rp.shape} / residual_mm {rm.shape}, expected ({N},)")
        cams = np.array(self.cameras, dtype=bool)
        obs = np.array(self.obs, dtype=np.int64)
        if cams.ndim != 2 or cams.shape[0] != N:
            raise ValueError(f"cameras.shape={cams.shape}, expected ({N}, C)")
        if obs.shape != cams.shape:
            raise ValueError(f"obs.shape={obs.shape}, expected {cams.shape}")
        if np.any((obs >= 0) != cams):
            raise ValueError("obs and cameras disagree: obs must be >= 0 exactly where cameras")
        object.__setattr__(self, "frame", int(self.frame))
        for name, a in (("points", p), ("residual_px", rp), ("residual_mm", rm),
                        ("cameras", cams), ("obs", obs)):
            object.__setattr__(self, name, _ro(a))

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_cameras(self) -> int:
        return int(self.cameras.shape[1])

    @classmethod
    def empty(cls, frame: int, n_cameras: int) -> "PointCloud":
        return cls(frame=frame, points=np.zeros((0, 3)), residual_px=np.zeros(0),
                   residual_mm=np.zeros(0), cameras=np.zeros((0, n_cameras), bool),
                   obs=np.full((0, n_cameras), -1, np.int64))


@dataclass(frozen=True, kw_only=True)
class MarkerCloudSequence:
    """Unlabelled point clouds of consecutive frames.

    Attributes:
        clouds: T point clouds (one per frame, in frame order; a frame with no points has an
            empty cloud).
        rate_hz: frame rate, or None when unknown.
    """

    clouds: tuple[PointCloud, ...]
    rate_hz: float | None = None

    def __post_init__(self):
        clouds = tuple(self.clouds)
        for c in clouds:
            if not isinstance(c, PointCloud):
                raise TypeError(f"clouds must hold PointCloud, got {type(c).__name__}")
        if clouds:
            C = clouds[0].n_cameras
            bad = [c.frame for c in clouds if c.n_cameras != C]
            if bad:
                raise ValueError(f"frames {bad[:5]} have a camera count other than {C}")
            fr = np.array([c.frame for c in clouds])
            if np.any(np.diff(fr) <= 0):
                raise ValueError("clouds must be in strictly increasing frame order")
        if self.rate_hz is not None and not self.rate_hz > 0:
            raise ValueError(f"rate_hz={self.rate_hz}, expected > 0")
        object.__setattr__(self, "clouds", clouds)

    def __len__(self) -> int:
        return len(self.clouds)

    def __getitem__(self, i) -> PointCloud:
        return self.clouds[i]

    @property
    def frames(self) -> np.ndarray:
        return np.array([c.frame for c in self.clouds], dtype=np.int64)

    def stacked(self) -> np.ndarray:
        """(T, N_max, 3) points padded with NaN."""
        n = max((len(c) for c in self.clouds), default=0)
        out = np.full((len(self.clouds), n, 3), np.nan)
        for i, c in enumerate(self.clouds):
            out[i, : len(c)] = c.points
        return out


@dataclass(frozen=True, kw_only=True)
class Trajectories:
    """Marker trajectories.

    Attributes:
        positions: (T, M, 3) m, NaN = gap ([arrays]).
        rate_hz: frame rate.
        labels: M marker names.
        first_frame: frame index of row 0.
        filled: (T, M) bool, samples produced by gap filling.
        rigidity_flag: (T, M) bool, samples failing the rigidity test.
        residual_mm: (T, M) reconstruction residual (NaN where not reconstructed).
    """

    positions: np.ndarray
    rate_hz: float
    labels: tuple[str, ...]
    first_frame: int = 0
    filled: np.ndarray | None = field(default=None)
    rigidity_flag: np.ndarray | None = field(default=None)
    residual_mm: np.ndarray | None = field(default=None)

    def __post_init__(self):
        p = np.array(self.positions, dtype=np.float64)
        if p.ndim != 3 or p.shape[2] != 3:
            raise ValueError(f"positions.shape={p.shape}, expected (T, M, 3)")
        T, M, _ = p.shape
        labels = tuple(str(s) for s in self.labels)
        if len(labels) != M:
            raise ValueError(f"{len(labels)} labels for {M} markers")
        if not (self.rate_hz and self.rate_hz > 0):
            raise ValueError(f"rate_hz={self.rate_hz}, expected > 0")
        out = {"positions": p}
        for name, dtype, default in (("filled", bool, False), ("rigidity_flag", bool, False),
                                     ("residual_mm", np.float64, np.nan)):
            a = getattr(self, name)
            a = np.full((T, M), default, dtype) if a is None else np.array(a, dtype=dtype)
            if a.shape != (T, M):
                raise ValueError(f"{name}.shape={a.shape}, expected ({T}, {M})")
            out[name] = a
        for k, a in out.items():
            object.__setattr__(self, k, _ro(a))
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "rate_hz", float(self.rate_hz))
        object.__setattr__(self, "first_frame", int(self.first_frame))

    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_markers(self) -> int:
        return int(self.positions.shape[1])

    def present(self) -> np.ndarray:
        """(T, M) bool: the sample is not a gap."""
        return np.all(np.isfinite(self.positions), axis=-1)

    def with_(self, **changes) -> "Trajectories":
        return replace(self, **changes)

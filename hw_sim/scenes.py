"""Marker scenes for the simulated rig: what is in the volume, frame by frame, with truth.

Public API::

    MarkerScene(positions (T, M, 3), marker_diameter_m (M,), rate_hz, labels (M,),
                occluder_segments (T, S, 2, 3) | None, occluder_radii_m (S,) | None,
                wand_spacing_m (M,) | None, joint_centres (T, J, 3) | None)
        .n_frames, .n_markers, .at_time(t_s) -> (points (N, 3), diameters (N,))
    static_markers(n_markers=20, n_frames=10, rng=None, *, rate_hz=100.0,
                   diameter_m=0.014, min_separation_m=0.15, volume_m=VOLUME_M) -> MarkerScene
    wand(n_frames=1000, *, spacing_mm=(0, 250, 500), rate_hz=100.0, rng=None,
         diameter_m=0.014, volume_m=VOLUME_M, sweeps=3.0) -> MarkerScene
    figure(n_frames=200, rate_hz=100.0, rng=None, *, rom_deg=None) -> MarkerScene

``positions`` are in metres in the world frame (z up, floor z = 0), NaN where a marker is
absent. ``occluder_segments`` are capsules (segment endpoints + radius) that hide markers
from cameras (the body of a figure); see ``hw_sim.observe.visibility``.
Conventions: docs/conventions.md [units], [frames], [arrays], [time].
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hw_sim.rig import VOLUME_M, volume_bounds

__all__ = ["MarkerScene", "static_markers", "wand", "figure"]


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, kw_only=True)
class MarkerScene:
    """Markers moving in the volume, with optional occluders and extra truth.

    Attributes:
        positions: (T, M, 3) float64 m, NaN where a marker is absent.
        marker_diameter_m: (M,) marker diameters, m.
        rate_hz: frame rate; frame ``t`` is at ``t / rate_hz`` s ([time]).
        labels: (M,) marker names.
        occluder_segments: (T, S, 2, 3) capsule axis endpoints (m) or None.
        occluder_radii_m: (S,) capsule radii (m) or None (given iff segments are).
        wand_spacing_m: for wand scenes, (M,) marker positions along the wand from the first
            marker (m); the wand length is ``wand_spacing_m[-1]``. None otherwise.
        joint_centres: (T, J, 3) true joint centres of a figure (m) or None.
    """

    positions: np.ndarray
    marker_diameter_m: np.ndarray
    rate_hz: float
    labels: tuple[str, ...]
    occluder_segments: np.ndarray | None = None
    occluder_radii_m: np.ndarray | None = None
    wand_spacing_m: np.ndarray | None = None
    joint_centres: np.ndarray | None = field(default=None)

    def __post_init__(self):
        p = np.array(self.positions, dtype=np.float64)
        if p.ndim != 3 or p.shape[2] != 3:
            raise ValueError(f"positions.shape={p.shape}, expected (T, M, 3)")
        T, M, _ = p.shape
        d = np.array(self.marker_diameter_m, dtype=np.float64).reshape(-1)
        if d.shape != (M,):
            raise ValueError(f"marker_diameter_m.shape={d.shape}, expected ({M},)")
        if np.any(~(d > 0)):
            raise ValueError(f"marker diameters must be > 0, got min {d.min()}")
        if not (self.rate_hz and self.rate_hz > 0):
            raise ValueError(f"rate_hz={self.rate_hz}, expected > 0")
        labels = tuple(str(s) for s in self.labels)
        if len(labels) != M:
            raise ValueError(f"{len(labels)} labels for {M} markers")
        segs, radii = self.occluder_segments, self.occluder_radii_m
        if (segs is None) != (radii is None):
            raise ValueError("occluder_segments and occluder_radii_m must be given together")
        if segs is not None:
            segs = np.array(segs, dtype=np.float64)
            if segs.ndim != 4 or segs.shape[0] != T or segs.shape[2:] != (2, 3):
                raise ValueError(f"occluder_segments.shape={segs.shape}, expected ({T}, S, 2, 3)")
            radii = np.array(radii, dtype=np.float64).reshape(-1)
            if radii.shape != (segs.shape[1],):
                raise ValueError(f"occluder_radii_m.shape={radii.shape}, "
                                 f"expected ({segs.shape[1]},)")
            segs, radii = _readonly(segs), _readonly(radii)
        ws = self.wand_spacing_m
        if ws is not None:
            ws = np.array(ws, dtype=np.float64).reshape(-1)
            if ws.shape != (M,):
                raise ValueError(f"wand_spacing_m.shape={ws.shape}, expected ({M},)")
            ws = _readonly(ws)
        jc = self.joint_centres
        if jc is not None:
            jc = np.array(jc, dtype=np.float64)
            if jc.ndim != 3 or jc.shape[0] != T or jc.shape[2] != 3:
                raise ValueError(f"joint_centres.shape={jc.shape}, expected ({T}, J, 3)")
            jc = _readonly(jc)
        object.__setattr__(self, "positions", _readonly(p))
        object.__setattr__(self, "marker_diameter_m", _readonly(d))
        object.__setattr__(self, "rate_hz", float(self.rate_hz))
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "occluder_segments", segs)
        object.__setattr__(self, "occluder_radii_m", radii)
        object.__setattr__(self, "wand_spacing_m", ws)
        object.__setattr__(self, "joint_centres", jc)

    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_markers(self) -> int:
        return int(self.positions.shape[1])

    def frame_at(self, t_s: float) -> int:
        """Frame index nearest to time ``t_s``, looping over the scene's duration."""
        return int(round(float(t_s) * self.rate_hz)) % self.n_frames

    def at_time(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Present markers at time ``t_s`` (looping): (points (N, 3) m, diameters (N,) m).

        Matches ``hw_sim.sim_camera.Scene`` (``t_s -> (points, diameters)``).
        """
        p = self.positions[self.frame_at(t_s)]
        ok = np.all(np.isfinite(p), axis=1)
        return p[ok], self.marker_diameter_m[ok]


def _rng(rng) -> np.random.Generator:
    return np.random.default_rng(rng)


def static_markers(n_markers: int = 20, n_frames: int = 10, rng=None, *, rate_hz: float = 100.0,
                   diameter_m: float = 0.014, min_separation_m: float = 0.15,
                   volume_m=VOLUME_M) -> MarkerScene:
    """``n_markers`` motionless markers spread uniformly in the volume (0.2 m from its faces),
    at least ``min_separation_m`` apart."""
    if n_markers < 1 or n_frames < 1:
        raise ValueError(f"n_markers={n_markers}, n_frames={n_frames}, expected >= 1")
    g = _rng(rng)
    lo, hi = volume_bounds(volume_m)
    lo, hi = lo + 0.2, hi - 0.2
    pts: list[np.ndarray] = []
    tries = 0
    while len(pts) < n_markers:
        tries += 1
        if tries > 1000 * n_markers:
            raise ValueError(f"cannot place {n_markers} markers {min_separation_m} m apart "
                             f"in volume {volume_m}")
        p = g.uniform(lo, hi)
        if all(np.linalg.norm(p - q) >= min_separation_m for q in pts):
            pts.append(p)
    P = np.broadcast_to(np.array(pts), (n_frames, n_markers, 3)).copy()
    return MarkerScene(positions=P, marker_diameter_m=np.full(n_markers, diameter_m),
                       rate_hz=rate_hz, labels=tuple(f"M{i + 1}" for i in range(n_markers)))


def wand(n_frames: int = 1000, *, spacing_mm=(0.0, 250.0, 500.0), rate_hz: float = 100.0,
         rng=None, diameter_m: float = 0.014, volume_m=VOLUME_M,
         sweeps: float = 3.0) -> MarkerScene:
    """A rigid collinear wand (2 or more markers) waved through the whole volume.

    The wand centre follows a Lissajous path (``sweeps`` to ~2x ``sweeps`` periods per axis
    over the sequence, random phases) filling the volume less half the wand length, and the
    wand axis turns through all orientations (a smooth random direction of the sphere).
    ``spacing_mm`` are the marker positions along the wand (mm), strictly increasing.
    Markers are labelled ``wand_1..wand_M`` in that order.
    """
    s = np.asarray(spacing_mm, dtype=np.float64).reshape(-1) / 1000.0
    if s.size < 2 or np.any(np.diff(s) <= 0):
        raise ValueError(f"spacing_mm={spacing_mm!r}: need >= 2 strictly increasing positions")
    if n_frames < 1:
        raise ValueError(f"n_frames={n_frames}, expected >= 1")
    g = _rng(rng)
    lo, hi = volume_bounds(volume_m)
    half_len = (s[-1] - s[0]) / 2
    lo_c, hi_c = lo + half_len + 0.05, hi - half_len - 0.05
    if np.any(lo_c >= hi_c):
        raise ValueError(f"wand of {2 * half_len:.3f} m does not fit in volume {volume_m}")
    u = np.arange(n_frames) / max(n_frames, 1)
    freqs = sweeps * np.array([1.0, 1.37, 1.83]) * g.uniform(0.9, 1.1, 3)
    phases = g.uniform(0, 2 * np.pi, 3)
    centre = (lo_c + hi_c) / 2 + (hi_c - lo_c) / 2 * np.sin(2 * np.pi * u[:, None] * freqs
                                                          + phases)
    # Direction: sum of sinusoids per component with incommensurate frequencies, normalised;
    # an offset keeps the vector away from zero. It sweeps the whole sphere.
    k = 3
    amp = g.uniform(0.5, 1.0, (k, 3))
    fr = sweeps * 2.0 * g.uniform(0.5, 2.0, (k, 3))
    ph = g.uniform(0, 2 * np.pi, (k, 3))
    v = np.sum(amp * np.sin(2 * np.pi * u[:, None, None] * fr + ph), axis=1)
    small = np.linalg.norm(v, axis=1) < 1e-3
    v[small] += np.array([1e-3, 0, 0])
    d = v / np.linalg.norm(v, axis=1, keepdims=True)
    offs = s - (s[0] + s[-1]) / 2
    P = centre[:, None, :] + offs[None, :, None] * d[:, None, :]
    M = s.size
    return MarkerScene(positions=P, marker_diameter_m=np.full(M, diameter_m), rate_hz=rate_hz,
                       labels=tuple(f"wand_{i + 1}" for i in range(M)),
                       wand_spacing_m=s - s[0])


def figure(n_frames: int = 200, rate_hz: float = 100.0, rng=None, *,
           rom_deg: float | None = None) -> MarkerScene:
    """An articulated humanoid (``hw_sim.articulated``) moving with a wide range of motion.

    Its body-segment capsules are the scene's occluders, so markers are hidden by the body.
    ``rom_deg`` (None: the animation's default) scales the joint range of motion.
    """
    import importlib

    articulated = importlib.import_module("hw_sim.articulated")
    g = _rng(rng)
    fig = articulated.humanoid(g)
    kw = {} if rom_deg is None else {"rom_deg": rom_deg}
    motion = articulated.animate(fig, n_frames, rate_hz, rng=g, **kw)
    markers = np.asarray(motion.markers, dtype=np.float64)
    M = markers.shape[1]
    labels = _first_attr((fig, motion), ("marker_names", "marker_labels", "labels"))
    labels = tuple(labels) if labels is not None else tuple(f"M{i + 1}" for i in range(M))
    diam = _first_attr((fig, motion), ("marker_diameter_m", "marker_diameters_m"))
    diam = np.broadcast_to(np.asarray(0.014 if diam is None else diam, np.float64), (M,))
    radii = _first_attr((fig, motion), ("capsule_radii_m", "capsule_radius_m",
                                        "segment_radii_m", "radii_m", "capsule_radii"))
    caps = _first_attr((motion,), ("capsules", "capsule_segments"))
    if caps is None or radii is None:
        raise ValueError("hw_sim.articulated gave no capsules/radii for occlusion "
                         f"(capsules={caps is not None}, radii={radii is not None})")
    jc = _first_attr((motion,), ("joint_centres", "joint_centers"))
    return MarkerScene(positions=markers, marker_diameter_m=diam, rate_hz=rate_hz,
                       labels=labels, occluder_segments=caps, occluder_radii_m=radii,
                       joint_centres=jc)


def _first_attr(objs, names):
    for o in objs:
        for n in names:
            v = getattr(o, n, None)
            if v is not None:
                return v
    return None

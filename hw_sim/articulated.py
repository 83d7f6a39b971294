"""Simulated articulated figures (a humanoid and random trees) and their motion, with truth.

Public API::

    Figure(segment_names, parents (S,), joint_offsets (S, 3), joint_types, hinge_axes (S, 3),
           marker_segment (M,), marker_offsets (M, 3), capsule_local (S, 2, 3),
           capsule_radii_m (S,), marker_names, marker_diameter_m)
    humanoid(rng=None) -> Figure                       # 15 segments, 45 markers, ~1.8 m
    random_tree(n_segments, markers_per_segment=(2, 4), rng=None) -> Figure
    animate(figure, n_frames, rate_hz=120.0, rom_deg=60.0, rng=None,
            root_path="loop") -> Motion

Each segment has a frame whose origin is its proximal joint (the root's origin is the pelvis
centre). At the rest pose every segment frame is parallel to the world frame, so a hinge axis
is the same vector in the parent and in the child frame. ``joint_offsets[s]`` is the position
of segment ``s``'s joint in its parent's frame (zero for the root). Markers are rigid in
their segment's frame and stand off the capsule surface (the body volume used for occlusion).
Conventions: docs/conventions.md [units], [frames] (world z up, floor z = 0), [arrays].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["Figure", "Motion", "humanoid", "random_tree", "animate", "JOINT_TYPES",
           "ROOT_PATHS"]

JOINT_TYPES = ("ball", "hinge")
ROOT_PATHS = ("loop", "fixed")
MARKER_STANDOFF_M = 0.012  # marker centre above the skin (half a 14 mm marker + base)
# Default smallest centre distance between two markers of one segment: a 14 mm body marker's
# diameter plus the 6 mm its base needs. Closer 14 mm markers would overlap.
MIN_MARKER_SPACING_M = 0.020


def _rng(rng) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


def _ro(a) -> np.ndarray:
    a = np.array(a, dtype=np.float64)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, kw_only=True)
class Figure:
    """A tree of rigid segments with markers (see module docstring for frames).

    Attributes:
        segment_names: (S,) names.
        parents: (S,) int parent index, -1 for the root (segment 0); parents[s] < s.
        joint_offsets: (S, 3) m, joint of segment s in its parent's frame (root: 0).
        joint_types: (S,) 'ball' or 'hinge' (the root's is 'ball': a free joint).
        hinge_axes: (S, 3) unit hinge axis (parent frame = segment frame); NaN for ball joints.
        marker_segment: (M,) int segment of each marker.
        marker_offsets: (M, 3) m, marker centre in its segment's frame.
        capsule_local: (S, 2, 3) m, capsule axis endpoints in the segment frame.
        capsule_radii_m: (S,) capsule radii.
        marker_names: (M,) names.
        marker_diameter_m: marker diameter.
    """

    segment_names: tuple[str, ...]
    parents: np.ndarray
    joint_offsets: np.ndarray
    joint_types: tuple[str, ...]
    hinge_axes: np.ndarray
    marker_segment: np.ndarray
    marker_offsets: np.ndarray
    capsule_local: np.ndarray
    capsule_radii_m: np.ndarray
    marker_names: tuple[str, ...]
    marker_diameter_m: float = 0.014

    def __post_init__(self):
        S = len(self.segment_names)
        par = np.asarray(self.parents)
        if par.shape != (S,) or not np.issubdtype(par.dtype, np.integer):
            raise ValueError(f"parents shape {par.shape} dtype {par.dtype}, expected ({S},) int")
        if S == 0 or par[0] != -1 or np.any(par[1:] < 0) or np.any(par[1:] >= np.arange(1, S)):
            raise ValueError(f"parents={par.tolist()}: need parents[0] == -1 and "
                             "0 <= parents[s] < s")
        for name, shape in (("joint_offsets", (S, 3)), ("hinge_axes", (S, 3)),
                            ("capsule_local", (S, 2, 3)), ("capsule_radii_m", (S,))):
            a = np.asarray(getattr(self, name))
            if a.shape != shape:
                raise ValueError(f"{name}.shape={a.shape}, expected {shape}")
        if len(self.joint_types) != S or any(j not in JOINT_TYPES for j in self.joint_types):
            raise ValueError(f"joint_types={self.joint_types!r}, expected {S} of {JOINT_TYPES}")
        ax = np.asarray(self.hinge_axes)
        for s, j in enumerate(self.joint_types):
            if j == "hinge" and abs(np.linalg.norm(ax[s]) - 1) > 1e-9:
                raise ValueError(f"hinge_axes[{s}]={ax[s]} is not a unit vector")
        ms = np.asarray(self.marker_segment)
        M = ms.shape[0] if ms.ndim == 1 else -1
        if M < 0 or not np.issubdtype(ms.dtype, np.integer) or np.any((ms < 0) | (ms >= S)):
            raise ValueError(f"marker_segment={ms!r}, expected (M,) ints in [0, {S})")
        if np.asarray(self.marker_offsets).shape != (M, 3):
            raise ValueError(f"marker_offsets.shape={np.asarray(self.marker_offsets).shape}, "
                             f"expected ({M}, 3)")
        if len(self.marker_names) != M:
            raise ValueError(f"len(marker_names)={len(self.marker_names)}, expected {M}")
        for name in ("parents", "joint_offsets", "hinge_axes", "marker_segment",
                     "marker_offsets", "capsule_local", "capsule_radii_m"):
            object.__setattr__(self, name, _ro(getattr(self, name)) if name not in
                               ("parents", "marker_segment") else
                               _ro_int(getattr(self, name)))

    @property
    def n_segments(self) -> int:
        return len(self.segment_names)

    @property
    def n_markers(self) -> int:
        return len(self.marker_names)

    @property
    def capsule_length_m(self) -> np.ndarray:
        """(S,) capsule axis lengths."""
        return np.linalg.norm(self.capsule_local[:, 1] - self.capsule_local[:, 0], axis=1)


def _ro_int(a) -> np.ndarray:
    a = np.array(a, dtype=np.int64)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, kw_only=True)
class Motion:
    """World poses of every segment per frame, and the resulting markers and joints.

    Attributes:
        world_from_segment_R: (T, S, 3, 3) rotations.
        world_from_segment_t: (T, S, 3) m, segment origins (= joint centres).
        markers: (T, M, 3) m.
        joint_centres: (T, S, 3) m, proximal joint of each segment (root: its origin).
        capsules: (T, S, 2, 3) m, capsule axis endpoints.
        rate_hz: frame rate ([time]).
    """

    world_from_segment_R: np.ndarray
    world_from_segment_t: np.ndarray
    markers: np.ndarray
    joint_centres: np.ndarray
    capsules: np.ndarray
    rate_hz: float

    def __post_init__(self):
        R = np.asarray(self.world_from_segment_R)
        if R.ndim != 4 or R.shape[2:] != (3, 3):
            raise ValueError(f"world_from_segment_R.shape={R.shape}, expected (T, S, 3, 3)")
        T, S = R.shape[:2]
        M = np.asarray(self.markers).shape[1] if np.asarray(self.markers).ndim == 3 else -1
        for name, shape in (("world_from_segment_t", (T, S, 3)), ("markers", (T, M, 3)),
                            ("joint_centres", (T, S, 3)), ("capsules", (T, S, 2, 3))):
            a = np.asarray(getattr(self, name))
            if a.shape != shape:
                raise ValueError(f"{name}.shape={a.shape}, expected {shape}")
        if not self.rate_hz > 0:
            raise ValueError(f"rate_hz={self.rate_hz!r}, expected > 0")
        for name in ("world_from_segment_R", "world_from_segment_t", "markers",
                     "joint_centres", "capsules"):
            object.__setattr__(self, name, _ro(getattr(self, name)))

    @property
    def world_from_segment(self) -> tuple[np.ndarray, np.ndarray]:
        return self.world_from_segment_R, self.world_from_segment_t

    @property
    def n_frames(self) -> int:
        return self.markers.shape[0]


def _perp_basis(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = a / np.linalg.norm(a)
    h = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(a, h)
    u /= np.linalg.norm(u)
    return u, np.cross(a, u)


def _surface_markers(cap: np.ndarray, radius: float, fracs, angles_rad) -> np.ndarray:
    """Marker offsets on a capsule surface (+ stand-off) at axis fractions and azimuths."""
    a = cap[1] - cap[0]
    if np.linalg.norm(a) < 1e-9:
        a = np.array([0, 0, 1.0])
    u, v = _perp_basis(a)
    out = []
    for f, ang in zip(fracs, angles_rad):
        p = cap[0] + f * (cap[1] - cap[0])
        out.append(p + (radius + MARKER_STANDOFF_M) * (np.cos(ang) * u + np.sin(ang) * v))
    return np.array(out)


def humanoid(rng=None) -> Figure:
    """A 15-segment human figure (~1.8 m tall) with 45 markers; knees and elbows are hinges.

    ``rng`` jitters the marker placement (a few cm along and around each segment); None or
    a fixed seed gives a reproducible layout.
    """
    g = _rng(rng)
    z = np.zeros(3)
    segs = []  # name, parent, offset, type, axis, capsule (2,3), radius, n_markers

    def add(name, parent, off, typ, axis, cap, r, nm):
        segs.append((name, parent, np.asarray(off, float), typ,
                     np.full(3, np.nan) if axis is None else np.asarray(axis, float),
                     np.asarray(cap, float), r, nm))

    add("pelvis", -1, z, "ball", None, [[0, -0.1, 0], [0, 0.1, 0]], 0.12, 4)
    add("torso", 0, [0, 0, 0.08], "ball", None, [[0, 0, 0.05], [0, 0, 0.45]], 0.14, 4)
    add("head", 1, [0, 0, 0.5], "ball", None, [[0, 0, 0.06], [0, 0, 0.14]], 0.1, 3)
    for side, sy in (("l", 1.0), ("r", -1.0)):
        base = len(segs)
        add(f"{side}_upperarm", 1, [0, 0.19 * sy, 0.45], "ball", None,
            [[0, 0, -0.03], [0, 0, -0.27]], 0.05, 3)
        add(f"{side}_forearm", base, [0, 0, -0.29], "hinge", [0, -1.0, 0],
            [[0, 0, -0.02], [0, 0, -0.25]], 0.04, 3)
        add(f"{side}_hand", base + 1, [0, 0, -0.27], "ball", None,
            [[0, 0, -0.03], [0, 0, -0.15]], 0.035, 2)
    for side, sy in (("l", 1.0), ("r", -1.0)):
        base = len(segs)
        add(f"{side}_thigh", 0, [0, 0.09 * sy, -0.05], "ball", None,
            [[0, 0, -0.05], [0, 0, -0.40]], 0.07, 3)
        add(f"{side}_shank", base, [0, 0, -0.43], "hinge", [0, 1.0, 0],
            [[0, 0, -0.04], [0, 0, -0.40]], 0.05, 3)
        add(f"{side}_foot", base + 1, [0, 0, -0.43], "ball", None,
            [[-0.04, 0, -0.04], [0.16, 0, -0.04]], 0.04, 3)
    return _build(segs, g)


def _seg_dist(p: np.ndarray, cap: np.ndarray) -> float:
    """Distance from point p to the capsule axis segment cap (2, 3)."""
    a, b = cap
    ab = b - a
    u = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-12), 0.0, 1.0)
    return float(np.linalg.norm(p - a - u * ab))


def _build(segs, g: np.random.Generator, min_spacing_m: float = 0.0) -> Figure:
    # rest-pose origins (all segment frames parallel to the world)
    origin = []
    for name, parent, off, *_ in segs:
        origin.append(off if parent < 0 else origin[parent] + off)
    caps_rest = [origin[s] + x[5] for s, x in enumerate(segs)]
    mseg, moff, mnames = [], [], []
    for s, (name, _, _, _, _, cap, r, nm) in enumerate(segs):
        fr = np.linspace(0.2, 0.9, nm) + g.uniform(-0.05, 0.05, nm)
        ang = np.arange(nm) * (2 * np.pi / max(nm, 3)) + g.uniform(-0.4, 0.4, nm) + 0.3 * s
        off = _surface_markers(cap, r, fr, ang)
        for k in range(nm):  # keep markers outside the other segments' bodies at rest,
            for _ in range(400):  # and apart from this segment's other markers
                p = origin[s] + off[k]
                if (all(_seg_dist(p, caps_rest[o]) > segs[o][6] + MARKER_STANDOFF_M
                        for o in range(len(segs)) if o != s)
                        and all(np.linalg.norm(off[k] - off[j]) >= min_spacing_m
                                for j in range(nm) if j != k)):
                    break
                off[k] = _surface_markers(cap, r, g.uniform(0.1, 0.95, 1),
                                          g.uniform(0, 2 * np.pi, 1))[0]
        mseg += [s] * nm
        moff.append(off)
        mnames += [f"{name}_{k + 1}" for k in range(nm)]
    return Figure(segment_names=tuple(x[0] for x in segs),
                  parents=np.array([x[1] for x in segs]),
                  joint_offsets=np.array([x[2] for x in segs]),
                  joint_types=tuple(x[3] for x in segs),
                  hinge_axes=np.array([x[4] for x in segs]),
                  marker_segment=np.array(mseg, dtype=np.int64),
                  marker_offsets=np.concatenate(moff),
                  capsule_local=np.array([x[5] for x in segs]),
                  capsule_radii_m=np.array([x[6] for x in segs], float),
                  marker_names=tuple(mnames))


def random_tree(n_segments: int, markers_per_segment=(2, 4), rng=None, *,
                hinge_fraction: float = 0.3,
                min_marker_spacing_m: float = MIN_MARKER_SPACING_M) -> Figure:
    """A random tree of ``n_segments`` limb-like segments (0.2-0.4 m capsules).

    Each non-root segment hangs from a random earlier segment at 60-100 % of the parent's
    capsule; about ``hinge_fraction`` of the joints are hinges with a random axis
    perpendicular to the child's capsule. Each segment carries a random number of markers in
    ``markers_per_segment`` (inclusive range), placed on the capsule surface at least
    ``min_marker_spacing_m`` apart (default: 14 mm body markers; hand-sized 6 mm markers
    may sit 7 mm apart; 0 allows markers to overlap).
    """
    if not isinstance(n_segments, (int, np.integer)) or n_segments < 1:
        raise ValueError(f"n_segments={n_segments!r}, expected an int >= 1")
    lo, hi = markers_per_segment
    if not 1 <= lo <= hi:
        raise ValueError(f"markers_per_segment={markers_per_segment!r}, expected 1 <= lo <= hi")
    if not 0.0 <= min_marker_spacing_m < 0.1:
        raise ValueError(f"min_marker_spacing_m={min_marker_spacing_m!r}, expected 0 <= m < 0.1")
    g = _rng(rng)
    segs = []
    for s in range(n_segments):
        d = g.normal(size=3)
        d /= np.linalg.norm(d)
        length = g.uniform(0.2, 0.4)
        r = g.uniform(0.03, 0.07)
        cap = np.array([0.03 * d, (0.03 + length) * d])
        nm = int(g.integers(lo, hi + 1))
        if s == 0:
            segs.append(("seg0", -1, np.zeros(3), "ball", np.full(3, np.nan), cap, r, nm))
            continue
        p = int(g.integers(0, s))
        pc = segs[p][5]
        off = pc[0] + g.uniform(0.6, 1.0) * (pc[1] - pc[0])
        if g.uniform() < hinge_fraction:
            u, v = _perp_basis(d)
            ang = g.uniform(0, 2 * np.pi)
            axis = np.cos(ang) * u + np.sin(ang) * v
            segs.append((f"seg{s}", p, off, "hinge", axis, cap, r, nm))
        else:
            segs.append((f"seg{s}", p, off, "ball", np.full(3, np.nan), cap, r, nm))
    return _build(segs, g, float(min_marker_spacing_m))


def _smooth_signal(g: np.random.Generator, t_s: np.ndarray, n_sines: int = 3) -> np.ndarray:
    """Sum of sinusoids (0.15-0.8 Hz) rescaled to span exactly [-1, 1] over ``t_s``."""
    if t_s.size < 2:
        return np.zeros_like(t_s)
    f = g.uniform(0.15, 0.8, n_sines)
    ph = g.uniform(0, 2 * np.pi, n_sines)
    a = g.uniform(0.5, 1.0, n_sines)
    s = (a[:, None] * np.sin(2 * np.pi * f[:, None] * t_s[None] + ph[:, None])).sum(0)
    # Short clips: add a linear ramp so the signal never stays (nearly) constant.
    s = s + np.linspace(-1.0, 1.0, t_s.size) * g.choice([-1, 1])
    span = s.max() - s.min()
    return 2 * (s - s.min()) / span - 1


def animate(figure: Figure, n_frames: int, rate_hz: float = 120.0, rom_deg: float = 60.0,
            rng=None, root_path: str = "loop", soft_tissue_m: float = 0.0) -> Motion:
    """Smooth motion of ``figure`` over ``n_frames`` frames at ``rate_hz``.

    Every non-root joint's rotation (relative to its parent, about the rest pose) has a
    primary angle spanning exactly ``rom_deg`` (hinges: about their axis, from 0 to rom_deg;
    ball joints: about a random axis, centred, plus two perpendicular components of half
    that span). The root walks a figure-eight of 1.2 m half-width centred at the origin,
    facing along its path (``root_path="loop"``) or turns on the spot (``"fixed"``); its
    height keeps the lowest body surface point on the floor z = 0 in every frame.

    ``soft_tissue_m``: skin markers are not rigid on their bone; with it > 0 each marker
    also slides in its segment's frame by a slow smooth displacement (per axis a sum of
    sinusoids at 0.15-0.8 Hz spanning exactly +-soft_tissue_m), as soft-tissue artefacts do
    on real recordings (the joints, the truth, do not move with it). Drawn after everything
    else, so figures animated without it are the same with or without this option.
    """
    if root_path not in ROOT_PATHS:
        raise ValueError(f"root_path={root_path!r}, expected one of {ROOT_PATHS}")
    if not soft_tissue_m >= 0:
        raise ValueError(f"soft_tissue_m={soft_tissue_m!r}, expected >= 0 (m)")
    if not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise ValueError(f"n_frames={n_frames!r}, expected an int >= 1")
    if not rate_hz > 0:
        raise ValueError(f"rate_hz={rate_hz!r}, expected > 0")
    g = _rng(rng)
    T, S = int(n_frames), figure.n_segments
    t_s = np.arange(T) / rate_hz
    rom = np.deg2rad(rom_deg)
    R_local = np.empty((T, S, 3, 3))
    for s in range(1, S):
        if figure.joint_types[s] == "hinge":
            theta = 0.5 * rom * (_smooth_signal(g, t_s) + 1.0)
            rv = theta[:, None] * figure.hinge_axes[s][None]
        else:
            d = g.normal(size=3)
            d /= np.linalg.norm(d)
            u, v = _perp_basis(d)
            rv = (0.5 * rom * _smooth_signal(g, t_s)[:, None] * d
                  + 0.25 * rom * _smooth_signal(g, t_s)[:, None] * u
                  + 0.25 * rom * _smooth_signal(g, t_s)[:, None] * v)
        R_local[:, s] = Rotation.from_rotvec(rv).as_matrix()
    # Root: heading along a figure-eight path plus small pitch/roll sway.
    period_s = 24.0
    ph = g.uniform(0, 2 * np.pi)
    w = 2 * np.pi / period_s
    if root_path == "loop":
        xy = np.stack([1.2 * np.sin(w * t_s + ph), 0.8 * np.sin(2 * (w * t_s + ph))], 1)
        vel = np.stack([1.2 * w * np.cos(w * t_s + ph),
                        1.6 * w * np.cos(2 * (w * t_s + ph))], 1)
        yaw = np.unwrap(np.arctan2(vel[:, 1], vel[:, 0]))
    else:
        xy = np.zeros((T, 2))
        yaw = ph + 0.3 * t_s  # 0.3 rad/s turn
    sway = np.deg2rad(8.0) * np.stack([_smooth_signal(g, t_s), _smooth_signal(g, t_s)], 1)
    R_root = Rotation.from_euler("ZYX", np.column_stack([yaw, sway]), degrees=False)
    R_w = np.empty((T, S, 3, 3))
    t_w = np.empty((T, S, 3))
    R_w[:, 0] = R_root.as_matrix()
    t_w[:, 0] = 0.0
    par = figure.parents
    for s in range(1, S):
        p = par[s]
        R_w[:, s] = R_w[:, p] @ R_local[:, s]
        t_w[:, s] = t_w[:, p] + R_w[:, p] @ figure.joint_offsets[s]
    caps = t_w[:, :, None, :] + np.einsum("tsij,skj->tski", R_w, figure.capsule_local)
    lowest = (caps[..., 2] - figure.capsule_radii_m[None, :, None]).min(axis=(1, 2))
    shift = np.zeros((T, 3))
    shift[:, :2] = xy
    shift[:, 2] = -lowest
    t_w += shift[:, None, :]
    caps += shift[:, None, None, :]
    ms = figure.marker_segment
    offsets = np.broadcast_to(figure.marker_offsets, (T,) + figure.marker_offsets.shape)
    if soft_tissue_m > 0:
        wobble = np.stack([np.stack([_smooth_signal(g, t_s) for _ in range(3)], 1)
                           for _ in range(figure.marker_offsets.shape[0])], 1)
        offsets = offsets + soft_tissue_m * wobble
    markers = t_w[:, ms] + np.einsum("tmij,tmj->tmi", R_w[:, ms], offsets)
    return Motion(world_from_segment_R=R_w, world_from_segment_t=t_w, markers=markers,
                  joint_centres=t_w.copy(), capsules=caps, rate_hz=float(rate_hz))

"""BVH export of a fitted rigid skeleton.

``write_bvh(path, rigid: RigidSkeleton, fit: SkeletonFit, rate_hz=None, units="m",
y_up=True) -> Path``. One BVH joint per segment, named after it; the root has six channels
(``Xposition Yposition Zposition Zrotation Xrotation Yrotation``), every other joint the three
rotations (``Zrotation Xrotation Yrotation``: the local rotation is ``Rz @ Rx @ Ry``, degrees,
docs/conventions.md [rotations]). ``ROOT OFFSET 0 0 0``; a joint's OFFSET is its centre in
the parent's frame (``RigidSkeleton.joint_offsets``); a leaf's End Site is its markers'
centroid. The rest pose (all rotations zero) is the skeleton in its reference posture.

Units and axes (docs/skeleton_outputs.md): lengths are written in ``units`` ("m" default,
"cm" or "mm"; BVH has no unit field); with ``y_up`` (default) the world is turned from our
z-up frame into the y-up frame most BVH tools assume: ``bvh = Q @ world`` with
``Q = [[1,0,0],[0,0,1],[0,-1,0]]`` (x stays, z -> y, y -> -z), applied to every frame too.

Frames where a segment could not be fitted (``SkeletonFit.status == FIT_NONE``) hold the
nearest fitted frame's local rotation (and root position) since BVH has no missing values;
``bvh_filled_frames`` says which.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from capture.atomic import write_text_atomic

from skeleton.fit import SkeletonFit
from skeleton.rigid_skeleton import RigidSkeleton

__all__ = ["write_bvh", "bvh_local_motion", "Y_UP_FROM_Z_UP", "UNITS"]

UNITS = {"m": 1.0, "cm": 100.0, "mm": 1000.0}
Y_UP_FROM_Z_UP = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
_ROT_CHANNELS = "Zrotation Xrotation Yrotation"


def _fill_nearest(valid: np.ndarray) -> np.ndarray:
    """(T,) index of the nearest valid frame for every frame (valid must have a True)."""
    idx = np.flatnonzero(valid)
    T = valid.size
    pos = np.searchsorted(idx, np.arange(T))
    lo = idx[np.clip(pos - 1, 0, idx.size - 1)]
    hi = idx[np.clip(pos, 0, idx.size - 1)]
    t = np.arange(T)
    return np.where(np.abs(t - lo) <= np.abs(hi - t), lo, hi)


def bvh_local_motion(rigid: RigidSkeleton, fit: SkeletonFit, y_up: bool = True):
    """Local rotations (T, S, 3, 3) (root: world_from_root), root positions (T, 3) m, all in
    the BVH axes, and filled (T, S) bool: frames held from the nearest fitted one."""
    Rw = np.asarray(fit.world_from_segment_R)
    T, S = Rw.shape[:2]
    if S != rigid.n_segments:
        raise ValueError(f"fit has {S} segments, rigid skeleton {rigid.n_segments}")
    Q = Y_UP_FROM_Z_UP if y_up else np.eye(3)
    loc = np.empty((T, S, 3, 3))
    filled = np.zeros((T, S), bool)
    for s in range(S):
        p = rigid.parents[s]
        R = Rw[:, s] if p < 0 else np.einsum("tji,tjk->tik", Rw[:, p], Rw[:, s])
        ok = ~np.isnan(R).any(axis=(1, 2))
        if ok.any():
            R = R[_fill_nearest(ok)]
        else:
            R = np.broadcast_to(np.eye(3), (T, 3, 3))
        loc[:, s] = Q @ R @ Q.T
        filled[:, s] = ~ok
    t = np.asarray(fit.world_from_segment_t)[:, rigid.root]
    ok = ~np.isnan(t).any(1)
    t = t[_fill_nearest(ok)] if ok.any() else np.zeros((T, 3))
    return loc, t @ Q.T, filled


def write_bvh(path, rigid: RigidSkeleton, fit: SkeletonFit, rate_hz: float | None = None,
              units: str = "m", y_up: bool = True) -> Path:
    if units not in UNITS:
        raise ValueError(f"units={units!r}, expected one of {tuple(UNITS)}")
    rate = float(fit.rate_hz if rate_hz is None else rate_hz)
    if not rate > 0:
        raise ValueError(f"rate_hz={rate_hz!r}, expected > 0")
    k = UNITS[units]
    Q = Y_UP_FROM_Z_UP if y_up else np.eye(3)
    loc, root_t, _ = bvh_local_motion(rigid, fit, y_up)
    T = loc.shape[0]
    kids = rigid.children
    fmt = "{:.9g}".format
    lines = ["HIERARCHY"]
    order: list[int] = []

    def vec(v):
        return " ".join(fmt(float(x)) for x in v)

    def joint(s, depth):
        ind = "  " * depth
        order.append(s)
        if s == rigid.root:
            lines.append(f"ROOT {rigid.segment_names[s]}")
            lines.extend([f"{ind}{{", f"{ind}  OFFSET 0 0 0",
                          f"{ind}  CHANNELS 6 Xposition Yposition Zposition {_ROT_CHANNELS}"])
        else:
            lines.append(f"{ind}JOINT {rigid.segment_names[s]}")
            lines.extend([f"{ind}{{", f"{ind}  OFFSET {vec(k * Q @ rigid.joint_offsets[s])}",
                          f"{ind}  CHANNELS 3 {_ROT_CHANNELS}"])
        for c in kids[s]:
            joint(c, depth + 1)
        if not kids[s]:
            lines.extend([f"{ind}  End Site", f"{ind}  {{",
                          f"{ind}    OFFSET {vec(k * Q @ rigid.end_sites[s])}", f"{ind}  }}"])
        lines.append(f"{ind}}}")

    joint(rigid.root, 0)
    eul = Rotation.from_matrix(loc[:, order].reshape(-1, 3, 3)).as_euler("ZXY", degrees=True)
    eul = eul.reshape(T, len(order) * 3)
    data = np.concatenate([k * root_t, eul], 1)
    lines += ["MOTION", f"Frames: {T}", f"Frame Time: {1.0 / rate:.9g}"]
    lines += [" ".join(fmt(float(x)) for x in row) for row in data]
    return write_text_atomic(path, "\n".join(lines) + "\n")

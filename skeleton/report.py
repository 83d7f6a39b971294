"""Skeleton JSON (write/read) and the thesis' evaluation table of marker deviations.

- ``write_skeleton_json(path, rigid, extra=None)`` / ``read_skeleton_json(path) ->
  RigidSkeleton``: segments (parent, markers, joint type, hinge axes, bone length, End
  Site), markers (segment, offset) and joints (parent, child, offset, type, axis, fit
  residual), in metres (layout: docs/skeleton_outputs.md). NaN is written as ``null``.
- ``marker_deviation_table(trajectories, rigid, fit) -> DeviationTable``: per marker, the
  average distance between the measured and the fitted marker over the frames where both
  exist (the thesis' Tables 5.2-5.7, 000 chapter 5); ``.format()`` prints it.
- ``summary_table(rigid, deviation, junctions=()) -> str``: segments, markers per segment,
  joints, bone lengths and mean marker deviation, and the junctions (segments meeting at
  one point, re-linked around a hub) (the ``mocap skeleton`` summary).
Conventions: docs/conventions.md [units] (files in m, printed tables in mm).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from capture.atomic import write_text_atomic

from skeleton.fit import SkeletonFit
from skeleton.rigid_skeleton import RigidSkeleton

__all__ = ["FORMAT", "skeleton_to_dict", "skeleton_from_dict", "write_skeleton_json",
           "read_skeleton_json", "DeviationTable", "marker_deviation_table", "summary_table"]

FORMAT = "openmocap-skeleton/1"


def _list(v) -> list:
    return [None if not np.isfinite(x) else float(x) for x in np.asarray(v, float).ravel()]


def _arr(v) -> np.ndarray:
    return np.array([np.nan if x is None else float(x) for x in v])


def skeleton_to_dict(rigid: RigidSkeleton, extra: dict | None = None) -> dict:
    S = rigid.n_segments
    kids = rigid.children
    segs = []
    for s in range(S):
        p = int(rigid.parents[s])
        segs.append({
            "name": rigid.segment_names[s],
            "parent": None if p < 0 else rigid.segment_names[p],
            "markers": [rigid.marker_names[m] for m in np.flatnonzero(rigid.marker_segment == s)],
            "children": [rigid.segment_names[c] for c in kids[s]],
            "end_site_m": _list(rigid.end_sites[s]),
        })
    markers = [{"name": rigid.marker_names[m],
                "segment": rigid.segment_names[int(rigid.marker_segment[m])],
                "offset_m": _list(rigid.marker_offsets[m])} for m in range(rigid.n_markers)]
    joints = []
    for s in rigid.order[1:]:
        s = int(s)
        joints.append({
            "parent": rigid.segment_names[int(rigid.parents[s])],
            "child": rigid.segment_names[s],
            "type": "hinge" if rigid.hinge[s] else "ball",
            "offset_in_parent_m": _list(rigid.joint_offsets[s]),
            "bone_length_m": float(rigid.bone_lengths[s]),
            "hinge_axis_parent": _list(rigid.hinge_axes_parent[s]),
            "hinge_axis_child": _list(rigid.hinge_axes_child[s]),
            "residual_m": _list([rigid.joint_residual_m[s]])[0],
        })
    out = {"format": FORMAT, "units": "m",
           "frames": "segment frames: origin at the proximal joint (root: markers' centroid), "
                     "axes of the world (z up) at the segment's reference frame",
           "root": rigid.segment_names[rigid.root], "segments": segs, "markers": markers,
           "joints": joints}
    if extra:
        out["extra"] = extra
    return out


def skeleton_from_dict(d: dict) -> RigidSkeleton:
    if d.get("format") != FORMAT:
        raise ValueError(f"format={d.get('format')!r}, expected {FORMAT!r}")
    names = [s["name"] for s in d["segments"]]
    idx = {n: i for i, n in enumerate(names)}
    S = len(names)
    parents = np.array([-1 if s["parent"] is None else idx[s["parent"]] for s in d["segments"]])
    mnames = [m["name"] for m in d["markers"]]
    jo = np.zeros((S, 3))
    hinge = np.zeros(S, bool)
    ap = np.full((S, 3), np.nan)
    ac = np.full((S, 3), np.nan)
    res = np.full(S, np.nan)
    for j in d["joints"]:
        c = idx[j["child"]]
        if parents[c] != idx[j["parent"]]:
            raise ValueError(f"joint {j['parent']}-{j['child']} disagrees with the segments' "
                             "parents")
        jo[c] = _arr(j["offset_in_parent_m"])
        hinge[c] = j["type"] == "hinge"
        ap[c] = _arr(j["hinge_axis_parent"])
        ac[c] = _arr(j["hinge_axis_child"])
        res[c] = np.nan if j["residual_m"] is None else j["residual_m"]
    return RigidSkeleton(
        segment_names=tuple(names), parents=parents, root=idx[d["root"]],
        marker_names=tuple(mnames),
        marker_segment=np.array([idx[m["segment"]] for m in d["markers"]], np.int64),
        marker_offsets=np.array([_arr(m["offset_m"]) for m in d["markers"]]).reshape(-1, 3),
        joint_offsets=jo, hinge=hinge, hinge_axes_parent=ap, hinge_axes_child=ac,
        joint_residual_m=res,
        end_sites=np.array([_arr(s["end_site_m"]) for s in d["segments"]]).reshape(S, 3))


def write_skeleton_json(path, rigid: RigidSkeleton, extra: dict | None = None) -> Path:
    return write_text_atomic(path, json.dumps(skeleton_to_dict(rigid, extra), indent=1) + "\n")


def read_skeleton_json(path) -> RigidSkeleton:
    return skeleton_from_dict(json.loads(Path(path).read_text()))


@dataclass(frozen=True, kw_only=True)
class DeviationTable:
    """Per-marker average deviation (m) between measured and fitted markers.

    segment (M,) int; marker_names (M,); mean_m (M,) (NaN: never both seen); max_m (M,);
    frames (M,) int frames used; segment_names (S,)."""

    segment: np.ndarray
    marker_names: tuple[str, ...]
    mean_m: np.ndarray
    max_m: np.ndarray
    frames: np.ndarray
    segment_names: tuple[str, ...]

    @property
    def overall_mean_m(self) -> float:
        """Mean deviation over every (frame, marker) sample."""
        w = self.frames
        return float(np.nansum(self.mean_m * w) / max(w.sum(), 1)) if w.sum() else np.nan

    def format(self) -> str:
        rows = [f"{'Segment':<12} {'Marker':<16} {'Average deviation mm':>21} "
                f"{'max mm':>8} {'frames':>7}"]
        for s in range(len(self.segment_names)):
            first = True
            for m in np.flatnonzero(self.segment == s):
                seg = self.segment_names[s] if first else ""
                first = False
                rows.append(f"{seg:<12} {self.marker_names[m]:<16} "
                            f"{1e3 * self.mean_m[m]:>21.4f} {1e3 * self.max_m[m]:>8.3f} "
                            f"{int(self.frames[m]):>7d}")
        rows.append(f"{'all':<12} {'':<16} {1e3 * self.overall_mean_m:>21.4f}")
        return "\n".join(rows)


def marker_deviation_table(trajectories, rigid: RigidSkeleton, fit: SkeletonFit) -> DeviationTable:
    dev = fit.marker_deviation(trajectories)                 # (T, M)
    ok = ~np.isnan(dev)
    n = ok.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, np.where(ok, dev, 0).sum(0) / n, np.nan)
    mx = np.where(n > 0, np.where(ok, dev, -np.inf).max(0), np.nan)
    return DeviationTable(segment=rigid.marker_segment, marker_names=rigid.marker_names,
                          mean_m=mean, max_m=mx, frames=n, segment_names=rigid.segment_names)


def summary_table(rigid: RigidSkeleton, deviation: DeviationTable, junctions=()) -> str:
    """Segments (markers, parent, joint type, bone length, mean deviation) as text; then a
    line per junction (``skeleton.junctions.Junction``: segments meeting at one point,
    whose parent-child choice rests on a prior as much as on the fit: with joints a few
    mm apart the alternatives are kinematically equivalent)."""
    rows = [f"{'segment':<8} {'parent':<8} {'markers':>7} {'joint':<6} {'bone mm':>8} "
            f"{'residual mm':>11} {'mean dev mm':>11}"]
    for s in rigid.order:
        s = int(s)
        p = int(rigid.parents[s])
        idx = rigid.marker_segment == s
        w = deviation.frames[idx]
        dev = (np.nansum(deviation.mean_m[idx] * w) / w.sum()) if w.sum() else np.nan
        kind = "-" if p < 0 else "hinge" if rigid.hinge[s] else "ball"
        parent = rigid.segment_names[p] if p >= 0 else "-"
        rows.append(f"{rigid.segment_names[s]:<8} {parent:<8} {int(idx.sum()):>7d} {kind:<6} "
                    f"{1e3 * rigid.bone_lengths[s]:>8.1f} {1e3 * rigid.joint_residual_m[s]:>11.3f} "
                    f"{1e3 * dev:>11.3f}")
    rows.append(f"{rigid.n_segments} segments, {rigid.n_markers} markers, "
                f"{rigid.n_segments - 1} joints ({int(rigid.hinge.sum())} hinges); "
                f"mean marker deviation {1e3 * deviation.overall_mean_m:.3f} mm")
    for jn in junctions:
        names = ", ".join(rigid.segment_names[m] for m in jn.segments)
        rows.append(f"junction: {names} (joints within {1e3 * jn.spread_m:.1f} mm) hang from "
                    f"{rigid.segment_names[jn.hub]} (the hub chosen by relative rotation "
                    f"and joint costs)")
    return "\n".join(rows)

"""Markers -> skeleton, wired end to end (the library behind ``mocap skeleton``).

``run_skeleton(markers: MarkerData, n_segments=None, rng=None, progress=None) ->
SkeletonRun``: marker sets (``skeleton.markersets``), the solver
(``skeleton.pipeline.solve_skeleton``), the rigid skeleton
(``skeleton.rigid_skeleton``), the per-frame fit back (``skeleton.fit``, closed form, then
the whole-skeleton IK ``skeleton.ik`` unless ``ik=False``) and the marker deviation table
(``skeleton.report``). ``write_outputs(run, bvh_path, json_path=None)``
writes the BVH and the skeleton JSON. No algorithm lives here.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skeleton.bvh import write_bvh
from skeleton.fit import SkeletonFit, fit_skeleton
from skeleton.ik import refine_fit
from skeleton.markersets import MarkerSets, merge_fragments
from skeleton.pipeline import SkeletonResult, solve_skeleton, warm_up
from skeleton.report import DeviationTable, marker_deviation_table, write_skeleton_json
from skeleton.rigid_skeleton import RigidSkeleton, build_rigid_skeleton

__all__ = ["SkeletonRun", "run_skeleton", "write_outputs"]


@dataclass(frozen=True, kw_only=True)
class SkeletonRun:
    """trajectories (T, M, 3) m after merging; marker_names (M,); rate_hz; markersets (None
    when merging was off); result; rigid; fit; deviation."""

    trajectories: np.ndarray
    marker_names: tuple[str, ...]
    rate_hz: float
    markersets: MarkerSets | None
    result: SkeletonResult
    rigid: RigidSkeleton
    fit: SkeletonFit
    deviation: DeviationTable

    def __post_init__(self):
        X = np.asarray(self.trajectories)
        if X.ndim != 3 or X.shape[2] != 3 or X.shape[1] != len(self.marker_names):
            raise ValueError(f"trajectories.shape={X.shape}, expected "
                             f"(T, {len(self.marker_names)}, 3)")


def run_skeleton(markers, n_segments: int | None = None, rng=None, progress=None,
                 merge: bool = True, min_frames: int = 10, ik: bool = True,
                 workers: int | None = None, star_margin: float | None = None) -> SkeletonRun:
    """``markers`` is a ``reconstruct.marker_files.MarkerData`` (or anything with
    ``positions`` (T, M, 3) m, ``labels`` and ``rate_hz``). ``workers``: processes for the
    pair costs; ``star_margin``: the star fits' margin, inf to turn them off (both
    ``skeleton.pipeline.solve_skeleton``; None: its defaults)."""
    say = progress or (lambda msg: None)
    X = np.asarray(markers.positions, np.float64)
    labels = tuple(markers.labels)
    if X.ndim != 3 or X.shape[2] != 3:
        raise ValueError(f"positions.shape={X.shape}, expected (T, M, 3)")
    if n_segments is not None and not (isinstance(n_segments, (int, np.integer))
                                       and n_segments >= 1):
        raise ValueError(f"n_segments={n_segments!r}, expected an integer >= 1")
    seen = ~np.isnan(X[..., 0])
    if not seen.any():
        raise ValueError(f"no marker has a sample ({X.shape[1]} trajectories, "
                         f"{X.shape[0]} frames)")
    empty = [labels[m] for m in np.flatnonzero(~seen.any(0))]
    if empty:
        say(f"{len(empty)} of {X.shape[1]} trajectories have no sample and are left out: "
            + ", ".join(empty[:8]) + (", ..." if len(empty) > 8 else ""))
    if merge and X.shape[0] < min_frames:
        raise ValueError(f"the recording has {X.shape[0]} frames, fewer than min_frames="
                         f"{min_frames}: every trajectory would be dropped")
    sets = None
    if not merge and empty:
        keep = np.flatnonzero(seen.any(0))
        X, labels = X[:, keep], tuple(labels[m] for m in keep)
    if merge:
        sets = merge_fragments(X, min_frames=min_frames)
        X = sets.positions
        labels = tuple(labels[g[0]] for g in sets.groups)
        short = len(sets.dropped) - len(empty)
        say(f"marker sets: {len(markers.labels)} trajectories -> {sets.n_markers} markers "
            f"({short} dropped as shorter than {min_frames} frames)")
    if X.shape[1] < 3:
        raise ValueError(f"{X.shape[1]} markers" + (" after merging" if merge else "")
                         + ", need at least 3")
    if n_segments is not None and n_segments > X.shape[1]:
        raise ValueError(f"n_segments={n_segments}: more segments than the {X.shape[1]} "
                         f"markers")
    extra = {} if star_margin is None else {"star_margin": star_margin}
    say("loading the solver's compiled fits (the first run in a checkout compiles them, "
        "~30 s)")
    warm_up()
    res = solve_skeleton(X, markers.rate_hz, n_segments=n_segments, rng=rng, progress=say,
                         workers=workers, **extra)
    say("rigid skeleton")
    rigid = build_rigid_skeleton(X, res, marker_names=labels)
    say(f"fit back: {X.shape[0]} frames")
    fit = fit_skeleton(X, rigid, markers.rate_hz)
    if ik:
        say("inverse kinematics (whole skeleton per frame)")
        fit = refine_fit(X, rigid, fit)
    dev = marker_deviation_table(X, rigid, fit)
    return SkeletonRun(trajectories=X, marker_names=labels, rate_hz=float(markers.rate_hz),
                       markersets=sets, result=res, rigid=rigid, fit=fit, deviation=dev)


def write_outputs(run: SkeletonRun, bvh_path, json_path=None, units: str = "m") -> list[Path]:
    out = [write_bvh(bvh_path, run.rigid, run.fit, run.rate_hz, units=units)]
    if json_path is not None:
        d = run.deviation
        extra = {"rate_hz": run.rate_hz, "n_frames": int(run.trajectories.shape[0]),
                 "eigengap_k": int(run.result.eigengap_k),
                 "mean_marker_deviation_mm": 1e3 * d.overall_mean_m,
                 "marker_deviation_mm": {n: (None if not np.isfinite(v) else 1e3 * float(v))
                                         for n, v in zip(d.marker_names, d.mean_m)},
                 "fitted_fraction": float((run.fit.status > 0).mean()),
                 "junctions": [{"segments": [run.rigid.segment_names[m] for m in jn.segments],
                                "hub": run.rigid.segment_names[jn.hub],
                                "joint_spread_m": (None if not np.isfinite(jn.spread_m)
                                                   else jn.spread_m)}
                               for jn in run.result.junctions]}
        if run.markersets is not None:
            extra["marker_sets"] = {"groups": [list(g) for g in run.markersets.groups],
                                    "dropped": list(run.markersets.dropped)}
        out.append(write_skeleton_json(json_path, run.rigid, extra))
    return out

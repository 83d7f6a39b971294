"""Skeleton JSON round trip and the thesis' marker deviation table."""
from __future__ import annotations

import json

import numpy as np
import pytest

from hw_sim.articulated import animate, humanoid, random_tree
from skeleton.fit import fit_skeleton
from skeleton.pipeline import solve_skeleton
from skeleton.report import (marker_deviation_table, read_skeleton_json, summary_table,
                             write_skeleton_json)
from skeleton.rigid_skeleton import build_rigid_skeleton
from tests.skeleton._figures import segment_map

NOISE_M = 1e-3


def _solve(fig, traj, rate=120.0):
    res = solve_skeleton(traj, rate, n_segments=fig.n_segments, rng=0)
    rig = build_rigid_skeleton(traj, res, marker_names=fig.marker_names)
    return rig, fit_skeleton(traj, rig, rate)


def test_json_round_trip(tmp_path):
    fig = humanoid(rng=0)                       # has hinges (NaN axes for ball joints)
    mo = animate(fig, 200, rng=0)
    rig, fit = _solve(fig, mo.markers)
    assert rig.hinge.sum() == 4
    p = write_skeleton_json(tmp_path / "s.json", rig, extra={"note": "x"})
    back = read_skeleton_json(p)
    for name in ("parents", "marker_segment", "marker_offsets", "joint_offsets", "hinge",
                 "hinge_axes_parent", "hinge_axes_child", "joint_residual_m", "end_sites"):
        np.testing.assert_array_equal(getattr(back, name), getattr(rig, name), err_msg=name)
    assert back.root == rig.root and back.segment_names == rig.segment_names
    assert back.marker_names == rig.marker_names == fig.marker_names
    d = json.loads(p.read_text())
    assert d["units"] == "m" and d["extra"] == {"note": "x"}
    assert len(d["joints"]) == fig.n_segments - 1
    hinge = [j for j in d["joints"] if j["type"] == "hinge"]
    assert len(hinge) == 4 and all(abs(np.linalg.norm(j["hinge_axis_parent"]) - 1) < 1e-9
                                   for j in hinge)
    # hinge axes: in the world (parent's fitted rotation) they are the truth's, up to sign
    segmap = segment_map(fig, rig.marker_segment)
    for s in range(1, fig.n_segments):
        if fig.joint_types[s] != "hinge":
            continue
        e = segmap[s]
        assert rig.hinge[e] and rig.parents[e] == segmap[fig.parents[s]]
        est = np.einsum("tij,j->ti", fit.world_from_segment_R[:, rig.parents[e]],
                        rig.hinge_axes_parent[e])
        est_c = np.einsum("tij,j->ti", fit.world_from_segment_R[:, e], rig.hinge_axes_child[e])
        true = np.einsum("tij,j->ti", mo.world_from_segment_R[:, s], fig.hinge_axes[s])
        assert np.abs(np.abs((est * true).sum(1)) - 1).max() < 1e-9
        assert np.abs(np.abs((est_c * true).sum(1)) - 1).max() < 1e-9
    names = list(rig.segment_names)
    for j in d["joints"]:
        assert j["bone_length_m"] == rig.bone_lengths[names.index(j["child"])]


def test_bad_format(tmp_path):
    p = tmp_path / "x.json"
    p.write_text(json.dumps({"format": "other"}))
    with pytest.raises(ValueError, match="format='other'"):
        read_skeleton_json(p)


def test_deviation_table_exact_and_noisy():
    fig = random_tree(5, (3, 4), rng=7)
    mo = animate(fig, 300, rng=7)
    rig, fit = _solve(fig, mo.markers)
    tab = marker_deviation_table(mo.markers, rig, fit)
    assert np.nanmax(tab.mean_m) < 1e-9 and (tab.frames == 300).all()
    noisy = mo.markers + np.random.default_rng(1).normal(0, NOISE_M, mo.markers.shape)
    noisy[:40, 0] = np.nan                         # marker 0 hidden in 40 frames
    rig, fit = _solve(fig, noisy)
    tab = marker_deviation_table(noisy, rig, fit)
    dev = np.linalg.norm(noisy - fit.fitted_markers, axis=2)
    np.testing.assert_allclose(tab.mean_m, np.nanmean(dev, 0))
    assert tab.frames[0] == 260
    # 1 mm isotropic noise: |noise| averages 1.6 mm; the fit absorbs a little (1.42 mm)
    assert NOISE_M < tab.overall_mean_m < 1.6 * NOISE_M
    text = tab.format()
    assert fig.marker_names[0] in text and "Average deviation" in text
    s = summary_table(rig, tab)
    assert f"{fig.n_segments} segments, {fig.n_markers} markers" in s

"""BVH export: joint world positions from an independent reader (bvhio) and from a parse of
the file with our own forward kinematics match the fitted skeleton."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hw_sim.articulated import animate, humanoid, random_tree
from skeleton.bvh import UNITS, Y_UP_FROM_Z_UP, write_bvh
from skeleton.fit import fit_skeleton
from skeleton.ik import refine_fit
from skeleton.pipeline import solve_skeleton
from skeleton.rigid_skeleton import build_rigid_skeleton
from tests.skeleton._figures import joint_errors, segment_map

BVH_POSITION_M = 1e-4     # issue 6 point 5 (bvhio computes in float32: ~3e-7 m)


def _fitted(fig, T, seed, hide=0.0, ik=False, noise_m=0.0):
    mo = animate(fig, T, rng=seed)
    traj = mo.markers + np.random.default_rng(seed).normal(0, noise_m, mo.markers.shape)
    res = solve_skeleton(traj, mo.rate_hz, n_segments=fig.n_segments, rng=0)
    rig = build_rigid_skeleton(traj, res)
    if hide:
        traj[np.random.default_rng(seed).uniform(size=traj.shape[:2]) < hide] = np.nan
    fit = fit_skeleton(traj, rig, mo.rate_hz)
    return mo, res, rig, (refine_fit(traj, rig, fit) if ik else fit)


def _bvhio_positions(path, names, T):
    import bvhio
    root = bvhio.readAsHierarchy(str(path))
    out = np.full((T, len(names), 3), np.nan)
    for f in range(T):
        root.loadPose(f)
        for joint, _, _ in root.layout():
            out[f, names.index(joint.Name)] = np.array(joint.PositionWorld)
    return out


@pytest.mark.parametrize("units,y_up", [("m", True), ("cm", True), ("mm", False)])
def test_bvhio_matches_fit_random_tree(tmp_path, units, y_up):
    fig = random_tree(8, (2, 4), rng=5)
    mo, res, rig, fit = _fitted(fig, 150, 5)
    p = write_bvh(tmp_path / "s.bvh", rig, fit, units=units, y_up=y_up)
    got = _bvhio_positions(p, list(rig.segment_names), 150) / UNITS[units]
    Q = Y_UP_FROM_Z_UP if y_up else np.eye(3)
    want = fit.joint_centres @ Q.T
    assert (fit.status > 0).all()
    assert np.abs(got - want).max() < BVH_POSITION_M
    # and the fitted joints are the truth (three-or-more-marker joints are exact)
    segmap = segment_map(fig, res.labels)
    assert joint_errors(fig, mo, rig.parents, fit.joint_centres, segmap).max() < 1e-8


def test_bvhio_humanoid_with_hidden_markers(tmp_path):
    fig = humanoid(rng=0)
    mo, res, rig, fit = _fitted(fig, 120, 2, hide=0.15, ik=True)
    p = write_bvh(tmp_path / "h.bvh", rig, fit)
    got = _bvhio_positions(p, list(rig.segment_names), 120)
    want = fit.joint_centres @ Y_UP_FROM_Z_UP.T
    ok = (fit.status > 0).all(1)                  # frames with the whole skeleton fitted
    assert 10 < ok.sum() < 120
    assert np.abs(got[ok] - want[ok]).max() < BVH_POSITION_M
    assert np.isfinite(got).all()                 # unfitted frames are held, never NaN


def test_bvhio_matches_ik_on_noisy_data(tmp_path):
    fig = random_tree(7, (2, 4), rng=9)
    mo, res, rig, fit = _fitted(fig, 100, 9, ik=True, noise_m=1e-3)
    p = write_bvh(tmp_path / "n.bvh", rig, fit)
    got = _bvhio_positions(p, list(rig.segment_names), 100)
    ok = (fit.status > 0).all(1)
    assert ok.all()
    assert np.abs(got - fit.joint_centres @ Y_UP_FROM_Z_UP.T).max() < BVH_POSITION_M


def _parse(path):
    """Minimal independent BVH parse: joints (name, parent, offset, channels), frames."""
    tok = path.read_text().split()
    i, stack, joints = 0, [], []
    while tok[i] != "MOTION":
        t = tok[i]
        if t in ("ROOT", "JOINT"):
            joints.append({"name": tok[i + 1], "parent": stack[-1] if stack else -1})
            i += 2
        elif t == "End":
            joints.append({"name": None, "parent": stack[-1]})
            i += 2
        elif t == "{":
            stack.append(len(joints) - 1)
            i += 1
        elif t == "}":
            stack.pop()
            i += 1
        elif t == "OFFSET":
            joints[stack[-1]]["offset"] = np.array(tok[i + 1:i + 4], float)
            i += 4
        elif t == "CHANNELS":
            n = int(tok[i + 1])
            joints[stack[-1]]["channels"] = tok[i + 2:i + 2 + n]
            i += 2 + n
        else:
            i += 1
    assert tok[i + 1] == "Frames:" and tok[i + 3:i + 5] == ["Frame", "Time:"]
    T, dt = int(tok[i + 2]), float(tok[i + 5])
    data = np.array(tok[i + 6:], float)
    return joints, T, dt, data


def _fk(joints, frame):
    """World positions of the named joints (Rz Rx Ry for Zrotation Xrotation Yrotation)."""
    pos, rot, k, out = {}, {}, 0, {}
    for j, jt in enumerate(joints):
        if jt["name"] is None:
            continue
        p = jt["parent"]
        vals = frame[k:k + len(jt["channels"])]
        k += len(jt["channels"])
        ch = dict(zip(jt["channels"], vals))
        order = "".join(c[0] for c in jt["channels"] if c.endswith("rotation"))
        R = Rotation.from_euler(order, [ch[c + "rotation"] for c in order], degrees=True)
        if p < 0:
            pos[j] = np.array([ch["Xposition"], ch["Yposition"], ch["Zposition"]])
            rot[j] = R.as_matrix()
        else:
            pos[j] = pos[p] + rot[p] @ jt["offset"]
            rot[j] = rot[p] @ R.as_matrix()
        out[jt["name"]] = pos[j]
    return out


def test_header_and_own_forward_kinematics(tmp_path):
    fig = random_tree(6, (3, 4), rng=3)
    mo, res, rig, fit = _fitted(fig, 50, 3)
    p = write_bvh(tmp_path / "s.bvh", rig, fit, rate_hz=100.0)
    joints, T, dt, data = _parse(p)
    named = [j for j in joints if j["name"]]
    S = rig.n_segments
    assert T == 50 and dt == pytest.approx(0.01)
    assert len(named) == S and named[0]["parent"] == -1
    assert named[0]["channels"][:3] == ["Xposition", "Yposition", "Zposition"]
    assert np.all(named[0]["offset"] == 0)
    assert all(j["channels"] == ["Zrotation", "Xrotation", "Yrotation"] for j in named[1:])
    n_leaves = sum(1 for k in rig.children if not k)
    assert sum(1 for j in joints if j["name"] is None) == n_leaves
    nch = 6 + 3 * (S - 1)
    assert data.size == T * nch
    data = data.reshape(T, nch)
    for f in (0, 17, 49):
        w = _fk(joints, data[f])
        for s, name in enumerate(rig.segment_names):
            assert np.abs(w[name] - Y_UP_FROM_Z_UP @ fit.joint_centres[f, s]).max() < 1e-6


def test_bad_units(tmp_path):
    fig = random_tree(3, (3, 3), rng=0)
    mo, res, rig, fit = _fitted(fig, 30, 0)
    with pytest.raises(ValueError, match="units='inch'"):
        write_bvh(tmp_path / "x.bvh", rig, fit, units="inch")

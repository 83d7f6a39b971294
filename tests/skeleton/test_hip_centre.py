"""Real (OpenSim-simulated) hip: pelvis (4 markers) and right thigh (3 markers), 973 frames.

The hip there is an ideal ball joint, so in the pelvis frame every thigh marker stays at a
constant distance from one point: issue 6 point 6 asks for a residual <= 0.1 mm. The
recorded motion is planar (every marker's z is constant), so the centre is only determined
up to the axis perpendicular to that plane (a hinge for the estimator)."""
from __future__ import annotations

import numpy as np
import pytest

from reconstruct.marker_files import MarkerData
from skeleton.app import run_skeleton
from skeleton.joints import fit_joint

STO = "joint_centres/fjc_hip_synthetic_OutputsVec3.sto"
HIP_RESIDUAL_M = 1e-4
PELVIS, THIGH = [3, 4, 5, 6], [0, 1, 2]


def read_sto_vec3(path):
    """OpenSim Vec3 .sto: header up to 'endheader', then time and 'x,y,z' columns (m)."""
    lines = path.read_text().splitlines()
    i = lines.index("endheader")
    names = [c.split("/")[-1].split("|")[0] for c in lines[i + 1].split("\t")[1:]]
    rows = [ln.split("\t") for ln in lines[i + 2:] if ln.strip()]
    t = np.array([float(r[0]) for r in rows])
    X = np.array([[[float(v) for v in c.split(",")] for c in r[1:]] for r in rows])
    return t, X, names


@pytest.fixture(scope="module")
def hip(shared_data):
    return read_sto_vec3(shared_data / STO)


def test_hip_centre_residual(hip):
    t, X, names = hip
    assert X.shape == (973, 7, 3) and names[3:] == ["R.Asis", "R.Psi", "L.Asis", "L.Psi"]
    f = fit_joint(X, PELVIS, THIGH)
    assert f.ok
    assert f.residual_m <= HIP_RESIDUAL_M
    # independent check: the centre's world track keeps every thigh marker at one distance
    d = np.linalg.norm(X[:, THIGH] - f.world[:, None], axis=2)
    assert np.nanstd(d, axis=0).max() <= HIP_RESIDUAL_M
    # the centre moves with the pelvis: constant distances to the pelvis markers too
    dp = np.linalg.norm(X[:, PELVIS] - f.world[:, None], axis=2)
    assert np.nanstd(dp, axis=0).max() <= HIP_RESIDUAL_M


def test_hip_through_the_whole_pipeline(hip):
    t, X, names = hip
    rate = (len(t) - 1) / (t[-1] - t[0])       # the .sto is not evenly sampled; nominal rate
    run = run_skeleton(MarkerData(positions=X, labels=names, rate_hz=rate), n_segments=2,
                       rng=0)
    groups = sorted(tuple(np.flatnonzero(run.result.labels == s)) for s in range(2))
    assert groups == [(0, 1, 2), (3, 4, 5, 6)]
    assert run.deviation.overall_mean_m <= HIP_RESIDUAL_M
    j = [f for f in run.result.joints if f is not None][0]
    assert j.residual_m <= HIP_RESIDUAL_M

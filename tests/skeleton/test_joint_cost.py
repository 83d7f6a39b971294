"""skeleton.joints.joint_cost: noise-normalised topology cost, vs simulated truth (fast)."""
from __future__ import annotations

import numpy as np

from hw_sim.articulated import animate, random_tree
from skeleton.joints import fit_joint, joint_cost
from tests.skeleton._figures import members

NOISE_M = 1e-3
EXACT_COST_M = 1e-9        # a true joint on noise-free data
SIGMA_REL = 0.25           # true-joint cost ~ marker noise sd, whatever the marker layout


def _two_two_figure():
    """A figure with a true joint between two 2-marker segments (searched by seed)."""
    for seed in range(200):
        fig = random_tree(6, (2, 4), rng=seed)
        nm = np.bincount(fig.marker_segment)
        for s in range(1, fig.n_segments):
            if nm[s] == 2 and nm[fig.parents[s]] == 2:
                return fig, s, seed
    raise AssertionError("no 2+2 figure in 200 seeds")


def test_two_marker_pair_exact():
    """2+2 markers: the closed-form lifted init + world fit reaches zero cost noise-free,
    and the fitted centre is the true joint."""
    fig, s, seed = _two_two_figure()
    mo = animate(fig, 300, rng=seed, rom_deg=60.0)
    m = members(fig)
    assert joint_cost(mo.markers, m[fig.parents[s]], m[s]) < EXACT_COST_M
    f = fit_joint(mo.markers, m[fig.parents[s]], m[s])
    err = np.linalg.norm(f.world - mo.joint_centres[:, s], axis=1)
    assert np.nanmax(err) < 1e-6


def test_cost_estimates_noise_for_true_joints_and_exceeds_it_for_false():
    fig = random_tree(8, (2, 4), rng=3)
    mo = animate(fig, 600, rng=3, rom_deg=60.0)
    tr = mo.markers + np.random.default_rng(0).normal(0, NOISE_M, mo.markers.shape)
    m = members(fig)
    true_pairs = {(int(fig.parents[s]), s) for s in range(1, fig.n_segments)}
    tc, fc = [], []
    for i in range(fig.n_segments):
        for j in range(i + 1, fig.n_segments):
            c = joint_cost(tr, m[i], m[j])
            (tc if (i, j) in true_pairs else fc).append(c)
    tc = np.array(tc)
    # 1 mm noise per coordinate -> radial residual sd ~ 1 mm for every true joint
    assert np.all(np.abs(tc / NOISE_M - 1) < SIGMA_REL), tc
    assert np.min(fc) > tc.max()


def test_compiled_sphere_residuals_and_jacobian():
    """fit_joint's compiled residuals equal the NumPy expression they replaced, and the
    Jacobian its finite differences."""
    from skeleton.joints import _sphere_jac, _sphere_res
    g = np.random.default_rng(0)
    pts = g.normal(0, 0.2, (500, 3))
    lab = g.integers(0, 3, 500)
    wsq = g.uniform(1.0, 2.0, 500)
    p = np.array([0.01, -0.02, 0.03, 0.2, 0.25, 0.3])
    ref = (np.linalg.norm(pts - p[:3], axis=1) - p[3:][lab]) / wsq
    assert np.array_equal(_sphere_res(p, pts, lab, wsq), ref)
    J = _sphere_jac(p, pts, lab, wsq, 3)
    h = 1e-7
    num = np.stack([(_sphere_res(p + h * e, pts, lab, wsq) - _sphere_res(p - h * e, pts, lab, wsq))
                    / (2 * h) for e in np.eye(6)], 1)
    assert np.abs(J - num).max() < 1e-6

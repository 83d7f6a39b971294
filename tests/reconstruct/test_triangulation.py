"""Triangulation: exact recovery, noise-limited accuracy, bad-ray rejection, residuals."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from hw_sim.rig import make_rig
from reconstruct.triangulation import rig_arrays, triangulate, triangulate_dlt

EXACT_M = 1e-9            # exact data recovers truth to this (m)
EXACT_PX = 1e-7           # and reprojects to this (px)
NOISE_PX = 0.05           # injected centroid noise (px per coordinate)
MSE_RATIO_RANGE = (0.75, 1.3)  # measured / first-order-predicted mean squared 3D error
BAD_RAY_PX = 25.0         # planted outlier offset (px)

DIST = (-0.08, 0.015, 0.0005, -0.0004, 0.0)


@pytest.fixture(scope="module")
def rig():
    return make_rig(8, dist=DIST, rng=7)


def _points(n, rng):
    return np.random.default_rng(rng).uniform([-1.5, -1.5, 0.1], [1.5, 1.5, 2.3], (n, 3))


def test_exact_data_recovers_truth(rig):
    X = _points(200, 0)
    r = triangulate(rig, rig.project(X))
    assert r.ok.all()
    assert np.abs(r.points - X).max() < EXACT_M
    assert r.residual_px.max() < EXACT_PX
    assert r.residual_mm.max() < EXACT_M * 1e3
    assert r.used.all()


def test_dlt_alone_is_exact_on_exact_data(rig):
    X = _points(50, 1)
    xy = rig.project(X)
    norm = np.stack([c.pixel_to_normalized(xy[i]) for i, c in enumerate(rig)])
    assert np.abs(triangulate_dlt(norm, rig_arrays(rig)) - X).max() < 1e-8


def _predicted_mse(rig, X, sigma):
    """trace of the first-order covariance sigma^2 (J^T J)^-1 of each point (pixel Jacobian)."""
    tot = 0.0
    eps = 1e-6
    for x in X:
        J = np.zeros((2 * len(rig), 3))
        for k in range(3):
            d = np.zeros(3)
            d[k] = eps
            J[:, k] = ((rig.project((x + d)[None]) - rig.project((x - d)[None])) / (2 * eps)
                       ).reshape(-1)
        tot += sigma ** 2 * np.trace(np.linalg.inv(J.T @ J))
    return tot / len(X)


def test_noise_limited_accuracy(rig):
    """Mean squared 3D error matches the first-order prediction from the injected noise."""
    g = np.random.default_rng(2)
    X = _points(400, 3)
    xy = rig.project(X) + g.normal(0, NOISE_PX, (len(rig), len(X), 2))
    r = triangulate(rig, xy)
    mse = np.mean(np.sum((r.points - X) ** 2, axis=1))
    ratio = mse / _predicted_mse(rig, X, NOISE_PX)
    assert MSE_RATIO_RANGE[0] < ratio < MSE_RATIO_RANGE[1], ratio
    # residual RMS of 2C coordinates with 3 fitted parameters: sigma^2 (2C - 3) / C per ray
    C = len(rig)
    exp_rms = NOISE_PX * np.sqrt((2 * C - 3) / C)
    assert abs(np.sqrt(np.mean(r.residual_px ** 2)) / exp_rms - 1) < 0.1


def test_one_bad_ray_is_rejected_exactly(rig):
    g = np.random.default_rng(4)
    X = _points(100, 5)
    xy = rig.project(X) + g.normal(0, NOISE_PX, (len(rig), len(X), 2))
    bad_cam = g.integers(0, len(rig), len(X))
    angle = g.uniform(0, 2 * np.pi, len(X))
    xy[bad_cam, np.arange(len(X))] += BAD_RAY_PX * np.stack([np.cos(angle), np.sin(angle)], 1)
    r = triangulate(rig, xy, bad_ray_px=1.0)
    expected_used = np.ones((len(X), len(rig)), bool)
    expected_used[np.arange(len(X)), bad_cam] = False
    assert np.array_equal(r.used, expected_used)
    # the remaining rays' noise only: 0.20 mm (0.18 mm with no bad ray at all)
    assert np.sqrt(np.mean(np.sum((r.points - X) ** 2, axis=1))) < 0.3e-3
    assert np.all(r.ray_error_px[np.arange(len(X)), bad_cam] > BAD_RAY_PX / 2)


def test_two_rays_bad_ray_is_not_rejected(rig):
    """With two rays there is nothing to vote with: both are kept."""
    X = _points(5, 6)
    xy = np.full((len(rig), 5, 2), np.nan)
    xy[[0, 3]] = rig.project(X)[[0, 3]]
    xy[0] += 10.0
    r = triangulate(rig, xy, bad_ray_px=1.0)
    assert r.ok.all() and r.used[:, [0, 3]].all() and r.used.sum() == 10


def test_missing_views_and_too_few_rays(rig):
    X = _points(10, 8)
    xy = rig.project(X)
    xy[:, 0] = np.nan
    xy[1:, 1] = np.nan          # one ray only
    xy[2:, 2] = np.nan          # two rays
    r = triangulate(rig, xy)
    assert not r.ok[0] and not r.ok[1] and np.isnan(r.points[:2]).all()
    assert r.ok[2:].all()
    assert np.abs(r.points[2:] - X[2:]).max() < EXACT_M


def test_residual_mm_is_mean_distance_to_rays(rig):
    X = _points(3, 9)
    xy = rig.project(X) + np.random.default_rng(1).normal(0, 0.5, (len(rig), 3, 2))
    r = triangulate(rig, xy, bad_ray_px=100.0)
    for n in range(3):
        dists = []
        for c, cam in enumerate(rig):
            o, d = cam.unproject(xy[c, n][None])
            v = r.points[n] - o
            dists.append(np.linalg.norm(np.cross(v, d[0])))
        assert r.residual_mm[n] == pytest.approx(1000 * np.mean(dists), rel=1e-9)


def test_bad_shape_raises(rig):
    with pytest.raises(ValueError, match="xy.shape"):
        triangulate(rig, np.zeros((3, 4, 2)))


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-1.5, 1.5), min_size=3, max_size=3),
       st.integers(2, 8))
def test_project_triangulate_roundtrip(rig, xyz, n_cams):
    X = np.array([xyz]) + np.array([0, 0, 1.2])
    xy = rig.project(X)
    xy[n_cams:] = np.nan
    r = triangulate(rig, xy)
    assert r.ok[0]
    assert np.abs(r.points - X).max() < 1e-8

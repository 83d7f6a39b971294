"""ML point refinement recovers exact points; its covariance predicts the scatter of noisy ones."""
import numpy as np

from calibration.points import point_covariance, refine_points
from hw_sim.rig import make_rig

EXACT_M = 1e-9
N_MC = 400
COV_REL_TOL = 0.15   # sample variance of 400 draws: ~7% relative SD; 15% is ~2 sigma


def _scene(seed=0, n=N_MC):
    rig = make_rig(6, rng=2, dist=(-0.05, 0.01, 0.0, 0.0, 0.0))
    g = np.random.default_rng(seed)
    X = np.tile(g.uniform([-1, -1, 0.5], [1, 1, 2.0]), (n, 1))
    xy = rig.project(X)
    return rig, X, xy, g


def test_refine_recovers_exact_points_from_a_poor_start():
    rig, X, xy, g = _scene(n=5)
    X0 = X + g.normal(0, 0.01, X.shape)
    np.testing.assert_allclose(refine_points(list(rig), xy, X0), X, atol=EXACT_M)


def test_covariance_predicts_monte_carlo_scatter_and_single_view_is_nan():
    rig, X, xy, g = _scene()
    sigma = 0.2
    noisy = xy + g.normal(0, sigma, xy.shape)
    est = refine_points(list(rig), noisy, X.copy())
    cov = point_covariance(list(rig), np.ones((len(rig), len(X)), bool), X, sigma)[0]
    emp = np.cov((est - X).T)
    w = np.linalg.eigvalsh(cov)
    for k, v in enumerate(np.linalg.eigh(cov)[1].T):
        assert abs(v @ emp @ v / w[k] - 1) < COV_REL_TOL
    seen = np.zeros((len(rig), 1), bool)
    seen[0] = True
    assert np.all(np.isnan(point_covariance(list(rig), seen, X[:1], sigma)))
    one = np.full_like(xy[:, :1], np.nan)
    one[0] = xy[0, :1]
    assert np.all(np.isnan(refine_points(list(rig), one, X[:1])))

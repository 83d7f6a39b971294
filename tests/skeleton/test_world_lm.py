"""skeleton.world_lm: the compiled world-frame Levenberg-Marquardt of 2+2 segment pairs."""
import numpy as np
import pytest
from scipy.optimize import least_squares

from skeleton.world_lm import world_lm

RTOL, ATOL_M = 1e-12, 1e-13


def _problem(seed, F=40, noise_m=0.0):
    """Markers at constant distances r (4,) from a moving centre c (F, 3), in directions
    spanning 3-D; optional marker noise."""
    g = np.random.default_rng(seed)
    c = np.cumsum(g.normal(0, 0.01, (F, 3)), 0) + [0.1, 0.2, 1.0]
    r = g.uniform(0.05, 0.3, 4)
    v = g.normal(size=(F, 4, 3))
    v /= np.linalg.norm(v, axis=2, keepdims=True)
    X = c[:, None] + r[None, :, None] * v + g.normal(0, noise_m, (F, 4, 3))
    return X, c, r


def test_recovers_the_centres_and_distances_of_noise_free_data():
    X, c, r = _problem(1)
    g = np.random.default_rng(2)
    c0, r0 = c + g.normal(0, 0.005, c.shape), r + g.normal(0, 0.005, r.shape)
    cf, rf, ssr = world_lm(X, c0, r0, 100, RTOL, ATOL_M)
    assert ssr < 1e-20
    np.testing.assert_allclose(rf, r, atol=1e-9)
    np.testing.assert_allclose(cf, c, atol=1e-9)


def test_noisy_minimum_matches_scipy_least_squares():
    """An independent solver (MINPACK through SciPy, finite differences) from the same start
    reaches the same minimum on noisy data."""
    X, c, r = _problem(3, F=15, noise_m=0.002)
    F = X.shape[0]

    def fun(p):
        cc, rr = p[:3 * F].reshape(F, 3), p[3 * F:]
        return (np.linalg.norm(X - cc[:, None], axis=2) - rr).ravel()

    ref = least_squares(fun, np.concatenate([c.ravel(), r]), method="lm", xtol=1e-15,
                        ftol=1e-15, gtol=1e-15)
    cf, rf, ssr = world_lm(X, c, r, 200, RTOL, ATOL_M)
    assert ssr == pytest.approx(2 * ref.cost, rel=1e-9)
    np.testing.assert_allclose(rf, ref.x[3 * F:], atol=1e-8)
    np.testing.assert_allclose(cf, ref.x[:3 * F].reshape(F, 3), atol=1e-8)
    assert ssr < ((np.linalg.norm(X - c[:, None], axis=2) - r) ** 2).sum()


def test_batched_problems_match_one_at_a_time_and_inputs_are_kept():
    probs = [_problem(s, noise_m=0.001) for s in (4, 5, 6)]
    X = np.stack([p[0] for p in probs])
    c0 = np.stack([p[1] + 0.01 for p in probs])
    r0 = np.stack([p[2] + 0.01 for p in probs])
    keep = c0.copy(), r0.copy()
    cb, rb, sb = world_lm(X, c0, r0, 60, RTOL, ATOL_M)
    np.testing.assert_array_equal(c0, keep[0])
    np.testing.assert_array_equal(r0, keep[1])
    for k in range(3):
        ck, rk, sk = world_lm(X[k], c0[k], r0[k], 60, RTOL, ATOL_M)
        np.testing.assert_array_equal(ck, cb[k])
        np.testing.assert_array_equal(rk, rb[k])
        assert sk == sb[k]


def test_a_step_that_does_not_lower_the_sum_of_squares_is_not_taken():
    """At the minimum of noisy data, more iterations change nothing."""
    X, c, r = _problem(7, noise_m=0.001)
    c1, r1, s1 = world_lm(X, c, r, 300, 0.0, 0.0)
    c2, r2, s2 = world_lm(X, c1, r1, 50, 0.0, 0.0)
    assert s2 <= s1
    assert s2 == pytest.approx(s1, rel=1e-12)


@pytest.mark.parametrize("shape_c, shape_r", [((40, 2), (4,)), ((40, 3), (3,))])
def test_bad_shapes_are_refused(shape_c, shape_r):
    X, _, _ = _problem(8)
    with pytest.raises(ValueError, match="expected"):
        world_lm(X, np.zeros(shape_c), np.zeros(shape_r), 10, RTOL, ATOL_M)
    with pytest.raises(ValueError, match="expected"):
        world_lm(X[..., :2], np.zeros((40, 3)), np.zeros(4), 10, RTOL, ATOL_M)

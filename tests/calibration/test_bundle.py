"""Bundle adjustment: the analytic Jacobian equals finite differences and fits the pattern."""
import numpy as np
import pytest
from scipy.optimize._numdiff import approx_derivative

from calibration.bundle import _Problem, bundle_adjust
from calibration.camera import Camera
from hw_sim.rig import make_rig

JAC_REL_TOL = 1e-7   # central differences of smooth residuals: ~1e-10 relative measured


def _problem(spacing, refine, seed=0):
    g = np.random.default_rng(seed)
    rig = make_rig(4, rng=1)
    cams = [Camera(name=c.name, size=c.size, K=c.K, dist=[-0.1, 0.05, 1e-3, -2e-3, 0.01],
                   R=c.R, t=c.t) for c in rig]
    T, M = 6, 3
    X0 = g.uniform(-1, 1, (T, M, 3)) + [0, 0, 1.2]
    if spacing is not None:
        d = g.normal(size=(T, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        X0 = X0[:, :1] + spacing[None, :, None] * d[:, None]
    xy = np.stack([c.project(X0.reshape(-1, 3)).reshape(T, M, 2) for c in cams])
    xy = xy + g.normal(0, 1, xy.shape)
    xy[1, 2, 0] = np.nan
    prob = _Problem(cams, xy, spacing, refine, 1e5, None if spacing is not None else 3.0)
    prob.set_frames(X0)
    prob.set_mask(np.all(np.isfinite(xy), axis=3))
    R = np.stack([c.R for c in cams])
    t = np.stack([c.t for c in cams])
    p = prob.pack(R, t, X0) + g.normal(0, 1e-3, prob.n_par())
    return prob, p


@pytest.mark.parametrize("wand", [True, False])
@pytest.mark.parametrize("refine", [False, True])
def test_analytic_jacobian_matches_finite_differences(wand, refine):
    prob, p = _problem(np.array([0.0, 0.25, 0.5]) if wand else None, refine)
    Ja = prob.jac(p).toarray()
    Jn = approx_derivative(prob.fun, p, method="3-point")
    assert Ja.shape == Jn.shape
    assert np.abs(Ja - Jn).max() < JAC_REL_TOL * np.abs(Jn).max()
    S = prob.sparsity().toarray() != 0
    assert np.all(S[Ja != 0])                # analytic entries lie inside the declared pattern
    assert np.abs(Jn[~S]).max() == 0.0       # and the pattern misses no dependency


def test_unknown_jacobian_raises():
    rig = make_rig(2, rng=1)
    with pytest.raises(ValueError, match="jac='exact'"):
        bundle_adjust(list(rig), np.zeros((2, 3, 3, 2)), np.zeros((3, 3, 3)), jac="exact")

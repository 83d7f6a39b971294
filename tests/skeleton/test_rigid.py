"""skeleton.rigid.kabsch (compiled Horn quaternion) against NumPy's SVD with the det fix."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from skeleton.rigid import kabsch, kabsch_svd


@pytest.mark.parametrize("n_markers", [3, 4, 6])
@pytest.mark.parametrize("noise_m", [0.0, 1e-3, 0.05])
def test_kabsch_matches_svd(n_markers, noise_m):
    g = np.random.default_rng(n_markers)
    P = g.normal(0, 0.1, (n_markers, 3))
    R = Rotation.random(300, random_state=n_markers).as_matrix()
    src = np.einsum("tij,nj->tni", R, P) + g.normal(0, 1, (300, 1, 3))
    src = src + g.normal(0, noise_m, src.shape)
    Rh, th = kabsch(src, P)
    Rs, ts = kabsch_svd(src, P)
    assert np.abs(Rh - Rs).max() < 1e-10
    assert np.abs(th - ts).max() < 1e-10
    assert np.allclose(np.linalg.det(Rh), 1.0)
    assert np.allclose(np.einsum("tji,tjk->tik", Rh, Rh), np.eye(3), atol=1e-12)
    if noise_m == 0:
        back = np.einsum("tij,tnj->tni", Rh, src) + th[:, None]
        assert np.abs(back - P).max() < 1e-12


def test_kabsch_reflection_gives_the_best_proper_rotation():
    g = np.random.default_rng(3)
    P = g.normal(0, 0.1, (5, 3))
    mirrored = (P * np.array([1.0, 1.0, -1.0]))[None]
    Rh, th = kabsch(mirrored, P)
    Rs, ts = kabsch_svd(mirrored, P)
    assert np.isclose(np.linalg.det(Rh[0]), 1.0)
    cost = lambda R, t: ((mirrored[0] @ R[0].T + t[0] - P) ** 2).sum()   # noqa: E731
    assert cost(Rh, th) <= cost(Rs, ts) + 1e-12


def test_kabsch_degenerate_and_missing_frames():
    line = np.zeros((1, 3, 3))
    line[0, :, 0] = [0.0, 1.0, 2.0]
    R, t = kabsch(line, line[0])            # a line: any roll about it fits; one is returned
    assert np.allclose(np.einsum("ij,nj->ni", R[0], line[0]) + t[0], line[0])
    src = np.repeat(np.eye(3)[None], 3, 0)
    src[1, 0, 0] = np.nan
    R, t = kabsch(src, np.eye(3))
    assert np.isnan(R[1]).all() and np.isnan(t[1]).all()
    assert np.allclose(R[[0, 2]], np.eye(3)) and np.allclose(t[[0, 2]], 0)
    R, t = kabsch(np.zeros((0, 3, 3)), np.eye(3))
    assert R.shape == (0, 3, 3) and t.shape == (0, 3)
    with pytest.raises(ValueError, match="expected"):
        kabsch(np.zeros((2, 3, 2)), np.zeros((3, 2)))

"""Calibration report figures from known inputs: RMS, counts, coverage, ray error, wand stats,
the noise floor of the wand SD, the printed summary and the PNG."""
import numpy as np
import pytest

from calibration.report import make_report
from hw_sim.rig import make_rig

EXACT = 1e-9


def _wand_frames(rig, T=50, seed=0, length=0.5):
    g = np.random.default_rng(seed)
    c = g.uniform([-1, -1, 0.8], [1, 1, 1.6], (T, 3))
    d = g.normal(size=(T, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    X = np.stack([c - d * length / 2, c + d * length / 2], axis=1)          # (T, 2, 3)
    xy = np.stack([cam.project(X.reshape(-1, 3)).reshape(T, 2, 2) for cam in rig])
    return X, xy


def test_exact_figures(tmp_path):
    rig = make_rig(4, rng=1)
    X, xy = _wand_frames(rig)
    C, T, M = xy.shape[0], xy.shape[1], 2
    inlier = np.ones((C, T, M), bool)
    inlier[1, :10] = False                                   # camera 1 loses 10 frames
    resid = np.zeros((C, T, M, 2))
    resid[2, ..., 0] = 0.3                                   # camera 2: 0.3 px in x everywhere
    rep = make_report(list(rig), xy, resid, inlier, X, spacing_m=np.array([0.0, 0.5]),
                      noise_px=0.05)
    np.testing.assert_array_equal(rep.n_obs, [T * M, (T - 10) * M, T * M, T * M])
    np.testing.assert_allclose(rep.rms_px, [0, 0, 0.3, 0], atol=EXACT)
    assert rep.mean_ray_error_mm < 1e-6                      # exact points lie on their rays
    assert abs(rep.wand_mean_mm - 500.0) < 1e-6 and rep.wand_sd_mm < 1e-6
    assert np.all((rep.coverage > 0) & (rep.coverage <= 1))
    assert rep.coverage_maps.sum(axis=(1, 2)).tolist() == rep.n_obs.tolist()
    # floor: proportional to the pixel noise
    rep2 = make_report(list(rig), xy, resid, inlier, X, spacing_m=np.array([0.0, 0.5]),
                       noise_px=0.1)
    assert abs(rep2.wand_sd_floor_mm / rep.wand_sd_floor_mm - 2) < 1e-9
    text = rep.summary()
    for cam in rig:
        assert cam.name in text
    assert "wand length 500.000 mm" in text and "noise floor" in text
    png = tmp_path / "r.png"
    rep.save_figure(png, resid)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_ray_error_of_a_displaced_point_and_single_point_mode():
    rig = make_rig(3, rng=2)
    X, xy = _wand_frames(rig, T=5)
    Xd = X.copy()
    Xd[:, :, 2] += 0.002                                     # every point 2 mm off its rays
    inlier = np.ones(xy.shape[:3], bool)
    rep = make_report(list(rig), xy, np.zeros(xy.shape), inlier, Xd)
    # the distance of a point moved 2 mm along z from a ray is 2 mm x sin(ray, z)
    d = X[None] - np.array([c.center for c in rig])[:, None, None]
    sin = np.linalg.norm(np.cross(d, [0.0, 0.0, 1.0]), axis=-1) / np.linalg.norm(d, axis=-1)
    assert rep.mean_ray_error_mm == pytest.approx(2.0 * sin.mean(), rel=1e-9)
    assert np.isnan(rep.wand_mean_mm) and np.isnan(rep.wand_sd_floor_mm)
    assert "no metric scale" in rep.summary()

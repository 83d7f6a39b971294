"""hw_sim.rig: geometry of the simulated camera ring."""
import numpy as np
import pytest

from calibration.camera import Rig
from hw_sim.rig import VOLUME_CENTRE, make_rig, volume_bounds

EXACT = 1e-9                 # px / m for noise-free geometry
JITTER_AIM_PX = 120.0        # 1 deg aim jitter (x3 sigma) at f ~ 1204 px is < ~65 px; margin
FOCAL_56DEG_PX = 640 / np.tan(np.radians(28))


def _grid(n=7):
    lo, hi = volume_bounds()
    axes = [np.linspace(lo[i], hi[i], n) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


@pytest.mark.parametrize("n", [8, 12, 16])
def test_names_in_order_and_centre_seen(n):
    rig = make_rig(n)
    assert isinstance(rig, Rig)
    assert rig.names == [f"cam_{i + 1}" for i in range(n)]
    for cam in rig:
        assert cam.size == (1280, 1024)
        assert abs(cam.K[0, 0] - FOCAL_56DEG_PX) < EXACT
        assert cam.depth(VOLUME_CENTRE[None])[0] > 3.0
        uv = cam.project(VOLUME_CENTRE[None])[0]
        # aimed at the centre: it projects onto the principal point
        assert np.allclose(uv, cam.K[:2, 2], atol=1e-6)


@pytest.mark.parametrize("n", [8, 12, 16])
def test_volume_is_covered_by_several_cameras(n):
    rig = make_rig(n)
    g = _grid()
    seen = np.array([cam.in_image(cam.project(g)) & (cam.depth(g) > 0) for cam in rig])
    assert seen.sum(0).min() >= n // 2  # every point of the volume in at least half the ring
    # cameras stand outside the volume and above its centre, in ring order
    lo, hi = volume_bounds()
    centres = np.array([c.center for c in rig])
    assert np.all(np.abs(centres[:, :2]).max(1) > hi[0])
    az = np.unwrap(np.arctan2(centres[:, 1], centres[:, 0]))
    assert np.all(np.diff(az) > 0)


def test_jitter_is_seeded_and_small():
    a, b, c = make_rig(8, rng=3), make_rig(8, rng=3), make_rig(8, rng=4)
    for ca, cb in zip(a, b):
        assert np.array_equal(ca.R, cb.R) and np.array_equal(ca.t, cb.t)
    assert not np.allclose(a[0].t, c[0].t)
    ideal = make_rig(8)
    for cj, ci in zip(a, ideal):
        assert np.linalg.norm(cj.center - ci.center) < 0.3
        uv = cj.project(VOLUME_CENTRE[None])[0]
        assert np.linalg.norm(uv - cj.K[:2, 2]) < JITTER_AIM_PX
        assert np.isclose(np.linalg.det(cj.R), 1.0)


def test_distortion_applied():
    d = (-0.1, 0.05, 0.001, -0.001, 0.0)
    rig = make_rig(4, dist=d)
    assert all(np.allclose(c.dist, d) for c in rig)
    per = np.arange(20, dtype=float).reshape(4, 5) * 1e-3
    assert np.array_equal(make_rig(4, dist=per)[2].dist, per[2])
    assert not np.any(make_rig(4)[0].dist)


@pytest.mark.parametrize("kw, msg", [
    (dict(n_cameras=0), "n_cameras"),
    (dict(dist=np.zeros((3, 5))), "dist.shape"),
    (dict(fov_deg=200), "fov_deg"),
    (dict(volume_m=(4, 4)), "volume_m"),
    (dict(radius_m=-1), "radius_m"),
])
def test_bad_input(kw, msg):
    with pytest.raises(ValueError, match=msg):
        make_rig(**kw)

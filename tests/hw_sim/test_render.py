"""hw_sim.render: rendered IR blobs sit at the projected points, with the requested noise."""
import numpy as np
import pytest

from calibration.camera import Camera, Rig, look_at
from hw_sim.render import blob_sigma_px, render_frame, render_scene
from hw_sim.rig import make_rig
from hw_sim.scenes import MarkerScene, static_markers

CENTROID_PX = 0.01        # noise-free, well-sampled (sigma >= 0.7 px), 16-bit blob
CENTROID_8BIT_PX = 0.03   # same, 8-bit quantisation of the intensities
SIGMA_REL = 0.01          # second moment of a rendered blob vs the model sigma
# measured background std vs the requested one: 320x240 = 76.8k pixels, so the sample
# std scatters by 1/sqrt(2N) = 0.26 % (measured: at most 0.31 %, 8-bit); ~4 sigma
NOISE_REL = 0.01
EXACT_PX = 1e-9


def _camera(dist=(0, 0, 0, 0, 0)):
    R, t = look_at((0.0, -4.0, 1.0), (0.0, 0.0, 1.0))
    return Camera.from_params(name="c", size=(320, 240), fx=1200, dist=dist, R=R, t=t)


def _centroid(img, uv, half, background):
    c0, r0 = int(round(uv[0])), int(round(uv[1]))
    win = img[r0 - half:r0 + half + 1, c0 - half:c0 + half + 1].astype(float) - background
    ys, xs = np.mgrid[r0 - half:r0 + half + 1, c0 - half:c0 + half + 1]
    m = win.sum()
    cx, cy = (win * xs).sum() / m, (win * ys).sum() / m
    var = (win * ((xs - cx) ** 2 + (ys - cy) ** 2)).sum() / m / 2
    return np.array([cx, cy]), np.sqrt(var)


def _isolated_points(cam, n, rng, depth=(3.0, 5.0)):
    """n world points at random sub-pixel positions on a coarse grid (blobs far apart)."""
    g = np.random.default_rng(rng)
    w, h = cam.size
    cols, rows = np.meshgrid(np.linspace(40, w - 40, 6), np.linspace(40, h - 40, 4))
    px = np.stack([cols.ravel(), rows.ravel()], 1)[:n] + g.uniform(-0.5, 0.5, (n, 2))
    o, d = cam.unproject(px)
    return o + d * g.uniform(*depth, (n, 1))


@pytest.mark.parametrize("dist", [(0, 0, 0, 0, 0), (-0.2, 0.1, 0.002, -0.001, 0.0)])
def test_noise_free_centroid_equals_projection(dist):
    cam = _camera(dist)
    P = _isolated_points(cam, 24, rng=1)
    img, tr = render_frame(cam, P, 0.014, rng=0, bit_depth=16, noise_sigma=0.0,
                           full_well_e=None, background=0.05)
    assert img.dtype == np.uint16
    assert np.abs(tr.xy - cam.project(P)).max() < EXACT_PX
    assert tr.visible.all()
    assert np.all((tr.diameter_px > 3.0) & (tr.diameter_px < 6.0))  # 14 mm at 3-5 m
    for uv, s in zip(tr.xy, tr.sigma_px):
        c, sig = _centroid(img, uv, int(np.ceil(4 * s + 1)), 0.05 * 65535)
        assert np.abs(c - uv).max() < CENTROID_PX
        # blob size follows marker diameter and depth: second moment ~ sigma^2 + 1/12 (pixel)
        assert abs(sig / np.sqrt(s ** 2 + 1 / 12) - 1) < SIGMA_REL


def test_8bit_centroid_and_size_scaling():
    cam = _camera()
    P = _isolated_points(cam, 12, rng=2)
    img, tr = render_frame(cam, P, 0.014, rng=0, bit_depth=8, noise_sigma=0.0,
                           full_well_e=None, background=0.0)
    assert img.dtype == np.uint8
    for uv, s in zip(tr.xy, tr.sigma_px):
        c, _ = _centroid(img, uv, int(np.ceil(4 * s + 1)), 0.0)
        assert np.abs(c - uv).max() < CENTROID_8BIT_PX
    z = cam.depth(P)
    assert np.allclose(tr.diameter_px, 0.014 * 1200 / z, rtol=1e-12)
    assert np.allclose(tr.sigma_px, blob_sigma_px(tr.diameter_px, 0.5))


@pytest.mark.parametrize("bit_depth", [8, 10, 12, 16])
def test_read_noise_level_and_bit_depth(bit_depth):
    cam = _camera()
    top = 2 ** bit_depth - 1
    img, _ = render_frame(cam, np.zeros((0, 3)), 0.014, rng=3, bit_depth=bit_depth,
                          background=0.1, noise_sigma=0.01, full_well_e=None)
    assert img.dtype == (np.uint8 if bit_depth == 8 else np.uint16)
    assert img.max() <= top
    expect = np.sqrt((0.01 * top) ** 2 + 1 / 12)  # read noise + rounding to integers
    assert abs(img.std() / expect - 1) < NOISE_REL
    assert abs(img.mean() / top - 0.1) < 0.001


def test_shot_noise_level():
    cam = _camera()
    top = 65535
    img, _ = render_frame(cam, np.zeros((0, 3)), 0.014, rng=4, bit_depth=16, background=0.3,
                          noise_sigma=0.002, full_well_e=5000.0)
    expect = top * np.sqrt(0.002 ** 2 + 0.3 / 5000.0)
    assert abs(img.std() / expect - 1) < NOISE_REL


def test_blob_noise_follows_signal():
    """Inside a bright blob the noise is the shot noise of its signal."""
    cam = _camera()
    P = _isolated_points(cam, 1, rng=5, depth=(3.0, 3.0))
    kw = dict(bit_depth=16, background=0.02, peak=0.8, noise_sigma=0.001, full_well_e=2000.0)
    clean, tr = render_frame(cam, P, 0.014, rng=0, **{**kw, "noise_sigma": 0.0,
                                                      "full_well_e": None})
    c0, r0 = np.round(tr.xy[0]).astype(int)
    diffs = [render_frame(cam, P, 0.014, rng=s, **kw)[0][r0, c0] / 65535.0
             - clean[r0, c0] / 65535.0 for s in range(400)]
    v = clean[r0, c0] / 65535.0
    expect = np.sqrt(0.001 ** 2 + v / 2000.0)
    assert abs(np.std(diffs) / expect - 1) < 0.12  # 400 samples: std of std ~3.5%


def test_saturation_clips_at_full_scale():
    cam = _camera()
    P = _isolated_points(cam, 3, rng=6)
    img, _ = render_frame(cam, P, 0.014, rng=0, bit_depth=10, peak=3.0)
    assert img.max() == 1023 and img.dtype == np.uint16
    assert (img == 1023).sum() >= 3


def test_occluded_and_behind_are_not_drawn_and_seeded():
    cam = _camera()
    P = _isolated_points(cam, 3, rng=7)
    P = np.vstack([P, [[0.0, -6.0, 1.0]], [[np.nan] * 3]])  # behind the camera, absent
    kw = dict(bit_depth=8, noise_sigma=0.0, full_well_e=None, background=0.0)
    img, tr = render_frame(cam, P, 0.014, rng=0, occluded=[False, True, False, False, False], **kw)
    assert np.array_equal(tr.visible, [True, False, True, False, False])
    assert np.isnan(tr.xy[3:]).all()
    c0, r0 = np.round(tr.xy[1]).astype(int)
    assert img[r0 - 3:r0 + 4, c0 - 3:c0 + 4].max() == 0
    c0, r0 = np.round(tr.xy[0]).astype(int)
    assert img[r0, c0] > 100
    a = render_frame(cam, P[:3], 0.014, rng=11)[0]
    b = render_frame(cam, P[:3], 0.014, rng=11)[0]
    c = render_frame(cam, P[:3], 0.014, rng=12)[0]
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_render_scene_truth_matches_rig_and_occlusion():
    R1, t1 = look_at((0.0, -4.0, 1.0), (0.0, 0.0, 1.0))
    R2, t2 = look_at((0.0, 4.0, 1.0), (0.0, 0.0, 1.0))
    rig = Rig(cameras=(Camera.from_params(name="front", size=(320, 240), fx=600, R=R1, t=t1),
                       Camera.from_params(name="back", size=(320, 240), fx=600, R=R2, t=t2)))
    segs = np.array([[[[0.0, 0.0, 0.5], [0.0, 0.0, 1.5]]]])
    P = np.array([[[0.0, 0.2, 1.0], [0.6, 0.0, 1.2]]])  # first hidden from the front camera
    scene = MarkerScene(positions=P, marker_diameter_m=[0.014] * 2, rate_hz=100, labels="ab",
                        occluder_segments=segs, occluder_radii_m=[0.15])
    sf = render_scene(rig, scene, 0, rng=1, noise_sigma=0.0, full_well_e=None, background=0.0)
    assert sf.camera_names == ("front", "back") and len(sf.images) == 2
    assert np.abs(sf.xy - rig.project(P[0])).max() < EXACT_PX
    assert np.array_equal(sf.visible, [[False, True], [True, True]])
    assert np.array_equal(sf.occluded, [[True, False], [False, False]])
    u, v = np.round(sf.xy[0, 0]).astype(int)
    assert sf.images[0][v - 2:v + 3, u - 2:u + 3].max() == 0


def test_render_scene_full_rig_fast_path():
    rig = make_rig(8)
    scene = static_markers(30, 2, rng=3)
    sf = render_scene(rig, scene, 1, rng=2)
    assert len(sf.images) == 8 and sf.images[0].shape == (1024, 1280)
    assert sf.visible.sum() > 0.9 * 8 * 30


@pytest.mark.parametrize("kw, msg", [
    (dict(bit_depth=9), "bit_depth"),
    (dict(noise_sigma=-1), "noise_sigma"),
    (dict(full_well_e=0), "full_well_e"),
    (dict(occluded=[True]), "occluded.shape"),
])
def test_bad_input(kw, msg):
    with pytest.raises(ValueError, match=msg):
        render_frame(_camera(), np.zeros((2, 3)) + [0, 0, 1], 0.014, **kw)


def test_bad_points_shape():
    with pytest.raises(ValueError, match="points_world.shape"):
        render_frame(_camera(), np.zeros((2, 2)), 0.014)
    with pytest.raises(ValueError, match="frame_index"):
        render_scene(make_rig(2), static_markers(2, 2, rng=0), 5)

"""Sub-pixel blob detection vs known rendered centres (docs/conventions.md [pixels])."""

import numpy as np
import pytest
from scipy.special import erf

from reconstruct.blobs import BlobConfig, Blobs, detect_blobs, detections_from_frames

NOISY_RMS_PX = 0.05         # acceptance: centroid RMS with realistic noise
EXACT_RMS_PX = 0.01         # noise-free rendering (moment truncation / quantisation bias only;
                            # worst of the 9 cases 0.0047 px)
MATCH_PX = 1.0              # detection <-> truth association radius


def render_blobs(shape, xy, sigma, *, bit_depth=8, peak=0.85, background=0.03,
                 read_noise=0.004, full_well_e=20000.0, rng=0):
    """Gaussian blobs integrated over pixel areas (erf differences); Poisson + read noise."""
    rng = np.random.default_rng(rng)
    H, W = shape
    full = 2 ** bit_depth - 1
    img = np.full(shape, background)
    for (x, y), s in zip(xy, np.broadcast_to(sigma, len(xy))):
        ex = np.arange(W + 1) - 0.5
        ey = np.arange(H + 1) - 0.5
        gx = np.diff(0.5 * erf((ex - x) / (np.sqrt(2) * s)))
        gy = np.diff(0.5 * erf((ey - y) / (np.sqrt(2) * s)))
        img += peak * 2 * np.pi * s * s * np.outer(gy, gx)  # peak ~ amplitude of the Gaussian
    if full_well_e:
        img = rng.poisson(np.clip(img, 0, None) * full_well_e) / full_well_e
    if read_noise:
        img = img + rng.normal(0, read_noise, shape)
    img = np.clip(np.round(img * full), 0, full)
    return img.astype(np.uint8 if bit_depth == 8 else np.uint16)


def grid_truth(n_side, spacing, rng):
    rng = np.random.default_rng(rng)
    g = (np.arange(n_side) + 1) * spacing
    xx, yy = np.meshgrid(g, g)
    return np.column_stack([xx.ravel(), yy.ravel()]) + rng.uniform(-0.5, 0.5, (n_side ** 2, 2))


def match_rms(det: Blobs, truth):
    d = np.linalg.norm(det.xy[None, :, :] - truth[:, None, :], axis=2)
    j = d.argmin(axis=1)
    assert np.all(d[np.arange(len(truth)), j] < MATCH_PX), "a true blob was not detected"
    assert len(det) == len(truth)
    err = det.xy[j] - truth
    return float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))


def sigma_of_diameter(d, psf=0.5):
    return np.sqrt((d / 4.0) ** 2 + psf ** 2)


@pytest.mark.parametrize("bit_depth", [8, 10, 16])
@pytest.mark.parametrize("diameter_px", [3.0, 5.0, 8.0])
def test_centroid_accuracy(bit_depth, diameter_px):
    truth = grid_truth(5, 20, rng=bit_depth + int(diameter_px))
    s = sigma_of_diameter(diameter_px)
    cfg = BlobConfig(bit_depth=bit_depth)
    exact = render_blobs((120, 120), truth, s, bit_depth=bit_depth, read_noise=0,
                         full_well_e=None)
    noisy = render_blobs((120, 120), truth, s, bit_depth=bit_depth, rng=int(diameter_px))
    rms_exact = match_rms(detect_blobs(exact, cfg), truth)
    rms_noisy = match_rms(detect_blobs(noisy, cfg), truth)
    print(f"bit_depth={bit_depth} d={diameter_px}px: RMS noise-free {rms_exact:.4f} px, "
          f"noisy {rms_noisy:.4f} px")
    assert rms_exact <= EXACT_RMS_PX
    assert rms_noisy <= NOISY_RMS_PX


def test_auto_threshold_tracks_background():
    truth = grid_truth(3, 30, rng=1)
    s = sigma_of_diameter(5.0)
    for bg in (0.03, 0.3):  # bright ambient: a fixed threshold tuned for 0.03 would flood
        img = render_blobs((100, 100), truth, s, bit_depth=10, background=bg, peak=0.5, rng=2)
        det = detect_blobs(img, BlobConfig(bit_depth=10))
        assert det.threshold > bg * 1023
        assert match_rms(det, truth) <= NOISY_RMS_PX
    flooded = detect_blobs(img, BlobConfig(bit_depth=10, threshold=0.1 * 1023))
    assert len(flooded) != len(truth)


def test_size_and_roundness_filters():
    s = sigma_of_diameter(4.0)
    single = np.array([[20.0, 20.0]])
    merged = np.array([[60.0, 20.0], [63.5, 20.2]])  # two touching blobs -> elongated
    img = render_blobs((40, 90), np.vstack([single, merged]), s, rng=3)
    det = detect_blobs(img, BlobConfig(min_roundness=0.75))
    assert len(det) == 1 and np.linalg.norm(det.xy[0] - single[0]) < NOISY_RMS_PX * 3
    det_all = detect_blobs(img, BlobConfig(min_roundness=0.0))
    assert len(det_all) == 2
    small = detect_blobs(img, BlobConfig(min_roundness=0.0, max_area_px=30))
    assert len(small) == 1  # the merged blob is too big


def test_bad_input():
    with pytest.raises(ValueError, match="bit_depth"):
        BlobConfig(bit_depth=9)
    with pytest.raises(ValueError, match="threshold"):
        BlobConfig(threshold="median")
    with pytest.raises(ValueError, match="image.shape"):
        detect_blobs(np.zeros((3, 3, 3), np.uint8), BlobConfig())
    with pytest.raises(ValueError, match="dtype"):
        detect_blobs(np.zeros((3, 3)), BlobConfig())


def test_detections_from_frames():
    truth = grid_truth(2, 25, rng=4)
    s = sigma_of_diameter(5.0)
    frames = [(t, [render_blobs((75, 75), truth + t * 0.1, s, rng=10 * t + c)
                   for c in range(2)]) for t in range(3)]
    det = detections_from_frames(frames, ["a", "b"], BlobConfig(), rate_hz=100.0)
    assert det.camera_names == ("a", "b") and det.rate_hz == 100.0
    assert len(det) == 3 * 2 * 4
    for t in range(3):
        rows = det.frame == t
        d = np.linalg.norm(det.xy[rows][:, None] - (truth + t * 0.1)[None], axis=2)
        assert np.all(d.min(axis=1) < 3 * NOISY_RMS_PX)


def test_hw_sim_render():
    from hw_sim import render
    from calibration.camera import Camera
    K = np.array([[800.0, 0, 159.5], [0, 800.0, 127.5], [0, 0, 1]])
    cam = Camera(name="c", size=(320, 256), K=K, dist=np.zeros(5), R=np.eye(3),
                 t=np.zeros(3))
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(-0.3, 0.3, (12, 2)), np.full(12, 2.0)])
    pts[:, :2] = np.round(pts[:, :2] / 0.06) * 0.06 + rng.uniform(-0.005, 0.005, (12, 2))
    pts = np.unique(pts, axis=0)
    for bit_depth in (8, 10, 16):
        img, tr = render.render_frame(cam, pts, 0.014, rng=6, bit_depth=bit_depth)
        det = detect_blobs(img, BlobConfig(bit_depth=bit_depth))
        vis = tr.visible
        assert match_rms(det, tr.xy[vis]) <= NOISY_RMS_PX


@pytest.mark.parametrize("diameter_px", [3.0, 8.0])
def test_gaussian_refine_beats_moments(diameter_px):
    truth = grid_truth(5, 20, rng=7)
    img = render_blobs((120, 120), truth, sigma_of_diameter(diameter_px), bit_depth=10, rng=8)
    rms_m = match_rms(detect_blobs(img, BlobConfig(bit_depth=10)), truth)
    rms_g = match_rms(detect_blobs(img, BlobConfig(bit_depth=10, refine="gaussian")), truth)
    print(f"d={diameter_px}px 10-bit: moments {rms_m:.4f} px, gaussian {rms_g:.4f} px")
    assert rms_g <= NOISY_RMS_PX
    assert rms_g < rms_m

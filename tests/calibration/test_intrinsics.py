"""Chessboard intrinsics from synthetic images rendered through a known camera."""
import cv2
import numpy as np
import pytest

from calibration.camera import rotation_from_rodrigues
from calibration.intrinsics import calibrate_chessboard

FOCAL_REL_TOL = 0.01      # rendered (bilinear, 8-bit) corners: f measured -0.42 % on both axes
PP_TOL_PX = 1.0           # principal point: 0.32 px measured
COLS, ROWS, SQ_PX = 9, 6, 40   # inner corners; board texture square size (px)
SQUARE_M = 0.03
W, H = 640, 480
K_TRUE = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])


def _board():
    img = np.full(((ROWS + 3) * SQ_PX, (COLS + 3) * SQ_PX), 255, np.uint8)
    for r in range(ROWS + 1):
        for c in range(COLS + 1):
            if (r + c) % 2 == 0:
                y, x = (r + 1) * SQ_PX, (c + 1) * SQ_PX
                img[y:y + SQ_PX, x:x + SQ_PX] = 0
    return img


def _views(n=8, seed=0):
    g = np.random.default_rng(seed)
    board = _board()
    s = SQUARE_M / SQ_PX                  # metres per texture pixel
    out = []
    for _ in range(n):
        R = rotation_from_rodrigues(g.uniform(-0.5, 0.5, 3))
        t = np.array([g.uniform(-0.1, 0.0), g.uniform(-0.1, 0.0), g.uniform(0.45, 0.6)])
        # texture pixel (u, v) -> board point (u s - 2 SQUARE_M, v s - 2 SQUARE_M, 0)
        # so the first inner corner (texture (2 SQ, 2 SQ) - 0.5) sits near the origin
        A = np.array([[s, 0, -2 * SQUARE_M + 0.5 * s], [0, s, -2 * SQUARE_M + 0.5 * s], [0, 0, 1]])
        Hm = K_TRUE @ np.c_[R[:, :2], t] @ A
        out.append(cv2.warpPerspective(board, Hm, (W, H), flags=cv2.INTER_LINEAR,
                                       borderValue=255))
    return out


def test_chessboard_recovers_intrinsics():
    res = calibrate_chessboard(_views(), cols=COLS, rows=ROWS, square_m=SQUARE_M)
    assert res.ok, res.reason
    K = res.camera.K
    assert abs(K[0, 0] / K_TRUE[0, 0] - 1) < FOCAL_REL_TOL
    assert abs(K[1, 1] / K_TRUE[1, 1] - 1) < FOCAL_REL_TOL
    assert np.hypot(K[0, 2] - K_TRUE[0, 2], K[1, 2] - K_TRUE[1, 2]) < PP_TOL_PX
    assert res.rms_px < 0.1                        # 0.037 px measured


def test_wrong_board_size_is_diagnosed():
    with pytest.raises(ValueError, match="found 9x6 inner corners but 10x6"):
        calibrate_chessboard(_views(2), cols=10, rows=6, square_m=SQUARE_M)

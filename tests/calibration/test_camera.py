"""Camera model against OpenCV, and its inverse operations."""
import cv2
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from calibration.camera import (Camera, Rig, look_at, rodrigues_from_rotation,
                                rotation_from_rodrigues)

EXACT_PX = 1e-9      # our projection vs OpenCV, pixels
INVERSE_PX = 1e-8    # project(unproject(p)) == p
DIST = (-0.12, 0.05, 0.0008, -0.0005, -0.01)


def _cam(dist=DIST, rvec=(0.1, -0.2, 0.05), t=(0.1, -0.2, 4.0)):
    return Camera.from_params(name="c", size=(1280, 1024), fx=1210.0, fy=1205.0, cx=641.3,
                              cy=509.8, dist=dist, R=rotation_from_rodrigues(rvec), t=t)


def test_project_matches_opencv():
    rng = np.random.default_rng(0)
    cam = _cam()
    pts = rng.uniform(-1, 1, size=(500, 3))
    ours = cam.project(pts)
    ref, _ = cv2.projectPoints(pts, cam.rvec, cam.t, cam.K, cam.dist)
    np.testing.assert_allclose(ours, ref.reshape(-1, 2), atol=EXACT_PX)


def test_points_behind_camera_are_nan():
    cam = _cam(dist=(0, 0, 0, 0, 0), rvec=(0, 0, 0), t=(0, 0, 0))
    uv = cam.project(np.array([[0, 0, -1.0], [0, 0, 1.0]]))
    assert np.isnan(uv[0]).all() and np.isfinite(uv[1]).all()


def test_undistort_matches_opencv():
    rng = np.random.default_rng(1)
    cam = _cam()
    px = np.column_stack([rng.uniform(0, 1279, 400), rng.uniform(0, 1023, 400)])
    ours = cam.pixel_to_normalized(px)
    ref = cv2.undistortPoints(px.reshape(-1, 1, 2), cam.K, cam.dist, None, None, None,
                                  (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15))
    np.testing.assert_allclose(ours, ref.reshape(-1, 2), atol=1e-7)
    # and ours is the exact inverse of the forward model
    back = cam.distort_normalized(ours)
    K = cam.K
    np.testing.assert_allclose(back[:, 0] * K[0, 0] + K[0, 2], px[:, 0], atol=INVERSE_PX)
    np.testing.assert_allclose(back[:, 1] * K[1, 1] + K[1, 2], px[:, 1], atol=INVERSE_PX)


@settings(max_examples=60, deadline=None)
@given(x=st.floats(-0.6, 0.6), y=st.floats(-0.5, 0.5), depth=st.floats(0.5, 8.0))
def test_unproject_project_roundtrip(x, y, depth):
    cam = _cam()
    p_cam = np.array([x * depth, y * depth, depth])
    p_world = cam.R.T @ (p_cam - cam.t)
    uv = cam.project(p_world[None])
    origin, d = cam.unproject(uv)
    # the world point lies on the returned ray
    v = p_world - origin
    perp = v - (v @ d[0]) * d[0]
    assert np.linalg.norm(perp) < 1e-9 * max(1.0, depth)


@settings(max_examples=50, deadline=None)
@given(r=st.lists(st.floats(-3, 3), min_size=3, max_size=3))
def test_rodrigues_roundtrip_and_proper(r):
    r = np.asarray(r)
    if np.linalg.norm(r) > np.pi - 1e-3:  # rotation vectors are unique below pi
        r = r / np.linalg.norm(r) * (np.pi - 1e-3)
    R = rotation_from_rodrigues(r)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(R, cv2.Rodrigues(r)[0], atol=1e-12)
    np.testing.assert_allclose(rodrigues_from_rotation(R), r, atol=1e-9)


def test_look_at_centre_projects_to_principal_point():
    R, t = look_at(eye=(4, 3, 2.5), target=(0, 0, 1.25))
    cam = Camera.from_params(name="a", size=(1280, 1024), fx=1200, R=R, t=t)
    np.testing.assert_allclose(cam.project(np.array([[0, 0, 1.25]]))[0], [639.5, 511.5], atol=1e-9)
    np.testing.assert_allclose(cam.center, [4, 3, 2.5], atol=1e-12)
    # world up appears as image up (negative y)
    up = cam.project(np.array([[0, 0, 1.5]]))[0]
    assert up[1] < 511.5


def test_bad_inputs_name_the_problem():
    cam = _cam()
    with pytest.raises(ValueError, match=r"points.shape=\(4, 2\)"):
        cam.project(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="K.shape"):
        Camera(name="x", size=(10, 10), K=np.eye(2))
    with pytest.raises(ValueError, match="dist has 3"):
        Camera(name="x", size=(10, 10), K=np.eye(3), dist=(0, 0, 0))
    with pytest.raises(ValueError, match="not a proper rotation"):
        Camera(name="x", size=(10, 10), K=np.eye(3), R=-np.eye(3))
    with pytest.raises(ValueError, match="duplicate camera names"):
        Rig(cameras=(cam, cam))
    rig = Rig(cameras=(cam,))
    with pytest.raises(ValueError, match="unknown camera 'zz'"):
        rig.index("zz")

"""Camera models: the pinhole Camera, the rectified StereoCamera (paper 001 eq. 6) and the
DepthCamera (paper 002 sec. 4.1), against values computed by hand."""

import numpy as np
import pytest

import gputrack
from gputrack.models import Camera, DepthCamera, StereoCamera
from gputrack.ops.kalman import ekf_update_stereo


def test_stereo_projects_as_eq_6_by_hand():
    cam = StereoCamera(f=500.0, cx=320.0, cy=240.0, b=0.12)
    # u = 500 * 0.5 / 2 + 320, v = 500 * -0.25 / 2 + 240, d = 0.12 * 500 / 2
    np.testing.assert_allclose(cam.project([0.5, -0.25, 2.0]), [445.0, 177.5, 30.0], rtol=0, atol=1e-12)
    # a point on the optical axis at 6 m: the principal point, d = 60 / 6
    np.testing.assert_allclose(cam.project([[0.0, 0.0, 6.0]]), [[320.0, 240.0, 10.0]], rtol=0, atol=1e-12)


def test_stereo_unprojects_by_hand_and_round_trips():
    cam = StereoCamera(f=500.0, cx=320.0, cy=240.0, b=0.12)
    # z = 0.12 * 500 / 30 = 2, x = (445 - 320) * 2 / 500, y = (177.5 - 240) * 2 / 500
    np.testing.assert_allclose(cam.unproject([445.0, 177.5, 30.0]), [0.5, -0.25, 2.0], rtol=0, atol=1e-12)
    rng = np.random.default_rng(0)
    pts = rng.uniform([-3, -2, 0.5], [3, 2, 20], (4, 5, 3))
    uvd = cam.project(pts)
    assert uvd.shape == (4, 5, 3)
    np.testing.assert_allclose(cam.unproject(uvd), pts, rtol=1e-12)


def test_stereo_projection_is_the_ekf_observation():
    """ekf_update_stereo with the camera's f, b, cx, cy observes exactly project(): an observation
    of the state's own position leaves the state unchanged; a principal point off by 5 px moves it."""
    cam = StereoCamera(f=480.0, cx=319.5, cy=239.5, b=0.12)
    dev = gputrack.device("numpy")
    x = np.array([[0.4, 0.1, -0.3, 0.0, 3.0, -0.2]], np.float64)
    P = np.eye(6)[None] * 0.5
    R = np.eye(3) * 0.01
    z = cam.project(x[:, 0::2])
    same = ekf_update_stereo(dev, x, P, z, R, f=cam.f, b=cam.b, cx=cam.cx, cy=cam.cy)
    np.testing.assert_allclose(same.x, x, rtol=0, atol=1e-12)
    moved = ekf_update_stereo(dev, x, P, z, R, f=cam.f, b=cam.b, cx=cam.cx + 5.0, cy=cam.cy)
    assert abs(moved.x[0, 0] - x[0, 0]) > 1e-3


def test_stereo_bad_input():
    with pytest.raises(ValueError, match="expected f > 0 and b > 0"):
        StereoCamera(f=500.0, cx=0.0, cy=0.0, b=0.0)
    with pytest.raises(TypeError, match="StereoCamera.f: expected a real number"):
        StereoCamera(f="500", cx=0.0, cy=0.0, b=0.1)
    with pytest.raises(ValueError, match="StereoCamera.cx: expected a finite number"):
        StereoCamera(f=500.0, cx=np.nan, cy=0.0, b=0.1)
    cam = StereoCamera(f=500.0, cx=0.0, cy=0.0, b=0.1)
    with pytest.raises(ValueError, match=r"points: expected z > 0 .* at index \(1,\)"):
        cam.project([[0, 0, 1.0], [0, 0, 0.0]])
    with pytest.raises(ValueError, match=r"points: expected a real array of shape \(\.\.\., 3\), got float64 \(2,\)"):
        cam.project([1.0, 2.0])
    with pytest.raises(ValueError, match="points: expected finite values"):
        cam.project([0, np.inf, 1.0])
    with pytest.raises(ValueError, match="uvd: expected a disparity d > 0"):
        cam.unproject([10.0, 10.0, 0.0])


def test_depth_camera_back_projects_by_hand():
    cam = DepthCamera(fx=2.0, fy=4.0, cx=1.0, cy=0.5, depth_scale=0.001, min_depth=0.3, max_depth=5.0)
    depth = np.array([[1000, 0, 6000], [2000, 500, np.nan]])  # millimetres
    np.testing.assert_array_equal(cam.valid(depth), [[True, False, False], [True, True, False]])
    pts, pix = cam.points(depth, return_pixels=True)
    # (row 0, col 0), z = 1: x = (0 - 1) 1 / 2, y = (0 - 0.5) 1 / 4; 0 = no measurement; 6 m is
    # beyond the range; (1, 0), z = 2: x = (0 - 1) 2 / 2, y = (1 - 0.5) 2 / 4; (1, 1), z = 0.5:
    # x = 0, y = (1 - 0.5) 0.5 / 4; NaN = no measurement
    want = [[-0.5, -0.125, 1.0], [-1.0, 0.25, 2.0], [0.0, 0.0625, 0.5]]
    np.testing.assert_allclose(pts, want, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(pix, [[0, 0], [1, 0], [1, 1]])
    np.testing.assert_allclose(cam.project(pts), pix[:, ::-1].astype(float), rtol=0, atol=1e-12)
    assert cam.points(np.zeros((3, 4))).shape == (0, 3)


def test_depth_camera_range_and_units():
    depth = np.array([[299.0, 300.0, 5000.0, 5001.0]])
    cam = DepthCamera(fx=1.0, fy=1.0, cx=0.0, cy=0.0)
    np.testing.assert_array_equal(cam.valid(depth), [[False, True, True, False]])
    mm = DepthCamera(fx=1.0, fy=1.0, cx=0.0, cy=0.0, depth_scale=1.0, min_depth=0.0, max_depth=1e4)
    np.testing.assert_allclose(mm.points(depth)[:, 2], depth[0])
    assert mm.pinhole == Camera(1.0, 1.0, 0.0, 0.0)


def test_depth_camera_bad_input():
    with pytest.raises(ValueError, match="expected fx, fy and depth_scale > 0"):
        DepthCamera(fx=1.0, fy=1.0, cx=0.0, cy=0.0, depth_scale=0.0)
    with pytest.raises(ValueError, match="expected 0 <= min_depth < max_depth"):
        DepthCamera(fx=1.0, fy=1.0, cx=0.0, cy=0.0, min_depth=5.0, max_depth=5.0)
    cam = DepthCamera(fx=1.0, fy=1.0, cx=0.0, cy=0.0)
    with pytest.raises(ValueError, match=r"depth: expected a real \(H, W\) image, got float64 \(4,\)"):
        cam.points(np.ones(4))
    with pytest.raises(ValueError, match="depth: expected a real"):
        cam.points(np.array([["a"]]))
    with pytest.raises(ValueError, match="points: expected z > 0"):
        cam.project([0.0, 0.0, -1.0])

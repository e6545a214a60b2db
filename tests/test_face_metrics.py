"""The face tracker's error measures (gputrack.trackers.face.metrics) and the pose fit they use
(gputrack.models.pose.fit_pose): pure NumPy/OpenCV, no device."""

from __future__ import annotations

import numpy as np
import pytest

from gputrack.models import Camera
from gputrack.models.pose import fit_pose, project, rodrigues, rotation_from_euler
from gputrack.trackers.face.metrics import error_parts, pose_errors, rotation_sources

CAM = Camera(700.0, 700.0, 320.0, 240.0)
#: a face-sized point set (mm, model frame; the face looks along -z)
SHAPE = np.array([[-45, -18, 13], [-18, -16, 7], [18, -16, 7], [45, -18, 13], [-13, 28, -9], [13, 28, -9],
                  [-26, 54, 1], [26, 54, 1], [-12, -45, -8], [12, -45, -8]], np.float64)  # fmt: skip


def _angles(n, yaw_offset=0.0):
    """(n, 3) roll, pitch, yaw (rad): yawed, pitched and rolled a little each."""
    return np.radians(np.column_stack([np.linspace(-3, 3, n), np.linspace(5, -5, n), np.linspace(-30, 30, n) + yaw_offset]))


def _frames(n=5):
    """n true poses (:func:`_angles`) and their exact points."""
    ang = _angles(n)
    R = rotation_from_euler(ang[:, 0], ang[:, 1], ang[:, 2])
    t = np.column_stack([np.linspace(-20, 20, n), np.zeros(n), np.linspace(500, 700, n)])
    return R, t, project(CAM, R, t, np.broadcast_to(SHAPE, (n, *SHAPE.shape)))


def test_fit_pose_recovers_the_pose_from_exact_points():
    R, t, pts = _frames(1)
    fit = fit_pose(CAM, SHAPE, pts[0], (np.zeros(3), np.array([0.0, 0.0, 550.0])))
    np.testing.assert_allclose(rodrigues(fit[0]), R[0], atol=1e-7)
    np.testing.assert_allclose(fit[1], t[0], atol=1e-4)
    some = pts[0].copy()
    some[[2, 7]] = np.nan  # unknown points are left out; 8 remain
    np.testing.assert_allclose(fit_pose(CAM, SHAPE, some, fit)[1], t[0], atol=1e-4)
    some[[0, 1, 3]] = np.nan  # 5 known: too few
    assert fit_pose(CAM, SHAPE, some, fit) is None


def test_signed_pose_errors_are_the_estimate_minus_the_truth():
    R, t, _ = _frames(3)
    est_R = rotation_from_euler(*np.radians([[2.0, -1.0, 0.5], [0.0, 3.0, 0.0], [-1.0, 0.0, 0.0]]).T) @ R
    est_R[1] = R[1] @ rotation_from_euler(0.0, np.radians(3.0), 0.0)  # pitch about the head's own axis: pure pitch
    est_t = t + np.array([1.0, -2.0, 3.0])
    signed = pose_errors(est_R, est_t, R, t, signed=True)
    np.testing.assert_allclose(signed[:, :3], np.tile([1.0, -2.0, 3.0], (3, 1)), atol=1e-12)
    np.testing.assert_allclose(signed[1, 3:], [0.0, 3.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(np.abs(signed), pose_errors(est_R, est_t, R, t), atol=0)
    # angles wrap: 179 deg against -179 deg is 2 deg apart
    a, b = rotation_from_euler(np.radians(179.0), 0, 0), rotation_from_euler(np.radians(-179.0), 0, 0)
    np.testing.assert_allclose(pose_errors([a], [t[0]], [b], [t[0]], signed=True)[0, 3], -2.0, atol=1e-9)


def test_error_parts_split_an_offset_a_slow_change_and_jitter():
    # column 0: an offset only; column 1: +-2 alternating (jitter only, window 2 frames would see it as
    # slow, 3 averages it out); column 2: a ramp (slow only); the NaN row is left out
    F = 41
    ramp = np.linspace(-1.0, 1.0, F)
    e = np.column_stack([np.full(F, 1.5), 2.0 * (-1.0) ** np.arange(F), ramp])
    e = np.vstack([e[:20], [np.nan, 9.0, 9.0], e[20:]])
    parts = error_parts(e, window=3)
    np.testing.assert_allclose(parts["offset"], [1.5, 2.0 / F, 0.0], atol=1e-12)
    np.testing.assert_allclose(parts["jitter"][0], 0.0, atol=1e-12)
    assert parts["jitter"][1] > 1.2 and parts["slow"][1] < 0.8  # alternating: mostly jitter
    assert parts["slow"][2] > 0.45 and parts["jitter"][2] < 0.01  # a ramp: slow, no jitter
    rng = np.random.default_rng(0)
    e = rng.normal(0.5, 1.0, (200, 3)) + np.sin(np.linspace(0, 6, 200))[:, None]
    parts = error_parts(e)
    assert (np.abs(e).mean(axis=0) <= parts["offset"] + parts["slow"] + parts["jitter"] + 1e-12).all()
    assert all(np.isnan(v).all() for v in error_parts(np.full((2, 3), np.nan)).values())
    with pytest.raises(ValueError, match=r"signed_errors: expected \(F, C\), got shape \(3,\)"):
        error_parts(np.zeros(3))
    with pytest.raises(ValueError, match=r"window: expected an int >= 1, got 0"):
        error_parts(e, window=0)


def test_rotation_sources_tell_the_points_from_the_shape():
    R, t, pts = _frames(5)
    shapes = np.broadcast_to(SHAPE, (5, *SHAPE.shape))
    exact = rotation_sources(CAM, pts, shapes, pts, shapes, R, t)
    assert np.nanmax(exact["points"]) < 1e-5 and np.nanmax(exact["shape"]) < 1e-5
    # a shape tilted 4 deg about its own x axis: the true points fit it 4 deg off in pitch, whatever the yaw
    tilted = SHAPE @ rotation_from_euler(0.0, np.radians(4.0), 0.0).T
    src = rotation_sources(CAM, pts, np.broadcast_to(tilted, shapes.shape), pts, shapes, R, t)
    np.testing.assert_allclose(src["shape"], np.tile([0.0, 4.0, 0.0], (5, 1)), atol=1e-5)
    assert np.nanmax(src["points"]) < 1e-5
    # points of the head turned 2 deg further: the true shape fits them 2 deg off in yaw, the shape is not to blame
    ang = _angles(5, yaw_offset=2.0)
    turned = project(CAM, rotation_from_euler(ang[:, 0], ang[:, 1], ang[:, 2]), t, shapes)
    src = rotation_sources(CAM, turned, shapes, pts, shapes, R, t)
    np.testing.assert_allclose(src["points"], np.tile([0.0, 0.0, 2.0], (5, 1)), atol=1e-5)
    assert np.nanmax(src["shape"]) < 1e-5
    # a frame with too few known points gets NaN
    lost = turned.copy()
    lost[2, :5] = np.nan
    src = rotation_sources(CAM, lost, shapes, pts, shapes, R, t)
    assert np.isnan(src["points"][2]).all() and np.isfinite(src["points"][[0, 1, 3, 4]]).all()
    with pytest.raises(ValueError, match=r"features: expected shape \(5, K, 2\), got \(4, 10, 2\)"):
        rotation_sources(CAM, pts[:4], shapes, pts, shapes, R, t)
    with pytest.raises(ValueError, match=r"expected the same K points, got K = \[9, 10\]"):
        rotation_sources(CAM, pts, shapes[:, :9], pts, shapes, R, t)

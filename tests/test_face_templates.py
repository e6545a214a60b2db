"""The face tracker's templates as the face is seen now (gputrack.trackers.face.templates): the frontal
plane's image Jacobians, the similarity of a roll and of a move in depth, and on rendered faces the
warped templates matching a rolled and receding face where the plain ones do not."""

import numpy as np

import gputrack
from gputrack.models import Camera
from gputrack.models.pose import project, rodrigues
from gputrack.ops.face_relocate import relocate_points, sample_patches
from gputrack.trackers.face.templates import frontal_jacobians, template_warp

CAM = Camera(700.0, 690.0, 319.5, 239.5)


def test_frontal_jacobians_are_the_projections_derivatives():
    rng = np.random.default_rng(0)
    X = rng.normal(0, 30, (10, 3))
    rvec, tvec = np.array([0.2, -0.5, 0.3]), np.array([20.0, -15.0, 600.0])
    J = frontal_jacobians(CAM, rvec, tvec, X)
    h = 1e-4
    for axis in range(2):
        step = np.zeros(3)
        step[axis] = h
        d = (project(CAM, rodrigues(rvec), tvec, X + step) - project(CAM, rodrigues(rvec), tvec, X - step)) / (2 * h)
        np.testing.assert_allclose(J[:, :, axis], d, rtol=1e-6, atol=1e-6)


def test_the_warp_of_a_roll_a_move_in_depth_and_an_edge_on_face():
    """On the optical axis: the same pose gives the identity; a roll of the head by theta, a pixel
    offset d now was the offset turned back by theta in the first frame; twice as far, twice as far
    apart; a face seen edge-on (singular) keeps the identity; the result is always a similarity."""
    X = np.zeros((1, 3))
    first = (np.zeros(3), np.array([0.0, 0.0, 500.0]))
    cam = Camera(700.0, 700.0, 319.5, 239.5)
    np.testing.assert_allclose(template_warp(cam, first, X, first, X), np.eye(2)[None], atol=1e-12)
    theta = np.radians(20.0)
    back = np.array([[np.cos(theta), np.sin(theta)], [-np.sin(theta), np.cos(theta)]])  # Rz(-theta)
    np.testing.assert_allclose(template_warp(cam, first, X, (np.array([0, 0, theta]), first[1]), X)[0], back,
                               atol=1e-12)  # fmt: skip
    far = (np.zeros(3), np.array([0.0, 0.0, 1000.0]))
    np.testing.assert_allclose(template_warp(cam, first, X, far, X)[0], 2.0 * np.eye(2), atol=1e-12)
    edge_on = (np.array([0.0, np.pi / 2, 0.0]), first[1])
    np.testing.assert_allclose(template_warp(cam, first, X, edge_on, X)[0], np.eye(2), atol=1e-12)
    rng = np.random.default_rng(1)
    Xs = rng.normal(0, 30, (10, 3))
    W = template_warp(CAM, first, Xs, (np.array([0.1, 0.4, -0.2]), np.array([10.0, 5.0, 700.0])), Xs)
    np.testing.assert_allclose(W[:, 0, 0], W[:, 1, 1])
    np.testing.assert_allclose(W[:, 0, 1], -W[:, 1, 0])


def test_warped_templates_match_a_rolled_and_receding_face(ict):
    """A face rendered frontal at 600 mm, then rolled 20 deg, turned 10 deg and at 750 mm: the first
    frame's templates warped by the true poses correlate better with the new frame's patches at the
    true points than the plain ones, and eq. 14's first-frame term alone, started at the true points,
    stays nearer them."""
    from gputrack.models.face import LANDMARKS
    from gputrack.sim.face import FACE_CAMERA, render_face, rotation_from_euler, rvec_from_rotation

    identity, expression = np.zeros(ict.identity_modes), np.zeros(len(ict.expression_names))
    X = ict.landmarks(identity, expression)[list(LANDMARKS)]
    poses = [(rotation_from_euler(0, 0, 0), np.array([0.0, 0.0, 600.0])),
             (rotation_from_euler(20, 0, 10), np.array([15.0, -10.0, 750.0]))]  # fmt: skip
    images, points = [], []
    for R, t in poses:
        gray, _ = render_face(ict, identity, expression, R, t)
        images.append(gray.astype(np.float64))
        points.append(project(FACE_CAMERA, R, t, X))
    S = 16
    warp = template_warp(FACE_CAMERA, (rvec_from_rotation(poses[0][0]), poses[0][1]), X,
                         (rvec_from_rotation(poses[1][0]), poses[1][1]), X)  # fmt: skip
    plain, warped = sample_patches(images[0], points[0], S), sample_patches(images[0], points[0], S, warp)
    now = sample_patches(images[1], points[1], S)

    def ncc(a, b):
        a, b = a - a.mean(axis=(1, 2), keepdims=True), b - b.mean(axis=(1, 2), keepdims=True)
        return (a * b).sum(axis=(1, 2)) / np.sqrt((a * a).sum(axis=(1, 2)) * (b * b).sum(axis=(1, 2)))

    assert ncc(warped, now).mean() > ncc(plain, now).mean() + 0.1
    assert (ncc(warped, now) > ncc(plain, now)).sum() >= 8
    ref = gputrack.device("numpy")

    def settled(templates):  # px from the truth where eq. 14's first-frame term alone puts each point
        m, _, _ = relocate_points(ref, images[1], points[1], templates, templates, rho=0.0, eps=0.0, iterations=20,
                               contrast=30.0)  # fmt: skip
        return np.hypot(*(m - points[1]).T)

    assert settled(warped).mean() < 0.5 * settled(plain).mean()

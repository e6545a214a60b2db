"""The estimate's pose and deformation fitted to the feature points (gputrack.trackers.face.refine):
against SciPy's least squares on the same objective, exact recovery, held components, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from gputrack.models import Camera
from gputrack.models.pose import fit_pose, project, rodrigues
from gputrack.trackers.face.refine import fit_pose_deformation

CAM = Camera(700.0, 700.0, 320.0, 240.0)
K, D = 10, 5


def _model(seed=0):
    """A face-sized mean shape (K, 3) mm and a deformation basis (K, 3, D) of a few mm per unit."""
    rng = np.random.default_rng(seed)
    mean = np.array([[-45, -18, 13], [-18, -16, 7], [18, -16, 7], [45, -18, 13], [-13, 28, -9], [13, 28, -9],
                     [-26, 54, 1], [26, 54, 1], [-12, -45, -8], [12, -45, -8]], np.float64)  # fmt: skip
    return mean, rng.normal(0.0, 3.0, (K, 3, D))


def _objective(mean, basis, points, a0, sd):
    free = sd > 0
    ok = np.isfinite(points).all(axis=1)

    def residuals(x):
        a = a0.copy()
        a[free] = x[6:]
        u = project(CAM, rodrigues(x[:3]), x[3:6], mean + basis @ a)
        return np.concatenate([(u - points)[ok].ravel(), (x[6:] - a0[free]) / sd[free]])

    return residuals, free


def test_the_fit_is_scipys_least_squares_minimum():
    mean, basis = _model()
    rng = np.random.default_rng(1)
    for trial in range(5):
        truth = np.concatenate([rng.normal(0, 0.3, 3), [rng.normal(0, 30), rng.normal(0, 30), rng.uniform(400, 900)],
                                rng.normal(0, 1, D)])  # fmt: skip
        pts = project(CAM, rodrigues(truth[:3]), truth[3:6], mean + basis @ truth[6:]) + rng.normal(0, 1.0, (K, 2))
        pts[trial] = np.nan  # an unknown point
        start = truth + np.concatenate([rng.normal(0, 0.03, 3), rng.normal(0, 5, 3), rng.normal(0, 0.5, D)])
        sd = np.array([0.5, 1.0, 0.0, 2.0, 0.5])  # the third component held
        x = fit_pose_deformation(CAM, mean, basis, pts, start, sd)
        residuals, free = _objective(mean, basis, pts, start[6:], sd)
        ref = least_squares(residuals, np.concatenate([start[:6], start[6:][free]]), method="lm", xtol=1e-15,
                            ftol=1e-15, gtol=1e-15).x  # fmt: skip
        mine = np.concatenate([x[:6], x[6:][free]])
        cost, ref_cost = (float(residuals(v) @ residuals(v)) for v in (mine, ref))
        assert cost <= ref_cost * (1 + 1e-9) + 1e-12, (trial, cost, ref_cost)  # at least as low
        # the same minimum, up to its flat directions (a turn against a sideways move: ~1e-6 rad)
        np.testing.assert_allclose(rodrigues(x[:3]), rodrigues(ref[:3]), atol=2e-5)
        np.testing.assert_allclose(x[3:6], ref[3:6], atol=1e-2)  # mm
        np.testing.assert_allclose(x[6:][free], ref[6:], atol=1e-4)
        assert x[6 + 2] == start[6 + 2]  # held


def test_exact_points_give_the_pose_and_deformation_back():
    mean, basis = _model(2)
    truth = np.concatenate([[0.1, -0.5, 0.05], [15.0, -10.0, 650.0], [1.0, -0.5, 0.3, 0.8, -1.2]])
    pts = project(CAM, rodrigues(truth[:3]), truth[3:6], mean + basis @ truth[6:])
    start = truth + np.concatenate([[0.02, 0.03, -0.02], [4.0, -3.0, 25.0], np.zeros(D)])
    # a prior centred at the truth: the minimum is the truth, cost 0
    x = fit_pose_deformation(CAM, mean, basis, pts, start, np.ones(D))
    np.testing.assert_allclose(x, truth, atol=1e-6)
    # all held: the pose fit alone, as OpenCV's PnP of the shape at the held deformation
    off = start.copy()
    off[6:] += 0.3
    x = fit_pose_deformation(CAM, mean, basis, pts, off, np.zeros(D))
    np.testing.assert_array_equal(x[6:], off[6:])
    r, t = fit_pose(CAM, mean + basis @ off[6:], pts, (off[:3], off[3:6]))
    np.testing.assert_allclose(rodrigues(x[:3]), rodrigues(r), atol=1e-6)
    np.testing.assert_allclose(x[3:6], t, atol=1e-3)


def test_too_few_points_or_bad_input():
    mean, basis = _model()
    state = np.concatenate([np.zeros(3), [0.0, 0.0, 600.0], np.zeros(D)])
    pts = project(CAM, np.eye(3), state[3:6], mean)
    few = pts.copy()
    few[:5] = np.nan
    assert fit_pose_deformation(CAM, mean, basis, few, state, np.ones(D)) is None
    behind = state.copy()
    behind[5] = -600.0
    assert fit_pose_deformation(CAM, mean, basis, pts, behind, np.ones(D)) is None
    with pytest.raises(ValueError, match=r"expected mean \(K, 3\), basis \(K, 3, D\), points \(K, 2\)"):
        fit_pose_deformation(CAM, mean, basis, pts[:9], state, np.ones(D))
    with pytest.raises(ValueError, match="prior_sd >= 0"):
        fit_pose_deformation(CAM, mean, basis, pts, state, -np.ones(D))
    with pytest.raises(ValueError, match="expected finite values"):
        fit_pose_deformation(CAM, mean, basis, pts, np.full(6 + D, np.nan), np.ones(D))

"""The estimate refined to the feature points: pose and deformation together (beyond the paper).

The particle filter (eq. 11-13) gives a pose and a deformation a; eq. 14 then gives the K feature
points. :func:`fit_pose_deformation` fits both to those points at once: the shape of eq. 11,
M(a) = mean + basis a (the identity held), seen at pose (R, t) (eq. 5), with a Gaussian prior that
holds a near the filter's value,

    min  sum_k ||P(R M_k(a) + t) - m_k||^2 + sum_b ((a_b - a0_b) / sd_b)^2,

by Levenberg-Marquardt with the analytic Jacobian (rotation increments on the left, R <- exp([w]x) R).
The deformation moves the points the way a pitch of the head does (the mouth and brows against the
eyes), so fitting the pose alone, with the filter's deformation held, turns the head to take up the
deformation's error. Components with sd_b = 0 are held.

A hand-written solver, not SciPy's ``least_squares``: on these 6 + 5 parameters and 20 + 5
residuals SciPy's took ~4 ms a frame on the 2-core VM (its finite differences and set-up), more
than the face tracker's whole frame budget; this one (the normal equations of the image rows, the
prior's curvature added to their diagonal) takes about 0.4 ms for its ~6 iterations and reaches the
same minimum (tests/test_face_refine.py).
"""

from __future__ import annotations

import numpy as np

from ...models.camera import Camera
from ...models.pose import MIN_POSE_POINTS, rotation_vector

__all__ = ["fit_pose_deformation"]

#: Levenberg-Marquardt: the start damping (relative to diag J^T J), the most iterations, and the
#: relative decrease of the cost under which the fit has converged
DAMPING, ITERATIONS, COST_RTOL = 1e-6, 20, 1e-12


def fit_pose_deformation(camera: Camera, mean, basis, points, state, prior_sd) -> np.ndarray | None:
    """The state (6 + D,) [rvec, tvec, a] whose shape ``mean + basis @ a`` (mean (K, 3), basis (K, 3, D),
    mm, model frame) seen through ``camera`` best fits ``points`` (K, 2) px (NaN: unknown), with the
    prior ((a - a0) / prior_sd)^2 per component (module docstring), from ``state`` (6 + D,), whose
    deformation a0 is the prior's centre. prior_sd (D,) >= 0: 0 holds that component at a0.

    Returns the fitted state, or None where fewer than 6 points are known, or a model point falls
    behind the camera or the fit is not finite."""
    import cv2

    mean, basis = np.asarray(mean, np.float64), np.asarray(basis, np.float64)
    pts = np.asarray(points, np.float64)
    x0 = np.asarray(state, np.float64)
    sd = np.asarray(prior_sd, np.float64)
    K, D = basis.shape[0], basis.shape[2]
    if mean.shape != (K, 3) or basis.shape != (K, 3, D) or pts.shape != (K, 2) or x0.shape != (6 + D,) \
            or sd.shape != (D,):  # fmt: skip
        raise ValueError(f"expected mean (K, 3), basis (K, 3, D), points (K, 2), state (6 + D,), prior_sd (D,), got "
                         f"{mean.shape}, {basis.shape}, {pts.shape}, {x0.shape}, {sd.shape}")  # fmt: skip
    if not np.isfinite(x0).all() or not np.isfinite(sd).all() or (sd < 0).any():
        raise ValueError("state, prior_sd: expected finite values, prior_sd >= 0")
    ok = np.isfinite(pts).all(axis=1)
    if ok.sum() < MIN_POSE_POINTS:
        return None
    free = sd > 0
    Bf, a0 = basis[ok][:, :, free], x0[6:][free]
    X0, m = (mean + basis[:, :, ~free] @ x0[6:][~free])[ok], pts[ok]  # the held components' shape included
    n, d = len(m), int(free.sum())
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    prior = np.zeros(6 + d)  # the prior's curvature on the diagonal of J^T J: (1 / sd_b)^2
    prior[6:] = 1.0 / sd[free] ** 2
    dY = np.zeros((n, 3, 6 + d))  # dY / (w, t, a): -[RX]x, I, R basis (the identity block set once)
    dY[:, 0, 3] = dY[:, 1, 4] = dY[:, 2, 5] = 1.0

    def evaluate(R, t, a):
        """(cost, image residuals (n, 2), the model points R X, camera points Y), or None where a point
        is behind the camera."""
        RX = (X0 + Bf @ a) @ R.T
        Y = RX + t
        z = Y[:, 2]
        if (z <= 0).any():
            return None
        r = np.empty((n, 2))
        r[:, 0] = fx * Y[:, 0] / z + cx - m[:, 0]
        r[:, 1] = fy * Y[:, 1] / z + cy - m[:, 1]
        p = (a - a0) * prior[6:] ** 0.5
        return float(np.sum(r * r) + p @ p), r, RX, Y

    def normal_equations(R, a, r, RX, Y):
        """J^T J and J^T r of the cost (image rows and the prior's)."""
        z = Y[:, 2]
        dY[:, 0, 1], dY[:, 0, 2], dY[:, 1, 2] = RX[:, 2], -RX[:, 1], RX[:, 0]
        dY[:, 1, 0], dY[:, 2, 0], dY[:, 2, 1] = -RX[:, 2], RX[:, 1], -RX[:, 0]
        dY[:, :, 6:] = R @ Bf
        J = np.empty((n, 2, 6 + d))  # d(u, v) / dY @ dY
        J[:, 0] = (fx / z)[:, None] * (dY[:, 0] - (Y[:, 0] / z)[:, None] * dY[:, 2])
        J[:, 1] = (fy / z)[:, None] * (dY[:, 1] - (Y[:, 1] / z)[:, None] * dY[:, 2])
        J = J.reshape(2 * n, -1)
        g = J.T @ r.ravel()
        g[6:] += (a - a0) * prior[6:]
        return J.T @ J + np.diag(prior), g

    R, t, a = cv2.Rodrigues(x0[:3])[0], x0[3:6].copy(), a0.copy()
    now = evaluate(R, t, a)
    if now is None:
        return None
    lam = DAMPING
    for _ in range(ITERATIONS):
        cost, r, RX, Y = now
        A, g = normal_equations(R, a, r, RX, Y)
        diag = np.diag(np.maximum(np.diag(A), 1e-12))
        while True:
            try:
                step = -np.linalg.solve(A + lam * diag, g)
            except np.linalg.LinAlgError:
                step = None
            if step is not None and np.isfinite(step).all():
                Rn, tn, an = cv2.Rodrigues(step[:3])[0] @ R, t + step[3:6], a + step[6:]
                new = evaluate(Rn, tn, an)
                if new is not None and new[0] <= cost:
                    break
            lam *= 10.0
            if lam > 1e12:
                return _state(R, t, x0[6:], free, a)
        R, t, a, now = Rn, tn, an, new
        lam = max(lam / 10.0, 1e-12)
        if cost - new[0] <= COST_RTOL * cost:
            break
    return _state(R, t, x0[6:], free, a)


def _state(R, t, a0, free, a) -> np.ndarray | None:
    """[rvec, t, a] with the free components of a0 (D,) replaced by a; None if not finite."""
    full = a0.copy()
    full[free] = a
    out = np.concatenate([rotation_vector(R), t, full])
    return out if np.isfinite(out).all() else None

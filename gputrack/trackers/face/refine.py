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
than the face tracker's whole frame budget; this one takes a few tenths of a millisecond and
reaches the same minimum (tests/test_face_refine.py).
"""

from __future__ import annotations

import numpy as np

from ...models.camera import Camera
from ...models.pose import rotation_vector

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
    if ok.sum() < 6:
        return None
    free = sd > 0
    Bf, a0, inv_sd = basis[ok][:, :, free], x0[6:], 1.0 / sd[free]
    X0, m = (mean + basis[:, :, ~free] @ x0[6:][~free])[ok], pts[ok]  # the held components' shape included
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy

    def evaluate(R, t, a):
        """(residuals, Jacobian or None where a point is behind the camera, the model point RX, Y)."""
        X = X0 + Bf @ a[free]
        RX = X @ R.T
        Y = RX + t
        z = Y[:, 2]
        if (z <= 0).any():
            return None, None, None
        u = np.stack([fx * Y[:, 0] / z + cx, fy * Y[:, 1] / z + cy], axis=1)
        r = np.concatenate([(u - m).ravel(), (a[free] - a0[free]) * inv_sd])
        return r, RX, Y

    def jacobian(R, RX, Y):
        z = Y[:, 2]
        dproj = np.zeros((len(Y), 2, 3))  # d(u, v) / dY
        dproj[:, 0, 0], dproj[:, 0, 2] = fx / z, -fx * Y[:, 0] / z**2
        dproj[:, 1, 1], dproj[:, 1, 2] = fy / z, -fy * Y[:, 1] / z**2
        J = np.zeros((2 * len(Y) + Bf.shape[2], 6 + Bf.shape[2]))
        dY = np.zeros((len(Y), 3, J.shape[1]))  # dY / (w, t, a): -[RX]x, I, R basis
        dY[:, 0, 1], dY[:, 0, 2], dY[:, 1, 2] = RX[:, 2], -RX[:, 1], RX[:, 0]
        dY[:, 1, 0], dY[:, 2, 0], dY[:, 2, 1] = -RX[:, 2], RX[:, 1], -RX[:, 0]
        dY[:, 0, 3] = dY[:, 1, 4] = dY[:, 2, 5] = 1.0
        dY[:, :, 6:] = np.einsum("ij,kjd->kid", R, Bf)
        J[: 2 * len(Y)] = (dproj @ dY).reshape(2 * len(Y), -1)
        J[2 * len(Y) :, 6:] = np.diag(inv_sd)
        return J

    R, t, a = cv2.Rodrigues(x0[:3])[0], x0[3:6].copy(), x0[6:].copy()
    r, RX, Y = evaluate(R, t, a)
    if r is None:
        return None
    cost, lam = float(r @ r), DAMPING
    for _ in range(ITERATIONS):
        J = jacobian(R, RX, Y)
        A, g = J.T @ J, J.T @ r
        diag = np.maximum(np.diag(A), 1e-12)
        while True:
            try:
                step = -np.linalg.solve(A + lam * np.diag(diag), g)
            except np.linalg.LinAlgError:
                step = None
            if step is not None and np.isfinite(step).all():
                Rn, tn, an = cv2.Rodrigues(step[:3])[0] @ R, t + step[3:6], a.copy()
                an[free] += step[6:]
                rn, RXn, Yn = evaluate(Rn, tn, an)
                if rn is not None and float(rn @ rn) <= cost:
                    break
            lam *= 10.0
            if lam > 1e12:
                return _state(R, t, a)
        done = cost - float(rn @ rn) <= COST_RTOL * cost
        R, t, a, r, RX, Y, cost = Rn, tn, an, rn, RXn, Yn, float(rn @ rn)
        lam = max(lam / 10.0, 1e-12)
        if done:
            break
    return _state(R, t, a)


def _state(R, t, a) -> np.ndarray | None:
    out = np.concatenate([rotation_vector(R), t, a])
    return out if np.isfinite(out).all() else None

"""Rigid poses of a model in front of a pinhole camera: rotation vectors, Euler angles, projection.

A pose (R, t) maps model coordinates to camera coordinates, X_cam = R X + t (camera: x right,
y down, z forward). Rotations travel as Rodrigues vectors r (axis times angle, rad), as OpenCV's
``cv2.Rodrigues``. The head-pose angles of paper 003 (Fig. 7): roll about the camera's z axis,
yaw about y, pitch about x, composed as R = Rz(roll) Ry(yaw) Rx(pitch).
Everything is vectorised over leading dimensions and runs in NumPy float64.
"""

from __future__ import annotations

import math

import numpy as np

from .camera import Camera

__all__ = ["MIN_POSE_POINTS", "euler_from_rotation", "facing", "fit_pose", "project", "rodrigues", "rotation_coefficients", "rotation_from_euler",
           "rotation_vector", "skew"]


#: the fewest known points :func:`fit_pose` fits a pose to
MIN_POSE_POINTS = 6
#: below this angle (rad) :func:`rotation_coefficients` (and :func:`rodrigues`) take their series
SMALL_ANGLE = 1e-3
#: :func:`rotation_vector`: below this sine of the angle its factor theta / (2 sin) comes from its
#: series; within this of a half turn (rad) the axis comes from the symmetric part
SMALL_SINE, NEAR_HALF_TURN = 1e-6, 1e-3


def _coefficient_series(t2):
    """sin t / t, (1 - cos t) / t^2 and (t - sin t) / t^3 by their series in t2 = t^2 (floats or arrays)."""
    return 1 - t2 / 6 + t2 * t2 / 120, 0.5 - t2 / 24 + t2 * t2 / 720, 1 / 6 - t2 / 120 + t2 * t2 / 5040


def _half_angle_factor(theta, sin):
    """theta / (2 sin theta) of rotation_vector, by its series where sin <= SMALL_SINE (floats or arrays)."""
    if isinstance(theta, float):
        return theta / max(2.0 * sin, 1e-300) if sin > SMALL_SINE else 0.5 + theta**2 / 12.0
    return np.where(sin > SMALL_SINE, theta / np.maximum(2.0 * sin, 1e-300), 0.5 + theta**2 / 12.0)


def skew(v) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices [v]x."""
    v = np.asarray(v, dtype=np.float64)
    K = np.zeros((*v.shape, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return K


def rotation_coefficients(r):
    """sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3 of t = |r| for r (..., 3), by series near t = 0."""
    r = np.asarray(r, dtype=np.float64)
    t2 = np.einsum("...c,...c->...", r, r)
    t = np.sqrt(t2)
    small = t < SMALL_ANGLE
    ts = np.where(small, 1.0, t)
    sa, sb, sc = _coefficient_series(t2)
    a = np.where(small, sa, np.sin(ts) / ts)
    b = np.where(small, sb, (1 - np.cos(ts)) / ts**2)
    c = np.where(small, sc, (ts - np.sin(ts)) / ts**3)
    return a, b, c


def rodrigues(rvec) -> np.ndarray:
    """(..., 3, 3) rotation matrices R = I + sin t/t [r]x + (1 - cos t)/t^2 [r]x^2 of Rodrigues vectors r (..., 3)."""
    r = np.asarray(rvec, dtype=np.float64)
    if r.shape == (3,):  # one vector (a tracker's pose, every frame): the same sums without the array calls
        return _rodrigues_one(*r.tolist())
    a, b, _ = rotation_coefficients(r)
    K = skew(r)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def _rodrigues_one(x: float, y: float, z: float) -> np.ndarray:
    """:func:`rodrigues` of one vector (x, y, z) with Python floats: I + a [r]x + b (r r^T - t^2 I)."""
    t2 = (x * x + z * z) + y * y  # the order of rotation_coefficients' einsum
    t = math.sqrt(t2)
    if t < SMALL_ANGLE:
        a, b, _ = _coefficient_series(t2)
    else:
        a, b = math.sin(t) / t, (1 - math.cos(t)) / t**2
    xx, yy, zz, xy, xz, yz = b * x * x, b * y * y, b * z * z, b * x * y, b * x * z, b * y * z
    return np.array([[1 - b * t2 + xx, xy - a * z, xz + a * y],
                     [xy + a * z, 1 - b * t2 + yy, yz - a * x],
                     [xz - a * y, yz + a * x, 1 - b * t2 + zz]])  # fmt: skip


def rotation_vector(R) -> np.ndarray:
    """(..., 3) Rodrigues vectors (angle in [0, pi]) of rotation matrices (..., 3, 3), as ``cv2.Rodrigues``."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape == (3, 3):  # one matrix: the same arithmetic with Python floats (away from a half turn)
        (a, b, c), (d, e, f), (g, h, i) = R.tolist()
        cos = min(max(((a + e + i) - 1.0) / 2.0, -1.0), 1.0)
        theta = math.acos(cos)
        if theta <= math.pi - NEAR_HALF_TURN:
            k = _half_angle_factor(theta, math.sin(theta))
            return np.array([(h - f) * k, (c - g) * k, (d - b) * k])
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    sin = np.sin(theta)
    out = w * _half_angle_factor(theta, sin)[..., None]
    near_pi = theta > np.pi - NEAR_HALF_TURN  # the axis from the symmetric part: (R + R^T) / 2 - cos I = (1 - cos) n n^T
    if np.any(near_pi):
        S = (R[near_pi] + np.swapaxes(R[near_pi], -1, -2)) / 2.0 - cos[near_pi, None, None] * np.eye(3)
        col = np.argmax(np.abs(np.diagonal(S, axis1=-2, axis2=-1)), axis=-1)
        n = np.take_along_axis(S, col[:, None, None], axis=-1)[..., 0]
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        n *= np.where(np.einsum("...i,...i->...", n, w[near_pi]) < 0, -1.0, 1.0)[:, None]
        out[near_pi] = n * theta[near_pi, None]
    return out


def rotation_from_euler(roll, pitch, yaw) -> np.ndarray:
    """(..., 3, 3) R = Rz(roll) Ry(yaw) Rx(pitch) from angles in radians."""
    roll, pitch, yaw = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (roll, pitch, yaw)))
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    R = np.empty(roll.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = cr * cy, cr * sy * sp - sr * cp, cr * sy * cp + sr * sp
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = sr * cy, sr * sy * sp + cr * cp, sr * sy * cp - cr * sp
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = -sy, cy * sp, cy * cp
    return R


def euler_from_rotation(R) -> np.ndarray:
    """(..., 3) (roll, pitch, yaw) in radians of R = Rz(roll) Ry(yaw) Rx(pitch), yaw in [-pi/2, pi/2]."""
    R = np.asarray(R, dtype=np.float64)
    yaw = np.arctan2(-R[..., 2, 0], np.hypot(R[..., 2, 1], R[..., 2, 2]))
    pitch = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    roll = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


def project(camera: Camera, R, t, points) -> np.ndarray:
    """(..., K, 2) pixels of model points (..., K, 3) seen at pose R (..., 3, 3), t (..., 3)."""
    X = np.einsum("...ij,...kj->...ki", np.asarray(R, np.float64), np.asarray(points, np.float64))
    X = X + np.asarray(t, np.float64)[..., None, :]
    z = X[..., 2]
    return np.stack([camera.fx * X[..., 0] / z + camera.cx, camera.fy * X[..., 1] / z + camera.cy], axis=-1)


def facing(R, t) -> np.ndarray:
    """(...,) the cosine between a model's z axis (the third column of R (..., 3, 3): into a head,
    for the face model) and the ray from the camera to the model's origin t (..., 3): 1 when the
    model faces the camera squarely, 0 when seen edge-on."""
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
    return np.einsum("...c,...c->...", R[..., :, 2], t) / np.maximum(np.linalg.norm(t, axis=-1), 1e-9)


def fit_pose(camera: Camera, points3d, points, guess):
    """(rvec, tvec) of model points ``points3d`` (K, 3) seen at ``points`` (K, 2) px (NaN: unknown; the
    finite ones, at least 6, are used) by OpenCV's iterative PnP (Levenberg-Marquardt on the
    reprojection error) from ``guess`` (rvec, tvec); None where fewer than 6 points are known, or
    the fit fails or puts the model's origin behind the camera."""
    import cv2

    pts = np.asarray(points, np.float64)
    ok = np.isfinite(pts).all(axis=1)
    if ok.sum() < MIN_POSE_POINTS:
        return None
    K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]])
    r0, t0 = (np.asarray(g, np.float64).reshape(3, 1).copy() for g in guess)
    found, r, t = cv2.solvePnP(np.asarray(points3d, np.float64)[ok], pts[ok], K, None, r0, t0, True,
                               cv2.SOLVEPNP_ITERATIVE)  # fmt: skip
    if not found or not np.isfinite(r).all() or not np.isfinite(t).all() or t[2, 0] <= 0:
        return None
    return r.ravel(), t.ravel()

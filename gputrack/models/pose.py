"""Rigid poses of a model in front of a pinhole camera: rotation vectors, Euler angles, projection.

A pose (R, t) maps model coordinates to camera coordinates, X_cam = R X + t (camera: x right,
y down, z forward). Rotations travel as Rodrigues vectors r (axis times angle, rad), as OpenCV's
``cv2.Rodrigues``. The head-pose angles of paper 003 (Fig. 7): roll about the camera's z axis,
yaw about y, pitch about x, composed as R = Rz(roll) Ry(yaw) Rx(pitch).
Everything is vectorised over leading dimensions and runs in NumPy float64.
"""

from __future__ import annotations

import numpy as np

from .camera import Camera

__all__ = ["euler_from_rotation", "project", "rodrigues", "rotation_from_euler", "rotation_vector"]


def rodrigues(rvec) -> np.ndarray:
    """(..., 3, 3) rotation matrices of Rodrigues vectors (..., 3) (exact near 0: Taylor terms)."""
    r = np.asarray(rvec, dtype=np.float64)
    th2 = np.einsum("...i,...i->...", r, r)
    th = np.sqrt(th2)
    small = th2 < 1e-12
    safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(safe) / safe)  # sin(th)/th
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(safe)) / np.where(small, 1.0, th2))  # (1-cos)/th^2
    K = np.zeros(r.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -r[..., 2], r[..., 1], -r[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = r[..., 2], -r[..., 1], r[..., 0]
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def rotation_vector(R) -> np.ndarray:
    """(..., 3) Rodrigues vectors of rotation matrices (..., 3, 3) (angles in [0, pi])."""
    R = np.asarray(R, dtype=np.float64)
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    c = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(c)
    s = np.linalg.norm(w, axis=-1) / 2.0
    out = w * np.where(th < 1e-6, 0.5, th / (2.0 * np.maximum(np.sin(th), 1e-300)))[..., None]
    near_pi = (th > np.pi - 1e-3) & (s < 1e-3)
    if near_pi.any():  # axis from the largest diagonal of (R + I) / 2
        B = (R[near_pi] + np.eye(3)) / 2.0
        i = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        axis = B[np.arange(len(i)), :, i] / np.sqrt(np.maximum(B[np.arange(len(i)), i, i], 1e-300))[:, None]
        out[near_pi] = axis / np.linalg.norm(axis, axis=-1, keepdims=True) * th[near_pi][:, None]
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
    yaw = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    pitch = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    roll = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


def project(camera: Camera, R, t, points) -> np.ndarray:
    """(..., K, 2) pixels of model points (..., K, 3) seen at pose R (..., 3, 3), t (..., 3)."""
    X = np.einsum("...ij,...kj->...ki", np.asarray(R, np.float64), np.asarray(points, np.float64))
    X = X + np.asarray(t, np.float64)[..., None, :]
    z = X[..., 2]
    return np.stack([camera.fx * X[..., 0] / z + camera.cx, camera.fy * X[..., 1] / z + camera.cy], axis=-1)

"""The first frame's templates as the face is seen now (beyond the paper: ``FaceConfig.warp_templates``).

Eq. 13 scores the hypotheses and eq. 14 re-localises the points against the K templates cut from the
first frame. As the head rolls or moves in depth, the patch around a feature point turns and scales in
the image, and the template's best match moves off the point: on the simulator's turns sequence,
eq. 14's first-frame term alone, started at the true points, settles 1-7 px away from them on the eye
corners, nostrils and mouth corners (the previous frame's term follows it there over a few frames).
So each frame the templates are sampled again from the first frame, turned and scaled as the
filter's estimate sees the face.

The map. A small patch of the face's frontal plane (the model's x-y plane) at model point X, seen with
the pose (R, t) model -> camera, moves in the image by J d for a step d in that plane, with the 2 x 2
Jacobian

    J(R, t, X) = dpi/dP (R X + t) R [e_x e_y],   dpi/dP (P) = [[fx / z, 0, -fx x / z^2], [0, fy / z, -fy y / z^2]].

A pixel offset d from the point in the current frame is the plane step J^-1 d, which was J_0 J^-1 d in
the first frame (J_0: the first frame's pose and shape). Of A = J_0 J^-1 only the nearest similarity
is kept, [[a, -b], [b, a]] with a = (A_00 + A_11) / 2 and b = (A_10 - A_01) / 2 (nearest in the
Frobenius norm): the in-plane turn and the scale are alike for any surface at the point, while the
foreshortening of a yaw or a pitch depends on the surface's direction there, which the K points do not
tell. (Measured on the simulator, seeds 0-11: the full map A of the frontal plane put the outer eye
corners and the nostrils, which do not lie in it, further off and lost yaw on the turns sequence; the
similarity lowered the yaw error on every sequence; the README's face section.)
"""

from __future__ import annotations

import numpy as np

from ...models.camera import Camera
from ...models.pose import rodrigues

__all__ = ["frontal_jacobians", "template_warp"]


def frontal_jacobians(camera: Camera, rvec, tvec, X) -> np.ndarray:
    """(K, 2, 2): the image motion (px) of a step (mm) along the model's x and y axes at each model point
    X (K, 3), seen with the pose (rvec Rodrigues, tvec mm) model -> camera."""
    R = rodrigues(np.asarray(rvec, np.float64))
    P = np.asarray(X, np.float64) @ R.T + np.asarray(tvec, np.float64)
    z = np.maximum(P[:, 2], 1e-6)
    D = np.zeros((len(P), 2, 3))
    D[:, 0, 0], D[:, 0, 2] = camera.fx / z, -camera.fx * P[:, 0] / z**2
    D[:, 1, 1], D[:, 1, 2] = camera.fy / z, -camera.fy * P[:, 1] / z**2
    return D @ R[:, :2]


def template_warp(camera: Camera, first_pose, first_shape, pose, shape) -> np.ndarray:
    """(K, 2, 2): for :func:`gputrack.ops.face_relocate.sample_patches` on the first frame, the
    similarity that maps a pixel offset from each feature point now to the offset in the first frame
    (see the module docstring). first_pose, pose: (rvec, tvec) model -> camera; first_shape, shape:
    (K, 3) mm, the model points then and now. A point seen edge-on (a singular J) keeps the identity."""
    J0 = frontal_jacobians(camera, *first_pose, first_shape)
    J = frontal_jacobians(camera, *pose, shape)
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    ok = np.abs(det) > 1e-9
    inv = np.stack([np.stack([J[:, 1, 1], -J[:, 0, 1]], -1), np.stack([-J[:, 1, 0], J[:, 0, 0]], -1)], -2)
    A = J0 @ (inv / np.where(ok, det, 1.0)[:, None, None])
    a = (A[:, 0, 0] + A[:, 1, 1]) / 2
    b = (A[:, 1, 0] - A[:, 0, 1]) / 2
    S = np.stack([np.stack([a, -b], -1), np.stack([b, a], -1)], -2)
    S[~ok | ~np.isfinite(S).all(axis=(1, 2))] = np.eye(2)
    return S

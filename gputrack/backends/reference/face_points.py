"""NumPy: the projection of face hypotheses (gputrack/ops/face_points.py), in float64."""

import numpy as np

from ...models.pose import facing as facing_of
from ...models.pose import rodrigues


def project_faces(device, states, model, cam, points, facing):
    """cam: fx, fy, cx, cy, the least depth (mm) and the coordinates' clip (px)."""
    st = np.asarray(states, np.float64)
    model = np.asarray(model, np.float64)
    N, K, D = len(st), model.shape[0], model.shape[2] - 1
    R = rodrigues(st[:, :3])
    # eq. 11: the shapes (N, 3, K); one 3 x 3 by 3 x K product per hypothesis
    shapes = (st[:, 6:] @ model[:, :, 1:].transpose(2, 1, 0).reshape(D, 3 * K)).reshape(N, 3, K) + model[:, :, 0].T
    X = R @ shapes + st[:, 3:6, None]
    fx, fy, cx, cy, near, clip = (float(v) for v in cam)
    iz = 1.0 / np.maximum(X[:, 2], near)  # eq. 5
    points[..., 0] = np.clip(fx * X[:, 0] * iz + cx, -clip, clip)
    points[..., 1] = np.clip(fy * X[:, 1] * iz + cy, -clip, clip)
    facing[...] = facing_of(R, st[:, 3:6])

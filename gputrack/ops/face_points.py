"""The K model points of N face hypotheses in the image (paper 003 eq. 5, 11), on the device.

A hypothesis u = (r (3) Rodrigues vector model -> camera, t (3) mm, a (D) deformation) places the
model points X_k = mean_k + basis_k a (eq. 11) at Y_k = R(r) X_k + t, projected by a pinhole camera
(eq. 5; a point nearer than 1 mm along the optical axis is projected as if it were there, far off
the image; coordinates are clipped to +-1e6 px). :func:`project_faces` also returns each
hypothesis's facing: the cosine between the model's z axis (into the head) in the camera frame,
R(r)[:, 2], and the ray to the head, t / |t| (the face tracker's turn test of eq. 13).

The face tracker's particle filter projects its 1000 hypotheses with it each frame, so that the
points it scores (:func:`gputrack.ops.ncc.patch_ncc`) never leave the device. The NumPy backend
computes in float64 (the oracle), the device kernels in float32 (the points' type).
"""

from __future__ import annotations

import numpy as np

from ..models.camera import Camera
from . import backend_module
from ._args import arg, check_device, out_arrays

__all__ = ["project_faces"]

#: a point nearer than this (mm) along the optical axis is projected as if it were this near
MIN_DEPTH = 1.0
#: projected coordinates are clipped to +-COORD_MAX px (far off any image, finite)
COORD_MAX = 1e6


def project_faces(device, states, shape_model, camera: Camera, *, out=None):
    """(points (N, K, 2) float32 px, facing (N,) float32) of N hypotheses ``states`` (N, 6 + D)
    float32 (NumPy or on the device) of the shape model ``shape_model`` (K, 3, 1 + D) float32: column
    0 the mean shape (mm), columns 1.. its deformation basis (the model of the current identity).
    The numpy device also takes float64 inputs (it computes in float64 either way).
    ``out``: (points, facing) on the device to write into."""
    check_device(device)
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a gputrack.models.Camera, got {type(camera).__name__}")
    dims: dict = {}
    dtype = (np.float32, np.float64) if device.backend == "numpy" else np.float32  # the host model: either
    model = arg(device, shape_model, "shape_model", ("K", 3, "D1"), dims, dtype=dtype)
    if dims["K"] < 1 or dims["D1"] < 1:
        raise ValueError(f"shape_model: expected shape (K >= 1, 3, 1 + D), got {tuple(model.shape)}")
    dims["P"] = 6 + dims["D1"] - 1
    st = arg(device, states, "states", ("N", "P"), dims, dtype=dtype)
    if dims["N"] < 1:
        raise ValueError(f"states: expected at least one hypothesis, got shape {tuple(st.shape)}")
    points, facing = out_arrays(device, out, (("points", (dims["N"], dims["K"], 2), np.float32),
                                              ("facing", (dims["N"],), np.float32)))  # fmt: skip
    be = backend_module(device, "face_points")
    cam = np.array([camera.fx, camera.fy, camera.cx, camera.cy, MIN_DEPTH, COORD_MAX], np.float32)
    be.project_faces(device, st, model, cam, points, facing)
    return points, facing

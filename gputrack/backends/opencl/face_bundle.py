"""OpenCL: the landmark residuals and Jacobian of gputrack/ops/face_bundle.py
(kernels/gt_face_bundle.cl), one launch, one work-item per (parameter vector, landmark or prior row)."""

import numpy as np

from ...device import per_device
from .program import enqueue, ndrange


@per_device
def _kernel(device, real, A, S):
    import pyopencl as cl

    defines = {"REAL": "double" if real == np.float64 else "float", "FB_A": A, "FB_S": S}
    if real == np.float64:
        defines["REAL_IS_DOUBLE"] = 1
    return cl.Kernel(device.program("gt_face_bundle.cl", defines), "gt_face_bundle")


def landmark_residuals(device, points, model, frames, consts, values, jacobian, out):
    R, J = out
    B = points.shape[0]
    kernel = _kernel(device, np.dtype(R.dtype).type, model.A, model.S)
    enqueue(device, kernel, *ndrange(B * (frames.n * model.K + model.S)), points.buffer.data, consts.buffer.data,
            values.buffer.data, R.buffer.data, J.buffer.data, np.int32(B), np.int32(frames.n), np.int32(model.K),
            np.int32(frames.prior is not None), np.int32(bool(jacobian)))  # fmt: skip

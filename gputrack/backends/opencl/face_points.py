"""OpenCL: the projection of face hypotheses (gputrack/ops/face_points.py; kernels/gt_face_points.cl),
one launch, one work-item per hypothesis."""

import numpy as np

from ...device import per_device
from ...uploads import constant
from .program import enqueue, ndrange


@per_device
def _kernel(device):
    import pyopencl as cl

    return cl.Kernel(device.program("gt_face_points.cl"), "gt_face_points")


def project_faces(device, states, model, cam, points, facing):
    N, K, D = states.shape[0], model.shape[0], model.shape[2] - 1
    enqueue(device, _kernel(device), *ndrange(N), states.buffer.data, model.buffer.data,
            constant(device, cam).buffer.data, points.buffer.data, facing.buffer.data, np.int32(N), np.int32(K),
            np.int32(D))  # fmt: skip

"""OpenCL: feature-point re-localisation (gputrack/ops/face_relocate.py; kernels/gt_face_relocate.cl), one
launch, one work-item per feature point, each its own work-group: the K ~ 10 points spread over a CPU
device's threads (in one group of 64, PoCL ran them all on one thread: the face frame's relocate stage
0.44 -> 0.33 ms on the 2-core VM, ``bench_face --stages``)."""

import numpy as np

from ...device import per_device
from ...uploads import constant
from .program import enqueue, ndrange


@per_device
def _kernel(device):
    import pyopencl as cl

    return cl.Kernel(device.program("gt_face_relocate.cl"), "gt_face_relocate")


def relocate_points(device, image, predicted, previous, first, consts, iterations, points, patches, match):
    K, S = previous.shape[0], previous.shape[1]
    H, W = image.shape
    enqueue(device, _kernel(device), *ndrange(K, group=(1,)), image.buffer.data, predicted.buffer.data, previous.buffer.data,
            first.buffer.data, constant(device, consts.astype(np.float32)).buffer.data, points.buffer.data,
            patches.buffer.data, match.buffer.data, np.int32(K), np.int32(S), np.int32(H), np.int32(W),
            np.int32(iterations))  # fmt: skip

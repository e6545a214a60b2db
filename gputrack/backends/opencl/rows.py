"""OpenCL launchers of :mod:`gputrack.ops.rows` (kernels/gt_rows.cl): rows moved as 4-byte words
when their size allows, else as bytes."""

from __future__ import annotations

import math

import numpy as np

from ...device import per_device
from .program import enqueue, ndrange, scalar_types

_I = np.int32
ARG_TYPES = [None, None, None, _I, _I, _I]


@per_device
def _kernel(device, name):
    import pyopencl as cl

    found = cl.Kernel(device.program("gt_rows.cl"), name)
    scalar_types(found, ARG_TYPES)
    return found


def scatter_rows(device, dst, index, src, K):
    row_bytes = math.prod(src.shape[1:]) * src.dtype.itemsize
    if row_bytes % 4 == 0:
        name, row = "gt_scatter_words", row_bytes // 4
    else:
        name, row = "gt_scatter_bytes", row_bytes
    enqueue(device, _kernel(device, name), *ndrange(row, K), dst.buffer.data, index.buffer.data, src.buffer.data, row,
            K, src.shape[0])  # fmt: skip
    return dst

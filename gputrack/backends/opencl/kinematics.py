"""OpenCL forward kinematics: launches gt_forward_kinematics (kernels/gt_kinematics.cl) once per call."""

from __future__ import annotations

import numpy as np

from ...device import per_device
from ...models.chain import chain_tables
from .program import enqueue, ndrange


@per_device
def _kernel(device, double: int):
    """The kernel, once per device and precision (retrieving it from the program each call is costly).
    float32 on a CPU device takes the vectorisable sines of kernels/gt_math.clh (GT_FK_POLY, see
    kernels/gt_kinematics.clh)."""
    import pyopencl as cl

    poly = int(not double and device.info.kind == "cpu")
    defines = {"GT_FK_DOUBLE": double, "GT_FK_POLY": poly}
    return cl.Kernel(device.program("gt_kinematics.cl", defines), "gt_forward_kinematics")


def forward_kinematics(device, chain, params, out):
    table, offsets = chain_tables(device, chain, params.dtype)
    b, p = params.shape
    j = chain.n_parts
    kernel = _kernel(device, int(params.dtype == np.float64))
    enqueue(
        device,
        kernel,
        *ndrange(b),
        params.buffer.data,
        table.buffer.data,
        offsets.buffer.data,
        out.buffer.data,
        np.int32(b),
        np.int32(p),
        np.int32(j),
    )
    return out

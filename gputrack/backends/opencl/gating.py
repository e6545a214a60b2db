"""OpenCL launcher of :mod:`gputrack.ops.gating` (kernels/gt_gating.cl): one work-item per track;
one program per (dtype, n, m, active, sorted_z), built once per device."""

from __future__ import annotations

import numpy as np

from ...device import per_device
from .program import enqueue, ndrange, scalar_types

PD_EPS_FACTOR = 4.0
STRIP_SLACK = 1e-3  # as gputrack/backends/taichi/gating.py


@per_device
def _kernel(device, dtype, n, m, has_active, sorted_z):
    import pyopencl as cl

    defines = {
        "REAL": "double" if dtype == np.float64 else "float",
        "N": n,
        "M": m,
        "HAS_ACTIVE": int(has_active),
        "SORTED_Z": int(sorted_z),
        "PD_TOL": repr(float(np.finfo(dtype).eps) * PD_EPS_FACTOR),
        "STRIP_SLACK": repr(STRIP_SLACK),
    }
    found = cl.Kernel(device.program("gt_gating.cl", defines), "gt_gate_pairs")
    scalar_types(found, [None] * 10 + [np.int32, np.int32, np.int32, dtype.type])
    return found


def gate_pairs(device, x, P, H, R, z, D, threshold, active, sorted_z, out):
    count, det, d2, trace = out
    T, n = x.shape
    knl = _kernel(device, x.dtype, n, H.shape[0], active is not None, sorted_z)
    act = active.buffer.data if active is not None else count.buffer.data
    enqueue(device, knl, *ndrange(T), x.buffer.data, P.buffer.data, H.buffer.data, R.buffer.data, z.buffer.data, act,
            count.buffer.data, det.buffer.data, d2.buffer.data, trace.buffer.data, T, int(D), det.shape[1],
            threshold)  # fmt: skip
    return out

"""OpenCL launchers of :mod:`gputrack.ops.point_groups` (kernels/gt_point_groups.cl): the group
factors (one work-item per group), their x order (one work-item), the assignment (one per
point), each group's points in order (one work-item) and the moments (one per group): five
launches in order on the device's queue."""

from __future__ import annotations

import numpy as np

from ...device import per_device
from .program import enqueue, ndrange, scalar_types

_I = np.int32
_ARGS = {
    "gt_pg_factors": [None] * 4 + [_I, _I, np.float32],
    "gt_pg_sort": [None, _I],
    "gt_pg_assign": [None] * 5 + [_I, _I, _I, np.float32],
    "gt_pg_order": [None, None, _I, _I, _I],
    "gt_pg_moments": [None] * 7 + [_I, _I],
    "gt_gf_predict": [None] * 3 + [_I],
    "gt_gf_buckets": [None, None, _I, _I, _I],
    "gt_gf_assign": [None] * 7 + [_I, _I, _I, _I],
    "gt_gf_update": [None] * 6 + [_I, _I],
    "gt_gf_candidates": [None, None, _I],
}
G = 23


@per_device
def _kernel(device, name):
    import pyopencl as cl

    found = cl.Kernel(device.program("gt_point_groups.cl"), name)
    scalar_types(found, _ARGS[name])
    return found


def assign_points(device, points, velocities, means, spreads, active, gamma, N, out):
    labels, counts, mean, cov = out
    T = means.shape[0]
    rows = labels.shape[0]
    g = device.empty((T, G), np.float32)
    idx = device.empty((rows + 2 * T,), np.int32)
    act = active.buffer.data if active is not None else counts.buffer.data
    enqueue(device, _kernel(device, "gt_pg_factors"), *ndrange(T), spreads.buffer.data, means.buffer.data, act,
            g.buffer.data, T, int(active is not None), np.float32(gamma))  # fmt: skip
    enqueue(device, _kernel(device, "gt_pg_sort"), (1,), None, g.buffer.data, T)
    if rows:
        enqueue(device, _kernel(device, "gt_pg_assign"), *ndrange(rows), points.buffer.data, velocities.buffer.data,
                means.buffer.data, g.buffer.data, labels.buffer.data, rows, int(N), T, np.float32(gamma))  # fmt: skip
    enqueue(device, _kernel(device, "gt_pg_order"), (1,), None, labels.buffer.data, idx.buffer.data, rows, int(N), T)
    enqueue(device, _kernel(device, "gt_pg_moments"), *ndrange(T), points.buffer.data, velocities.buffer.data,
            means.buffer.data, idx.buffer.data, counts.buffer.data, mean.buffer.data, cov.buffer.data, rows,
            T)  # fmt: skip
    return out


GC = 32  # scratch floats per slot (kernels/gt_point_groups.cl)


def group_frame(device, table, points, velocities, constants, n, labels):
    """Six launches in order (kernels/gt_point_groups.cl, "group_frame")."""
    T = table.shape[0]
    rows = labels.shape[0]
    K = max(1, min(2 * T, 16384 // T))  # as the Taichi kernel's buckets
    g = _scratch(device, "g", T * GC, np.float32)
    idx = _scratch(device, "idx", rows + 2 * T + 2 * K + 1 + T * K, np.int32)
    tab, pts, vel = table.buffer.data, points.buffer.data, velocities.buffer.data
    c, lab = constants.buffer.data, labels.buffer.data
    enqueue(device, _kernel(device, "gt_gf_predict"), *ndrange(T), tab, c, g, T)
    enqueue(device, _kernel(device, "gt_gf_buckets"), (1,), None, g, idx, rows, T, K)
    if rows:
        enqueue(device, _kernel(device, "gt_gf_assign"), *ndrange(rows), pts, vel, tab, c, g, idx, lab, rows, int(n),
                T, K)  # fmt: skip
    enqueue(device, _kernel(device, "gt_pg_order"), (1,), None, lab, idx, rows, int(n), T)
    enqueue(device, _kernel(device, "gt_gf_update"), *ndrange(T), pts, vel, tab, c, g, idx, rows, T)
    enqueue(device, _kernel(device, "gt_gf_candidates"), *ndrange(T), tab, g, T)
    return table, labels


@per_device(maxsize=8)
def _scratch_buffer(device, name, size, itemsize):
    import pyopencl as cl

    return cl.Buffer(device.context, cl.mem_flags.READ_WRITE, max(1, size) * itemsize)


def _scratch(device, name, size, dtype):
    return _scratch_buffer(device, name, int(size), np.dtype(dtype).itemsize)

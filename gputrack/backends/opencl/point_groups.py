"""OpenCL launchers of :mod:`gputrack.ops.point_groups` (kernels/gt_point_groups.cl): the group
factors (one work-item per group), their x order (one work-item), the assignment (one per
point), each group's points in order (one work-item) and the moments (one per group): five
launches in order on the device's queue."""

from __future__ import annotations

import numpy as np

from ...device import per_device

_I = np.int32
_ARGS = {
    "gt_pg_factors": [None] * 4 + [_I, _I, np.float32],
    "gt_pg_sort": [None, _I],
    "gt_pg_assign": [None] * 5 + [_I, _I, _I, np.float32],
    "gt_pg_order": [None, None, _I, _I, _I],
    "gt_pg_moments": [None] * 7 + [_I, _I],
}
G = 23


@per_device
def _kernel(device, name):
    import pyopencl as cl

    found = cl.Kernel(device.program("gt_point_groups.cl"), name)
    found.set_scalar_arg_dtypes(_ARGS[name])
    return found


def assign_points(device, points, velocities, means, spreads, active, gamma, N, out):
    labels, counts, mean, cov = out
    T = means.shape[0]
    rows = labels.shape[0]
    g = device.empty((T, G), np.float32)
    idx = device.empty((rows + 2 * T,), np.int32)
    act = active.buffer.data if active is not None else counts.buffer.data
    q = device.queue
    _kernel(device, "gt_pg_factors")(q, (T,), None, spreads.buffer.data, means.buffer.data, act, g.buffer.data, T,
                                     int(active is not None), np.float32(gamma))  # fmt: skip
    _kernel(device, "gt_pg_sort")(q, (1,), None, g.buffer.data, T)
    if rows:
        _kernel(device, "gt_pg_assign")(q, (rows,), None, points.buffer.data, velocities.buffer.data,
                                        means.buffer.data, g.buffer.data, labels.buffer.data, rows, int(N), T,
                                        np.float32(gamma))  # fmt: skip
    _kernel(device, "gt_pg_order")(q, (1,), None, labels.buffer.data, idx.buffer.data, rows, int(N), T)
    _kernel(device, "gt_pg_moments")(q, (T,), None, points.buffer.data, velocities.buffer.data, means.buffer.data,
                                     idx.buffer.data, counts.buffer.data, mean.buffer.data, cov.buffer.data, rows, T)  # fmt: skip
    return out

"""Taichi kernels of :mod:`gputrack.ops.rows`: one loop over the K rows written, nested loops
over a row (one kernel per rank of ``dst``, as gputrack/backends/taichi/arrays.py does: a
``ti.grouped`` loop recomputes the multi-index per element)."""

import math

from .launch import launch
from .runtime import ti

#: scatters of at most this many elements run on the calling thread (a parallel loop's dispatch
#: costs more than the copy)
SERIAL = 1 << 16


@ti.kernel
def _scatter1(dst: ti.types.ndarray(ndim=1), index: ti.types.ndarray(ndim=1), src: ti.types.ndarray(ndim=1),
              K: ti.i32, serial: ti.template()):  # fmt: skip
    ti.loop_config(serialize=serial)
    for k in range(K):
        dst[index[k]] = src[ti.min(k, src.shape[0] - 1)]  # src (1,): one value for every index


@ti.kernel
def _scatter2(dst: ti.types.ndarray(ndim=2), index: ti.types.ndarray(ndim=1), src: ti.types.ndarray(ndim=2),
              K: ti.i32, serial: ti.template()):  # fmt: skip
    ti.loop_config(serialize=serial)
    for k in range(K):
        s = ti.min(k, src.shape[0] - 1)
        for i in range(dst.shape[1]):
            dst[index[k], i] = src[s, i]


@ti.kernel
def _scatter3(dst: ti.types.ndarray(ndim=3), index: ti.types.ndarray(ndim=1), src: ti.types.ndarray(ndim=3),
              K: ti.i32, serial: ti.template()):  # fmt: skip
    ti.loop_config(serialize=serial)
    for k in range(K):
        s = ti.min(k, src.shape[0] - 1)
        for i, j in ti.ndrange(dst.shape[1], dst.shape[2]):
            dst[index[k], i, j] = src[s, i, j]


_KERNELS = {1: _scatter1, 2: _scatter2, 3: _scatter3}


def scatter_rows(device, dst, index, src, K):
    row = math.prod(dst.shape[1:])
    kernel = _KERNELS.get(dst.ndim)
    if kernel is None:  # rows of rank > 2: flat views are not available on Taichi ndarrays
        raise ValueError(f"dst: expected an array of rank 1 to 3 on {device.spec}, got shape {dst.shape}")
    launch(kernel, (dst.buffer, index.buffer, src.buffer), (K * row <= SERIAL,), scalars=(int(K),))
    return dst

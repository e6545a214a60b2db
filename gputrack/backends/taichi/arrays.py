"""Taichi array kernels used by the device itself: copies between NumPy and Taichi arrays.

On the CPU arch a NumPy array passed to a kernel is read and written in place, so one parallel
copy kernel moves several GB/s, where ``Ndarray.from_numpy``/``to_numpy`` move about 0.7 GB/s.
Loops are nested per dimension (outermost parallel): Taichi's ``ti.grouped`` loop over an
external array recomputes the multi-index per element and runs ten times slower. Arrays of up to
``SERIAL_COPY`` elements are copied on the calling thread (``serial``): a parallel loop's dispatch
costs ~60 us on a CPU, more than copying them. The 2-D and 3-D copies move COPY_LANES elements of
a row at a time, loads before stores: a VGA upload or download 0.75-0.91 -> 0.55-0.65 ms (uint8)
and 0.77-0.82 -> 0.58-0.63 ms (float32), three rounds in turn, median of 300 (2026-11-27).
"""

import numpy as np

from .launch import launch
from .runtime import ti

#: the largest copy (elements) done on the calling thread
SERIAL_COPY = 1 << 16
#: elements of a row a 2-D or 3-D copy loads before it stores them
COPY_LANES = 16


@ti.kernel
def _copy1(src: ti.types.ndarray(ndim=1), dst: ti.types.ndarray(ndim=1), serial: ti.template()):
    ti.loop_config(serialize=serial)
    for i in range(src.shape[0]):
        dst[i] = src[i]


@ti.func
def _copy_row(src: ti.template(), dst: ti.template(), lead: ti.template(), n):
    """dst[lead + (j,)] = src[lead + (j,)] for j < n, COPY_LANES elements at a time: their loads
    first, then their stores (Taichi reloads an array's address and shape after a store, so one
    store per load is slower), the tail one by one."""
    for k in range(n // COPY_LANES):
        j0 = k * COPY_LANES
        v = ti.Vector([src[(*lead, j0 + j)] for j in ti.static(range(COPY_LANES))])
        for j in ti.static(range(COPY_LANES)):
            dst[(*lead, j0 + j)] = v[j]
    for j in range(n // COPY_LANES * COPY_LANES, n):
        dst[(*lead, j)] = src[(*lead, j)]


@ti.kernel
def _copy2(src: ti.types.ndarray(ndim=2), dst: ti.types.ndarray(ndim=2), serial: ti.template()):
    ti.loop_config(serialize=serial)
    for i in range(src.shape[0]):
        _copy_row(src, dst, (i,), src.shape[1])


@ti.kernel
def _copy3(src: ti.types.ndarray(ndim=3), dst: ti.types.ndarray(ndim=3), serial: ti.template()):
    ti.loop_config(serialize=serial)
    for i in range(src.shape[0]):
        for j in range(src.shape[1]):
            _copy_row(src, dst, (i, j), src.shape[2])


@ti.kernel
def _copy4(src: ti.types.ndarray(ndim=4), dst: ti.types.ndarray(ndim=4), serial: ti.template()):
    ti.loop_config(serialize=serial)
    for i in range(src.shape[0]):
        for j, k, m in ti.ndrange(src.shape[1], src.shape[2], src.shape[3]):
            dst[i, j, k, m] = src[i, j, k, m]


COPY = {1: _copy1, 2: _copy2, 3: _copy3, 4: _copy4}


def copy(src, dst) -> bool:
    """dst[...] = src[...] (Taichi ndarrays or C-contiguous NumPy arrays of the same shape and dtype)
    in one directly launched kernel; False (nothing done) if ndim > 4."""
    kernel = COPY.get(len(dst.shape))
    if kernel is not None:
        launch(kernel, (src, dst), (int(np.prod(dst.shape)) <= SERIAL_COPY,))
    return kernel is not None

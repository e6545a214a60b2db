"""Copies between NumPy and Taichi arrays, used by the device itself.

On the CPU arch a Taichi ndarray lives in host memory: a copy between it and a NumPy array is
NumPy's own copy into or out of a view of that memory (:func:`host_view`; Taichi's CPU kernels
have returned when their launch does, so no kernel is using it). Measured on the 2-core VM
(2026-12-05, median of 400): a 640x480 float32 upload 468 -> ~80 us, a (16384, 6) one 157 -> ~15
us, against the copy kernels below. Where no view can be made (direct launches off in this
process, see ``runtime.direct_off``; a Taichi without ``get_ndarray_data_ptr_as_int``), and between
two Taichi arrays, a copy kernel runs.

On the CPU arch a NumPy array passed to a kernel is read and written in place, so one parallel
copy kernel moves several GB/s, where ``Ndarray.from_numpy``/``to_numpy`` move about 0.7 GB/s.
Loops are nested per dimension (outermost parallel): Taichi's ``ti.grouped`` loop over an
external array recomputes the multi-index per element and runs ten times slower. Arrays of up to
``SERIAL_COPY`` elements are copied on the calling thread (``serial``): a parallel loop's dispatch
costs ~60 us on a CPU, more than copying them. The 2-D and 3-D copies move COPY_LANES elements of
a row at a time, loads before stores: a VGA upload or download 0.75-0.91 -> 0.55-0.65 ms (uint8)
and 0.77-0.82 -> 0.58-0.63 ms (float32), three rounds in turn, median of 300 (2026-11-27).
"""

import ctypes
import logging

import numpy as np

from . import runtime
from .launch import launch
from .runtime import ti

#: the largest copy (elements) done on the calling thread
SERIAL_COPY = 1 << 16
#: elements of a row a 2-D or 3-D copy loads before it stores them
COPY_LANES = 16

log = logging.getLogger("gputrack")
_views = True  # False once Taichi could not give an array's address (another Taichi version)


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


def host_view(arr, like: np.ndarray) -> np.ndarray | None:
    """A NumPy array over the memory of the Taichi ndarray ``arr`` on the CPU arch, the same as
    ``like`` in shape and dtype, or None where there is none: another arch, another shape or dtype,
    direct launches off (arrays of a stopped Taichi program may be alive), or a Taichi that cannot
    give the address. Valid while ``arr`` is, in this Taichi program; no kernel may be writing it
    (Taichi's CPU launches return when their kernel has run)."""
    global _views
    if not _views or runtime.current_arch() != "cpu" or runtime.direct_off is not None:
        return None
    if not isinstance(arr, ti.lang._ndarray.Ndarray) or tuple(arr.shape) != like.shape or like.nbytes == 0:
        return None
    try:
        if runtime.taichi_dtype(like.dtype) is not arr.dtype:  # another type (the copy kernel casts), or
            return None  # an ndarray of vectors
    except KeyError:  # not a type of the package's arrays
        return None
    try:
        ptr = ti.lang.impl.get_runtime().prog.get_ndarray_data_ptr_as_int(arr.arr)
    except Exception as e:  # noqa: BLE001 - another Taichi: the copy kernels from now on
        log.debug("taichi: host views of arrays unavailable (%s); copying with kernels", e)
        _views = False
        return None
    return np.frombuffer((ctypes.c_char * like.nbytes).from_address(ptr), like.dtype).reshape(like.shape)


def copy(src, dst) -> bool:
    """dst[...] = src[...] (Taichi ndarrays or C-contiguous NumPy arrays of the same shape and dtype):
    NumPy's copy through :func:`host_view` between a NumPy and a Taichi array on the CPU arch, else
    one directly launched kernel; False (nothing done) if neither applies (ndim > 4)."""
    if type(src) is np.ndarray and type(dst) is not np.ndarray:
        view = host_view(dst, src)
        if view is not None:
            np.copyto(view, src)
            return True
    elif type(dst) is np.ndarray and type(src) is not np.ndarray:
        view = host_view(src, dst)
        if view is not None:
            np.copyto(dst, view)
            return True
    kernel = COPY.get(len(dst.shape))
    if kernel is not None:
        launch(kernel, (src, dst), (int(np.prod(dst.shape)) <= SERIAL_COPY,))
    return kernel is not None

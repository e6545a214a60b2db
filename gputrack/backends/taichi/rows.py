"""Taichi kernel of :mod:`gputrack.ops.rows`: one thread per element of ``src``."""

from .launch import launch
from .runtime import ti

nd = ti.types.ndarray()


@ti.kernel
def _scatter(dst: nd, index: nd, src: nd):
    for I in ti.grouped(src):  # I = (k, row element ...)
        J = I
        J[0] = index[I[0]]
        dst[J] = src[I]


def scatter_rows(device, dst, index, src):
    launch(_scatter, (dst.buffer, index.buffer, src.buffer))
    return dst

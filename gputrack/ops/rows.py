"""Rows of a device array written by index, in one launch: ``scatter_rows``.

A track table keeps one row per track slot in arrays of shape (C, ...) (state (C,n), covariance
(C,n,n), flags (C,)); new tracks are written into free slots, and a grown table receives the
old rows, without a round trip through the host per track::

    scatter_rows(device, dst, index, src)      # dst[index[k]] = src[k], k = 0 .. K-1

Shapes: ``dst`` (C, *row) (rank 1 to 3), ``index`` (K,) int32 with distinct values in [0, C),
``src`` (K, *row) of ``dst``'s dtype, or (1, *row): that one row written at every index (e.g.
the same initial covariance for every new track, uploaded once). ``dst`` is written in place
and returned; rows not named by ``index`` are left as they are. Every dtype a DeviceArray holds
is copied bit for bit (the OpenCL kernel moves 4-byte words when a row's size allows, else
bytes).

Validation: ``dst`` must be an array of ``device`` (a writeable C-contiguous NumPy array on the
``numpy`` device). A NumPy ``index`` is checked (range, distinct values); a device ``index`` is
trusted (checking it would cost a download). A NumPy ``src`` is uploaded (and counted) and must
be finite where it is floating point. K = 0 returns ``dst`` unchanged.
"""

from __future__ import annotations

import numpy as np

from ..device import DeviceArray, as_host_array
from . import backend_module
from ._args import arg, check_device, shape_of

__all__ = ["scatter_rows"]


def _dst(device, dst):
    if device.backend == "numpy":
        if not (isinstance(dst, np.ndarray) and dst.flags.c_contiguous and dst.flags.writeable):
            raise TypeError(f"dst: expected a writeable C-contiguous NumPy array on numpy, got {type(dst).__name__}")
    elif not (isinstance(dst, DeviceArray) and dst.device is device):
        got = f"an array on {dst.device.spec}" if isinstance(dst, DeviceArray) else type(dst).__name__
        raise TypeError(f"dst: expected a DeviceArray on {device.spec}, got {got}")
    if dst.ndim < 1:
        raise ValueError(f"dst: expected an array of rows (C, ...), got shape {tuple(dst.shape)}")
    return dst


def scatter_rows(device, dst, index, src, *, n_rows=None):
    """``dst[index[k]] = src[k]`` for every k, in one launch; returns ``dst`` (see the module).

    ``n_rows``: only the first n_rows entries of ``index`` (and rows of ``src``) are used
    (default: all), so that a caller can upload every frame's rows into one buffer of a fixed
    size; the entries after them are not read."""
    device = check_device(device)
    dst = _dst(device, dst)
    if dst.ndim > 3:
        raise ValueError(f"dst: expected an array of rank 1 to 3 (C, *row), got shape {tuple(dst.shape)}")
    C = dst.shape[0]
    dims: dict = {}
    host = None
    if not isinstance(index, DeviceArray):
        host = as_host_array(index, "index")
        if host.dtype.kind not in "iu":
            raise TypeError(f"index: expected integer row indices (int32), got dtype {host.dtype.name}")
        index = host.astype(np.int32, copy=False)
    index = arg(device, index, "index", ("K",), dims, dtype=np.int32)
    rows = 1 if tuple(shape_of(src, "src"))[:1] == (1,) else "K"  # one row for every index
    src = arg(device, src, "src", (rows, *dst.shape[1:]), dims, dtype=dst.dtype)
    K = dims["K"]
    if n_rows is not None:
        if isinstance(n_rows, bool) or not isinstance(n_rows, (int, np.integer)) or not 0 <= n_rows <= K:
            raise ValueError(f"n_rows: expected an integer in [0, {K}] (entries of index), got {n_rows!r}")
        K = int(n_rows)
    if host is not None:
        h = host[:K]
        if h.size and (h.min() < 0 or h.max() >= C):
            bad = int(h[(h < 0) | (h >= C)][0])
            raise ValueError(f"index: expected row indices in [0, {C}), got {bad}")
        if np.unique(h).size != h.size:
            raise ValueError("index: expected distinct row indices (two rows written to one slot), got duplicates")
    if K == 0:
        return dst
    backend_module(device, "rows").scatter_rows(device, dst, index, src, K)
    return dst

"""OpenCL launchers of :mod:`gputrack.ops.clusters` (kernels/gt_clusters.cl): one fixed sequence
of launches per call (bin, scan, place, [count], link cells, label, [border]: 11 kernels and 3
buffer fills), no host read-back; one
program per point dimension, scratch buffers kept per device and number of rows."""

from __future__ import annotations

import numpy as np

from ...device import per_device
from .program import enqueue, ndrange, scalar_types

#: as gputrack/backends/taichi/clusters.py: cells of side r (1 - CELL_SLACK) / sqrt(dim), the box
#: p +- r (1 + CELL_SLACK) searched; buckets are a power of two >= 2N, scanned in chunks of CHUNK
CELL_SLACK = 1e-3
CHUNK = 256

_I, _F = np.int32, np.float32


def buckets(N: int) -> int:
    return max(CHUNK, 1 << max(0, (2 * N - 1).bit_length()))


_SCALARS = {
    "gt_clu_bin": [None] * 6 + [_I, _I, _F],
    "gt_clu_chunk_sums": [None, None],
    "gt_clu_scan_chunks": [None, None, _I, _I],
    "gt_clu_chunk_scan": [None, None, None],
    "gt_clu_place": [None] * 6 + [_I],
    "gt_clu_count": [None] * 4 + [_I, _F, _F, _F, _I, _I],
    "gt_clu_link_cell": [None] * 7 + [_I, _F, _F, _I, _I],
    "gt_clu_box": [None] * 6 + [_I, _F, _I],
    "gt_clu_link_cells": [None] * 8 + [_I, _F, _F, _F, _I, _I],
    "gt_clu_label": [None] * 3 + [_I, _I],
    "gt_clu_border": [None] * 5 + [_I, _F, _F, _F, _I],
}


@per_device
def _kernels(device, dim):
    import pyopencl as cl

    prog = device.program("gt_clusters.cl", {"DIM": dim, "CHUNK": CHUNK})
    found = {}
    for name, types in _SCALARS.items():
        k = cl.Kernel(prog, name)
        scalar_types(k, types)
        found[name] = k
    return found


@per_device(maxsize=8)
def _scratch(device, N, dim):
    import pyopencl as cl

    H = buckets(N)
    mf = cl.mem_flags.READ_WRITE

    def buf(count, itemsize=4):
        device.check_alloc((max(1, count),), np.float32 if itemsize == 4 else np.float64)
        return cl.Buffer(device.context, mf, max(1, count) * itemsize)

    return {
        "cnt": buf(H), "start": buf(H + 1), "csum": buf(H // CHUNK), "key": buf(N), "rank": buf(N),
        "order": buf(N), "spts": buf(N * dim), "parent": buf(N), "core": buf(N), "loose": buf(H), "heads": buf(N + 1),
        "box": buf(6 * N),
    }  # fmt: skip


def _run(device, points, n, r2, ms, out, is_dbscan):
    """The launches over all N rows (the kernels skip the rows at or beyond n, or beyond the
    points binned): one NDRange size per buffer size, so a driver that builds a kernel for each
    new size (PoCL picks the work-group size from it) builds it once, not once per point count."""
    import pyopencl as cl

    N, dim = points.shape
    H = buckets(N)
    chunks = H // CHUNK
    mask = H - 1
    r = np.sqrt(np.float64(r2))
    w = np.float32(r * (1.0 + CELL_SLACK))  # the searched box p +- w
    inv = np.float32(np.sqrt(dim) / (r * (1.0 - CELL_SLACK)))  # 1 / the cell side
    r2 = np.float32(r2)
    k = _kernels(device, dim)
    b = _scratch(device, N, dim)
    q = device.queue
    pts = points.buffer.data
    rng = ndrange(N)  # the kernels over the N rows skip the padding (each tests n, start[H], heads[n] or N)
    cl.enqueue_fill_buffer(q, b["cnt"], np.int32(0), 0, 4 * H)
    cl.enqueue_fill_buffer(q, b["loose"], np.int32(0), 0, 4 * H)
    enqueue(device, k["gt_clu_bin"], *rng, pts, b["cnt"], b["key"], b["rank"], b["parent"], b["core"], n, mask, inv)
    enqueue(device, k["gt_clu_chunk_sums"], (chunks,), None, b["cnt"], b["csum"])
    enqueue(device, k["gt_clu_scan_chunks"], (1,), None, b["csum"], b["start"], chunks, H)
    enqueue(device, k["gt_clu_chunk_scan"], (chunks,), None, b["cnt"], b["csum"], b["start"])
    enqueue(device, k["gt_clu_place"], *rng, pts, b["key"], b["rank"], b["start"], b["order"], b["spts"], n)
    grid = (b["spts"], b["order"], b["start"])
    if is_dbscan:
        enqueue(device, k["gt_clu_count"], *rng, *grid, b["core"], mask, r2, w, inv, int(ms), H)
    cl.enqueue_fill_buffer(q, b["heads"], np.int32(0), 4 * n, 4)  # heads[n]: the number of heads
    link = (*grid, b["core"], b["parent"], b["loose"], b["heads"], mask, r2)
    enqueue(device, k["gt_clu_link_cell"], *rng, *link, inv, H, n)
    enqueue(device, k["gt_clu_box"], *rng, *grid, b["core"], b["heads"], b["box"], mask, inv, n)
    # one work-item per cell head, uneven work: on a CPU device one-item work-groups spread it over
    # the cores (the heads are the first items); a GPU keeps the driver's work-group size
    local = (1,) if device.info.kind == "cpu" else None
    enqueue(device, k["gt_clu_link_cells"], (N,), local, *link[:-2], b["box"], mask, r2, w, inv, H, n)
    enqueue(device, k["gt_clu_label"], *rng, b["parent"], b["core"], out.buffer.data, n, N)
    if is_dbscan:
        enqueue(device, k["gt_clu_border"], *rng, *grid, b["core"], out.buffer.data, mask, r2, w, inv, H)
    return out


def radius_components(device, points, n, r2, out):
    return _run(device, points, n, r2, 1, out, False)


def dbscan(device, points, n, r2, min_samples, out):
    return _run(device, points, n, r2, min_samples, out, True)

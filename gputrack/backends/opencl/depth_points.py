"""OpenCL launchers of :mod:`gputrack.ops.depth_points` (kernels/gt_depth_points.cl): five kernels
on the device's queue, then the three counts (N, C, level) read back for ``count``. The keys are
computed once, a work-item per pixel (PoCL vectorises that across work-items; computing them in
the per-chunk loops instead cost 4x more on one core) but not stored: a byte per pixel holds the
levels each key is below, the per-chunk steps read the bytes and the compaction hashes the
candidates' keys again.

A host (NumPy) depth image is copied into a buffer kept per image size, enqueued without a wait
(:func:`reads_host`); with ``host_out`` the points are read back beside the counts, both enqueued
without a wait, and the queue is finished once: one wait for PoCL's threads per call. The frame's
other transfers of the pedestrian tracker use :func:`enqueue_upload`, :func:`enqueue_download`
and :func:`packed_arrays` (several small device arrays in one buffer, filled by one copy)."""

from __future__ import annotations

import numpy as np

from ...device import per_device
from .program import enqueue, scalar_types
from .background import CL_PIXEL

_I, _U, _F = np.int32, np.uint32, np.float32
LEVELS = 4  # GT_LEVELS
CHUNK = 32  # GT_CHUNK
RADIX = 256
ARG_TYPES = {
    "gt_dp_keys": [None, None, _I, _I, _U, _U, _F, _F, _I, None],
    "gt_dp_count": [None, _I, _I, None],
    "gt_dp_plan": [None, _I, _I, None, None],
    "gt_dp_compact": [None, _I, _I, _U, _U, None, None, None, None, None],
    "gt_dp_select": [None, _I, None, None, None, None, None, None, _I, _F, _F, _F, _F, None],
}


@per_device
def _kernel(device, name, pixel):
    import pyopencl as cl

    found = cl.Kernel(device.program("gt_depth_points.cl", {"GT_PIXEL": CL_PIXEL[pixel]}), name)
    scalar_types(found, ARG_TYPES[name])
    return found


@per_device(maxsize=4)
def _scratch(device, H, W):
    """Buffers of one image size: the levels of the keys (a byte per pixel), per-chunk counts,
    offsets, info, candidates (keys and pixels, twice)."""
    import pyopencl as cl

    rw = cl.mem_flags.READ_WRITE
    size = H * W * 4
    G = H * ((W + CHUNK - 1) // CHUNK)

    def buf(nbytes):
        device.check_alloc((max(nbytes, 4) // 4,), np.float32)  # MemoryError, not INVALID_BUFFER_SIZE
        return cl.Buffer(device.context, rw, max(nbytes, 4))

    return {
        "hist": buf(G * LEVELS * 4), "below": buf(H * W), "offs": buf((G + 1) * 4), "info": buf(16),
        "cnt": buf(RADIX * 4),
        "k0": buf(size), "i0": buf(size), "k1": buf(size), "i1": buf(size),
        "host_info": np.zeros(4, np.int32), "depth": {},
    }  # fmt: skip


def reads_host(device) -> bool:
    """A host (NumPy) depth image is taken as it is and copied into a kept buffer by
    :func:`depth_points`, enqueued without a wait (no device array allocated per frame)."""
    return True


def enqueue_upload(device, arr, host):
    """Copy the C-contiguous NumPy array ``host`` into the device array ``arr`` (same bytes),
    enqueued without a wait; counted. Returns the event, which keeps ``host`` alive: hold it until
    the queue has been waited for (dropping an unfinished one waits for it)."""
    import pyopencl as cl

    device.transfers.h2d += host.nbytes
    return cl.enqueue_copy(device.queue, arr.buffer.data, host, is_blocking=False)


def enqueue_download(device, arr, host):
    """Copy the device array ``arr`` into the C-contiguous NumPy array ``host`` (same bytes),
    enqueued without a wait; counted. ``host`` holds the values once the queue has been waited
    for; hold the returned event until then."""
    import pyopencl as cl

    device.transfers.d2h += host.nbytes
    return cl.enqueue_copy(device.queue, host, arr.buffer.data, is_blocking=False)


def packed_arrays(device, specs):
    """Device arrays ``[(shape, dtype), ...]`` as sub-buffers of one buffer, each at an offset
    aligned to the device's base address alignment, for one copy to fill them all: returns
    ``(arrays, whole, host, views)``, ``whole`` the buffer as a uint8 device array, ``host`` a
    uint8 NumPy array of its bytes and ``views[i]`` the NumPy view of ``host`` that ``arrays[i]``
    receives when ``host`` is copied into ``whole`` (:func:`enqueue_upload`)."""
    import math

    import pyopencl as cl
    import pyopencl.array as cla

    align = max(int(device.cl_device.mem_base_addr_align) // 8, 16)
    offsets, end = [], 0
    for shape, dtype in specs:
        offsets.append(end)
        end += -(-max(math.prod(shape) * np.dtype(dtype).itemsize, 1) // align) * align
    device.check_alloc((end,), np.uint8)
    buf = cl.Buffer(device.context, cl.mem_flags.READ_WRITE, end)
    whole = device._wrap(cla.Array(device.queue, (end,), np.uint8, data=buf), (end,), np.dtype(np.uint8))
    host = np.zeros(end, np.uint8)
    arrays, views = [], []
    for (shape, dtype), off in zip(specs, offsets):
        dt, shape = np.dtype(dtype), tuple(int(v) for v in shape)
        n = math.prod(shape) * dt.itemsize
        sub = buf.get_sub_region(off, max(n, 1))
        arrays.append(device._wrap(cla.Array(device.queue, shape, dt, data=sub), shape, dt))
        views.append(host[off:off + n].view(dt).reshape(shape))
    return arrays, whole, host, views


def depth_points(device, depth, bg, pixel, fx, fy, cx, cy, threshold, max_range, nearer, a, b, out, host_out=None):
    """``depth``: a device array or a C-contiguous NumPy array (:func:`reads_host`); ``host_out``:
    None or a NumPy (n, 3) float32 array the points are read into, in the wait for the counts."""
    import pyopencl as cl

    H, W = bg.shape
    s = _scratch(device, H, W)
    q = device.queue
    events = []
    if isinstance(depth, np.ndarray):  # into the kept buffer of this size, no wait
        kept = s["depth"].get(depth.nbytes)
        if kept is None:
            device.check_alloc((max(depth.nbytes, 4) // 4,), np.float32)
            kept = s["depth"][depth.nbytes] = cl.Buffer(device.context, cl.mem_flags.READ_WRITE, max(depth.nbytes, 4))
        device.transfers.h2d += depth.nbytes
        events.append(cl.enqueue_copy(q, kept, depth, is_blocking=False))
        d = kept
    else:
        d = depth.buffer.data
    g = bg.buffer.data
    common = (H, W, a, b, float(threshold), float(max_range), int(nearer))
    chunks = (W + CHUNK - 1) // CHUNK
    enqueue(device, _kernel(device, "gt_dp_keys", pixel), (H * W,), None, d, g, *common, s["below"])
    enqueue(device, _kernel(device, "gt_dp_count", pixel), (chunks, H), None, s["below"], H, W, s["hist"])
    enqueue(device, _kernel(device, "gt_dp_plan", pixel), (1,), None, s["hist"], H * chunks, out.shape[0], s["offs"],
            s["info"])  # fmt: skip
    enqueue(device, _kernel(device, "gt_dp_compact", pixel), (chunks, H), None, s["below"], H, W, a, b, s["hist"],
            s["offs"], s["info"], s["k0"], s["i0"])  # fmt: skip
    enqueue(device, _kernel(device, "gt_dp_select", pixel), (1,), None, d, W, s["info"], s["k0"], s["i0"], s["k1"],
            s["i1"], s["cnt"], out.shape[0], float(fx), float(fy), float(cx), float(cy), out.buffer.data)  # fmt: skip
    info = s["host_info"]
    device.transfers.d2h += info.nbytes
    if host_out is None:
        cl.enqueue_copy(q, info, s["info"])  # blocking: waits for the kernels
    else:  # the counts and the points, one wait
        device.transfers.d2h += host_out.nbytes
        events.append(cl.enqueue_copy(q, info, s["info"], is_blocking=False))
        events.append(cl.enqueue_copy(q, host_out, out.buffer.data, is_blocking=False))
        q.finish()
    events.clear()  # finished (each event keeps its host array alive until then)
    return int(info[0])

"""OpenCL launchers of :mod:`gputrack.ops.depth_points` (kernels/gt_depth_points.cl): five kernels
on the device's queue, then the three counts (N, C, level) read back for ``count``. The keys are
computed once, a work-item per pixel (PoCL vectorises that across work-items; computing them in
the per-chunk loops instead cost 4x more on one core) but not stored: a byte per pixel holds the
levels each key is below, the per-chunk steps read the bytes and the compaction hashes the
candidates' keys again."""

from __future__ import annotations

import numpy as np

from ...device import per_device
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
    found.set_scalar_arg_dtypes(ARG_TYPES[name])
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
        "host_info": np.zeros(4, np.int32),
    }  # fmt: skip


def depth_points(device, depth, bg, pixel, fx, fy, cx, cy, threshold, max_range, nearer, a, b, out):
    import pyopencl as cl

    H, W = bg.shape
    s = _scratch(device, H, W)
    q = device.queue
    d, g = depth.buffer.data, bg.buffer.data
    common = (H, W, a, b, float(threshold), float(max_range), int(nearer))
    chunks = (W + CHUNK - 1) // CHUNK
    _kernel(device, "gt_dp_keys", pixel)(q, (H * W,), None, d, g, *common, s["below"])
    _kernel(device, "gt_dp_count", pixel)(q, (chunks, H), None, s["below"], H, W, s["hist"])
    _kernel(device, "gt_dp_plan", pixel)(q, (1,), None, s["hist"], H * chunks, out.shape[0], s["offs"], s["info"])
    _kernel(device, "gt_dp_compact", pixel)(q, (chunks, H), None, s["below"], H, W, a, b, s["hist"], s["offs"],
                                            s["info"], s["k0"], s["i0"])  # fmt: skip
    _kernel(device, "gt_dp_select", pixel)(q, (1,), None, d, W, s["info"], s["k0"], s["i0"], s["k1"], s["i1"],
                                           s["cnt"], out.shape[0], float(fx), float(fy), float(cx), float(cy),
                                           out.buffer.data)  # fmt: skip
    info = s["host_info"]
    cl.enqueue_copy(q, info, s["info"])  # blocking: waits for the kernels
    return int(info[0])

"""OpenCL launchers of :mod:`gputrack.ops.model_template` (kernels/gt_model_template.cl).

``render``: one launch over the crop (the part table copied into a buffer kept per device, enqueued
without a wait). ``classify``: a launch over the crop (the interior flags and the 64-bit strength
numerators of step 2-3's integers, and the reset of the counts), one over
its rows (the per-part statistics, a run of a row at a time) and one over its rows (every candidate
into its part's bin). ``render`` and the classes take GT_MT_LANES pixels of a row per work-item
(explicit vectors on CPU devices; the classes stage each window row's part ids and q once). The
render computes in double on devices with fp64 (GT_MT_DOUBLE=1: the part table, the texture's
waves and the constants sent in float64, as the reference's float64 render), in float otherwise; it
stores float32 either way.
``emit``: one launch, per part and kind the greedy extrema from a heap of the part's bin, the
farthest-point fill over the compacted pool and the points: on CPU devices a work-group of one
(``gt_mt_emit``, GT_MT_LANES pixels per step), on GPUs a work-group of :func:`emit_group`
work-items (``gt_mt_emit_wg``: the pool's passes shared out, each fill point's argmax reduced in
local memory; one work-item walking the pool took the H100's template to 34.5 ms). No host
wait in any of them (one in-order queue); the op downloads the counts after ``classify``.
"""

from __future__ import annotations

import math

import numpy as np

from ...device import per_device, per_device_cache
from ...uploads import constant
from .depth_points import enqueue_upload
from .program import enqueue, ndrange, scalar_types

__all__ = ["classify", "emit", "render", "render_dtype"]

_I, _F = np.int32, np.float32
ARG_TYPES = {
    "gt_mt_render": [None, None, None, _I, _I, _I, _I, _I, _I, _I, _I, None, None, None],
    "gt_mt_classify": [None, None, _I, _I, _I, _I, _I, _I, _F, _F, _I, _I, _I, None, None, None, None, None],
    "gt_mt_stats": [None, None, _I, _I, _I, _I, _I, None],
    "gt_mt_bin": [None, None, None, None, _I, _I, _I, _I, _I, _I, None, None, _I],
    "gt_mt_emit": [None, None, None, _I, _I, None, None, None, None, None, None, None, None, None, _I, _I, None, None],
}
ARG_TYPES["gt_mt_emit_wg"] = ARG_TYPES["gt_mt_emit"]


CPU_LANES = 8


def lanes(device) -> int:
    """Pixels of a row per work-item of the render and classification kernels (GT_MT_LANES): explicit
    vector lanes on CPU devices, 1 on GPUs."""
    return CPU_LANES if device.info.kind == "cpu" else 1


#: work-items per part and kind of the pick on GPUs (gt_mt_emit_wg; at most the kernel's MT_WG_MAX):
#: render + pick 34.5 -> 1.68 ms on an H100 against one work-item per part (other sizes not tried)
EMIT_WG = 128


def emit_group(device) -> int:
    """Work-items per part and kind of the pick: 1 on CPU devices (``gt_mt_emit``, the fill's passes
    in vector lanes), else EMIT_WG or the device's largest power of two below it
    (``gt_mt_emit_wg``: the passes shared out, the argmax reduced in local memory)."""
    if device.info.kind == "cpu":
        return 1
    most = min(EMIT_WG, device.info.max_work_group_size or EMIT_WG)
    return 1 << (most.bit_length() - 1)


def double(device) -> bool:
    """Whether the render computes in double (GT_MT_DOUBLE): on devices with fp64."""
    return bool(device.fp64)


def render_dtype(device):
    """The type the render computes in: np.float64 on devices with fp64 (GT_MT_DOUBLE), else np.float32."""
    return np.float64 if double(device) else np.float32


@per_device
def _kernel(device, name):
    import pyopencl as cl

    defines = {"GT_MT_LANES": lanes(device), "GT_MT_DOUBLE": int(double(device))}  # one program for every kernel
    found = cl.Kernel(device.program("gt_model_template.cl", defines), name)
    scalar_types(found, ARG_TYPES[name])
    return found


#: per device: the part table's array (made again when its shape or type changes) and the event of
#: its last copy, which keeps that call's host table alive until the copy has run
_TABLE = per_device_cache()


def _upload_table(device, table: np.ndarray):
    """``table`` into the device's kept part-table array, enqueued without a wait; its buffer."""
    host = np.ascontiguousarray(table)
    kept = _TABLE.get(device)
    if kept is None or kept["array"].shape != host.shape or kept["array"].dtype != host.dtype:
        kept = _TABLE[device] = {"array": device.empty(host.shape, host.dtype), "event": None}
    kept["event"] = enqueue_upload(device, kept["array"], host)
    return kept["array"].buffer.data


#: Work-group shape of the crop's kernels (program.ndrange: fixed, the NDRange padded; left to the
#: driver, PoCL made a crop one work-group and built a new kernel for every new crop size)
CROP_WG = (4, 8)


def _lim(s2) -> int:
    """The largest integer d^2 with d^2 < s2 (the spacing test on integer offsets, exactly)."""
    return int(math.ceil(float(s2))) - 1


def render(device, chain, transforms, texture, table, waves, consts, crop, part, values, local):
    """Step 1 over the crop: part, gray and depth Z, the part-local point (computed in double on
    devices with fp64, else float; stored float32)."""
    r0, r1, c0, c1 = (int(v) for v in crop)
    if r1 <= r0 or c1 <= c0:
        return
    H, W = part.shape
    J, Wv = int(waves.shape[0]), int(waves.shape[1])
    dt = np.float64 if double(device) else np.float32  # the op's tables are float64
    tb = _upload_table(device, np.ascontiguousarray(table, dt))
    wv = constant(device, np.ascontiguousarray(waves, dt))
    cs = constant(device, np.ascontiguousarray(consts, dt))
    L = lanes(device)
    glob, wg = ndrange(-(-(c1 - c0) // L), r1 - r0, group=CROP_WG)
    enqueue(device, _kernel(device, "gt_mt_render"), glob, wg, tb, wv.buffer.data, cs.buffer.data, J, Wv, H, W, r0, r1,
            c0, c1, part.buffer.data, values.buffer.data, local.buffer.data)  # fmt: skip


def classify(device, part, values, crop, scales, window, border, interior, num, cnt, bins, stats, surv):
    """Steps 2-4: the interior flags (int32), the strength numerators num (2, H, W) int64 (-1: not an
    extremum), per-part statistics, every candidate binned per part (see the reference)."""
    r0, r1, c0, c1 = (int(v) for v in crop)
    H, W = part.shape
    J = int(stats.shape[0])
    q = device.queue
    pb, vb, cnb = part.buffer.data, values.buffer.data, cnt.buffer.data
    ib, nb = interior.buffer.data, num.buffer.data
    stb, svb = stats.buffer.data, surv.buffer.data
    sc = np.asarray(scales, np.float32)
    if r1 <= r0 or c1 <= c0:  # nothing to read: the counts only
        import pyopencl as cl

        init = np.zeros((J, 10), np.int32)
        init[:, 2::2], init[:, 3::2] = 1 << 30, -1
        device.transfers.h2d += init.nbytes + 8 * J
        cl.enqueue_copy(q, stb, init)
        cl.enqueue_copy(q, svb, np.zeros((2, J), np.int32))
        return
    glob, wg = ndrange(-(-(c1 - c0) // lanes(device)), r1 - r0, group=CROP_WG)
    enqueue(device, _kernel(device, "gt_mt_classify"), glob, wg, pb, vb, H, W, r0, r1, c0, c1, float(sc[0]),
            float(sc[1]), int(window) // 2, int(border), J, ib, nb, cnb, stb, svb)  # fmt: skip
    rows = ndrange(r1 - r0, group=(8,))
    enqueue(device, _kernel(device, "gt_mt_stats"), *rows, pb, ib, W, r0, r1, c0, c1, stb)
    enqueue(device, _kernel(device, "gt_mt_bin"), *rows, pb, ib, nb, stb, H, W, r0, r1, c0, c1, bins.buffer.data, svb,
            J)  # fmt: skip


def emit(device, part, values, local, crop, plan, stats, surv, bins, interior, num, cnt, dist, used, s2, out0, out1):
    """Steps 6-8: per kind and part (a work-group of one each) the greedy extrema, the farthest-point
    fill and the points, into out0 (RGB) and out1 (depth). ``dist`` holds the fill's distances with
    each pool pixel's row / column flags; ``used`` the seeds' rows and columns."""
    H, W = part.shape
    J = int(stats.shape[0])
    if out0.shape[0] + out1.shape[0] == 0:
        return
    dummy = out0 if out0.shape[0] else out1
    o0 = (out0 if out0.shape[0] else dummy).buffer.data
    o1 = (out1 if out1.shape[0] else dummy).buffer.data
    wg = emit_group(device)
    name = "gt_mt_emit" if wg == 1 else "gt_mt_emit_wg"
    enqueue(device, _kernel(device, name), (J * wg, 2), (wg, 1), part.buffer.data, values.buffer.data,
            local.buffer.data, H, W, plan.buffer.data, stats.buffer.data, surv.buffer.data, bins.buffer.data,
            interior.buffer.data, num.buffer.data, cnt.buffer.data, dist.buffer.data, used.buffer.data, _lim(s2), J, o0,
            o1)  # fmt: skip

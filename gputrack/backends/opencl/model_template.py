"""OpenCL launchers of :mod:`gputrack.ops.model_template` (kernels/gt_model_template.cl).

``render``: one launch over the crop (the part table copied into a buffer kept per device, enqueued
without a wait). ``classify``: three launches over the crop (classes and the reset of the counts;
the per-part statistics a run of a row at a time; the suppression into the bins) and one over its
rows. ``emit``: the ranks of the survivors with the extrema and their spacing stamps, then the fill.
No host wait in any of them (one in-order queue); the op downloads the counts after ``classify``.
"""

from __future__ import annotations

import math

import numpy as np

from ...device import per_device, per_device_cache
from ...uploads import constant

__all__ = ["classify", "emit", "render"]

_I, _F = np.int32, np.float32
ARG_TYPES = {
    "gt_mt_render": [None, None, None, _I, _I, _I, _I, _I, _I, _I, None, None, None],
    "gt_mt_classify": [None, None, _I, _I, _I, _I, _I, _I, _F, _F, _I, _I, _I, None, None, None, None],
    "gt_mt_stats": [None, None, _I, _I, _I, _I, None],
    "gt_mt_suppress": [None, None, None, None, _I, _I, _I, _I, _I, _I, _I, _I, _I, None, None],
    "gt_mt_extrema": [None, None, None, _I, _I, _I, _I, _I, _I, None, None, None, None, None, None, None, _I, _I,
                      _I, _I, None, None],  # fmt: skip
    "gt_mt_fill": [None, None, None, _I, _I, None, None, None, None, _I, _I, _I, _I, None, None],
}


CPU_LANES = 8


def lanes(device) -> int:
    """Pixels of a row per work-item of the render and classification kernels (GT_MT_LANES): explicit
    vector lanes on CPU devices, 1 on GPUs."""
    return CPU_LANES if device.info.kind == "cpu" else 1


@per_device
def _kernel(device, name):
    import pyopencl as cl

    found = cl.Kernel(device.program("gt_model_template.cl", {"GT_MT_LANES": lanes(device)}), name)
    found.set_scalar_arg_dtypes(ARG_TYPES[name])
    return found


#: per device: the part table's buffer (grown as needed) and the event of its last copy, which
#: keeps that call's host table alive until the copy has run (dropped at the next call)
_TABLE = per_device_cache()


def _upload_table(device, table: np.ndarray):
    import pyopencl as cl

    host = np.ascontiguousarray(table, np.float32)
    kept = _TABLE.get(device)
    if kept is None or kept["nbytes"] < host.nbytes:
        device.check_alloc((max(host.size, 1),), np.float32)
        kept = _TABLE[device] = {"buffer": cl.Buffer(device.context, cl.mem_flags.READ_ONLY, max(host.nbytes, 4)),
                                 "nbytes": max(host.nbytes, 4), "event": None}  # fmt: skip
    device.transfers.h2d += host.nbytes
    kept["event"] = cl.enqueue_copy(device.queue, kept["buffer"], host, is_blocking=False)
    return kept["buffer"]


def _lim(s2) -> int:
    """The largest integer d^2 with d^2 < s2 (the spacing test on integer offsets, exactly)."""
    return int(math.ceil(float(s2))) - 1


def render(device, chain, transforms, texture, table, waves, consts, crop, part, values, local):
    """Step 1 over the crop: part, gray and depth Z, the part-local point (float32)."""
    r0, r1, c0, c1 = (int(v) for v in crop)
    if r1 <= r0 or c1 <= c0:
        return
    H, W = part.shape
    J, Wv = int(waves.shape[0]), int(waves.shape[1])
    tb = _upload_table(device, table)
    wv = constant(device, np.ascontiguousarray(waves, np.float32))
    cs = constant(device, np.ascontiguousarray(consts, np.float32))
    L = lanes(device)
    _kernel(device, "gt_mt_render")(device.queue, (-(-(c1 - c0) // L), r1 - r0), None, tb, wv.buffer.data,
                                    cs.buffer.data, J, Wv, H, W, r0, c0, c1, part.buffer.data, values.buffer.data,
                                    local.buffer.data)  # fmt: skip


def classify(device, part, values, crop, scales, window, border, rad, s2, cls, cnt, bins, stats, surv):
    """Steps 2-5: classes, per-part statistics, the survivors binned per part (see the reference)."""
    r0, r1, c0, c1 = (int(v) for v in crop)
    H, W = part.shape
    J = int(stats.shape[0])
    q = device.queue
    pb, vb, clb, cnb = part.buffer.data, values.buffer.data, cls.buffer.data, cnt.buffer.data
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
    _kernel(device, "gt_mt_classify")(q, (-(-(c1 - c0) // lanes(device)), r1 - r0), None, pb, vb, H, W, r0, r1, c0, c1, float(sc[0]), float(sc[1]),
                                      int(window) // 2, int(border), J, clb, cnb, stb, svb)  # fmt: skip
    _kernel(device, "gt_mt_stats")(q, (r1 - r0,), None, pb, clb, W, r0, c0, c1, stb)
    _kernel(device, "gt_mt_suppress")(q, (c1 - c0, r1 - r0), None, pb, clb, cnb, stb, H, W, r0, r1, c0, c1, int(rad), _lim(s2), J,
                                      bins.buffer.data, svb)  # fmt: skip


def emit(device, part, values, local, crop, plan, stats, surv, bins, cls, cnt, mask, stamp, rad, s2, n0, n1,
         total_area, out0, out1):  # fmt: skip
    """Steps 7-9: the strongest survivors (ranked on the device), then the fill, into out0 / out1."""
    r0, r1, c0, c1 = (int(v) for v in crop)
    H, W = part.shape
    J = int(stats.shape[0])
    n0, n1, total_area = int(n0), int(n1), int(total_area)
    if n0 + n1 == 0:
        return
    q = device.queue
    dummy = out0 if n0 else out1
    o0 = (out0 if n0 else dummy).buffer.data
    o1 = (out1 if n1 else dummy).buffer.data
    pb, vb, lb = part.buffer.data, values.buffer.data, local.buffer.data
    plb, stb, clb, cnb, mb = plan.buffer.data, stats.buffer.data, cls.buffer.data, cnt.buffer.data, mask.buffer.data
    lim = _lim(s2)
    if total_area > 0:
        _kernel(device, "gt_mt_extrema")(q, (total_area, 2), None, pb, vb, lb, H, W, r0, r1, c0, c1, plb, stb,
                                         surv.buffer.data, bins.buffer.data, clb, cnb, mb, int(stamp), int(rad), lim,
                                         J, o0, o1)  # fmt: skip
    _kernel(device, "gt_mt_fill")(q, (max(n0, n1), 2), None, pb, vb, lb, H, W, plb, stb, clb, mb, int(stamp), J, n0,
                                  n1, o0, o1)  # fmt: skip

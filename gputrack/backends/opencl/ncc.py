"""OpenCL launchers for kernels/gt_ncc.cl: zero-mean NCC of templates with image patches (paper 003 eq. 13).

Two launches per op call, in one queue without a wait: the templates' shifted values and sums
(``gt_ncc_templates``, one work-item per template: they are the same for every hypothesis), then one
work-item per (hypothesis, point), or per hypothesis for the sum. Conventions: gputrack/ops/ncc.py.
"""

from __future__ import annotations

import numpy as np

from ...device import per_device
from .program import enqueue, ndrange, scalar_types

# scalar argument types per kernel (None = a buffer): pyopencl then packs the arguments directly
_I = np.int32
ARG_TYPES = {
    "gt_ncc_templates": [None, _I, _I, None, None],
    "gt_patch_ncc_points": [None, _I, _I, None, None, _I, None, _I, _I, None],
    "gt_patch_ncc": [None, _I, _I, None, None, _I, None, _I, _I, None],
}


@per_device
def _kernel(device, name):
    """The kernel ``name`` of gt_ncc.cl (one cl.Kernel per device)."""
    import pyopencl as cl

    found = cl.Kernel(device.program("gt_ncc.cl"), name)
    scalar_types(found, ARG_TYPES[name])
    return found


@per_device(maxsize=8)
def _template_buffers(device, nk, s):
    """The shifted templates (nk, s, s) and their sums (nk, 4) of gt_ncc_templates, kept per size."""
    return device.empty((nk, s, s), np.float32), device.empty((nk, 4), np.float32)


def patch_ncc(device, pts, tpl, img, *, per_point):
    nb, nk = pts.shape[:2]
    s = tpl.shape[1]
    h, w = img.shape
    ts, tstat = _template_buffers(device, int(tpl.shape[0]), int(s))
    enqueue(device, _kernel(device, "gt_ncc_templates"), *ndrange(int(tpl.shape[0])), tpl.buffer.data,
            int(tpl.shape[0]), s, ts.buffer.data, tstat.buffer.data)  # fmt: skip
    args = (pts.buffer.data, nb, nk, ts.buffer.data, tstat.buffer.data, s, img.buffer.data, h, w)
    if per_point:
        out = device.empty((nb, nk), np.float32)
        enqueue(device, _kernel(device, "gt_patch_ncc_points"), *ndrange(nb * nk), *args, out.buffer.data)
    else:
        out = device.empty((nb,), np.float32)
        enqueue(device, _kernel(device, "gt_patch_ncc"), *ndrange(nb), *args, out.buffer.data)
    return out

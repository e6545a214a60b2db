"""OpenCL launchers for kernels/gt_particles.cl: counter-based sampling (eq. 12) and best-k."""

from __future__ import annotations

import numpy as np

from ...device import per_device
from .program import enqueue, ndrange, scalar_types

_I, _U, _F = np.int32, np.uint32, np.float32
# scalar argument types (None = a buffer): pyopencl then packs the arguments directly (fast launches)
ARG_TYPES = {
    "gt_sample_around": [None, _I, _I, None, _I, _I, _U, _U, _I, None],
    "gt_best_k": [None, _I, _I, None, None, None, None, _I, None],
}


@per_device
def _kernel(device, name):
    import pyopencl as cl

    found = cl.Kernel(device.program("gt_particles.cl"), name)
    scalar_types(found, ARG_TYPES[name])
    return found


def sample_around(device, cand, sig, n, lo, hi, *, per_candidate, keep_candidates, out=None):
    c, p = cand.shape
    out = device.empty((n, p), np.float32) if out is None else out
    enqueue(
        device, _kernel(device, "gt_sample_around"), *ndrange((p + 1) // 2 * n), cand.buffer.data, c, p,
        sig.buffer.data, int(per_candidate), n, lo, hi, int(keep_candidates), out.buffer.data,
    )  # fmt: skip
    return out


@per_device(maxsize=4)
def _keys(device, k):
    """A scratch buffer for the k-list's keys, kept per device and k."""
    import pyopencl as cl

    device.check_alloc((k,), np.uint32)
    return cl.Buffer(device.context, cl.mem_flags.READ_WRITE, 4 * k)


def best_k(device, scores, k, rows, out):
    """out: the (idx, val, sel) arrays to write (gputrack/ops/particles.py best_k_out)."""
    idx, val, sel = out
    keys = _keys(device, k)
    p = rows.shape[1] if rows is not None else 0
    rows_buf = rows.buffer.data if rows is not None else scores.buffer.data
    sel_buf = sel.buffer.data if sel is not None else val.buffer.data
    enqueue(
        device, _kernel(device, "gt_best_k"), (1,), (1,), scores.buffer.data, scores.shape[0], k, idx.buffer.data,
        val.buffer.data, keys, rows_buf, p, sel_buf,
    )  # fmt: skip
    return idx, val, sel

"""OpenCL launchers for kernels/gt_template.cl: sparse-template cost and residuals.

One launch per op call. On CPU devices a work-item evaluates ``LANES`` hypotheses with explicit
vector types (the compiler maps them onto SIMD registers); on GPUs LANES = 1 (one work-item per
hypothesis). Conventions: gputrack/ops/template.py.
"""

from __future__ import annotations

import numpy as np

from ... import tuning_cache
from ...device import per_device
from ...tuning_cache import Tunable
from .program import enqueue, ndrange, scalar_types, source

CPU_LANES = 8
WORK_GROUP = 4


def lanes(device) -> int:
    """Hypotheses per work-item on ``device`` (the default; ``gputrack tune`` may choose another)."""
    return CPU_LANES if device.info.kind == "cpu" else 1


def default_params(device) -> dict:
    """Launch parameters without a tuning-cache entry: lanes per work-item and work-group size."""
    return {"lanes": lanes(device), "work_group": WORK_GROUP if device.info.kind == "cpu" else 64}


# The launch parameters of gt_rgbd, read by rgbd_cost and rgbd_residuals at every call and swept
# by ``gputrack tune``: ``lanes`` = hypotheses per work-item (LANES), ``work_group`` = the
# work-group size. Results are identical whatever the choice (each lane computes its own
# hypothesis with the same sums); only the speed differs. Representative sizes: a particle-filter
# stage (paper 000: K = 1500, N = N' = 128) and the batched LM's residuals (B = 280 .. 400
# perturbed poses share the bucket B=512).
TUNABLES = {
    op: Tunable(
        op=op,
        backend="opencl",
        candidates={"lanes": [1, 4, 8, 16], "work_group": [1, 2, 4, 8, 16, 32, 64, 128]},
        default=default_params,
        sizes=(size,),
        sources=(source("gt_template.cl"), source("gt_lanes.clh")),
    )
    for op, size in (("rgbd_cost", {"B": 1500, "N": 128}), ("rgbd_residuals", {"B": 400, "N": 128}))
}


def _tuned(device, op, tf, rgb, depth) -> dict:
    """The launch parameters of ``op`` for this device and size (cached choice, else default)."""
    n = max(rgb["pts"].shape[0], depth["pts"].shape[0])
    return tuning_cache.choose(device, TUNABLES[op], {"B": tf.shape[0], "N": n})


def _buffer(device, name, nbytes):
    """A scratch buffer of at least ``nbytes`` kept per device (sizes rounded up to a power of two,
    so that batches of similar sizes share one)."""
    nbytes = 1 << max(2, (int(nbytes) - 1).bit_length())
    device.check_alloc((nbytes // 4,), np.float32)  # MemoryError naming the size, not INVALID_BUFFER_SIZE
    return _scratch(device, name, nbytes)


@per_device(maxsize=12)
def _scratch(device, name, nbytes):
    import pyopencl as cl

    return cl.Buffer(device.context, cl.mem_flags.READ_WRITE, nbytes)


# scalar argument types per kernel (None = a buffer): with them pyopencl packs the arguments
# directly, which takes a launch from ~150 us to ~20 us on PoCL
_I, _F = np.int32, np.float32
ARG_TYPES = {
    "gt_rgbd": [None, _I, _I, None, None, _I, _I, None, None, _I, _I, None, None, _I, _I] + [_F] * 8 + [None] * 8
    + [_I, None, _I],
}


def _kernel(device, name, **defines):
    """The kernel ``name`` of gt_template.cl built with ``defines`` (one cl.Kernel per device)."""
    return _built_kernel(device, name, tuple(sorted(defines.items())))


@per_device
def _built_kernel(device, name, defines):
    import pyopencl as cl

    found = cl.Kernel(device.program("gt_template.cl", dict(defines)), name)
    scalar_types(found, ARG_TYPES[name])
    return found


def _run(device, tf, rgb, depth, gray, dimg, camera, consts, outs, residuals, params, reuse=None, plan=None):
    """``params``: {"lanes", "work_group"}. ``reuse``: None, or (moved (J,) int32 buffer, sources): the cost of ``sources`` blocks of
    samples that pose the parts with moved[j] == 0 as their first sample does (kernels/gt_template.cl
    REUSE): one launch caches the sources, a second scores every sample from it. ``plan``: None, or
    (stride, order, moved) of a central-difference stack (gputrack/ops/pose_residuals.py, grouped by
    ``params["lanes"]``): one launch caches the problems' points, a second computes the residuals
    that the groups' rows move (REUSE=3). ``consts``: (lam, c_rgb, c_depth, depth_tol)."""
    nl = int(params["lanes"])
    wg = int(params["work_group"])
    nb, nj = tf.shape[:2]
    n = rgb["pts"].shape[0]
    m = depth["pts"].shape[0]
    h, w = gray.shape
    groups = (nb + nl - 1) // nl
    dummy = _buffer(device, "dummy", 4)
    order, ngroups = dummy, 0
    if plan is not None:
        stride, order_d, moved_d = plan
        groups = ngroups = order_d.shape[0] // nl  # the plan's groups of nl rows
        order = order_d.buffer.data
        reuse = (moved_d.buffer.data, nb // stride)
    sample = _buffer(device, "sample", groups * n * nl * 4)
    valid = _buffer(device, "valid", groups * n * nl)
    if residuals:
        res_buf = outs[0].buffer.data
        outs = (dummy, dummy, dummy)
    else:
        res_buf = dummy
        outs = tuple(o.buffer.data for o in outs)
    fx, fy, cx, cy = (float(c) for c in camera)
    moved, cache, sources = dummy, dummy, 0
    if reuse is not None:
        moved, sources = reuse
        cache = _buffer(device, "cache", sources * (2 * n + 3 * rgb["parts"] + depth["parts"]) * 4)
    args = (
        tf.buffer.data, nb, nj,
        rgb["pts"].buffer.data, rgb["index"].buffer.data, rgb["parts"], n,
        depth["pts"].buffer.data, depth["index"].buffer.data, depth["parts"], m,
        gray.buffer.data, dimg.buffer.data, h, w,
        fx, fy, cx, cy, *consts,
        sample, valid, outs[0], outs[1], outs[2], res_buf, moved, cache, sources, order, ngroups,
    )  # fmt: skip
    if reuse is not None:
        source = _kernel(device, "gt_rgbd", LANES=nl, RESIDUALS=0, REUSE=1)
        enqueue(device, source, *ndrange((sources + nl - 1) // nl, group=(wg,)), *args)  # a source per lane
    mode = 0 if reuse is None else (3 if plan is not None else 2)
    kernel = _kernel(device, "gt_rgbd", LANES=nl, RESIDUALS=int(residuals), REUSE=mode)
    enqueue(device, kernel, *ndrange(groups, group=(wg,)), *args)


def rgbd_cost(device, tf, rgb, depth, gray, dimg, camera, total, eps_c, eps_d, *, lam, c_rgb, c_depth, depth_tol,
              params=None, reuse=None):  # fmt: skip
    """``params``: {"lanes", "work_group"}; None = the tuned choice (TUNABLES["rgbd_cost"]).
    ``reuse``: see _run (the particle filter's cascade stages, gputrack/backends/opencl/pf.py)."""
    consts = (lam, c_rgb, c_depth, depth_tol)
    params = params or _tuned(device, "rgbd_cost", tf, rgb, depth)
    _run(device, tf, rgb, depth, gray, dimg, camera, consts, (total, eps_c, eps_d), False, params, reuse)


def rgbd_residuals(device, tf, rgb, depth, gray, dimg, camera, out, *, lam, c_rgb, c_depth, depth_tol, params=None,
                   plan=None):  # fmt: skip
    """``params``: {"lanes", "work_group"}; None = the tuned choice (TUNABLES["rgbd_residuals"]).
    ``plan``: see _run (gputrack/ops/pose_residuals.py; its groups of :func:`residual_lanes` rows)."""
    params = params or _tuned(device, "rgbd_residuals", tf, rgb, depth)
    _run(device, tf, rgb, depth, gray, dimg, camera, (lam, c_rgb, c_depth, depth_tol), (out,), True, params,
         plan=plan)  # fmt: skip


def residual_lanes(device, tf, rgb, depth) -> int:
    """The rows per work-item :func:`rgbd_residuals` takes for these sizes (the tuned choice): a
    central-difference plan groups its rows by it."""
    return int(_tuned(device, "rgbd_residuals", tf, rgb, depth)["lanes"])

"""OpenCL launchers for kernels/gt_template.cl: sparse-template cost/residuals and NCC patches.

One launch per op call. On CPU devices a work-item evaluates ``LANES`` hypotheses with explicit
vector types (the compiler maps them onto SIMD registers); on GPUs LANES = 1 (one work-item per
hypothesis). Conventions: gputrack/ops/template.py.
"""

from __future__ import annotations

import weakref

import numpy as np

import os

CPU_LANES = int(os.environ.get("GT_LANES", 8))
_scratch = weakref.WeakKeyDictionary()
_kernels = weakref.WeakKeyDictionary()


def lanes(device) -> int:
    """Hypotheses per work-item on ``device``."""
    return CPU_LANES if device.info.kind == "cpu" else 1


def _buffer(device, name, nbytes):
    """A scratch buffer of at least ``nbytes`` kept per device."""
    import pyopencl as cl

    per_device = _scratch.setdefault(device, {})
    found = per_device.get(name)
    if found is None or found.size < nbytes:
        found = cl.Buffer(device.context, cl.mem_flags.READ_WRITE, max(int(nbytes), 4))
        per_device[name] = found
    return found


def _kernel(device, name, **defines):
    """The kernel ``name`` of gt_template.cl built with ``defines`` (one cl.Kernel per device)."""
    import pyopencl as cl

    key = (name, tuple(sorted(defines.items())))
    per_device = _kernels.setdefault(device, {})
    found = per_device.get(key)
    if found is None:
        found = cl.Kernel(device.program("gt_template.cl", defines), name)
        per_device[key] = found
    return found


def _run(device, tf, rgb, depth, gray, dimg, camera, lam, c_rgb, c_depth, residuals):
    nl = lanes(device)
    kernel = _kernel(device, "gt_rgbd", LANES=nl, RESIDUALS=int(residuals))
    nb, nj = tf.shape[:2]
    n = rgb["pts"].shape[0]
    m = depth["pts"].shape[0]
    h, w = gray.shape
    groups = (nb + nl - 1) // nl
    sample = _buffer(device, "sample", groups * n * nl * 4)
    valid = _buffer(device, "valid", groups * n * nl)
    if residuals:
        res = device.empty((nb, n + m), np.float32)
        dummy = _buffer(device, "dummy", 4)
        outs = (dummy, dummy, dummy)
        res_buf = res.buffer.data
    else:
        res = tuple(device.empty((nb,), np.float32) for _ in range(3))
        outs = tuple(r.buffer.data for r in res)
        res_buf = _buffer(device, "dummy", 4)
    i32, f32 = np.int32, np.float32
    fx, fy, cx, cy = (f32(c) for c in camera)
    kernel(
        device.queue, (groups,), None,
        tf.buffer.data, i32(nb), i32(nj),
        rgb["pts"].buffer.data, rgb["start"].buffer.data, i32(rgb["start"].shape[0] - 1), i32(n), rgb["perm"].buffer.data,
        depth["pts"].buffer.data, depth["start"].buffer.data, i32(depth["start"].shape[0] - 1), i32(m), depth["perm"].buffer.data,
        gray.buffer.data, dimg.buffer.data, i32(h), i32(w),
        fx, fy, cx, cy, f32(lam), f32(c_rgb), f32(c_depth),
        sample, valid, outs[0], outs[1], outs[2], res_buf,
    )  # fmt: skip
    return res


def rgbd_cost(device, tf, rgb, depth, gray, dimg, camera, *, lam, c_rgb, c_depth):
    return _run(device, tf, rgb, depth, gray, dimg, camera, lam, c_rgb, c_depth, False)


def rgbd_residuals(device, tf, rgb, depth, gray, dimg, camera, *, lam, c_rgb, c_depth):
    return _run(device, tf, rgb, depth, gray, dimg, camera, lam, c_rgb, c_depth, True)


def patch_ncc(device, pts, tpl, img, *, per_point):
    nb, nk = pts.shape[:2]
    s = tpl.shape[1]
    h, w = img.shape
    i32 = np.int32
    args = (pts.buffer.data, i32(nb), i32(nk), tpl.buffer.data, i32(s), img.buffer.data, i32(h), i32(w))
    if per_point:
        out = device.empty((nb, nk), np.float32)
        _kernel(device, "gt_patch_ncc_points", LANES=1, RESIDUALS=0)(device.queue, (nb * nk,), None, *args, out.buffer.data)
    else:
        out = device.empty((nb,), np.float32)
        _kernel(device, "gt_patch_ncc", LANES=1, RESIDUALS=0)(device.queue, (nb,), None, *args, out.buffer.data)
    return out

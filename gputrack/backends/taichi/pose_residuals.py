"""Taichi: pose residuals (gputrack/ops/pose_residuals.py) as one kernel launch.

The kernel runs its tasks in order (Taichi finishes one before the next). A plain call poses every
parameter vector (eq. 1-11; on the calling thread for up to SERIAL_ROWS rows on a CPU), then
evaluates the residuals (eq. 20-21, template.py's kernel body, one parallel loop). A
central-difference stack (a plan from the op): one serial task poses each problem's point and
evaluates it once to cache its per-part sums (template.py's re-use); then one parallel loop in
which each group of lanes takes rows that move the same parts (the plan), poses them, flags a row
that differs from its problem's point in more than its own parameter, and projects and writes only
the parts its rows move (all of them for a flagged row). Posing inside the parallel loop instead of
in a serial task first: the serial task of a B=10, P=20 stack 0.106 -> 0.056 ms (kernel profiler
minimum, taichi:cpu, 2026-11-23); its problems' points taken as lane vectors, L at a time:
0.050-0.054 -> 0.024-0.028 ms (2026-11-24).
"""

from .kinematics import pose_f32
from .launch import launch
from .runtime import scratch, ti
from .tasks import CPU_TASK, chunk, cpu_chunks
from .template import F1, F2, F4, I1, I2, REUSE_SPARSE, _rgbd_body, _source_cache, cam_array, default_params

#: on the CPU, up to this many rows are posed on the calling thread (~0.15 us a row for the upper
#: body; a parallel loop's dispatch costs ~60 us)
SERIAL_ROWS = 1024


@ti.func
def _pose_row(params: ti.template(), offsets: ti.template(), tf: ti.template(), full: ti.template(), b,
              chain: ti.template(), stride: ti.template()):  # fmt: skip
    """Pose row b (eq. 1-11); in a central-difference stack, flag it when it differs from its
    problem's point in more than its own parameter."""
    pose_f32(params, b, chain, offsets, tf)
    if ti.static(stride > 0):
        s = b % stride  # row s of its problem's block: 0 the point, 1 + 2k and 2 + 2k parameter k moved
        k = (s - 1) // 2
        bad = 0
        for q in range(params.shape[1]):
            if s > 0 and q != k and params[b, q] != params[b - s, q]:
                bad = 1  # not the promised layout: evaluate the row in full
        full[b] = bad


@ti.kernel
def _pose_residuals(
    params: F2, offsets: F2, tf: F4, rpts: F2, ridx: I1, dpts: F2, didx: I1, gray: F2, dimg: F2, cam: F1, work: F2,
    residuals: F2, moved: I2, order: I1, full: I1, cache: F2, groups: ti.i32,
    rparts: ti.template(), dparts: ti.template(), L: ti.template(), chunks: ti.template(),
    chain: ti.template(), stride: ti.template(), serial: ti.template(),
):  # fmt: skip
    n = params.shape[0]
    if ti.static(stride > 0):  # each group poses its own rows (the problems' points first, for the cache)
        pose = ti.static((_pose_hook, (params, offsets, tf, full, chain, stride)))
        _source_cache(tf, rpts, ridx, rparts, dpts, didx, dparts, gray, dimg, cam, cache, chunks > 0, stride, L,
                      pose)  # fmt: skip
        _rgbd_body(tf, rpts, ridx, rparts, dpts, didx, dparts, gray, dimg, cam, work, residuals, residuals, residuals,
                   residuals, groups, True, L, chunks, REUSE_SPARSE, moved, cache, order, full, stride,
                   pose)  # fmt: skip
    else:
        if ti.static(serial):  # a few hundred rows: cheaper on the calling thread than dispatched
            ti.loop_config(serialize=True)
            for b in range(n):
                _pose_row(params, offsets, tf, full, b, chain, stride)
        else:
            for it in range(n if ti.static(chunks == 0) else chunks * CPU_TASK):
                b0, b1 = chunk(it, n, chunks)
                for b in range(b0, b1):
                    _pose_row(params, offsets, tf, full, b, chain, stride)
        _rgbd_body(tf, rpts, ridx, rparts, dpts, didx, dparts, gray, dimg, cam, work, residuals, residuals, residuals,
                   residuals, groups, True, L, chunks, 0, moved, cache, order, full, stride)  # fmt: skip


@ti.func
def _pose_hook(args: ti.template(), b):
    """_rgbd_body's pose hook: row b of a central-difference stack (see _pose_row)."""
    params, offsets, tf, full, chain, stride = ti.static(args)
    _pose_row(params, offsets, tf, full, b, chain, stride)


def lanes(device) -> int:
    """Rows per thread (the op's plan groups rows in multiples of it)."""
    return int(default_params(device)["lanes"])


def pose_residuals(device, chain, params, offsets, rgb, depth, gray, dimg, camera, out, plan, *, lam, c_rgb, c_depth,
                   depth_tol):  # fmt: skip
    """``plan``: None (every entry), or (stride, order, moved) on the device (gputrack/ops/pose_residuals.py)."""
    n = params.shape[0]
    J = chain.n_parts
    nl = lanes(device)
    nr = rgb["pts"].shape[0]
    if plan is None:  # the tables are not read: placeholders of the right types
        stride, groups = 0, (n + nl - 1) // nl
        order = full = scratch(device, "unused_i1", (1,), ti.i32)
        moved = scratch(device, "unused_i2", (1, 1), ti.i32)
        cache = scratch(device, "unused_f2", (1, 1), ti.f32)
    else:
        stride, order, moved = plan
        groups = order.shape[0] // nl
        order, moved = order.buffer, moved.buffer
        full = scratch(device, "pose_full", (n,), ti.i32)
        cache = scratch(device, "rgbd_cache", (max(n // stride, 1), 2 * nr + 4 * J), ti.f32)
    arrays = (
        params.buffer, offsets.buffer, scratch(device, "pose_tf", (n, J, 3, 4), ti.f32), rgb["pts"].buffer,
        rgb["index"].buffer, depth["pts"].buffer, depth["index"].buffer, gray.buffer, dimg.buffer,
        cam_array(camera, lam, c_rgb, c_depth, depth_tol), scratch(device, "rgbd", (groups, 2 * nr * nl), ti.f32),
        out.buffer,
        moved, order, full, cache,
    )  # fmt: skip
    chunks = cpu_chunks(device)
    serial = chunks > 0 and n <= SERIAL_ROWS
    consts = (rgb["parts"], depth["parts"], nl, chunks, chain.structure(), stride, serial)
    launch(_pose_residuals, arrays, consts, scalars=(groups,), scalarize=False, ir_passes=False)
    return out


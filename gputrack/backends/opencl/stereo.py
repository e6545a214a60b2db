"""OpenCL launchers of :mod:`gputrack.ops.stereo` (kernels/gt_stereo.cl; conventions in the op):
five launches, the steps of gputrack/backends/taichi/stereo.py (16 disparities a work-item in a
short16 for uint8 input, whose costs fit in 16 bits, 8 in an int8 for float32: the program is
built once per lane count). On CPU devices the costs are one work-item per (group, tile of runs),
carrying the window's column sums along, in work-groups of one work-item: the kernels vectorise
explicitly, and PoCL then builds each kernel once instead of once per work-group size it picks for
a new NDRange (3-4 s of the tests' time). On GPUs (:func:`per_pixel`), where a VGA frame's few
hundred tiles left the H100 idle (the matching ~19 ms of its 15 % frame), the costs are one
work-item per (pixel or marked right position, group) summing its window whole, and every kernel
runs in work-groups of GPU_GROUP work-items."""

from __future__ import annotations

import numpy as np

from ...device import per_device
from .program import enqueue, ndrange, scalar_types

#: disparities a work-item (gt_stereo.cl): 16 in a short16 for uint8 input (every cost fits in
#: 16 bits), 8 in an int8 for float32 input
LANES_U8, LANES = 16, 8

#: work-items per work-group of every stereo kernel on GPUs (on an H100: ``stereo_match`` 640x480 with a
#: 15 % mask in 3.09 ms; other sizes not tried)
GPU_GROUP = 64

_I = np.int32
ARG_TYPES = {
    "gt_stereo_prefilter_u8": [None, None, None, None, None, _I, _I, _I, _I, _I, _I],
    "gt_stereo_prefilter_f32": [None, None, None, None, None, _I, _I, _I, _I, _I, _I],
    "gt_stereo_left_costs": [None, None, None, None, None, None, None, _I, _I, _I, _I],
    "gt_stereo_left_wta": [None, None, None, None, None, None, None, None, _I, _I, _I, _I],
    "gt_stereo_right_costs": [None, None, None, None, None, None, None, None, None, _I, _I, _I, _I],
    "gt_stereo_right_check": [None, None, None, None, _I, _I, _I, _I],
    "gt_stereo_left_costs_px": [None, None, None, None, _I, _I, _I, _I, _I],
    "gt_stereo_right_costs_px": [None, None, None, None, None, _I, _I, _I, _I, _I],
}


def per_pixel(device) -> bool:
    """Whether the costs run a work-item per pixel and disparity group (GPUs) rather than per tile
    of runs and group (CPU devices)."""
    return device.info.kind != "cpu"


def needs_tiles(device) -> bool:
    """Whether the costs read the runs' tiles (:func:`gputrack.ops.stereo.run_tiles`): the per-tile
    layout only (the per-pixel one gets none)."""
    return not per_pixel(device)


@per_device
def _kernel(device, name, lanes=LANES):
    import pyopencl as cl

    found = cl.Kernel(device.program("gt_stereo.cl", {"GT_STEREO_LANES": lanes}), name)
    scalar_types(found, ARG_TYPES[name])
    return found


def _capacity(n: int) -> int:
    """``n`` rounded up to 4 significant bits (at most 1/8 more): few buffer shapes for the pool."""
    step = 1 << max(int(n).bit_length() - 4, 0)
    return -(-int(n) // step) * step


def stereo_match(device, L, R, mask, runs, tiles, D, block, U, cap, out):
    H, W = L.shape
    S = len(runs)
    nl = LANES_U8 if L.dtype == np.uint8 else LANES
    size = 2 if nl == LANES_U8 else 4  # bytes of the prefiltered values, sums and costs (short or int)

    def ints(n):  # n of them, as a byte buffer (the device's arrays have no 16-bit dtype)
        return device.empty((n * size,), np.uint8)

    G = -(-D // nl)
    Dp = G * nl
    Wp = W + Dp + 2 * nl
    y0, y1 = (int(runs[0, 0]) - block // 2, int(runs[-1, 0]) + block // 2 + 1) if S else (0, 0)  # rows read
    pl, pr = ints(H * Wp), ints(H * Wp)
    name = "gt_stereo_prefilter_u8" if L.dtype == np.uint8 else "gt_stereo_prefilter_f32"
    gpu = per_pixel(device)
    rows = ndrange(H, group=(GPU_GROUP,)) if gpu else ((H,), (1,))
    enqueue(device, _kernel(device, name, nl), *rows, L.buffer.data, R.buffer.data, pl.buffer.data, pr.buffer.data,
            out.buffer.data, H, W, Wp, cap, y0, y1)  # fmt: skip
    if S == 0:
        return out
    tiles, order, run_tile = tiles
    T = len(tiles)
    P = int(runs[-1, 2] - runs[-1, 1] + 1 + runs[-1, 3])
    Vn = int(tiles[-1, 6] + tiles[-1, 7]) if T else 0  # column sums of every tile
    Sc, Tc, Pc, P2c, Vc = (_capacity(max(n, 1)) for n in (S, T, P, P + S * (D - 1), Vn))
    runs_host = np.zeros((Sc, 5), np.int32)
    runs_host[:S] = runs
    tiles_host = np.zeros((Tc, 8), np.int32)
    tiles_host[:T] = tiles
    order_host, run_tile_host = np.zeros(Sc, np.int32), np.zeros(Sc, np.int32)
    order_host[:S], run_tile_host[:S] = order, run_tile
    marked = np.empty((Tc, 2), np.int32)
    marked[:, 0], marked[:, 1] = W, -1  # no marked position yet
    runs_d, tiles_d, order_d, run_tile_d, marked_d = (
        device.asarray(a) for a in (runs_host, tiles_host, order_host, run_tile_host, marked))
    mask_d = device.asarray(mask if mask is not None else np.ones((H, W), np.uint8))
    cost, rcost = ints(Pc * Dp), ints(P2c * Dp)
    ldisp = device.empty((Pc,), np.int32)
    rmark = device.empty((P2c,), np.int32)
    b = lambda a: a.buffer.data
    per_run = ndrange(S, group=(GPU_GROUP,)) if gpu else ((S,), (1,))
    if gpu:
        P2 = P + S * (D - 1)  # the runs' right positions (each run's x1 - x0 + D)
        enqueue(device, _kernel(device, "gt_stereo_left_costs_px", nl), *ndrange(P, G, group=(GPU_GROUP, 1)), b(pl),
                b(pr), b(runs_d), b(cost), S, P, D, block, Wp)  # fmt: skip
    else:
        vsum = ints(Vc * Dp)
        enqueue(device, _kernel(device, "gt_stereo_left_costs", nl), (G, T), (1, 1), b(pl), b(pr), b(runs_d),
                b(tiles_d), b(order_d), b(vsum), b(cost), T, D, block, Wp)  # fmt: skip
    enqueue(device, _kernel(device, "gt_stereo_left_wta", nl), *per_run, b(runs_d), b(mask_d), b(cost), b(ldisp),
            b(rmark), b(run_tile_d), b(marked_d), b(out), S, D, U, W)  # fmt: skip
    if gpu:
        enqueue(device, _kernel(device, "gt_stereo_right_costs_px", nl), *ndrange(P2, G, group=(GPU_GROUP, 1)), b(pl),
                b(pr), b(runs_d), b(rmark), b(rcost), S, P2, D, block, Wp)  # fmt: skip
    else:
        enqueue(device, _kernel(device, "gt_stereo_right_costs", nl), (G, T), (1, 1), b(pl), b(pr), b(runs_d),
                b(tiles_d), b(order_d), b(marked_d), b(rmark), b(vsum), b(rcost), T, D, block, Wp)  # fmt: skip
    enqueue(device, _kernel(device, "gt_stereo_right_check", nl), *per_run, b(runs_d), b(ldisp), b(rcost), b(out), S,
            D, block, W)  # fmt: skip
    return out

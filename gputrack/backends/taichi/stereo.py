"""Taichi kernels of :mod:`gputrack.ops.stereo` (conventions there): one launch, five loops.

1. Every pixel: the prefiltered integer images (x-Sobel clipped to [-cap, cap], plus cap), kept
   with LANES columns of padding on the left and max_disparity + LANES on the right (so that a
   lane of a disparity group past max_disparity reads inside the array), and a NaN in the output.
2. One thread per (run of the mask, group of LANES disparities): the left costs C(x, d) along
   the run as running box sums (the column sum entering the window replaces the one leaving,
   kept in a ring of the window's block column sums: (block + 2) operations per pixel and
   disparity, not block^2), LANES disparities at once in an integer vector (SIMD on the CPU:
   compiled with ``scalarize=False``), into a cost buffer (pixel, d).
3. One thread per run: winner, uniqueness, parabola vertex; the right-image position x - d of
   each winner is marked.
4. One thread per (run, group): the right image's costs C_R(x_r, d') = C(x_r + d', d') at the
   marked positions only, the same way (running along consecutive marked positions, restarted
   after a gap).
5. One thread per run: the right winners and the left-right check.

Measured on the 2-core VM (taichi:cpu, VGA, 100 runs of 100 pixels, left costs only): 40 ms with
one scalar thread per (run, d) and 2-D indexing, 17 ms with flat indexing, 5.3 ms with 8-lane
vectors (16 lanes: 9.7 ms).
"""

import math

import numpy as np

from .launch import launch
from .runtime import scratch, ti

BIG = np.iinfo(np.int32).max // 4


#: disparities per thread (an 8 x int32 vector: one AVX2 register)
LANES = 8
V = ti.types.vector(LANES, ti.i32)


@ti.func
def _q(v, is_float: ti.template()):
    q = 0
    if ti.static(is_float):
        q = ti.cast(ti.floor(ti.min(ti.max(v, 0.0), 1.0) * 4096.0), ti.i32)  # exact: * 2^12
    else:
        q = ti.cast(v, ti.i32)
    return q


@ti.func
def _sobel(img: ti.template(), y, x, cap, is_float: ti.template()):
    h, w = img.shape[0], img.shape[1]
    p = cap
    if y >= 1 and y < h - 1 and x >= 1 and x < w - 1:
        s = (_q(img[y - 1, x + 1], is_float) + 2 * _q(img[y, x + 1], is_float) + _q(img[y + 1, x + 1], is_float)) - (
            _q(img[y - 1, x - 1], is_float) + 2 * _q(img[y, x - 1], is_float) + _q(img[y + 1, x - 1], is_float)
        )
        p = ti.min(ti.max(s, -cap), cap) + cap
    return p


@ti.kernel
def _stereo(left: ti.types.ndarray(ndim=2), right: ti.types.ndarray(ndim=2),
            pl: ti.types.ndarray(dtype=ti.i32, ndim=1), pr: ti.types.ndarray(dtype=ti.i32, ndim=1),
            mask: ti.types.ndarray(dtype=ti.u8, ndim=2), runs: ti.types.ndarray(dtype=ti.i32, ndim=2),
            ring: ti.types.ndarray(dtype=ti.i32, ndim=1), cost: ti.types.ndarray(dtype=ti.i32, ndim=1),
            rcost: ti.types.ndarray(dtype=ti.i32, ndim=1), ldisp: ti.types.ndarray(dtype=ti.i32, ndim=1),
            rmark: ti.types.ndarray(dtype=ti.i32, ndim=1), out: ti.types.ndarray(dtype=ti.f32, ndim=2),
            S: ti.i32, D: ti.i32, B: ti.i32, U: ti.i32, cap: ti.i32, Wp: ti.i32, nan: ti.f32,
            is_float: ti.template()):  # fmt: skip
    r = B // 2
    H, W = out.shape[0], out.shape[1]
    G = (D + LANES - 1) // LANES  # disparity groups
    Dp = G * LANES  # a pixel's slots in the cost buffers
    # 1. prefilter (padding: cap) and NaN
    for y, xp in ti.ndrange(H, Wp):
        x = xp - LANES
        a, b = cap, cap
        if x >= 0 and x < W:
            a = _sobel(left, y, x, cap, is_float)
            b = _sobel(right, y, x, cap, is_float)
            out[y, x] = nan
        pl[y * Wp + xp] = a
        pr[y * Wp + xp] = b
    # 2. left costs: C(x, d) = sum over the window of |P_L(x') - P_R(x' - d)|
    for s, g in ti.ndrange(S, G):
        y, x0, x1, off = runs[s, 0], runs[s, 1], runs[s, 2], runs[s, 3]
        d0 = g * LANES
        c = V(0)
        for x in range(x0 - r, x1 + r + 1):
            v = V(0)
            for i in range(B):
                at = (y - r + i) * Wp + LANES + x
                lv = pl[at]
                rv = V(0)
                for j in ti.static(range(LANES)):
                    rv[j] = pr[at - d0 - j]
                t = lv - rv
                v += ti.max(t, -t)
            ring_at = (s * B + x % B) * Dp + d0
            if x >= x0 + r + 1:  # column x - B, in the same ring slot, leaves the window
                for j in ti.static(range(LANES)):
                    c[j] -= ring[ring_at + j]
            c += v
            for j in ti.static(range(LANES)):
                ring[ring_at + j] = v[j]
            if x >= x0 + r:
                at = (off + x - r - x0) * Dp + d0
                for j in ti.static(range(LANES)):
                    cost[at + j] = c[j]
    # 3. left winners
    for s in range(S):
        y, x0, x1, off, roff = runs[s, 0], runs[s, 1], runs[s, 2], runs[s, 3], runs[s, 4]
        rlo = x0 - D + 1  # the run's first right-image position
        for k in range(x1 - x0 + D):
            rmark[roff + k] = 0
        for x in range(x0, x1 + 1):
            p = (off + x - x0) * Dp
            ld = -1
            if mask[y, x] != 0:
                best = 0
                cb = cost[p]
                for d in range(1, D):  # winner-take-all, the smallest d of equal costs
                    if cost[p + d] < cb:
                        cb = cost[p + d]
                        best = d
                unique = True
                for d in range(D):  # uniqueness
                    if ti.abs(d - best) > 1 and 100 * cost[p + d] <= (100 + U) * cb:
                        unique = False
                if unique:
                    val = ti.cast(best, ti.f32)
                    if best > 0 and best < D - 1:  # the parabola's vertex
                        cm = cost[p + best - 1]
                        cp = cost[p + best + 1]
                        val += ti.cast(cm - cp, ti.f32) / ti.cast(2 * (cm - 2 * cb + cp), ti.f32)
                    out[y, x] = val
                    ld = best
                    rmark[roff + x - best - rlo] = 1
            ldisp[off + x - x0] = ld
    # 4. right costs at the marked positions: C_R(xr, d) = sum |P_L(x' + d) - P_R(x')|
    #    (garbage but in bounds where x' + d >= W: such d are not candidates)
    for s, g in ti.ndrange(S, G):
        y, x0, x1, roff = runs[s, 0], runs[s, 1], runs[s, 2], runs[s, 4]
        rlo = x0 - D + 1
        d0 = g * LANES
        c = V(0)
        last = -(1 << 30)
        for k in range(x1 - x0 + D):
            if rmark[roff + k] != 0:
                xr = rlo + k
                running = xr == last + 1
                first = xr - r  # the columns to add: the whole window after a gap, else one
                if running:
                    first = xr + r
                else:
                    c = V(0)
                for x in range(first, xr + r + 1):
                    v = V(0)
                    for i in range(B):
                        at = (y - r + i) * Wp + LANES + x
                        rv = pr[at]
                        lv = V(0)
                        for j in ti.static(range(LANES)):
                            lv[j] = pl[at + d0 + j]
                        t = lv - rv
                        v += ti.max(t, -t)
                    ring_at = (s * B + x % B) * Dp + d0
                    if running:
                        for j in ti.static(range(LANES)):
                            c[j] -= ring[ring_at + j]
                    c += v
                    for j in ti.static(range(LANES)):
                        ring[ring_at + j] = v[j]
                at = (roff + k) * Dp + d0
                for j in ti.static(range(LANES)):
                    rcost[at + j] = c[j]
                last = xr
    # 5. right winners (d' whose left window is inside the image, the smallest of equal costs)
    #    and the left-right check
    for s in range(S):
        y, x0, x1, off, roff = runs[s, 0], runs[s, 1], runs[s, 2], runs[s, 3], runs[s, 4]
        rlo = x0 - D + 1
        for x in range(x0, x1 + 1):
            ld = ldisp[off + x - x0]
            if ld >= 0:
                xr = x - ld
                q = (roff + xr - rlo) * Dp
                best = 0
                cb = rcost[q]
                for d in range(1, ti.min(D, W - r - xr)):
                    if rcost[q + d] < cb:
                        cb = rcost[q + d]
                        best = d
                if ti.abs(best - ld) > 1:
                    out[y, x] = nan


def _capacity(n: int) -> int:
    return 1 << max(int(n) - 1, 0).bit_length()  # the next power of two: few scratch shapes


def stereo_match(device, L, R, mask, runs, D, block, U, cap, out):
    H, W = L.shape
    S = len(runs)
    Dp = -(-D // LANES) * LANES
    Wp = W + Dp + 2 * LANES
    P = int(runs[-1, 2] - runs[-1, 1] + 1 + runs[-1, 3]) if S else 0
    Sc, Pc, P2c = _capacity(max(S, 1)), _capacity(max(P, 1)), _capacity(max(P + S * (D - 1), 1))
    runs_host = np.zeros((Sc, 5), np.int32)
    runs_host[:S] = runs
    runs_d = device.asarray(runs_host)  # pooled: one shape per capacity
    mask_d = device.asarray(mask if mask is not None else np.ones((H, W), np.uint8))
    i32 = ti.i32
    arrays = (L.buffer, R.buffer, scratch(device, "stereo pl", (H * Wp,), i32),
              scratch(device, "stereo pr", (H * Wp,), i32), mask_d.buffer, runs_d.buffer,
              scratch(device, "stereo ring", (Sc * block * Dp,), i32), scratch(device, "stereo cost", (Pc * Dp,), i32),
              scratch(device, "stereo rcost", (P2c * Dp,), i32), scratch(device, "stereo ldisp", (Pc,), i32),
              scratch(device, "stereo rmark", (P2c,), i32), out.buffer)  # fmt: skip
    scalars = (S, int(D), int(block), int(U), int(cap), Wp, math.nan)
    launch(_stereo, arrays, (L.dtype == np.float32,), scalars=scalars, scalarize=False)
    return out

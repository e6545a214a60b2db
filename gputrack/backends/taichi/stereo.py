"""Taichi kernels of :mod:`gputrack.ops.stereo` (conventions there): one launch, five loops.

1. NaN into the output; on the rows the runs' windows read, a row per thread: the prefiltered
   integer images (x-Sobel clipped to [-cap, cap], plus cap; LANES columns at a time as vectors),
   kept with LANES columns of padding on the left and max_disparity + LANES on the right (so that
   a lane of a disparity group past max_disparity reads inside the array).
2. One thread per (tile of runs, group of LANES disparities) (gputrack/ops/stereo.py
   ``run_tiles``: the runs of a band of 16 rows whose column ranges touch): the window column
   sums V(x) = sum over the window's rows of |P_L(x) - P_R(x - d)| over the tile's columns,
   carried down its rows (the row entering added, the one leaving subtracted: 2 absolute
   differences per column and row, not block), then running box sums along each run of the row
   (2 additions per pixel), LANES disparities at once in an integer vector (SIMD on the CPU:
   compiled with ``scalarize=False``; 16 int16 lanes for uint8 input on the CPU archs, 8 int32
   lanes otherwise, :func:`lanes`), into a cost buffer (pixel, d). A row's right-image pixels of
   the group, P_R(x - d0), ..., P_R(x - d0 - LANES + 1), are one vector that slides along the
   columns: one load and a lane shift a column.
3. One thread per run: winner, uniqueness, parabola vertex; the right-image position x - d of
   each winner is marked.
4. One thread per (tile, group): the right image's costs C_R(x_r, d') = C(x_r + d', d') the same
   way over the columns of the tile's marked span (its smallest and largest marked position,
   gathered by atomic min / max in 3), stored at the marked positions only; the left-image
   pixels P_L(x + d0), ..., P_L(x + d0 + LANES - 1) slide the same way.
5. One thread per run: the right winners and the left-right check.

On CUDA and on Vulkan on a GPU (:func:`per_pixel`) steps 2 and 4 are instead one thread per
(pixel of the runs, group) and per (marked right position, group), each summing its window whole
(the same integers): a VGA frame's few hundred tile threads left an H100 idle (~48 ms of matching
in the group benchmark's 15 % frame on taichi:cuda); per pixel, ``stereo_match`` on a 640x480 pair
with a 15 % mask took 5.45 ms there and the group frame's stereo stage 10 ms (perf/README.md).

On taichi:cpu the runs, tiles and mask are NumPy arrays the kernel reads in place (no copy
launches); elsewhere they are uploaded.

Measured on the 2-core VM (taichi:cpu, VGA, 100 runs of 100 pixels, left costs only, each column
sum over the window's 9 rows): 40 ms with one scalar thread per (run, d) and 2-D indexing, 17 ms
with flat indexing, 5.1 ms with 8-lane vectors gathered by 8 scalar loads (16 lanes: 9.7 ms),
1.7 ms with each pixel's neighbourhood vector stored beforehand (up to 2026-11-27: 32 bytes a
pixel and image, ~23 MB written a VGA call). Carrying the column sums down the tiles' rows then
took the left costs of the benchmark's masked VGA pair from ~17-21 to ~12 ms (mean of 5, loaded
VM). 16 int16 lanes instead of 8 int32 (uint8 input, 2026-11-27, loaded VM, Taichi's kernel
profiler on the group benchmark's pair with 17 % foreground): left costs 17.0 -> 7.0 ms, right
costs 18.7 -> 7.6 ms; the whole call 59 -> 40 ms of CPU time (median of 15, old and new
alternating). Sliding vectors instead of the stored neighbourhoods, the prefilter by vectors of
LANES columns and the tables read in place (2026-11-27, night, the same pair, kernel profiler,
two rounds in turn): the kernel's loops 14.9 / 11.8 -> 9.5 / 10.1 ms (mean), prefilter and
neighbourhoods 5.4-7.1 -> 1.1 ms (min), 8 -> 2 launches a call.
"""

import functools
import math

import numpy as np

from .launch import launch
from .runtime import current_arch, scratch, ti

BIG = np.iinfo(np.int32).max // 4


#: disparities per thread and their integer type: on the CPU archs with uint8 input, 16 int16
#: lanes (one AVX2 register; every uint8 cost fits: block <= 31 gives at most 961 x 30 = 28830);
#: otherwise 8 int32 lanes
LANES_U8_CPU, LANES = 16, 8


def lanes(is_float: bool) -> tuple:
    """(lanes, Taichi integer type) of the cost vectors for this input on the current arch."""
    if not is_float and current_arch() == "cpu":
        return LANES_U8_CPU, ti.i16
    return LANES, ti.i32


@ti.func
def _q(v, is_float: ti.template()):
    q = 0
    if ti.static(is_float):
        q = ti.cast(ti.floor(ti.min(ti.max(v, 0.0), 1.0) * 4096.0), ti.i32)  # exact: * 2^12
    else:
        q = ti.cast(v, ti.i32)
    return q


@ti.func
def _col(img: ti.template(), y, x, is_float: ti.template()):
    """The x-Sobel's column sum I(y - 1, x) + 2 I(y, x) + I(y + 1, x) (integer levels)."""
    return _q(img[y - 1, x], is_float) + 2 * _q(img[y, x], is_float) + _q(img[y + 1, x], is_float)


@ti.func
def _sobel(img: ti.template(), y, x, cap, is_float: ti.template()):
    """The prefiltered pixel (y, x) inside the image's border: the x-Sobel clipped to [-cap, cap], plus cap."""
    return ti.min(ti.max(_col(img, y, x + 1, is_float) - _col(img, y, x - 1, is_float), -cap), cap) + cap


@ti.func
def _run_of(runs: ti.template(), S, p, col: ti.template()):
    """The run holding slot p of the offsets in column col (3: pixels, 4: right positions): the
    last run whose offset is <= p (the offsets ascend with the runs)."""
    lo, hi = 0, S - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if runs[mid, col] <= p:
            lo = mid
        else:
            hi = mid - 1
    return lo


def per_pixel(device) -> bool:
    """Whether the costs run a thread per pixel and disparity group (CUDA, Vulkan on a GPU) rather
    than per tile of runs and group (the CPU archs, lavapipe)."""
    return device.arch == "cuda" or (device.arch == "vulkan" and device.info.kind == "gpu")


def needs_tiles(device) -> bool:
    """Whether the costs read the runs' tiles (:func:`gputrack.ops.stereo.run_tiles`): the per-tile
    layout only (the per-pixel one gets none)."""
    return not per_pixel(device)


@functools.lru_cache(maxsize=None)
def _kernel(LANES: int, T):
    """The stereo kernel with cost vectors of ``LANES`` integers of type ``T`` (module docstring)."""
    assert LANES in (8, 16), LANES
    V = ti.types.vector(LANES, T)
    VI = ti.types.vector(LANES, ti.i32)

    @ti.func
    def _argmin(c: ti.template(), at, n, G):
        """The smallest cost among c[at .. at + G) (vectors of LANES costs, d = LANES g + lane) over
        d < n, and the smallest d that has it."""
        best = VI(BIG)
        idx = VI(0)
        lane = VI([j for j in range(LANES)])
        for g in range(G):
            v = ti.cast(c[at + g], ti.i32)
            d = lane + g * LANES
            take = (v < best) & (d < n)  # strict: each lane keeps its smallest d
            best = ti.select(take, v, best)
            idx = ti.select(take, d, idx)
        cb = _hmin(best)  # across the lanes: the smallest cost, then the smallest d among its lanes
        return cb, _hmin(ti.select(best == cb, idx, VI(BIG)))

    @ti.func
    def _hmin(v):
        """The smallest lane of the integer vector v (LANES 8 or 16), by halves: no branches."""
        a = ti.Vector([ti.min(v[j], v[j + LANES // 2]) for j in ti.static(range(LANES // 2))])
        b = ti.Vector([ti.min(a[j], a[j + LANES // 4]) for j in ti.static(range(LANES // 4))])
        c = ti.Vector([ti.min(b[j], b[j + LANES // 8]) for j in ti.static(range(LANES // 8))])
        m = c[0]
        if ti.static(LANES == 16):
            m = ti.min(c[0], c[1])
        return m

    @ti.func
    def _sobel_lanes(img: ti.template(), p: ti.template(), y, x0, at, cap, is_float: ti.template()):
        """p[at + l] = the clipped x-Sobel of img at (y, x0 + l) plus cap, l < LANES."""
        s = VI([_col(img, y, x0 + 1 + j, is_float) - _col(img, y, x0 - 1 + j, is_float)
                for j in ti.static(range(LANES))])  # fmt: skip
        v = ti.min(ti.max(s, -cap), cap) + cap
        for j in ti.static(range(LANES)):
            p[at + j] = ti.cast(v[j], T)

    @ti.func
    def _right_lanes(p: ti.template(), at):
        """P_R(at), P_R(at - 1), ..., P_R(at - LANES + 1) as a vector (lane l: disparity d0 + l)."""
        return V([p[at - j] for j in ti.static(range(LANES))])

    @ti.func
    def _right_slide(v, nxt):
        """The vector of _right_lanes one column on: P_R(at + 1) in lane 0, the others one lane up."""
        return V([nxt] + [v[j] for j in ti.static(range(LANES - 1))])

    @ti.func
    def _left_lanes(p: ti.template(), at):
        """P_L(at), P_L(at + 1), ..., P_L(at + LANES - 1) as a vector (lane l: disparity d0 + l)."""
        return V([p[at + j] for j in ti.static(range(LANES))])

    @ti.func
    def _left_slide(v, nxt):
        """The vector of _left_lanes one column on: the others one lane down, P_L(at + LANES) last."""
        return V([v[j + 1] for j in ti.static(range(LANES - 1))] + [nxt])

    @ti.kernel
    def _stereo(left: ti.types.ndarray(ndim=2), right: ti.types.ndarray(ndim=2),
                pl: ti.types.ndarray(dtype=T, ndim=1), pr: ti.types.ndarray(dtype=T, ndim=1),
                mask: ti.types.ndarray(dtype=ti.u8, ndim=2), runs: ti.types.ndarray(dtype=ti.i32, ndim=2),
                tiles: ti.types.ndarray(dtype=ti.i32, ndim=2), order: ti.types.ndarray(dtype=ti.i32, ndim=1),
                run_tile: ti.types.ndarray(dtype=ti.i32, ndim=1), marked: ti.types.ndarray(dtype=ti.i32, ndim=2),
                vsum: ti.types.ndarray(dtype=V, ndim=1),
                cost: ti.types.ndarray(dtype=V, ndim=1),
                rcost: ti.types.ndarray(dtype=V, ndim=1), ldisp: ti.types.ndarray(dtype=ti.i32, ndim=1),
                rmark: ti.types.ndarray(dtype=ti.i32, ndim=1), out: ti.types.ndarray(dtype=ti.f32, ndim=2),
                S: ti.i32, NB: ti.i32, D: ti.i32, B: ti.i32, U: ti.i32, cap: ti.i32, Wp: ti.i32, y0: ti.i32, y1: ti.i32,
                nan: ti.f32, P: ti.i32, P2: ti.i32, is_float: ti.template(), per_px: ti.template()):  # fmt: skip
        r = B // 2
        W = out.shape[1]
        G = (D + LANES - 1) // LANES  # disparity groups: a pixel's vectors in the cost buffers
        # 1. NaN; the prefilter (padding: cap) of the rows the windows read (parallel over rows,
        # serial along them: a 2-D parallel loop divides per element)
        for y in range(out.shape[0]):
            for x in range(W):
                out[y, x] = nan
        for yy in range(y1 - y0):  # a row per thread
            y = y0 + yy
            row = y * Wp
            pad = ti.cast(cap, T)
            inner = y >= 1 and y < left.shape[0] - 1 and W >= 3
            for xp in range(Wp):  # the padding, and the image's border (no x-Sobel there)
                if not inner or xp <= LANES or xp >= LANES + W - 1:
                    pl[row + xp] = pad
                    pr[row + xp] = pad
            if inner:
                # the x-Sobel of columns 1..W-2, LANES columns at a time as vectors (their loads
                # consecutive), the rest one by one
                nv = (W - 2) // LANES
                for c in range(nv):
                    x0 = 1 + c * LANES
                    _sobel_lanes(left, pl, y, x0, row + LANES + x0, cap, is_float)
                    _sobel_lanes(right, pr, y, x0, row + LANES + x0, cap, is_float)
                for x in range(1 + nv * LANES, W - 1):
                    pl[row + LANES + x] = ti.cast(_sobel(left, y, x, cap, is_float), T)
                    pr[row + LANES + x] = ti.cast(_sobel(right, y, x, cap, is_float), T)
        # 2. left costs. per_px: one thread per (pixel of the runs, group), its window summed whole.
        #    Else one thread per (tile, group): the window column sums
        #    V(x) = sum over the window's rows of |P_L(x) - P_R(x - d)| of the tile's columns, carried
        #    down its rows (the row entering added, the one leaving subtracted), then running box sums
        #    along each run of the row: C(x, d) = C(x - 1, d) + V(x + r) - V(x - r - 1)
        if ti.static(per_px):
            for p, g in ti.ndrange(P, G):
                s = _run_of(runs, S, p, 3)
                y, x, d0 = runs[s, 0], runs[s, 1] + p - runs[s, 3], g * LANES
                c = V(0)
                for k in range(B):
                    row = (y - r + k) * Wp + LANES + x - r
                    for m in range(B):
                        t = pl[row + m] - _right_lanes(pr, row + m - d0)  # lane l: P_L(x) - P_R(x - d0 - l)
                        c += ti.max(t, -t)
                cost[p * G + g] = c
        else:
            for b, g in ti.ndrange(NB, G):
                by0, by1, xa, xb, i0, i1, voff, w = (tiles[b, 0], tiles[b, 1], tiles[b, 2], tiles[b, 3], tiles[b, 4],
                                                   tiles[b, 5], tiles[b, 6], tiles[b, 7])  # fmt: skip
                d0 = g * LANES
                vb = voff * G + g * w  # this thread's column sums
                first = xa - r
                i = i0
                n = xb - xa + 2 * r + 1
                for y in range(by0, by1 + 1):
                    if y == by0:  # the window's B rows, a pass along the columns each
                        for j in range(n):
                            vsum[vb + j] = V(0)
                        for k in range(B):
                            at = (y - r + k) * Wp + LANES + first
                            pv = _right_lanes(pr, at - d0)
                            for j in range(n):
                                if j > 0:
                                    pv = _right_slide(pv, pr[at + j - d0])
                                t = pl[at + j] - pv  # lane l: P_L(x) - P_R(x - d0 - l)
                                vsum[vb + j] = vsum[vb + j] + ti.max(t, -t)
                    else:  # the row entering added, the one leaving subtracted
                        add, sub = (y + r) * Wp + LANES + first, (y - r - 1) * Wp + LANES + first
                        pa, ps = _right_lanes(pr, add - d0), _right_lanes(pr, sub - d0)
                        for j in range(n):
                            if j > 0:
                                pa = _right_slide(pa, pr[add + j - d0])
                                ps = _right_slide(ps, pr[sub + j - d0])
                            t1 = pl[add + j] - pa
                            t2 = pl[sub + j] - ps
                            vsum[vb + j] = vsum[vb + j] + ti.max(t1, -t1) - ti.max(t2, -t2)
                    while i < i1 and runs[order[i], 0] == y:
                        q = order[i]
                        x0, x1, off = runs[q, 1], runs[q, 2], runs[q, 3]
                        c = V(0)
                        for k in range(B):
                            c += vsum[vb + x0 - r - first + k]
                        cost[off * G + g] = c
                        for x in range(x0 + 1, x1 + 1):
                            c += vsum[vb + x + r - first] - vsum[vb + x - r - 1 - first]
                            cost[(off + x - x0) * G + g] = c
                        i += 1
        # 3. left winners
        for s in range(S):
            y, x0, x1, off, roff = runs[s, 0], runs[s, 1], runs[s, 2], runs[s, 3], runs[s, 4]
            rlo = x0 - D + 1  # the run's first right-image position
            for k in range(x1 - x0 + D):
                rmark[roff + k] = 0
            mlo, mhi = W, -1  # the run's marked right-image positions
            for x in range(x0, x1 + 1):
                p = (off + x - x0) * G
                ld = -1
                if mask[y, x] != 0:
                    cb, best = _argmin(cost, p, D, G)  # winner-take-all, the smallest d of equal costs
                    rival = VI(0)  # uniqueness: a d more than 1 px away within (100 + U) % of the best
                    lane = VI([j for j in range(LANES)])
                    for g in range(G):
                        d = lane + g * LANES
                        c = ti.cast(cost[p + g], ti.i32)
                        rival |= ((d < best - 1) | (d > best + 1)) & (d < D) & (100 * c <= (100 + U) * cb)
                    if _hmin(ti.select(rival == 0, VI(1), VI(0))) == 1:  # no lane found a rival
                        val = ti.cast(best, ti.f32)
                        if best > 0 and best < D - 1:  # the parabola's vertex
                            cm = ti.cast(cost[p + (best - 1) // LANES][(best - 1) % LANES], ti.i32)
                            cp = ti.cast(cost[p + (best + 1) // LANES][(best + 1) % LANES], ti.i32)
                            val += ti.cast(cm - cp, ti.f32) / ti.cast(2 * (cm - 2 * cb + cp), ti.f32)
                        out[y, x] = val
                        ld = best
                        rmark[roff + x - best - rlo] = 1
                        mlo = ti.min(mlo, x - best)
                        mhi = ti.max(mhi, x - best)
                ldisp[off + x - x0] = ld
            if mlo <= mhi:  # the tile's marked span, for the right costs
                ti.atomic_min(marked[run_tile[s], 0], mlo)
                ti.atomic_max(marked[run_tile[s], 1], mhi)
        # 4. right costs at the marked positions, the same ways: per_px, a thread per (right position
        #    of the runs, group) that is marked. Else V(x) = sum over the window's rows of
        #    |P_L(x + d) - P_R(x)| over the columns of the tile's marked span (garbage but in bounds
        #    where x + d >= W: such d are not candidates), C_R(xr, d) running along each run's
        #    positions in that span
        if ti.static(per_px):
            for q, g in ti.ndrange(P2, G):
                if rmark[q] != 0:
                    s = _run_of(runs, S, q, 4)
                    y, xr, d0 = runs[s, 0], runs[s, 1] - D + 1 + q - runs[s, 4], g * LANES
                    c = V(0)
                    for k in range(B):
                        row = (y - r + k) * Wp + LANES + xr - r
                        for m in range(B):
                            t = _left_lanes(pl, row + m + d0) - pr[row + m]  # lane l: P_L(xr + d0 + l) - P_R(xr)
                            c += ti.max(t, -t)
                    rcost[q * G + g] = c
        else:
            for b, g in ti.ndrange(NB, G):
                by0, by1, xa, i0, i1, voff, w = (tiles[b, 0], tiles[b, 1], tiles[b, 2], tiles[b, 4], tiles[b, 5],
                                                 tiles[b, 6], tiles[b, 7])  # fmt: skip
                mlo, mhi = marked[b, 0], marked[b, 1]
                d0 = g * LANES
                vb = voff * G + g * w
                first = xa - D + 1 - r  # column sums cover [first, first + w); those of [mlo - r, mhi + r] are used
                i = i0
                jlo, jhi = mlo - r - first, mhi + r - first
                for y in range(by0, by1 + 1):
                    if mlo <= mhi and y == by0:
                        for j in range(jlo, jhi + 1):
                            vsum[vb + j] = V(0)
                        for k in range(B):
                            at = (y - r + k) * Wp + LANES + first
                            pv = _left_lanes(pl, at + jlo + d0)
                            for j in range(jlo, jhi + 1):
                                if j > jlo:
                                    pv = _left_slide(pv, pl[at + j + d0 + LANES - 1])
                                t = pv - pr[at + j]  # lane l: P_L(x + d0 + l) - P_R(x)
                                vsum[vb + j] = vsum[vb + j] + ti.max(t, -t)
                    elif mlo <= mhi:
                        add, sub = (y + r) * Wp + LANES + first, (y - r - 1) * Wp + LANES + first
                        pa, ps = _left_lanes(pl, add + jlo + d0), _left_lanes(pl, sub + jlo + d0)
                        for j in range(jlo, jhi + 1):
                            if j > jlo:
                                pa = _left_slide(pa, pl[add + j + d0 + LANES - 1])
                                ps = _left_slide(ps, pl[sub + j + d0 + LANES - 1])
                            t1 = pa - pr[add + j]
                            t2 = ps - pr[sub + j]
                            vsum[vb + j] = vsum[vb + j] + ti.max(t1, -t1) - ti.max(t2, -t2)
                    while i < i1 and runs[order[i], 0] == y:
                        q = order[i]
                        x0, x1, roff = runs[q, 1], runs[q, 2], runs[q, 4]
                        rlo = x0 - D + 1
                        k0, k1 = ti.max(0, mlo - rlo), ti.min(x1 - x0 + D - 1, mhi - rlo)
                        if k0 <= k1:
                            c = V(0)
                            for k in range(B):
                                c += vsum[vb + rlo + k0 - r - first + k]
                            for k in range(k0, k1 + 1):
                                xr = rlo + k
                                if k > k0:
                                    c += vsum[vb + xr + r - first] - vsum[vb + xr - r - 1 - first]
                                if rmark[roff + k] != 0:
                                    rcost[(roff + k) * G + g] = c
                        i += 1
        # 5. right winners (d' whose left window is inside the image, the smallest of equal costs)
        #    and the left-right check
        for s in range(S):
            y, x0, x1, off, roff = runs[s, 0], runs[s, 1], runs[s, 2], runs[s, 3], runs[s, 4]
            rlo = x0 - D + 1
            for x in range(x0, x1 + 1):
                ld = ldisp[off + x - x0]
                if ld >= 0:
                    xr = x - ld
                    cb, best = _argmin(rcost, (roff + xr - rlo) * G, ti.min(D, W - r - xr), G)
                    if ti.abs(best - ld) > 1:
                        out[y, x] = nan

    return _stereo, V  # the same vector type object every call: the scratch arrays are kept by it


def _capacity(n: int) -> int:
    """``n`` rounded up to 4 significant bits (at most 1/8 more): few scratch shapes as the mask changes."""
    step = 1 << max(int(n).bit_length() - 4, 0)
    return -(-int(n) // step) * step


def stereo_match(device, L, R, mask, runs, tiles, D, block, U, cap, out):
    H, W = L.shape
    tiles, order, run_tile = tiles
    S, NB = len(runs), len(tiles)
    is_float = L.dtype == np.float32
    nl, T = lanes(is_float)
    kernel, V = _kernel(nl, T)
    Dp = -(-D // nl) * nl
    G = Dp // nl
    Wp = W + Dp + 2 * nl
    P = int(runs[-1, 2] - runs[-1, 1] + 1 + runs[-1, 3]) if S else 0
    Vn = int(tiles[-1, 6] + tiles[-1, 7]) if NB else 0  # column sums of every tile
    Sc, NBc, Pc, P2c, Vc = (_capacity(max(n, 1)) for n in (S, NB, P, P + S * (D - 1), Vn))
    runs_host = np.zeros((Sc, 5), np.int32)
    runs_host[:S] = runs
    tiles_host = np.zeros((NBc, 8), np.int32)
    tiles_host[:NB] = tiles
    order_host, run_tile_host = np.zeros(Sc, np.int32), np.zeros(Sc, np.int32)
    order_host[:S], run_tile_host[:S] = order, run_tile
    marked = np.empty((NBc, 2), np.int32)
    marked[:, 0], marked[:, 1] = W, -1  # no marked position yet
    small = (runs_host, tiles_host, order_host, run_tile_host, marked)
    if mask is None:
        mask = np.ones((H, W), np.uint8)
    if current_arch() == "cpu":  # the kernel reads (and writes ``marked``) NumPy arrays in place: no copy launches
        device.transfers.h2d += sum(a.nbytes for a in small)
        runs_d, tiles_d, order_d, run_tile_d, marked_d = small
    else:
        runs_d, tiles_d, order_d, run_tile_d, marked_d = (device.asarray(a).buffer for a in small)  # pooled shapes
    mask_d = np.ascontiguousarray(mask) if current_arch() == "cpu" else device.asarray(mask).buffer
    i32 = ti.i32
    px = per_pixel(device)
    arrays = (L.buffer, R.buffer, scratch(device, "stereo pl", (H * Wp,), T),
              scratch(device, "stereo pr", (H * Wp,), T), mask_d, runs_d, tiles_d, order_d, run_tile_d, marked_d,
              scratch(device, "stereo vsum", ((1 if px else Vc) * G,), V), scratch(device, "stereo cost", (Pc * G,), V),
              scratch(device, "stereo rcost", (P2c * G,), V), scratch(device, "stereo ldisp", (Pc,), i32),
              scratch(device, "stereo rmark", (P2c,), i32), out.buffer)  # fmt: skip
    y0, y1 = (int(runs[0, 0]) - block // 2, int(runs[-1, 0]) + block // 2 + 1) if S else (0, 0)  # rows read
    scalars = (S, NB, int(D), int(block), int(U), int(cap), Wp, y0, y1, math.nan, P, P + S * (D - 1))
    launch(kernel, arrays, (is_float, px), scalars=scalars, scalarize=False)
    return out

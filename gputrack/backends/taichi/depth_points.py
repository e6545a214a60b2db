"""Taichi kernels of :mod:`gputrack.ops.depth_points`: six launches (steps 1-3 in one kernel, a
kernel per radix pass, the points; on the CPU arch two: steps 4-5 in one kernel, the sort on one
thread), no host sync until the count is read. On the CPU arch a host depth image is read in
place (:func:`reads_host`: no upload).

1. one thread per image row: per chunk of 32 pixels a bit mask of the foreground pixels (a cheap,
   branch-free pass), then, only in chunks with foreground, the key of each pixel (branch-free,
   so that the loop vectorises), the row's count of foreground keys below each of LEVELS bounds
   2**31, 2**28, 2**25, 2**22 (the first: every foreground key), and the smallest key of each
   chunk of 32 pixels;
2. one task: the count N, the tightest bound with at least min(n, N) keys below it (C
   candidates) and each row's offset among the candidates;
3. one thread per row with candidates: the keys again in the chunks holding one, and (key, pixel)
   of each candidate at its offset (row order);
4. a stable LSD radix sort of the C candidates by key (8 bits a pass; per pass: digit counts per
   block of 256 candidates, per-digit block offsets, digit starts, a stable scatter per block);
5. the first min(n, C) points back-projected, NaN rows after them.

Scratch arrays are kept per device and image size (gputrack/backends/taichi/runtime.py scratch).
"""

import numpy as np

from .arrays import copy
from .launch import launch
from .particles import _pcg
from .pixels import is_nan, mode, pixel2
from .runtime import loop_limit, scratch, ti

nd1 = ti.types.ndarray(ndim=1)
nd2 = ti.types.ndarray(ndim=2)
#: key bounds 2**(31 - STEP q), q = 0 .. LEVELS - 1: 2**31 (every foreground key) down to 2**22;
#: the tightest bound holding n keys keeps about n to 8n candidates (for N / n <= 8**3; beyond,
#: about N / 512). Fewer levels: fewer compares per pixel in step 1 (the costly step)
CHUNK = 32  # pixels whose smallest key step 1 keeps: step 3 rescans only chunks with a candidate
LEVELS = 4
STEP = 3
BOUNDS = [1 << (31 - STEP * q) for q in range(LEVELS)]
RADIX = 256
BLOCK = 256  # candidates per block of the radix sort


@ti.func
def _digit(key, shift):
    return ti.cast((key >> ti.cast(shift, ti.u32)) & ti.u32(RADIX - 1), ti.i32)


@ti.func
def _fg(depth: ti.template(), bg: ti.template(), r, c, threshold, max_range, u16: ti.template(),
        nearer: ti.template()):  # fmt: skip
    """1 if the pixel is foreground, else 0 (branch-free: the row loops vectorise)."""
    z = pixel2(depth, r, c, u16)
    g = bg[r, c]
    d = g - z
    if ti.static(not nearer):
        d = ti.abs(d)
    # paper 002 sec. 4.1: a reading within range, >= threshold off a background value
    # NaN by its bits: Taichi compiles with fast math, which may assume no NaN in a compare
    fg = (not is_nan(z)) & (z > 0.0) & (z <= max_range) & (not is_nan(g)) & (g != 0.0) & (d >= threshold)
    return ti.cast(fg, ti.u32)


@ti.func
def _key(i, a, b, fg):
    """The 31-bit key of pixel index i if ``fg`` (1), else a key >= 2**31."""
    key = _pcg(_pcg(ti.cast(i, ti.u32) ^ a) + b) >> ti.u32(1)
    return key | (ti.u32(0x80000000) * (ti.u32(1) - fg))


@ti.func
def _fg_bits(depth: ti.template(), bg: ti.template(), r, c0, m, threshold, max_range, u16: ti.template(),
             nearer: ti.template()):  # fmt: skip
    """Bit e set where pixel (r, c0 + e) is foreground, e < m <= 32 (one cheap pass: a chunk
    without foreground needs no keys)."""
    bits = ti.u32(0)
    for e in range(m):
        bits |= _fg(depth, bg, r, c0 + e, threshold, max_range, u16, nearer) << ti.cast(e, ti.u32)
    return bits


@ti.kernel
def _candidates(depth: nd2, bg: nd2, hist: nd2, lows: nd2, offs: nd1, info: nd1, k0: nd1, i0: nd1, n: ti.i32,
                threshold: ti.f32, max_range: ti.f32, wa: ti.i32, wb: ti.i32, u16: ti.template(),
                nearer: ti.template()):  # fmt: skip
    """Steps 1-3: the candidates (k0, i0) in row order, info = [N, C, level]."""
    H = bg.shape[0]
    W = bg.shape[1]
    a = ti.cast(wa, ti.u32)
    b = ti.cast(wb, ti.u32)
    for r in range(H):  # 1. per row: the number of foreground keys below each level's bound
        hv = ti.Vector([0] * LEVELS, dt=ti.i32)
        for chunk in range((W + CHUNK - 1) // CHUNK):  # and each chunk's smallest key (for step 3)
            c0 = chunk * CHUNK
            m = ti.min(CHUNK, W - c0)
            low = ti.u32(0xFFFFFFFF)
            bits = _fg_bits(depth, bg, r, c0, m, threshold, max_range, u16, nearer)
            if bits != ti.u32(0):  # keys only in chunks with foreground (most are background)
                for e in range(m):
                    key = _key(r * W + c0 + e, a, b, (bits >> ti.cast(e, ti.u32)) & ti.u32(1))
                    low = ti.min(low, key)
                    for q in ti.static(range(LEVELS)):
                        hv[q] += ti.cast(key < ti.u32(BOUNDS[q]), ti.i32)
            lows[r, chunk] = low
        for q in ti.static(range(LEVELS)):
            hist[r, q] = hv[q]
    ti.loop_config(serialize=True)
    for _ in range(1):  # 2. N, the level, row offsets
        N = 0
        for r in range(H):
            N += hist[r, 0]
        need = ti.min(n, N)
        k = 0
        for q in range(1, LEVELS):  # the tightest bound with at least `need` keys below it
            tot = 0
            for r in range(H):
                tot += hist[r, q]
            if tot >= need:
                k = q
        run = 0
        for r in range(H):
            offs[r] = run
            run += hist[r, k]
        offs[H] = run
        info[0] = N
        info[1] = run
        info[2] = k
    for r in range(H):  # 3. candidates (key below the bound) in row order
        j = offs[r]
        if offs[r + 1] > j:
            t = ti.u32(1) << ti.cast(31 - STEP * info[2], ti.u32)
            for chunk in range((W + CHUNK - 1) // CHUNK):  # only chunks holding a candidate
                if lows[r, chunk] < t:
                    c0 = chunk * CHUNK
                    m = ti.min(CHUNK, W - c0)
                    fg = _fg_bits(depth, bg, r, c0, m, threshold, max_range, u16, nearer)
                    bits = ti.u32(0)  # a branch-free pass for a bit mask of the candidates
                    for e in range(m):
                        key = _key(r * W + c0 + e, a, b, (fg >> ti.cast(e, ti.u32)) & ti.u32(1))
                        bits |= ti.cast(key < t, ti.u32) << ti.cast(e, ti.u32)
                    for e in range(m):  # then the candidates, in order
                        if (bits >> ti.cast(e, ti.u32)) & ti.u32(1) != ti.u32(0):
                            k0[j] = _key(r * W + c0 + e, a, b, ti.u32(1))
                            i0[j] = r * W + c0 + e
                            j += 1


@ti.kernel
def _radix_pass(info: nd1, sk: nd1, si: nd1, dk: nd1, di: nd1, blk: nd2, starts: nd1, p: ti.i32):
    """Pass p (bits 8p .. 8p + 7) of the stable LSD radix sort of the C = info[1] candidates, in
    blocks of BLOCK (every thread's serial work is bounded: one long serial task was seen to
    return garbage on lavapipe Vulkan past ~10^4 iterations); nothing when the keys (below
    2**(31 - STEP level)) have no bits there."""
    for blo in range(blk.shape[0]):  # a. each block's digit counts
        C = info[1]
        if p < (31 - STEP * info[2] + 7) // 8 and blo * BLOCK < C:
            for q in range(RADIX):
                blk[blo, q] = 0
            for j in range(blo * BLOCK, ti.min(C, (blo + 1) * BLOCK)):
                q = _digit(sk[j], 8 * p)
                blk[blo, q] = blk[blo, q] + 1
    for q in range(RADIX):  # b. per digit: offsets of the blocks, the digit's total
        C = info[1]
        if p < (31 - STEP * info[2] + 7) // 8:
            run = 0
            for blo in range((C + BLOCK - 1) // BLOCK):
                t = blk[blo, q]
                blk[blo, q] = run
                run += t
            starts[q] = run
    ti.loop_config(serialize=True)
    for _ in range(1):  # c. the digits' starts
        if p < (31 - STEP * info[2] + 7) // 8:
            run = 0
            for q in range(RADIX):
                t = starts[q]
                starts[q] = run
                run += t
    for blo in range(blk.shape[0]):  # d. stable scatter, each block in order
        C = info[1]
        if p < (31 - STEP * info[2] + 7) // 8 and blo * BLOCK < C:
            for j in range(blo * BLOCK, ti.min(C, (blo + 1) * BLOCK)):
                q = _digit(sk[j], 8 * p)
                at = starts[q] + blk[blo, q]
                blk[blo, q] = blk[blo, q] + 1
                dk[at] = sk[j]
                di[at] = si[j]


@ti.func
def _counting_pass(sk: ti.template(), si: ti.template(), dk: ti.template(), di: ti.template(), cnt: ti.template(),
                   C, shift):  # fmt: skip
    """One stable counting sort of C (key, index) pairs by the 8 key bits at ``shift`` (serial)."""
    for q in range(RADIX):
        cnt[q] = 0
    for j in range(C):
        q = _digit(sk[j], shift)
        cnt[q] = cnt[q] + 1
    run = 0
    for q in range(RADIX):
        t = cnt[q]
        cnt[q] = run
        run += t
    for j in range(C):
        q = _digit(sk[j], shift)
        at = cnt[q]
        cnt[q] = at + 1
        dk[at] = sk[j]
        di[at] = si[j]


@ti.kernel
def _select(depth: nd2, info: nd1, k0: nd1, i0: nd1, k1: nd1, i1: nd1, cnt: nd1, out: nd2, fx: ti.f32,
            fy: ti.f32, cx: ti.f32, cy: ti.f32, u16: ti.template()):  # fmt: skip
    """Steps 4-5 in one launch for the CPU arch: the radix sort of the C candidates on one thread
    (about n to 8 n of them: ~0.1 ms for n = 1024, less than the four launches of
    :func:`_radix_pass`), then the points as :func:`_points`."""
    ti.loop_config(serialize=True)
    for _ in range(1):
        C = info[1]
        for p in range((31 - STEP * info[2] + 7) // 8):
            if p % 2 == 0:
                _counting_pass(k0, i0, k1, i1, cnt, C, 8 * p)
            else:
                _counting_pass(k1, i1, k0, i0, cnt, C, 8 * p)
    _write_points(depth, info, i0, i1, out, fx, fy, cx, cy, u16)


@ti.kernel
def _points(depth: nd2, info: nd1, i0: nd1, i1: nd1, out: nd2, fx: ti.f32, fy: ti.f32, cx: ti.f32, cy: ti.f32,
            u16: ti.template()):  # fmt: skip
    """The first min(n, C) sorted candidates back-projected, NaN rows after them."""
    _write_points(depth, info, i0, i1, out, fx, fy, cx, cy, u16)


@ti.func
def _write_points(depth: ti.template(), info: ti.template(), i0: ti.template(), i1: ti.template(),
                  out: ti.template(), fx, fy, cx, cy, u16: ti.template()):  # fmt: skip
    """The first min(n, C) sorted candidates back-projected, NaN rows after them."""
    W = i0.shape[0] // depth.shape[0]
    nan = ti.bit_cast(ti.u32(0x7FC00000), ti.f32)
    for j in range(out.shape[0]):
        C = info[1]
        passes = (31 - STEP * info[2] + 7) // 8
        x = nan
        y = nan
        zz = nan
        if j < C:
            i = i0[j]
            if passes % 2 == 1:  # an odd number of passes ends in the second buffer
                i = i1[j]
            r = i // W
            c = i - r * W
            zz = pixel2(depth, r, c, u16)
            x = (ti.cast(c, ti.f32) - cx) * zz / fx  # pinhole back-projection
            y = (ti.cast(r, ti.f32) - cy) * zz / fy
        out[j, 0] = x
        out[j, 1] = y
        out[j, 2] = zz


def _i32(word: int) -> int:
    """A 32-bit word as the signed int that carries its bits into a ti.i32 argument."""
    return word - (1 << 32) if word >= 1 << 31 else word


def reads_host(device) -> bool:
    """The kernels read a host (NumPy) depth image in place on the CPU arch (no upload)."""
    return device.arch == "cpu"


def depth_points(device, depth, bg, pixel, fx, fy, cx, cy, threshold, max_range, nearer, a, b, out):
    """``depth``: a device array or, where :func:`reads_host`, a C-contiguous NumPy array."""
    img = depth if isinstance(depth, np.ndarray) else depth.buffer
    H, W = bg.shape
    limit = loop_limit(device)
    chunks = (W + CHUNK - 1) // CHUNK
    # the longest invocations: step 2's serial task ((LEVELS + 1) H passes) and step 3's rows (three
    # 32-pixel passes a chunk); the radix passes run at most RADIX + BLOCK
    if limit is not None and max((LEVELS + 1) * H, 3 * CHUNK * chunks) > limit:
        raise ValueError(f"depth: at most {limit // (LEVELS + 1)} rows and {limit // 3} columns on {device.spec} "
                         f"(its shader invocations run at most {limit} loop passes), got {H} x {W}")  # fmt: skip
    size = H * W
    hist = scratch(device, "dp hist", (H, LEVELS), ti.i32)
    lows = scratch(device, "dp lows", (H, (W + CHUNK - 1) // CHUNK), ti.u32)
    offs = scratch(device, "dp offs", (H + 1,), ti.i32)
    info = scratch(device, "dp info", (4,), ti.i32)
    k0, k1 = scratch(device, "dp k0", (size,), ti.u32), scratch(device, "dp k1", (size,), ti.u32)
    i0, i1 = scratch(device, "dp i0", (size,), ti.i32), scratch(device, "dp i1", (size,), ti.i32)
    blk = scratch(device, "dp blocks", ((size + BLOCK - 1) // BLOCK, RADIX), ti.i32)
    starts = scratch(device, "dp starts", (RADIX,), ti.i32)
    launch(_candidates, (img, bg.buffer, hist, lows, offs, info, k0, i0), (mode(pixel, depth), bool(nearer)),
           scalars=(int(out.shape[0]), float(threshold), float(max_range), _i32(a), _i32(b)))  # fmt: skip
    cam = (float(fx), float(fy), float(cx), float(cy))
    if device.arch == "cpu":  # one thread sorts the few candidates: one launch for steps 4-5
        launch(_select, (img, info, k0, i0, k1, i1, starts, out.buffer), (mode(pixel, depth),), scalars=cam)
        host = np.empty(4, np.int32)
        copy(info, host)  # a host-memory copy (arrays.copy), not to_numpy
        return int(host[0])
    for p in range(4):  # the kernel skips the passes the level's keys do not need
        src, dst = ((k0, i0), (k1, i1)) if p % 2 == 0 else ((k1, i1), (k0, i0))
        launch(_radix_pass, (info, *src, *dst, blk, starts), scalars=(p,))
    launch(_points, (img, info, i0, i1, out.buffer), (mode(pixel, depth),), scalars=cam)
    return int(info.to_numpy()[0])

"""Taichi kernels of :mod:`gputrack.ops.depth_points`: six launches (steps 1-3 in one kernel, a
kernel per radix pass, the points), no host sync until the count is read.

1. one thread per image row: foreground test and key of each pixel (branch-free, so that the
   row loop vectorises), the row's count of foreground keys below each of LEVELS bounds
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

from .launch import launch
from .particles import _pcg
from .pixels import is_nan, mode, pixel2
from .runtime import scratch, ti

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
def _key(depth: ti.template(), bg: ti.template(), r, c, W, a, b, threshold, max_range, u16: ti.template(),
         nearer: ti.template()):  # fmt: skip
    """The pixel's 31-bit key if it is foreground, else a key >= 2**31 (branch-free: the row loops
    vectorise)."""
    z = pixel2(depth, r, c, u16)
    g = bg[r, c]
    d = g - z
    if ti.static(not nearer):
        d = ti.abs(d)
    # paper 002 sec. 4.1: a reading within range, >= threshold off a background value
    # NaN by its bits: Taichi compiles with fast math, which may assume no NaN in a compare
    fg = (not is_nan(z)) & (z > 0.0) & (z <= max_range) & (not is_nan(g)) & (g != 0.0) & (d >= threshold)
    key = _pcg(_pcg(ti.cast(r * W + c, ti.u32) ^ a) + b) >> ti.u32(1)
    return key | (ti.u32(0x80000000) * ti.cast(1 - ti.cast(fg, ti.i32), ti.u32))


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
            low = ti.u32(0xFFFFFFFF)
            for e in range(ti.min(CHUNK, W - c0)):
                key = _key(depth, bg, r, c0 + e, W, a, b, threshold, max_range, u16, nearer)
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
                    bits = ti.u32(0)  # a branch-free pass for a bit mask of the candidates
                    for e in range(ti.min(CHUNK, W - c0)):
                        key = _key(depth, bg, r, c0 + e, W, a, b, threshold, max_range, u16, nearer)
                        bits |= ti.cast(key < t, ti.u32) << ti.cast(e, ti.u32)
                    while bits != ti.u32(0):  # then the candidates, in order
                        e = 0
                        while (bits >> ti.cast(e, ti.u32)) & ti.u32(1) == ti.u32(0):
                            e += 1
                        bits ^= ti.u32(1) << ti.cast(e, ti.u32)
                        k0[j] = _key(depth, bg, r, c0 + e, W, a, b, threshold, max_range, u16, nearer)
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


@ti.kernel
def _points(depth: nd2, info: nd1, i0: nd1, i1: nd1, out: nd2, fx: ti.f32, fy: ti.f32, cx: ti.f32, cy: ti.f32,
            u16: ti.template()):  # fmt: skip
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


def depth_points(device, depth, bg, pixel, fx, fy, cx, cy, threshold, max_range, nearer, a, b, out):
    H, W = bg.shape
    size = H * W
    hist = scratch(device, "dp hist", (H, LEVELS), ti.i32)
    lows = scratch(device, "dp lows", (H, (W + CHUNK - 1) // CHUNK), ti.u32)
    offs = scratch(device, "dp offs", (H + 1,), ti.i32)
    info = scratch(device, "dp info", (4,), ti.i32)
    k0, k1 = scratch(device, "dp k0", (size,), ti.u32), scratch(device, "dp k1", (size,), ti.u32)
    i0, i1 = scratch(device, "dp i0", (size,), ti.i32), scratch(device, "dp i1", (size,), ti.i32)
    blk = scratch(device, "dp blocks", ((size + BLOCK - 1) // BLOCK, RADIX), ti.i32)
    starts = scratch(device, "dp starts", (RADIX,), ti.i32)
    launch(_candidates, (depth.buffer, bg.buffer, hist, lows, offs, info, k0, i0), (mode(pixel, depth), bool(nearer)),
           scalars=(int(out.shape[0]), float(threshold), float(max_range), _i32(a), _i32(b)))  # fmt: skip
    for p in range(4):  # the kernel skips the passes the level's keys do not need
        src, dst = ((k0, i0), (k1, i1)) if p % 2 == 0 else ((k1, i1), (k0, i0))
        launch(_radix_pass, (info, *src, *dst, blk, starts), scalars=(p,))
    launch(_points, (depth.buffer, info, i0, i1, out.buffer), (mode(pixel, depth),),
           scalars=(float(fx), float(fy), float(cx), float(cy)))  # fmt: skip
    return int(info.to_numpy()[0])

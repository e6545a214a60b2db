"""Taichi kernels: sparse-template cost and residuals (paper 000 eq. 17-21).

One launch per op call. The outermost (parallel) loop runs over groups of ``LANES`` consecutive
hypotheses; the serial inner loop runs over the template points, grouped by part so that each
part's transform is loaded once per group, and evaluates the point for every lane of the group
(branch-free: the samples of a particle filter are close, so the lanes read neighbouring pixels,
and there is no data-dependent branch to mispredict). A group's per-lane values are lane vectors
(``ti.Vector`` of L): on the CPU the kernels are compiled with Taichi's matrix scalarisation off
(``launch(..., scalarize=False)``), so the projection, the bilinear weights, the robust terms and
the sums are SIMD arithmetic over the lanes; only the pixel reads are per lane (gathers).
Single-threaded, kernel profiler minimum, taichi:cpu, 2026-11-23: ``rgbd_cost`` B=1500 3.3-3.5
-> 2.3 ms and ``rgbd_residuals`` B=400 1.3 -> 0.76 ms on the benchmark scene; the same cost on
1500 samples of a simulated frame 2.5 -> 2.3 ms (its pixel reads dominate). Sums are blocked
(``CHUNK`` points per partial sum), so float32 keeps its accuracy for thousands of points. RGB
needs two passes (alpha and beta are sums over the valid points): the first stores each point's
sample and validity in a scratch row per hypothesis. Conventions: gputrack/ops/template.py.

Block-shared-memory reductions compile only on CUDA; this one-group-per-thread form runs on
every arch (on a GPU each thread then handles LANES hypotheses, LANES = 1 there).
"""

from pathlib import Path

import numpy as np

from ... import tuning_cache
from ...abi import INTENSITY_MAX
from ...tuning_cache import Tunable
from .launch import launch
from .runtime import scratch, ti
from .tasks import CPU_TASK, chunk, cpu_chunks

CHUNK = 64
CPU_LANES = 8
REUSE_PF, REUSE_SPARSE = 1, 2  # _rgbd_body's re-use modes
TINY = 1e-12
BIG = 3.0e38

def lanes(device) -> int:
    """Hypotheses per thread: CPU_LANES on taichi:cpu; 1 on GPUs and on Vulkan (lavapipe already
    runs 8 invocations per SIMD register)."""
    return CPU_LANES if getattr(device, "arch", "") == "cpu" else 1


def default_params(device) -> dict:
    """Launch parameters without a tuning-cache entry (``gputrack tune`` may choose others)."""
    return {"lanes": lanes(device)}


# The launch parameter of the rgbd kernels, read by rgbd_cost and rgbd_residuals at every call
# and swept by ``gputrack tune``: ``lanes`` = hypotheses per thread (the kernels' L). Results are
# identical whatever the choice (each lane computes its own hypothesis with the same sums); only
# the speed differs. Representative sizes: a particle-filter stage (paper 000: K = 1500,
# N = N' = 128) and the batched LM's residuals (B = 280 .. 400 perturbed poses share the bucket
# B=512). This file is the source that keys the cache.
TUNABLES = {
    op: Tunable(
        op=op,
        backend="taichi",
        candidates={"lanes": [1, 2, 4, 8, 16]},
        default=default_params,
        sizes=(size,),
        sources=(str(Path(__file__).resolve()),),
    )
    for op, size in (("rgbd_cost", {"B": 1500, "N": 128}), ("rgbd_residuals", {"B": 400, "N": 128}))
}


def _tuned(device, op, tf, rgb, depth) -> dict:
    """The launch parameters of ``op`` for this device and size (cached choice, else default)."""
    n = max(rgb["pts"].shape[0], depth["pts"].shape[0])
    return tuning_cache.choose(device, TUNABLES[op], {"B": tf.shape[0], "N": n})


@ti.func
def _lanes(L: ti.template()):
    """A float32 vector of L lanes (one per hypothesis of a group), zero."""
    return ti.Vector([0.0] * L, dt=ti.f32)


@ti.func
def _project(P: ti.template(), x, y, z, fx, fy, cx, cy, wm1, hm1):
    """Every lane's camera-frame Z, pixel (u, v) (0 where invalid) and in-image flag of one point;
    P: 12 lane vectors, the rows of the lanes' 3 x 4 transforms."""
    X = P[0] * x + P[1] * y + P[2] * z + P[3]  # eq. 4: M_C = D M_O
    Y = P[4] * x + P[5] * y + P[6] * z + P[7]
    Z = P[8] * x + P[9] * y + P[10] * z + P[11]
    iz = 1.0 / Z
    u = fx * X * iz + cx  # eq. 5
    v = fy * Y * iz + cy
    ok = (Z > 0.0) & (Z < BIG) & (u >= 0.0) & (u <= wm1) & (v >= 0.0) & (v <= hm1)
    return Z, ti.select(ok, u, 0.0), ti.select(ok, v, 0.0), ok


@ti.func
def _corners(img: ti.template(), u, v, w, h):
    """Every lane's four pixels around (u, v) (u, v >= 0) and the bilinear weights: (i00, i01, i10,
    i11, a, b). The pixel index is taken per lane (the gathers); the rest is lane-vector arithmetic."""
    fx0 = ti.min(ti.floor(u), ti.f32(w - 2))
    fy0 = ti.min(ti.floor(v), ti.f32(h - 2))
    i00 = u * 0.0
    i01 = u * 0.0
    i10 = u * 0.0
    i11 = u * 0.0
    for l in ti.static(range(ti.static(u.n))):
        xi = ti.cast(fx0[l], ti.i32)
        yi = ti.cast(fy0[l], ti.i32)
        i00[l] = img[yi, xi]
        i01[l] = img[yi, xi + 1]
        i10[l] = img[yi + 1, xi]
        i11[l] = img[yi + 1, xi + 1]
    return i00, i01, i10, i11, u - fx0, v - fy0


@ti.func
def _clamp_i(i):
    """A gray pixel clamped to [-INTENSITY_MAX, INTENSITY_MAX] (gputrack/abi.py); NaN stays NaN."""
    m = ti.f32(float(INTENSITY_MAX))
    return ti.select(i > m, m, ti.select(i < -m, -m, i))


@ti.func
def _gray_at(P: ti.template(), x, y, z, gray: ti.template(), fx, fy, cx, cy):
    """Every lane's bilinear intensity I(M_i; D) (sec. 3.5) of one RGB point, and its validity."""
    h = gray.shape[0]
    w = gray.shape[1]
    Z, u, v, ok = _project(P, x, y, z, fx, fy, cx, cy, ti.f32(w - 1), ti.f32(h - 1))
    i00, i01, i10, i11, a, bw = _corners(gray, u, v, w, h)
    i00, i01, i10, i11 = _clamp_i(i00), _clamp_i(i01), _clamp_i(i10), _clamp_i(i11)
    top = i00 + a * (i01 - i00)
    bot = i10 + a * (i11 - i10)
    return top + bw * (bot - top), ok  # sec. 3.5: bilinear


@ti.func
def _depth_term(P: ti.template(), x, y, z, dimg: ti.template(), fx, fy, cx, cy, cd, tol):
    """Every lane's d'_i = Zhat - Z shrunk by tol (eq. 18; 0 where invalid), its validity and rho_c'(d'_i)
    (1 if invalid)."""
    h = dimg.shape[0]
    w = dimg.shape[1]
    Z, u, v, ok = _project(P, x, y, z, fx, fy, cx, cy, ti.f32(w - 1), ti.f32(h - 1))
    d00, d01, d10, d11, a, bw = _corners(dimg, u, v, w, h)
    # a measurement is > 0 and finite (NaN fails both tests)
    okd = ok & (ti.min(ti.min(d00, d01), ti.min(d10, d11)) > 0.0)
    okd = okd & (d00 < BIG) & (d01 < BIG) & (d10 < BIG) & (d11 < BIG)
    top = d00 + a * (d01 - d00)
    bot = d10 + a * (d11 - d10)
    e = top + bw * (bot - top) - Z  # eq. 18: d'_i = Zhat - Z
    dd = ti.select(okd, e - ti.min(ti.max(e, -tol), tol), 0.0)  # |e| <= tol counts as 0 (depth_tol)
    q = cd + dd * dd
    return dd, q, okd, ti.select(okd, dd * dd / q, 1.0)


@ti.func
def _load_pose(P: ti.template(), l: ti.template(), tf: ti.template(), b, j):
    for e in ti.static(range(12)):
        P[e][l] = tf[b, j, e // 4, e % 4]


@ti.func
def _source_row(s, nb, nc, stride: ti.template()):
    """The hypothesis that cache row s of the re-use modes holds (see _source_cache)."""
    b = s * stride  # LM problem s's point
    if ti.static(stride == 0):
        b = (s * nb + nc - 1) // nc  # PF: the first hypothesis of candidate s's block
    return b


@ti.func
def _source_cache(
    tf: ti.template(), rpts: ti.template(), ridx: ti.template(), rparts, dpts: ti.template(), didx: ti.template(),
    dparts, gray: ti.template(), dimg: ti.template(), cam: ti.template(), cache: ti.template(),
    serial: ti.template(), stride: ti.template(), L: ti.template(), pose: ti.template() = (),
):  # fmt: skip
    """Re-use modes, first task (on the calling thread when ``serial``: a few sources, and a
    thread-pool dispatch costs ~50 us on a CPU): evaluate the source hypothesis of cache row s in
    full: with ``stride`` = 0 (PF), the first hypothesis of candidate s's block (s B // C .. the
    samples of sample_around); else hypothesis s * stride (the point of LM problem s in the
    central-difference stack). cache[s] = [I_i (n), valid_i (n), then per part j: sum T, sum T^2,
    sum T I over its valid RGB points and the sum of rho_c' over its depth points (4 J)]. The
    sources are taken L at a time as lane vectors (the last group repeats its last source)."""
    nb = tf.shape[0]
    nc = cache.shape[0]
    n = rpts.shape[0]
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    cd = cam[6] * cam[6]
    tol = cam[7]
    ti.loop_config(serialize=serial)
    for sg in range((nc + L - 1) // L):
        src = ti.Vector([0] * L, dt=ti.i32)  # the lanes' cache rows
        row = ti.Vector([0] * L, dt=ti.i32)  # and their hypotheses
        for l in ti.static(range(L)):
            src[l] = ti.min(sg * L + l, nc - 1)
            row[l] = _source_row(src[l], nb, nc, stride)
        if ti.static(len(pose) > 0):
            for l in range(L):  # a loop, not unrolled: one copy of the posing code (compile time)
                ti.static(pose[0])(ti.static(pose[1]), _source_row(ti.min(sg * L + l, nc - 1), nb, nc, stride))
        P = [_lanes(L) for _ in ti.static(range(12))]
        for j in range(rparts):
            for l in ti.static(range(L)):
                _load_pose(P, l, tf, row[l], j)
            sT = _lanes(L)
            sTT = _lanes(L)
            sTI = _lanes(L)
            bT = _lanes(L)
            bTT = _lanes(L)
            bTI = _lanes(L)
            cnt = 0
            for i in range(ridx[j], ridx[j + 1]):
                T = rpts[i, 3]
                I, ok = _gray_at(P, rpts[i, 0], rpts[i, 1], rpts[i, 2], gray, fx, fy, cx, cy)
                Tv = ti.select(ok, T, 0.0)
                bT += Tv
                bTT += Tv * T
                bTI += Tv * I
                okf = ti.select(ok, 1.0, 0.0)
                for l in ti.static(range(L)):
                    cache[src[l], i] = I[l]
                    cache[src[l], n + i] = okf[l]
                sT, sTT, sTI, bT, bTT, bTI, cnt = _blocked3(sT, sTT, sTI, bT, bTT, bTI, cnt)
            sT += bT
            sTT += bTT
            sTI += bTI
            for l in ti.static(range(L)):
                cache[src[l], 2 * n + 4 * j] = sT[l]
                cache[src[l], 2 * n + 4 * j + 1] = sTT[l]
                cache[src[l], 2 * n + 4 * j + 2] = sTI[l]
        for j in range(dparts):
            for l in ti.static(range(L)):
                _load_pose(P, l, tf, row[l], j)
            acc = _lanes(L)
            blk = _lanes(L)
            cnt = 0
            for i in range(didx[j], didx[j + 1]):
                _, _, _, rho = _depth_term(P, dpts[i, 0], dpts[i, 1], dpts[i, 2], dimg, fx, fy, cx, cy, cd, tol)
                acc, blk, cnt = _blocked(acc, blk + rho, cnt)
            acc += blk
            for l in ti.static(range(L)):
                cache[src[l], 2 * n + 4 * j + 3] = acc[l]


@ti.func
def _rgbd_body(
    tf: ti.template(),
    rpts: ti.template(),
    ridx: ti.template(),
    rparts,
    dpts: ti.template(),
    didx: ti.template(),
    dparts,
    gray: ti.template(),
    dimg: ti.template(),
    cam: ti.template(),
    scratch: ti.template(),
    total: ti.template(),
    eps_c: ti.template(),
    eps_d: ti.template(),
    residuals: ti.template(),
    groups,
    want_residuals: ti.template(),
    L: ti.template(),
    chunks: ti.template(),
    reuse: ti.template(),
    moved: ti.template(),
    cache: ti.template(),
    order: ti.template(),
    full: ti.template(),
    stride: ti.template(),
    pose: ti.template() = (),
):
    """cam = [fx, fy, cx, cy, lam, c_rgb, c_depth, depth_tol]; ridx/didx = [start (parts + 1), perm (points)].

    ``pose``: () (the transforms tf are given), or (func, args) with a ti.func ``func(args, b)``
    that writes hypothesis b's transforms into tf; a group calls it for its lanes' hypotheses first
    (pf.py samples and poses there, pose_residuals.py poses its rows, so that one parallel loop
    does the whole op).

    ``reuse`` (static): 0 = every part of every hypothesis. ``REUSE_PF`` (cost only): the B
    hypotheses are C = cache.shape[0] blocks of samples of sample_around (hypothesis b belongs to
    candidate b C // B) that pose the parts with moved[j] == 0 as their candidate does: those
    parts are not projected, their samples and sums come from the candidate's cache row (filled by
    _source_cache); gputrack/backends/taichi/pf.py uses it for the parts a cascade stage does not
    sample. ``REUSE_SPARSE`` (residuals only, paper 000 Fig. 2): lane l of group g evaluates row
    order[g L + l] of a central-difference stack (``stride`` = 2P + 1 rows per problem, its first
    row the source of cache row row // stride); the group projects the parts with moved[g, j] != 0
    (all of them when a lane's full[row] != 0) and writes only their residuals; the other parts'
    sums (eq. 17's alpha, beta) come from the cache, their residuals are not written.
    gputrack/backends/taichi/pose_residuals.py uses it for the LM's block-sparse Jacobian."""
    nb = tf.shape[0]
    n = rpts.shape[0]
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    lam = cam[4]
    cc = cam[5] * cam[5]
    cd = cam[6] * cam[6]
    tol = cam[7]
    wc = ti.sqrt(1.0 - lam)
    wd = ti.sqrt(lam)
    # groups = ceil(B / L) (compile-time in the rgbd and PF kernels, run-time in pose_residuals.py),
    # cut into chunks on the CPU (see chunk)
    for it in range(groups if ti.static(chunks == 0) else chunks * CPU_TASK):
        g0, g1 = chunk(it, groups, chunks)
        for g in range(g0, g1):
            P = [_lanes(L) for _ in ti.static(range(12))]  # the lanes' transforms, row-major 3 x 4
            row = ti.Vector([0] * L, dt=ti.i32)  # lanes past the batch repeat the last hypothesis
            own = ti.Vector([0] * L, dt=ti.i32)  # reuse: each lane's source (cache row)
            every = 0  # REUSE_SPARSE: a lane's row must be evaluated in full
            if ti.static(len(pose) > 0):
                for l in range(L):  # a loop, not unrolled: one copy of the posing code (compile time)
                    b = ti.min(g * L + l, nb - 1)
                    if ti.static(reuse == REUSE_SPARSE):
                        b = order[g * L + l]
                    ti.static(pose[0])(ti.static(pose[1]), b)
            for l in ti.static(range(L)):
                row[l] = ti.min(g * L + l, nb - 1)
                if ti.static(reuse == REUSE_PF):
                    own[l] = row[l] * cache.shape[0] // nb  # as in sample_around
                if ti.static(reuse == REUSE_SPARSE):
                    row[l] = order[g * L + l]
                    own[l] = row[l] // stride
                    every |= full[row[l]]
            # sums of the parts taken from the cache (kept apart from the blocked sums below)
            cT = ti.Vector([0.0] * L, dt=ti.f32)
            cTT = ti.Vector([0.0] * L, dt=ti.f32)
            cTI = ti.Vector([0.0] * L, dt=ti.f32)
            cD = ti.Vector([0.0] * L, dt=ti.f32)
            # ---- RGB pass 1: samples I_i, validity, sums over the valid points (eq. 17)
            sT = ti.Vector([0.0] * L, dt=ti.f32)
            sTT = ti.Vector([0.0] * L, dt=ti.f32)
            sTI = ti.Vector([0.0] * L, dt=ti.f32)
            bT = ti.Vector([0.0] * L, dt=ti.f32)
            bTT = ti.Vector([0.0] * L, dt=ti.f32)
            bTI = ti.Vector([0.0] * L, dt=ti.f32)
            cnt = 0
            for j in range(rparts):
                if _project_part(moved, g, j, reuse, every):
                    for l in ti.static(range(L)):
                        _load_pose(P, l, tf, row[l], j)
                    for i in range(ridx[j], ridx[j + 1]):
                        x = rpts[i, 0]
                        y = rpts[i, 1]
                        z = rpts[i, 2]
                        T = rpts[i, 3]
                        I, ok = _gray_at(P, x, y, z, gray, fx, fy, cx, cy)
                        Tv = ti.select(ok, T, 0.0)
                        bT += Tv
                        bTT += Tv * T
                        bTI += Tv * I
                        okf = ti.select(ok, 1.0, 0.0)
                        for l in ti.static(range(L)):  # samples, then validity flags: contiguous lanes
                            scratch[g, i * L + l] = I[l]
                            scratch[g, (n + i) * L + l] = okf[l]
                        sT, sTT, sTI, bT, bTT, bTI, cnt = _blocked3(sT, sTT, sTI, bT, bTT, bTI, cnt)
                else:  # the sources' sums (pass 2 reads their samples from the cache)
                    for l in ti.static(range(L)):
                        cT[l] += cache[own[l], 2 * n + 4 * j]
                        cTT[l] += cache[own[l], 2 * n + 4 * j + 1]
                        cTI[l] += cache[own[l], 2 * n + 4 * j + 2]
            sT += bT + cT
            sTT += bTT + cTT
            sTI += bTI + cTI
            alpha = ti.select(sT > TINY, 1.0 / sT, 0.0)  # eq. 17: alpha = 1 / sum T_i
            beta = ti.select(sTI > TINY, alpha * sTT / sTI, 0.0)  # eq. 17: beta
            # ---- RGB pass 2: eps_C = sum rho_c(d_i) (eq. 17); residuals r_i (eq. 20-21)
            eC = ti.Vector([0.0] * L, dt=ti.f32)
            blk = ti.Vector([0.0] * L, dt=ti.f32)
            cnt = 0
            for j in range(rparts):
                if ti.static(want_residuals):  # the projected parts' (every part's but with REUSE_SPARSE)
                    if _project_part(moved, g, j, reuse, every):
                        for i in range(ridx[j], ridx[j + 1]):
                            _rgb_residuals(scratch, residuals, ridx, rparts, row, g, i, n, rpts[i, 3], alpha,
                                           beta, cc, wc, L)  # fmt: skip
                elif _project_part(moved, g, j, reuse, every):  # rho_c over every point: samples in scratch
                    for i in range(ridx[j], ridx[j + 1]):
                        I, valid = _scratch_lanes(scratch, g, i, n, L)
                        blk += _rho_c(beta * I - alpha * rpts[i, 3], valid, cc)
                        eC, blk, cnt = _blocked(eC, blk, cnt)
                elif own[0] == own[L - 1]:  # REUSE_PF, one source for the group (all but ~1 group in 19)
                    o = own[0]
                    for i in range(ridx[j], ridx[j + 1]):  # the source's sample, broadcast to the lanes
                        I = _lanes(L) + cache[o, i]
                        valid = _lanes(L) + cache[o, n + i]
                        blk += _rho_c(beta * I - alpha * rpts[i, 3], valid, cc)
                        eC, blk, cnt = _blocked(eC, blk, cnt)
                else:  # REUSE_PF: each lane's source's samples, in the cache
                    for i in range(ridx[j], ridx[j + 1]):
                        I = _lanes(L)
                        valid = _lanes(L)
                        for l in ti.static(range(L)):
                            I[l] = cache[own[l], i]
                            valid[l] = cache[own[l], n + i]
                        blk += _rho_c(beta * I - alpha * rpts[i, 3], valid, cc)
                        eC, blk, cnt = _blocked(eC, blk, cnt)
            eC += blk
            # ---- depth: eps_D = sum rho_c'(d'_i) (eq. 18); residuals r'_i (eq. 20-21)
            eD = ti.Vector([0.0] * L, dt=ti.f32)
            blk.fill(0.0)
            cnt = 0
            for j in range(dparts):
                if _project_part(moved, g, j, reuse, every):
                    for l in ti.static(range(L)):
                        _load_pose(P, l, tf, row[l], j)
                    for i in range(didx[j], didx[j + 1]):
                        x = dpts[i, 0]
                        y = dpts[i, 1]
                        z = dpts[i, 2]
                        dd, q, okd, rho = _depth_term(P, x, y, z, dimg, fx, fy, cx, cy, cd, tol)
                        if ti.static(want_residuals):
                            col = n + didx[dparts + 1 + i]
                            r = ti.select(okd, wd * dd / ti.sqrt(q), wd)  # eq. 20-21
                            for l in ti.static(range(L)):
                                residuals[row[l], col] = r[l]
                        else:
                            blk += rho
                        cnt += 1
                        if cnt == CHUNK:
                            eD += blk
                            blk.fill(0.0)
                            cnt = 0
                elif ti.static(reuse == REUSE_PF):  # the sources' depth sums
                    for l in ti.static(range(L)):
                        cD[l] += cache[own[l], 2 * n + 4 * j + 3]
            eD += blk + cD
            if ti.static(not want_residuals):
                for l in ti.static(range(L)):
                    if g * L + l < nb:
                        total[row[l]] = (1.0 - lam) * eC[l] + lam * eD[l]  # eq. 19
                        eps_c[row[l]] = eC[l]
                        eps_d[row[l]] = eD[l]


@ti.func
def _project_part(moved: ti.template(), g, j, reuse: ti.template(), every):
    """Whether group g projects part j: always; with REUSE_PF when the sampled parameters move it;
    with REUSE_SPARSE when its rows' parameters move it or a row must be evaluated in full."""
    yes = 1
    if ti.static(reuse == REUSE_PF):
        yes = moved[j]
    if ti.static(reuse == REUSE_SPARSE):
        yes = moved[g, j] | every
    return yes != 0


@ti.func
def _blocked(acc, blk, cnt):
    """One more term in a blocked sum: every CHUNK terms, the block's sum moves into acc."""
    a = acc
    b = blk
    c = cnt + 1
    if c == CHUNK:
        a += b
        b.fill(0.0)
        c = 0
    return a, b, c


@ti.func
def _blocked3(sT, sTT, sTI, bT, bTT, bTI, cnt):
    """One more term in eq. 17's three blocked sums (sum T, sum T^2, sum T I; see _blocked)."""
    a0, a1, a2 = sT, sTT, sTI
    b0, b1, b2 = bT, bTT, bTI
    c = cnt + 1
    if c == CHUNK:
        a0 += b0
        a1 += b1
        a2 += b2
        b0.fill(0.0)
        b1.fill(0.0)
        b2.fill(0.0)
        c = 0
    return a0, a1, a2, b0, b1, b2, c


@ti.func
def _rho_c(d, valid, cc):
    """rho_c(d_i) of eq. 17 (d_i = beta I_i - alpha T_i); an invalid point (valid == 0) adds 1."""
    return ti.select(valid != 0.0, d * d / (cc + d * d), 1.0)


@ti.func
def _scratch_lanes(scratch: ti.template(), g, i, n, L: ti.template()):
    """Grouped point i's samples and validity flags of the L lanes, from pass 1's scratch row."""
    I = _lanes(L)
    valid = _lanes(L)
    for l in ti.static(range(L)):
        I[l] = scratch[g, i * L + l]
        valid[l] = scratch[g, (n + i) * L + l]
    return I, valid


@ti.func
def _rgb_residuals(scratch: ti.template(), residuals: ti.template(), ridx: ti.template(), rparts, row, g, i, n, T,
                   alpha, beta, cc, wc, L: ti.template()):  # fmt: skip
    """RGB pass 2 of grouped point i for the L lanes: r_i (eq. 20-21) from the samples in scratch."""
    col = ridx[rparts + 1 + i]  # the caller's index of grouped point i
    I, valid = _scratch_lanes(scratch, g, i, n, L)
    d = beta * I - alpha * T  # eq. 17: d_i
    r = ti.select(valid != 0.0, wc * d / ti.sqrt(cc + d * d), wc)  # eq. 20-21
    for l in ti.static(range(L)):
        # lanes past the batch repeat the last hypothesis: their (equal) rows overwrite it
        residuals[row[l], col] = r[l]


F1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
F2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
F4 = ti.types.ndarray(dtype=ti.f32, ndim=4)
I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
I2 = ti.types.ndarray(dtype=ti.i32, ndim=2)


# Kernel arguments: arrays first, then compile-time values, so that gputrack/backends/taichi/launch.py
# can launch them without Taichi's per-call Python (the part counts and the group count are
# compile-time values: a new count compiles a variant, which the tracker's few sizes afford).
@ti.kernel
def _rgbd_cost_kernel(
    tf: F4, rpts: F2, ridx: I1, dpts: F2, didx: I1, gray: F2, dimg: F2, cam: F1, scratch: F2,
    total: F1, eps_c: F1, eps_d: F1,
    rparts: ti.template(), dparts: ti.template(), groups: ti.template(), L: ti.template(), chunks: ti.template(),
):  # fmt: skip
    _rgbd_body(tf, rpts, ridx, rparts, dpts, didx, dparts, gray, dimg, cam, scratch, total, eps_c, eps_d, total,
               groups, False, L, chunks, 0, ridx, scratch, ridx, ridx, 0)  # fmt: skip


@ti.kernel
def _rgbd_res_kernel(
    tf: F4, rpts: F2, ridx: I1, dpts: F2, didx: I1, gray: F2, dimg: F2, cam: F1, scratch: F2, residuals: F2,
    rparts: ti.template(), dparts: ti.template(), groups: ti.template(), L: ti.template(), chunks: ti.template(),
):  # fmt: skip
    _rgbd_body(tf, rpts, ridx, rparts, dpts, didx, dparts, gray, dimg, cam, scratch, residuals, residuals,
               residuals, residuals, groups, True, L, chunks, 0, ridx, scratch, ridx, ridx, 0)  # fmt: skip


def cam_array(camera, lam, c_rgb, c_depth, depth_tol) -> np.ndarray:
    """The kernels' ``cam`` argument: (8,) float32 [fx, fy, cx, cy, lam, c_rgb, c_depth, depth_tol]."""
    return np.array([*camera, lam, c_rgb, c_depth, depth_tol], np.float32)


def _common(device, tf, rgb, depth, gray, dimg, camera, lam, c_rgb, c_depth, depth_tol, params):
    """(leading arrays, trailing compile-time values) of the rgbd kernels; ``params``: {"lanes"}."""
    nl = int(params["lanes"])
    groups = (tf.shape[0] + nl - 1) // nl
    work = scratch(device, "rgbd", (groups, 2 * rgb["pts"].shape[0] * nl), ti.f32)
    arrays = (
        tf.buffer, rgb["pts"].buffer, rgb["index"].buffer, depth["pts"].buffer, depth["index"].buffer, gray.buffer,
        dimg.buffer, cam_array(camera, lam, c_rgb, c_depth, depth_tol), work,
    )  # fmt: skip
    return arrays, (rgb["parts"], depth["parts"], groups, nl, cpu_chunks(device))


def rgbd_cost(device, tf, rgb, depth, gray, dimg, camera, total, eps_c, eps_d, *, lam, c_rgb, c_depth, depth_tol,
              params=None):  # fmt: skip
    """``params``: {"lanes"}; None = the tuned choice (TUNABLES["rgbd_cost"])."""
    params = params or _tuned(device, "rgbd_cost", tf, rgb, depth)
    arrays, consts = _common(device, tf, rgb, depth, gray, dimg, camera, lam, c_rgb, c_depth, depth_tol, params)
    launch(_rgbd_cost_kernel, (*arrays, total.buffer, eps_c.buffer, eps_d.buffer), consts, scalarize=False)


def rgbd_residuals(device, tf, rgb, depth, gray, dimg, camera, out, *, lam, c_rgb, c_depth, depth_tol,
              params=None):  # fmt: skip
    """``params``: {"lanes"}; None = the tuned choice (TUNABLES["rgbd_residuals"])."""
    params = params or _tuned(device, "rgbd_residuals", tf, rgb, depth)
    arrays, consts = _common(device, tf, rgb, depth, gray, dimg, camera, lam, c_rgb, c_depth, depth_tol, params)
    launch(_rgbd_res_kernel, (*arrays, out.buffer), consts, scalarize=False)

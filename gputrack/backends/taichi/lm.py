"""Taichi batched Levenberg-Marquardt: the same steps as backends/reference/lm.py.

One launch per op call and one per solver iteration on taichi:cpu (two per iteration on the
parallel archs, a few more for a large P on lavapipe), through ``launch.launch`` (the compiled
kernel launched directly: ~13 us with six ndarray arguments on taichi:cpu instead of ~38 us
through ``kernel(...)``). The solver packs its state into few arrays (gputrack.ops.lm.Layout:
S small float state, I int32, W workspace, Out result).

taichi:cpu runs one serial loop over the problems (``_per_problem``): every phase of problem b
in order (Jacobian rows, acceptance, J^T J and J^T r, damped Cholesky step, next points), so that
the problem's data stays in cache between the phases (why not parallel: see ``_per_problem``).
The parallel archs (Vulkan, CUDA) run every phase as a parallel loop over small items (a row of
J^T, a 2 x 4 block of J^T J, a problem's acceptance, damped factorisation or next points) whose
loop passes per invocation are bounded: lavapipe stops all loops of a shader invocation after
65535 passes in total and goes on with wrong numbers (section "the parallel archs" below).

``lm_solve``, ``normal_equations`` and the solver with a Jacobian on taichi:cpu read J (B, M, P)
as stored, in SIMD lane vectors of columns (the kernels are compiled with scalarisation off): for
P <= STATIC_P_MAX, P is a compile-time value and each row of J adds its outer product with itself
to J^T J (``_gram_static``); above it, J^T J is summed in 8 x 8 tiles (``_gram_tiles``). The
solver reads a Jacobian callable's float64 NumPy result of an even P in place as pairs of columns
(``_update_pairs``: two-lane vector loads, where LLVM gathers the scalars of a row): a whole solve
of the exponential fits of perf/bench_lm.py (B = 10, M = 256, P = 20) 4.40 / 4.21 -> 4.20 / 3.94 ms,
two runs alternating both in one process (2026-12-06).
Elsewhere (the parallel archs, and the solver's central differences from the stacked residuals)
the normal equations are dot products over contiguous rows of J^T, two rows by four columns per
pass over M (``_gram_pair``); strided dot products were 3-4x slower, so J is first transposed.
Taichi reloads an ndarray's address and shape after every store (it
cannot rule out aliasing), so a loop that stores per element is not vectorised and costs
~1-1.5 ns per element: the transpose groups its loads, and the solver, with central differences
and no mask, computes J^T J and J^T r straight from the stacked residuals (``fused``) instead of
storing J^T first. Measured on taichi:cpu (2 cores shared with other work, 2026-11-23; minimum
over repeats, per problem, B = 10, M = 256, float64), P = 20 / P = 14:

- ``lm_solve`` transposing first: transpose ~4.5 / 3.5 us, J^T J and J^T r ~4 / 2.2 us, Cholesky
  < 1 us; ~110-120 / 75-80 us per call for B = 10 including the launch (the other core busy).
  With ``_gram_static``: kernel ~65 us for B = 10, P = 20 (kernel profiler minimum, ~73 us
  taking each row element from the loaded vector instead of a broadcast load).
- solver iteration: finite flags ~1 / 0.8 us, acceptance ~0.4 us, fused normal equations
  ~10 / 5.3 us (6.6 + 5.5 / 4.7 + 2.4 us storing J^T first), step ~4 / 1.7 us; ~150-155 /
  ~90 us per launch for B = 10.

The per-solve ``_init`` launch (one
serial task, ~15-20 us) replaces uploading ~340 KB and downloading ~330 KB per solve for B = 10,
P = 14, M = 256 in float64; on taichi:cpu the start points go up and the result comes down
through one host-memory copy each (``arrays.copy``; ``from_numpy`` / ``to_numpy`` took ~0.1 ms).

On taichi:vulkan (lavapipe, a CPU; B = 10, M = 256, P = 20, float64, 2 shared cores, 2026-11-26,
bench medians): a solver iteration ~4 ms, ``lm_solve`` ~7 ms, most of it the dispatch of each
task (``_grid``). On CUDA the solver's step runs as ``_step_block`` (a block of BLOCK_STEP threads
per problem with Taichi's block barriers, which it compiles for CUDA only): the parallel archs'
``_step_tasks`` gave each problem's O(P^3) factorisation one thread, ~3 ms a launch for P = 92 on
an H100 (the face bundle: its step 27.7 -> 9.8 ms, perf/README.md). The ops (``lm_step``,
``lm_solve``) still factor on one thread per problem there.

On taichi:cpu the first and the last iteration are run-time flags of the one ``_update`` kernel a
solve launches, not template values: a warm process loaded three variants of it for a body frame's
first LM solve, ~1.0 s against ~0.5 s for one (timed around the kernel's first calls, 2026-12-06;
perf/README.md).

Finiteness is tested on the bit pattern (Taichi compiles with fast-math, where x != x may be
folded away).
"""

import numpy as np

from ...abi import LMLayout as LAY
from ...abi import LMReason, LMScale, LMStatus
from .arrays import copy
from .launch import address, launch
from .runtime import SPIRV_GRID_ITEMS, current_arch, loop_limit, scratch, ti

nd = ti.types.ndarray()

# status and reason codes and the packed layout's slots (gputrack/abi.py), folded into the kernels
RUNNING, CONVERGED, MAX_ITER, FAILED = (int(s) for s in (LMStatus.RUNNING, LMStatus.CONVERGED, LMStatus.MAX_ITER,
                                                          LMStatus.FAILED))
R_FTOL, R_XTOL, R_GTOL, R_MAXIT = (int(r) for r in (LMReason.FTOL, LMReason.XTOL, LMReason.GTOL, LMReason.MAX_ITER))
R_NONFINITE, R_NOTPD, R_DAMPING = (int(r) for r in (LMReason.NONFINITE, LMReason.NOT_PD, LMReason.DAMPING))
MAX_CHOL_TRIES = 40
# the damping's scaling, a global of S (see backends/reference/lm.py): C I, C diag(J^T J), C D (running max)
G_SCALE = LAY.G_SCALE
SCALE_IDENTITY, SCALE_MARQUARDT, SCALE_MINPACK = (int(m) for m in LMScale)  # gputrack.abi
GRAM_SEG = 8  # columns per SIMD vector of _gram_static (8 float64: one AVX-512 register)
STATIC_P_MAX = 32  # _gram_static unrolls P (P (P / 8 + 1) / 2 vector products per row of J)
TILES = -1  # the SP template value of _gram_tiles (P at run time, above STATIC_P_MAX)


def _per_problem() -> bool:
    """Compile-time choice: on taichi:cpu one serial loop over the problems, every phase of a
    problem in order; elsewhere parallel loops over (problem, row) with serial per-problem phases
    in between.

    On the CPU a parallel loop over B = 10 problems is one task anyway (Taichi gives each task of
    a parallel loop at least 512 indices), and the serial loop saves the thread-pool dispatch. Two
    tasks of five problems (a loop over 2 x 512 indices) measured 10-15% slower than the serial
    loop for B = 10, M = 256, P = 14 and 20 while another process kept one of the two cores busy
    (2026-11-23); not measured on an idle machine."""
    return current_arch() == "cpu"


def _ti_dtype(dt):
    return ti.f64 if np.dtype(dt) == np.float64 else ti.f32


@ti.func
def _finite(v, dt: ti.template()) -> ti.i32:
    ok = 1
    if ti.static(dt == ti.f64):
        bits = ti.bit_cast(ti.cast(v, ti.f64), ti.u64)
        ok = ti.i32(((bits >> ti.u64(52)) & ti.u64(0x7FF)) != ti.u64(0x7FF))
    else:
        bits = ti.bit_cast(ti.cast(v, ti.f32), ti.u32)
        ok = ti.i32(((bits >> ti.u32(23)) & ti.u32(0xFF)) != ti.u32(0xFF))
    return ok


@ti.func
def _nonzero(v, dt: ti.template()) -> ti.i32:
    """v is not +-0 (NaN and inf count), tested on the bit pattern as ``_finite``."""
    nz = 1
    if ti.static(dt == ti.f64):
        nz = ti.i32((ti.bit_cast(ti.cast(v, ti.f64), ti.u64) << ti.u64(1)) != ti.u64(0))
    else:
        nz = ti.i32((ti.bit_cast(ti.cast(v, ti.f32), ti.u32) << ti.u32(1)) != ti.u32(0))
    return nz


# ------------------------------------------------------------------------------------------------
# ops


@ti.func
def _transpose(J: ti.template(), W: ti.template(), b, i, off, M):
    """Column i of J[b] (stride P) into the contiguous row W[off + i*M : off + (i+1)*M]. Eight loads,
    then eight stores: Taichi reloads an ndarray's address after every store, so grouping the
    loads saves ~25% here."""
    o = off + i * M
    m = 0
    while m + 8 <= M:
        v0, v1, v2, v3 = J[b, m, i], J[b, m + 1, i], J[b, m + 2, i], J[b, m + 3, i]
        v4, v5, v6, v7 = J[b, m + 4, i], J[b, m + 5, i], J[b, m + 6, i], J[b, m + 7, i]
        W[o + m] = v0
        W[o + m + 1] = v1
        W[o + m + 2] = v2
        W[o + m + 3] = v3
        W[o + m + 4] = v4
        W[o + m + 5] = v5
        W[o + m + 6] = v6
        W[o + m + 7] = v7
        m += 8
    while m < M:
        W[o + m] = J[b, m, i]
        m += 1


@ti.func
def _jv(J: ti.template(), row, m, dt: ti.template(), diff: ti.template(), rm):
    """Entry m of a row of J^T: J[row + m] (a stored row, ``diff`` 0), or the unscaled difference of
    stacked residual rows (eq. 24 without 1 / den): J[row, m] - J[row + 1, m] (``diff`` 1, central)
    or J[row, m] - J[rm, m] (``diff`` 2, forward: rm the point's row)."""
    v = ti.cast(0, dt)
    if ti.static(diff == 1):
        v = ti.cast(J[row, m], dt) - ti.cast(J[row + 1, m], dt)
    elif ti.static(diff == 2):
        v = ti.cast(J[row, m], dt) - ti.cast(J[rm, m], dt)
    else:
        v = J[row + m]
    return v


@ti.func
def _inv(S: ti.template(), deno, n, dt: ti.template(), diff: ti.template()):
    """Scale of row n of J^T: 1 / den[n] for residual differences (0 for a zero step), else 1."""
    v = ti.cast(1, dt)
    if ti.static(diff):
        d = S[deno + n]
        v = ti.cast(0, dt)
        if d != 0:
            v = 1 / d
    return v


@ti.func
def _gram_pair(
    J: ti.template(),
    jt,
    jstep,
    W: ti.template(),
    a,
    R: ti.template(),
    rrow,
    G: ti.template(),
    goff,
    i,
    M,
    P,
    dt: ti.template(),
    diff: ti.template(),
    S: ti.template(),
    deno,
):
    """Rows i and k = min(i + 1, P - 1) of J^T J (both triangles) into W[a + i*P + j] and J^T r into
    G[goff + i] (eq. 22), with r = R[rrow, :]. Row n of J^T starts at ``jt + n * jstep`` of J: a
    contiguous stored row (``diff`` 0), or the stacked residual row whose difference with the next
    one (``diff`` 1, central, eq. 24) or with the point's row rrow (``diff`` 2, forward) over the
    denominators S[deno + n] is that row (the scale is applied to the sums).

    Two rows by four columns per pass over M (each column row is loaded once for both rows): ~25%
    faster than one row by four columns on taichi:cpu (3.9 instead of 5.2 us for P = 20, M = 256,
    float64). For an odd P the last pass computes row P - 1 twice."""
    k = ti.min(i + 1, P - 1)
    ri = jt + i * jstep
    rk = jt + k * jstep
    ci = _inv(S, deno, i, dt, diff)
    ck = _inv(S, deno, k, dt, diff)
    j = 0
    while j + 3 <= i:
        s0 = ti.cast(0, dt)
        s1 = ti.cast(0, dt)
        s2 = ti.cast(0, dt)
        s3 = ti.cast(0, dt)
        t0 = ti.cast(0, dt)
        t1 = ti.cast(0, dt)
        t2 = ti.cast(0, dt)
        t3 = ti.cast(0, dt)
        r0 = jt + j * jstep
        for m in range(M):
            x = _jv(J, ri, m, dt, diff, rrow)
            y = _jv(J, rk, m, dt, diff, rrow)
            w0 = _jv(J, r0, m, dt, diff, rrow)
            w1 = _jv(J, r0 + jstep, m, dt, diff, rrow)
            w2 = _jv(J, r0 + 2 * jstep, m, dt, diff, rrow)
            w3 = _jv(J, r0 + 3 * jstep, m, dt, diff, rrow)
            s0 += x * w0
            s1 += x * w1
            s2 += x * w2
            s3 += x * w3
            t0 += y * w0
            t1 += y * w1
            t2 += y * w2
            t3 += y * w3
        c0 = _inv(S, deno, j, dt, diff)
        c1 = _inv(S, deno, j + 1, dt, diff)
        c2 = _inv(S, deno, j + 2, dt, diff)
        c3 = _inv(S, deno, j + 3, dt, diff)
        _put4(W, a, P, i, j, s0 * ci * c0, s1 * ci * c1, s2 * ci * c2, s3 * ci * c3)
        _put4(W, a, P, k, j, t0 * ck * c0, t1 * ck * c1, t2 * ck * c2, t3 * ck * c3)
        j += 4
    while j <= k:
        s = ti.cast(0, dt)
        t = ti.cast(0, dt)
        rj = jt + j * jstep
        for m in range(M):
            w = _jv(J, rj, m, dt, diff, rrow)
            s += _jv(J, ri, m, dt, diff, rrow) * w
            t += _jv(J, rk, m, dt, diff, rrow) * w
        cj = _inv(S, deno, j, dt, diff)
        if j <= i:
            W[a + i * P + j] = s * ci * cj
            W[a + j * P + i] = s * ci * cj
        W[a + k * P + j] = t * ck * cj
        W[a + j * P + k] = t * ck * cj
        j += 1
    s = ti.cast(0, dt)
    t = ti.cast(0, dt)
    for m in range(M):
        v = ti.cast(R[rrow, m], dt)
        s += _jv(J, ri, m, dt, diff, rrow) * v
        t += _jv(J, rk, m, dt, diff, rrow) * v
    G[goff + i] = s * ci
    G[goff + k] = t * ck


@ti.func
def _put4(W: ti.template(), a, P, i, j, s0, s1, s2, s3):
    """A[i, j..j+3] and A[j..j+3, i] of the P x P matrix at W[a]."""
    W[a + i * P + j] = s0
    W[a + i * P + j + 1] = s1
    W[a + i * P + j + 2] = s2
    W[a + i * P + j + 3] = s3
    W[a + j * P + i] = s0
    W[a + (j + 1) * P + i] = s1
    W[a + (j + 2) * P + i] = s2
    W[a + (j + 3) * P + i] = s3


@ti.func
def _jrow(J: ti.template(), b, m, c0: ti.template(), w: ti.template(), V: ti.template(), dt: ti.template()):
    """J[b, m, c0 .. c0 + w - 1] of the (B, M, P) Jacobian as one lane vector: w scalar loads where
    J holds scalars (V = 1), w / V vector loads where it holds V-lane vectors (c0, w multiples of V)."""
    out = ti.Vector([0.0] * w, dt=dt)
    if ti.static(V == 1):
        out = ti.Vector([ti.cast(J[b, m, c0 + e], dt) for e in ti.static(range(w))], dt=dt)
    else:
        parts = [J[b, m, c0 // V + k] for k in ti.static(range(w // V))]
        out = ti.Vector([ti.cast(parts[e // V][e % V], dt) for e in ti.static(range(w))], dt=dt)
    return out


@ti.func
def _gram_static(J: ti.template(), r: ti.template(), b, M, W: ti.template(), a, go, P: ti.template(),
                 dt: ti.template(), V: ti.template()):  # fmt: skip
    """J^T J (both triangles) into W[a + i*P + j] and J^T r into W[go + i] (eq. 22) from J[b] (M, P)
    as stored, P a compile-time value: the sum over rows m of J of the outer product of row m with
    itself, each product row i..P-1 kept as SIMD vectors of GRAM_SEG columns (lane vectors: the
    kernel is compiled with scalarisation off on the CPU). No transpose, and each row of J is read
    once. ``V``: 1 where J holds scalars, 2 where it holds pairs (``JAC_PAIRS``): LLVM gathers the
    scalars of a row (Taichi's int32 index arithmetic hides that they are adjacent) and loads the
    pairs as vectors. Per problem, P = 20 / 14, M = 256, float64, kernel profiler, one thread, in
    one run (2026-12-06): ~9 / 7 us from scalars, ~5.5 / 3.5 us from pairs (~5 / 3 us from scalars
    on 2026-11-23: the machine's speed varies); ~8.5 / 5.7 us transposing first (``_transpose`` +
    ``_gram_pair``, 2026-11-23)."""
    S = ti.static(GRAM_SEG)
    NS = ti.static((P + S - 1) // S)
    WS = ti.static([min(S, P - S * q) for q in range(NS)])  # segment widths (the last one may be narrower)
    acc = [[ti.Vector([0.0] * WS[q], dt=dt) for q in ti.static(range(i // S + 1))] for i in ti.static(range(P))]
    accg = [ti.Vector([0.0] * WS[q], dt=dt) for q in ti.static(range(NS))]
    for m in range(M):
        seg = [_jrow(J, b, m, S * q, WS[q], V, dt) for q in ti.static(range(NS))]
        rm = ti.cast(r[b, m], dt)
        for i in ti.static(range(P)):
            x = _jrow(J, b, m, i // V * V, V, V, dt)[i % V]  # a broadcast load, or a lane of a pair
            for q in ti.static(range(i // S + 1)):
                acc[i][q] += x * seg[q]
        for q in ti.static(range(NS)):
            accg[q] += rm * seg[q]
    for i in ti.static(range(P)):
        for q in ti.static(range(i // S + 1)):
            for e in ti.static(range(WS[q])):
                if ti.static(S * q + e <= i):
                    W[a + i * P + S * q + e] = acc[i][q][e]
                    W[a + (S * q + e) * P + i] = acc[i][q][e]
    for q in ti.static(range(NS)):
        for e in ti.static(range(WS[q])):
            W[go + S * q + e] = accg[q][e]


@ti.func
def _lane_row(J: ti.template(), b, m, c0, P, dt: ti.template(), edge: ti.template()):
    """J[b, m, c0 .. c0 + GRAM_SEG - 1] as one lane vector; with ``edge`` the columns >= P read 0."""
    T = ti.static(GRAM_SEG)
    v = ti.Vector([0.0] * T, dt=dt)
    if ti.static(edge):
        v = ti.Vector([ti.select(c0 + e < P, ti.cast(J[b, m, ti.min(c0 + e, P - 1)], dt), ti.cast(0, dt))
                       for e in ti.static(range(T))], dt=dt)  # fmt: skip
    else:
        v = ti.Vector([ti.cast(J[b, m, c0 + e], dt) for e in ti.static(range(T))], dt=dt)
    return v


@ti.func
def _gram_tile(J: ti.template(), b, M, P, W: ti.template(), a, i0, j0, z, NB, dt: ti.template(), edge: ti.template(),
               sparse: ti.template()):  # fmt: skip
    """Rows i0.. and columns j0.. (GRAM_SEG each, j0 <= i0) of J^T J into W[a + i*P + j] and its
    mirror: the sum over the rows m of J of row m's entries i times its lane vector of columns j.
    With ``sparse``, W[z + m NB + k] is 0 where row m of J is 0 in column block k (``_row_blocks``):
    the rows that are 0 in either block are skipped."""
    T = ti.static(GRAM_SEG)
    acc = [ti.Vector([0.0] * T, dt=dt) for _ in ti.static(range(T))]
    bi, bj = i0 // T, j0 // T
    for m in range(M):
        take = 1
        if ti.static(sparse):
            take = W[z + m * NB + bi] * W[z + m * NB + bj] != 0  # marks 0 or 1
        if take:
            col = _lane_row(J, b, m, j0, P, dt, edge)
            for q in ti.static(range(T)):
                x = ti.cast(0, dt)
                if ti.static(edge):
                    x = ti.select(i0 + q < P, ti.cast(J[b, m, ti.min(i0 + q, P - 1)], dt), ti.cast(0, dt))
                else:
                    x = ti.cast(J[b, m, i0 + q], dt)
                acc[q] += x * col
    for q in ti.static(range(T)):
        for e in ti.static(range(T)):
            i, j = i0 + q, j0 + e
            if i < P and j <= i:
                W[a + i * P + j] = acc[q][e]
                W[a + j * P + i] = acc[q][e]


@ti.func
def _row_blocks(J: ti.template(), b, M, P, W: ti.template(), z, NB, dt: ti.template()):
    """W[z + m NB + k] = 1 where row m of J[b] has an entry other than 0 (NaN counts) in columns
    GRAM_SEG k .. GRAM_SEG (k + 1) - 1, else 0: the row blocks ``_gram_tile`` skips."""
    T = ti.static(GRAM_SEG)
    full = P // T
    for m in range(M):
        for k in range(NB):
            v = ti.Vector([0.0] * T, dt=dt)
            if k < full:
                v = _lane_row(J, b, m, k * T, P, dt, False)
            else:
                v = _lane_row(J, b, m, k * T, P, dt, True)
            nz = 0  # lane by lane: a vector comparison's any() came out 0 for some rows (no scalarisation)
            for e in ti.static(range(T)):
                nz |= _nonzero(v[e], dt)
            W[z + m * NB + k] = ti.select(nz != 0, ti.cast(1, dt), ti.cast(0, dt))


@ti.func
def _gram_tiles(J: ti.template(), r: ti.template(), b, M, P, W: ti.template(), a, go, dt: ti.template(), z=-1):
    """J^T J (both triangles) into W[a + i*P + j] and J^T r into W[go + i] (eq. 22) from J[b] (M, P)
    as stored, P at run time (taichi:cpu, P > STATIC_P_MAX): the lower triangle in GRAM_SEG x
    GRAM_SEG tiles, each a pass over the rows of J with GRAM_SEG lane-vector sums (no spills, each
    row of J read once per tile; only the tiles of the last row band test the columns against P).
    For P = 92, M = 155, float64 (the face bundle's update) 84-102 us against 96-114 us copying J
    into rows of J^T and summing row pairs (``_phase_jacobian`` + ``_gram_pair``; minimum of 300
    launches each, two runs, 2026-12-06); the tiled sums also serve ``lm_solve`` and
    ``normal_equations``, where J was transposed first.

    ``z`` >= 0 (the solver's given Jacobian): M NB values of scratch at W[z], where the rows of J that
    are 0 in a column block are marked first (``_row_blocks``) and each tile skips the rows that are 0
    in either of its blocks: the same sums (products of 0 left out), for a block-sparse J (the face
    bundle's: a frame's rows are 0 outside its pose, deformation and the identity) in fewer passes.
    The solver's update for the face bundle (P = 92, M = 155, 7 frames; the solver's profile over
    103 frames, three rounds in turn): 0.182 / 0.188 / 0.206 ms without the marks, 0.132 / 0.154 /
    0.153 ms with them; the tiles alone for a dense J (a scratch kernel, direct launches, two runs):
    100 / 133 us without the marks, 116 / 175 us with them (taichi:cpu, 2026-12-06)."""
    T = ti.static(GRAM_SEG)
    NB = (P + T - 1) // T
    full = P // T  # row bands without columns past P
    if z >= 0:
        _row_blocks(J, b, M, P, W, z, NB, dt)
    for bi in range(NB):
        for bj in range(bi + 1):
            if z >= 0:
                if bi < full:
                    _gram_tile(J, b, M, P, W, a, bi * T, bj * T, z, NB, dt, False, True)
                else:
                    _gram_tile(J, b, M, P, W, a, bi * T, bj * T, z, NB, dt, True, True)
            elif bi < full:
                _gram_tile(J, b, M, P, W, a, bi * T, bj * T, z, NB, dt, False, False)
            else:
                _gram_tile(J, b, M, P, W, a, bi * T, bj * T, z, NB, dt, True, False)
    for bi in range(NB):
        acc = ti.Vector([0.0] * T, dt=dt)
        if bi < full:
            for m in range(M):
                acc += ti.cast(r[b, m], dt) * _lane_row(J, b, m, bi * T, P, dt, False)
        else:
            for m in range(M):
                acc += ti.cast(r[b, m], dt) * _lane_row(J, b, m, bi * T, P, dt, True)
        for e in ti.static(range(T)):
            if bi * T + e < P:
                W[go + bi * T + e] = acc[e]


@ti.func
def _ops_block(P, M):
    """Per-problem block of the ops' 1-D workspace: A[P*P] (J^T J, then its factor), J^T [P*M], g[P]."""
    return P * P + P * M + P


@ti.kernel
def _normal_equations(J: nd, r: nd, JtJ: nd, Jtr: nd, W: nd, dt: ti.template(), SP: ti.template()):
    """taichi:cpu (the parallel archs run ``_normal_equations_tasks``). SP: P as a compile-time value
    for ``_gram_static``, or TILES (``_gram_tiles``)."""
    B, M, P = J.shape[0], J.shape[1], J.shape[2]
    WB = _ops_block(P, M)
    ti.loop_config(serialize=True)  # B small problems: one task (see _per_problem)
    for b in range(B):
        if ti.static(SP > 0):
            _gram_static(J, r, b, M, W, b * WB, b * WB + SP * SP + SP * M, SP, dt, 1)  # eq. 22
        else:
            _gram_tiles(J, r, b, M, P, W, b * WB, b * WB + P * P + P * M, dt)  # eq. 22
    for t in range(B * P * P):
        b, k = t // (P * P), t % (P * P)
        JtJ[b, k // P, k % P] = W[b * WB + k]
    for t in range(B * P):
        b, i = t // P, t % P
        Jtr[b, i] = W[b * WB + P * P + P * M + i]


@ti.func
def _chol_solve(W: ti.template(), a, delta: ti.template(), b, P, C, dt: ti.template()) -> ti.i32:
    """In place: W[a + i*P + j] (lower triangle read, + C I) -> L; delta[b] (rhs) -> solution.
    Returns 0 (and delta = 0) if the damped matrix is not positive definite."""
    ok = 1
    for j in range(P):
        if ok:
            s = W[a + j * P + j] + C
            for k in range(j):
                s -= W[a + j * P + k] * W[a + j * P + k]
            if s <= 0 or not _finite(s, dt):
                ok = 0
            else:
                d = ti.sqrt(s)
                W[a + j * P + j] = d
                for i in range(j + 1, P):
                    v = W[a + i * P + j]
                    for k in range(j):
                        v -= W[a + i * P + k] * W[a + j * P + k]
                    W[a + i * P + j] = v / d
    if ok:
        for i in range(P):
            v = delta[b, i]
            for k in range(i):
                v -= W[a + i * P + k] * delta[b, k]
            delta[b, i] = v / W[a + i * P + i]
        for ii in range(P):
            i = P - 1 - ii
            v = delta[b, i]
            for k in range(i + 1, P):
                v -= W[a + k * P + i] * delta[b, k]
            delta[b, i] = v / W[a + i * P + i]
    else:
        for i in range(P):
            delta[b, i] = ti.cast(0, dt)
    return ok


@ti.kernel
def _lm_step(JtJ: nd, Jtr: nd, damping: nd, delta: nd, ok: nd, W: nd, dt: ti.template()):
    """W: (B*P*P,) work for the factors. taichi:cpu; the parallel archs run ``_lm_step_tasks``."""
    B, P = Jtr.shape[0], Jtr.shape[1]
    for b in range(B):
        for i in range(P):
            delta[b, i] = Jtr[b, i]
            for j in range(i + 1):
                W[b * P * P + i * P + j] = JtJ[b, i, j]
        ok[b] = _chol_solve(W, b * P * P, delta, b, P, damping[b], dt)  # eq. 22


@ti.kernel
def _lm_solve(J: nd, r: nd, damping: nd, delta: nd, ok: nd, W: nd, dt: ti.template(), SP: ti.template()):
    """W: (B * _ops_block(P, M),) work. taichi:cpu: one problem after the other (``_per_problem``;
    the problem's data stays in cache between the products and the factorisation); the parallel
    archs run ``_lm_solve_tasks``. SP: P as a compile-time value for ``_gram_static``, or TILES
    (``_gram_tiles``)."""
    B = J.shape[0]
    ti.loop_config(serialize=True)
    for b in range(B):
        _solve_one(J, r, damping, delta, ok, W, b, dt, SP)


@ti.func
def _solve_one(
    J: ti.template(),
    r: ti.template(),
    damping: ti.template(),
    delta: ti.template(),
    ok: ti.template(),
    W: ti.template(),
    b,
    dt: ti.template(),
    SP: ti.template(),
):
    M, P = J.shape[1], J.shape[2]
    a = b * _ops_block(P, M)
    jt = a + P * P
    if ti.static(SP > 0):
        _gram_static(J, r, b, M, W, a, jt + SP * M, SP, dt, 1)  # eq. 22: J^T J, J^T r
    else:
        _gram_tiles(J, r, b, M, P, W, a, jt + P * M, dt)  # eq. 22: J^T J, J^T r
    for i in range(P):
        delta[b, i] = W[jt + P * M + i]
    ok[b] = _chol_solve(W, a, delta, b, P, damping[b], dt)  # eq. 22: (J^T J + C I) delta = J^T r


def _work(device, shape, dtype):
    """The ops' work array (runtime.scratch: kept per device and shape; Taichi allocations are slow)."""
    return scratch(device, "lm_ops", shape, _ti_dtype(dtype))


def _in_pairs(J) -> bool:
    """The solver's Jacobian J (B, M, P) is read as pairs of columns on taichi:cpu (``_update_pairs``):
    a float64 NumPy array (the kernels read it in place) with P even and <= STATIC_P_MAX, C-contiguous
    and 16-byte aligned (as NumPy allocates; a vector load assumes it)."""
    P = J.shape[2]
    return (type(J) is np.ndarray and J.dtype == np.float64 and P % 2 == 0 and P <= STATIC_P_MAX
            and J.flags.c_contiguous and address(J) % 16 == 0)  # fmt: skip


def _static_p(P: int) -> int:
    """How the taichi:cpu kernels (``_per_problem``) sum J^T J from a stored J: P as a compile-time
    value for ``_gram_static`` (P <= STATIC_P_MAX), else TILES (``_gram_tiles``)."""
    return P if P <= STATIC_P_MAX else TILES


def normal_equations(device, J, r, out):
    B, M, P = J.shape
    JtJ, Jtr = out
    W = _work(device, (B * (P * P + P * M + P),), J.dtype)
    args = (J.buffer, r.buffer, JtJ.buffer, Jtr.buffer, W)
    if _per_problem():
        launch(_normal_equations, args, (_ti_dtype(J.dtype), _static_p(P)), scalarize=False)
    else:
        _tasks_plan(device, B, P, M, "normal")  # raises where the device cannot run it
        launch(_normal_equations_tasks, args, (_ti_dtype(J.dtype), _grid(B * ((P + 1) // 2) * ((P + 3) // 4 + 1))))
    return JtJ, Jtr


def lm_step(device, JtJ, Jtr, damping, out):
    B, P = Jtr.shape
    delta, ok = out
    if _per_problem():
        W = _work(device, (B * P * P,), Jtr.dtype)
        args = (JtJ.buffer, Jtr.buffer, damping.buffer, delta.buffer, ok.buffer, W)
        launch(_lm_step, args, (_ti_dtype(Jtr.dtype),))
    else:
        ncol, nt = _tasks_plan(device, B, P, 0, "ops")
        W = _work(device, (B * (P * P + P),), Jtr.dtype)
        args = (JtJ.buffer, Jtr.buffer, damping.buffer, delta.buffer, ok.buffer, W)
        for it in range(nt):
            launch(_lm_step_tasks, args, (_ti_dtype(Jtr.dtype), _grid(B * P)), scalars=(ncol, it, nt))
    return delta, ok


def lm_solve(device, J, r, damping, out):
    B, M, P = J.shape
    delta, ok = out
    W = _work(device, (B * (P * P + P * M + P),), J.dtype)
    args = (J.buffer, r.buffer, damping.buffer, delta.buffer, ok.buffer, W)
    if _per_problem():
        launch(_lm_solve, args, (_ti_dtype(J.dtype), _static_p(P)), scalarize=False)
    else:
        ncol, nt = _tasks_plan(device, B, P, M, "ops")
        NI = _grid(B * ((P + 1) // 2) * ((P + 3) // 4 + 1))
        for it in range(nt):
            launch(_lm_solve_tasks, args, (_ti_dtype(J.dtype), NI), scalars=(ncol, it, nt))
    return delta, ok


# ------------------------------------------------------------------------------------------------
# solver: packed state (gputrack.ops.lm.Layout), one launch per iteration


@ti.func
def _sb(P):
    return LAY.S_NVEC * P + LAY.NSCAL


@ti.func
def _ib(b, P):
    """Offset of problem b's int block in I."""
    return LAY.NIGLOB + b * (LAY.I_NFIX + P)


@ti.func
def _wb(P, M):
    return LAY.W_NSQ * P * P + P * M + P


@ti.func
def _wd(b, P, M):
    """Offset of problem b's damping scale D[P] in W (after J^T)."""
    return b * _wb(P, M) + LAY.W_NSQ * P * P + P * M


@ti.func
def _cref(W: ti.template(), A, P, scale, dt: ti.template()):
    """What the damping's limits are relative to: 1 + max diag(J^T J) for C I, 1 when scaled."""
    dmax = ti.cast(0, dt)
    for i in range(P):
        dmax = ti.max(dmax, W[A + i * P + i])
    return ti.select(scale == SCALE_IDENTITY, dmax + 1, ti.cast(1, dt))


@ti.func
def _step_norms(S: ti.template(), W: ti.template(), base, wd, P, weighted, xslot: ti.template(),
                dt: ti.template()):  # fmt: skip
    """(||xt - x||^2, ||p||^2) of a problem (p: x or xt, by ``xslot``), weighted by the last step's
    damping scale D when ``weighted`` (as MINPACK's ||D x||: scale-invariant)."""
    sn = ti.cast(0, dt)
    xn = ti.cast(0, dt)
    for i in range(P):
        w = ti.select(weighted, W[wd + i], ti.cast(1, dt))
        d = S[base + LAY.S_XT * P + i] - S[base + LAY.S_X * P + i]
        p = S[base + xslot * P + i]
        sn += w * d * d
        xn += w * p * p
    return sn, xn


@ti.func
def _gtol_test(S: ti.template(), I: ti.template(), W: ti.template(), b, A, P, G, scale, dt: ti.template()):
    """Converged (GTOL) when the projected gradient's max-norm (scaled modes: MINPACK's
    |J_n^T r| / (||J_n|| ||r||)) is <= gtol."""
    base = b * _sb(P)
    ib = _ib(b, P)
    xo, go = base + LAY.S_X * P, base + LAY.S_G * P
    loo, hio = base + LAY.S_LO * P, base + LAY.S_HI * P
    F = S[base + LAY.S_NVEC * P + LAY.SC_F]
    gmax = ti.cast(0, dt)
    for i in range(P):
        if not _active(S, xo, loo, hio, go, i):
            gi = ti.abs(S[go + i])
            if scale != SCALE_IDENTITY:
                nrm = ti.sqrt(W[A + i * P + i] * F)
                gi = ti.select(nrm > 0, gi / ti.select(nrm > 0, nrm, ti.cast(1, dt)), ti.cast(0, dt))
            gmax = ti.max(gmax, gi)
    if gmax <= S[G + LAY.G_GTOL]:
        I[ib + LAY.I_STATUS] = CONVERGED
        I[ib + LAY.I_REASON] = R_GTOL


@ti.func
def _damping_scale(I: ti.template(), W: ti.template(), b, A, wd, P, scale, dt: ti.template()):
    """D of this step into W[wd]: 1 (C I, eq. 22), diag(J^T J) (Marquardt) or its running maximum
    over the problem's iterations (MINPACK); 1 for a zero column."""
    it = I[_ib(b, P) + LAY.I_ITER]
    for i in range(P):
        d = ti.cast(1, dt)
        if scale != SCALE_IDENTITY:
            d = W[A + i * P + i]
            if scale == SCALE_MINPACK and it > 0:
                d = ti.max(d, W[wd + i])
            d = ti.select(d > 0, d, ti.cast(1, dt))
        W[wd + i] = d


@ti.func
def _phase_jacobian(
    S: ti.template(),
    I: ti.template(),
    W: ti.template(),
    R: ti.template(),
    Jg: ti.template(),
    b,
    n,
    dt: ti.template(),
    use_jac: ti.template(),
):
    """Jt[b, n, :] at the evaluated trial (eq. 24 or given) and its finite flag."""
    P, M, B = I[LAY.IG_P], R.shape[1], I[LAY.IG_B]
    SB = _sb(P)
    base = b * SB
    ibase = _ib(b, P)
    jt = b * _wb(P, M) + LAY.W_NSQ * P * P + n * M
    ok = 1
    if ti.static(use_jac):
        mag = ti.cast(0, dt)
        for m in range(M):
            v = ti.cast(Jg[b, m, n], dt)
            mag += ti.abs(v)
            W[jt + m] = v
        ok = _finite(mag, dt)
    else:
        SR = R.shape[0] // B
        den = S[base + LAY.S_DEN * P + n]
        inv = ti.cast(0, dt)
        if den != 0:
            inv = 1 / den
        # the row moved by +eps in parameter n and the one it is compared with: the row moved by -eps
        # (central, eq. 24) or the point's (forward)
        rp, rq = b * SR + 1 + 2 * n, b * SR + 2 + 2 * n
        if SR != 2 * P + 1:
            rp, rq = b * SR + 1 + n, b * SR
        mbase = B * SB + LAY.NGLOB
        # a non-finite difference makes the sum of magnitudes non-finite: one test per row
        mag = ti.cast(0, dt)
        if I[LAY.IG_HAS_MASK]:
            for m in range(M):
                d = ti.select(
                    S[mbase + m * P + n] != 0, ti.cast(R[rp, m], dt) - ti.cast(R[rq, m], dt), ti.cast(0, dt)
                )
                mag += ti.abs(d)
                W[jt + m] = d * inv  # eq. 24, only where the mask is set
        else:
            for m in range(M):
                d = ti.cast(R[rp, m], dt) - ti.cast(R[rq, m], dt)  # r(x + eps e_n) - r(x -+ eps e_n)
                mag += ti.abs(d)
                W[jt + m] = d * inv  # eq. 24
        ok = _finite(mag, dt)
    I[ibase + LAY.I_FIN + n] = ok


@ti.func
def _phase_accept(
    S: ti.template(),
    I: ti.template(),
    W: ti.template(),
    R: ti.template(),
    b,
    dt: ti.template(),
    first,
    final,
):
    """Acceptance of problem b's trial (eq. 20-22's cost and gain ratio, the damping's update, the
    ftol and xtol tests). ``first`` (the start point) and ``final`` (the last call) are run-time
    flags: one compiled ``_update`` serves every iteration (see the module docstring)."""
    P, M, B = I[LAY.IG_P], R.shape[1], I[LAY.IG_B]
    SB = _sb(P)
    base = b * SB
    sc = base + LAY.S_NVEC * P
    A = b * _wb(P, M) + LAY.W_A * P * P
    ib = _ib(b, P)
    G = B * SB
    ftol, xtol, cmax = S[G + LAY.G_FTOL], S[G + LAY.G_XTOL], S[G + LAY.G_CMAX]
    scale = ti.cast(S[G + G_SCALE], ti.i32)
    wd = _wd(b, P, M)
    weighted = ti.i32(scale != SCALE_IDENTITY) * ti.i32(first == 0)
    SR = R.shape[0] // B
    I[ib + LAY.I_ACCEPTED] = 0
    if I[ib + LAY.I_STATUS] == RUNNING:
        ok = 1
        Ft = ti.cast(0, dt)
        for m in range(M):
            v = ti.cast(R[b * SR, m], dt)
            ok &= _finite(v, dt)
            Ft += v * v  # eq. 20-21: cost = r^T r
        ok &= _finite(Ft, dt)
        if final == 0:
            for n in range(P):
                ok &= I[ib + LAY.I_FIN + n]
        S[sc + LAY.SC_FT] = Ft
        acc = 0
        if first:
            if not ok:
                I[ib + LAY.I_STATUS] = FAILED
                I[ib + LAY.I_REASON] = R_NONFINITE
                S[sc + LAY.SC_F] = ti.cast(np.inf, dt)  # no finite cost at x0
            else:
                acc = 1
        else:
            I[ib + LAY.I_ITER] += 1
            F, pred = S[sc + LAY.SC_F], S[sc + LAY.SC_PRED]
            dF = F - Ft
            if ok and dF > 0:  # a trial with non-finite residuals or Jacobian is rejected (as MINPACK)
                acc = 1
                rho = ti.cast(1, dt)
                if pred > 0:
                    rho = dF / pred
                q = 2 * rho - 1
                # Nielsen: lower C near the optimum
                S[sc + LAY.SC_C] *= ti.max(ti.cast(1.0 / 3.0, dt), 1 - q * q * q)
                S[sc + LAY.SC_NU] = ti.cast(2, dt)
            else:
                S[sc + LAY.SC_C] *= S[sc + LAY.SC_NU]  # rejected: raise this problem's C only
                S[sc + LAY.SC_NU] *= 2
                sn, xn = _step_norms(S, W, base, wd, P, weighted, LAY.S_X, dt)
                if ti.sqrt(sn) <= xtol * (xtol + ti.sqrt(xn)):
                    I[ib + LAY.I_STATUS] = CONVERGED  # no step this small improves the cost
                    I[ib + LAY.I_REASON] = R_XTOL
                elif S[sc + LAY.SC_C] > cmax * _cref(W, A, P, scale, dt):
                    I[ib + LAY.I_STATUS] = FAILED
                    I[ib + LAY.I_REASON] = R_DAMPING
        if acc:
            I[ib + LAY.I_ACCEPTED] = 1
            sn2, xn = _step_norms(S, W, base, wd, P, weighted, LAY.S_XT, dt)  # |x| at the new x
            for i in range(P):
                S[base + LAY.S_X * P + i] = S[base + LAY.S_XT * P + i]
            sn = ti.sqrt(sn2)
            S[sc + LAY.SC_SNORM] = sn
            F_old = S[sc + LAY.SC_F]
            S[sc + LAY.SC_F] = Ft
            if first == 0:
                if F_old - Ft <= ftol * F_old:
                    I[ib + LAY.I_STATUS] = CONVERGED
                    I[ib + LAY.I_REASON] = R_FTOL
                elif sn <= xtol * (xtol + ti.sqrt(xn)):
                    I[ib + LAY.I_STATUS] = CONVERGED
                    I[ib + LAY.I_REASON] = R_XTOL
        if final and I[ib + LAY.I_STATUS] == RUNNING:
            I[ib + LAY.I_STATUS] = MAX_ITER
            I[ib + LAY.I_REASON] = R_MAXIT


@ti.func
def _phase_normal(
    S: ti.template(),
    I: ti.template(),
    W: ti.template(),
    R: ti.template(),
    b,
    i,
    dt: ti.template(),
    fused: ti.template(),
):
    """Rows i and i + 1 of J^T J and J^T r at the accepted point (eq. 22): from the rows of J^T in W,
    or with ``fused`` straight from the stacked residuals (1: central differences, 2: forward ones;
    no mask)."""
    P, M, B = I[LAY.IG_P], R.shape[1], I[LAY.IG_B]
    if I[_ib(b, P) + LAY.I_ACCEPTED]:
        A = b * _wb(P, M) + LAY.W_A * P * P
        SR = R.shape[0] // B
        base = b * _sb(P)
        if ti.static(fused):
            g, den = base + LAY.S_G * P, base + LAY.S_DEN * P
            _gram_pair(R, b * SR + 1, 3 - fused, W, A, R, b * SR, S, g, i, M, P, dt, fused, S, den)
        else:
            jt = A + (LAY.W_NSQ - LAY.W_A) * P * P
            _gram_pair(W, jt, M, W, A, R, b * SR, S, base + LAY.S_G * P, i, M, P, dt, 0, S, 0)


@ti.func
def _phase_finite(S: ti.template(), I: ti.template(), R: ti.template(), b, dt: ti.template()):
    """The finite flags of the perturbed rows of problem b (``_phase_jacobian`` without storing J^T)."""
    P, M, B = I[LAY.IG_P], R.shape[1], I[LAY.IG_B]
    SR = R.shape[0] // B
    for n in range(P):
        rp, rq = b * SR + 1 + 2 * n, b * SR + 2 + 2 * n  # central (eq. 24)
        if SR != 2 * P + 1:
            rp, rq = b * SR + 1 + n, b * SR  # forward
        mag = ti.cast(0, dt)
        for m in range(M):
            mag += ti.abs(ti.cast(R[rp, m], dt) - ti.cast(R[rq, m], dt))
        I[_ib(b, P) + LAY.I_FIN + n] = _finite(mag, dt)


@ti.func
def _envelope(W: ti.template(), A, env, P, dt: ti.template()):
    """W[env + i] = the first column of row i of the P x P matrix at W[A] that is not 0 (NaN counts;
    i where the row has none before the diagonal)."""
    for i in range(P):
        f = i
        for k in range(i):
            if f == i and _nonzero(W[A + i * P + k], dt):
                f = k
        W[env + i] = ti.cast(f, dt)


@ti.func
def _active(S: ti.template(), xo, loo, hio, go, i) -> ti.i32:
    """Parameter i is held at a bound by the gradient (the step is x - delta)."""
    x, gi = S[xo + i], S[go + i]
    return ti.i32((x >= S[hio + i] and gi < 0) or (x <= S[loo + i] and gi > 0))


@ti.func
def _phase_step(S: ti.template(), I: ti.template(), W: ti.template(), X: ti.template(), b, M, dt: ti.template()):
    """gtol test, damped Cholesky step, trial point and the next points to evaluate."""
    P, B = I[LAY.IG_P], I[LAY.IG_B]
    SB = _sb(P)
    base = b * SB
    sc = base + LAY.S_NVEC * P
    ib = _ib(b, P)
    G = B * SB
    rel, ctiny, cmax = S[G + LAY.G_REL], S[G + LAY.G_CTINY], S[G + LAY.G_CMAX]
    scale = ti.cast(S[G + G_SCALE], ti.i32)
    A = b * _wb(P, M) + LAY.W_A * P * P
    L = A + (LAY.W_L - LAY.W_A) * P * P
    wd = _wd(b, P, M)
    xo, xto, go = base + LAY.S_X * P, base + LAY.S_XT * P, base + LAY.S_G * P
    loo, hio = base + LAY.S_LO * P, base + LAY.S_HI * P
    if I[ib + LAY.I_STATUS] == RUNNING and I[ib + LAY.I_ACCEPTED]:
        _gtol_test(S, I, W, b, A, P, G, scale, dt)  # projected gradient (active bounds removed)
    if I[ib + LAY.I_STATUS] == RUNNING:
        _damping_scale(I, W, b, A, wd, P, scale, dt)
        dmax = _cref(W, A, P, scale, dt)
        C = S[sc + LAY.SC_C]
        env = b * _wb(P, M) + LAY.W_NSQ * P * P  # J^T's first P entries: free after the normal equations
        _envelope(W, A, env, P, dt)
        ok = 0
        tries = 0
        while tries <= MAX_CHOL_TRIES:
            # Cholesky of J^T J + C I (eq. 22) into L, within the rows' envelope (the factor has no
            # entry before a row's first entry of A: a block-sparse J^T J, the face bundle's, is
            # factored in fewer operations)
            ok = 1
            for j in range(P):
                if ok:
                    aj = _active(S, xo, loo, hio, go, j)
                    fj = ti.cast(W[env + j], ti.i32)
                    s = W[A + j * P + j] + C * W[wd + j]
                    if aj:
                        s = 1 + C
                    for k in range(fj, j):
                        s -= W[L + j * P + k] * W[L + j * P + k]
                    if s <= 0 or not _finite(s, dt):
                        ok = 0
                    else:
                        d = ti.sqrt(s)
                        W[L + j * P + j] = d
                        for i in range(j + 1, P):
                            fi = ti.cast(W[env + i], ti.i32)
                            v = ti.cast(0, dt)
                            if fi <= j:
                                v = W[A + i * P + j]
                                if aj or _active(S, xo, loo, hio, go, i):
                                    v = ti.cast(0, dt)
                                for k in range(ti.max(fi, fj), j):
                                    v -= W[L + i * P + k] * W[L + j * P + k]
                            W[L + i * P + j] = v / d
            if ok or C > cmax * dmax:
                break
            C = ti.max(10 * C, ctiny * dmax)  # not PD: raise C tenfold and try again
            tries += 1
        S[sc + LAY.SC_C] = C
        if not ok:
            I[ib + LAY.I_STATUS] = FAILED
            I[ib + LAY.I_REASON] = R_NOTPD
        else:
            # delta = (J^T J + C I)^-1 J^T r by substitution, in the xt slots
            for i in range(P):
                v = S[go + i]
                if _active(S, xo, loo, hio, go, i):
                    v = ti.cast(0, dt)
                for k in range(i):
                    v -= W[L + i * P + k] * S[xto + k]
                S[xto + i] = v / W[L + i * P + i]
            for ii in range(P):
                i = P - 1 - ii
                v = S[xto + i]
                for k in range(i + 1, P):
                    v -= W[L + k * P + i] * S[xto + k]
                S[xto + i] = v / W[L + i * P + i]
            for i in range(P):
                # eq. 22 step, projected into the box (paper 003 eq. 8-9)
                S[xto + i] = ti.min(ti.max(S[xo + i] - S[xto + i], S[loo + i]), S[hio + i])
            # predicted reduction of the model ||r - J s||^2 for s = x - xt
            pr = ti.cast(0, dt)
            for i in range(P):
                si = S[xo + i] - S[xto + i]
                As = ti.cast(0, dt)
                for j in range(P):
                    As += W[A + i * P + j] * (S[xo + j] - S[xto + j])
                pr += 2 * si * S[go + i] - si * As
            S[sc + LAY.SC_PRED] = pr
    # next points: the trial and its perturbed copies (eq. 24), or the accepted x when stopped
    src = xto
    if I[ib + LAY.I_STATUS] != RUNNING:
        src = xo
    _points(S, X, b, src, B, P, rel, dt)


@ti.func
def _eps(p, h, rel, dt: ti.template()):
    """The finite-difference step: h where given (> 0), else rel |p| (rel where p = 0, as MINPACK)."""
    a = ti.abs(p)
    return ti.select(h > 0, h, rel * ti.select(a > 0, a, ti.cast(1, dt)))


@ti.func
def _points(S: ti.template(), X: ti.template(), b, src, B, P, rel, dt: ti.template()):
    """Rows b*SX .. of X: the point S[src : src + P] and, when SX > 1, its perturbed copies
    (eq. 24); their denominators (over the stored, possibly rounded, points) into den."""
    base = b * _sb(P)
    deno, loo, hio, ho = base + LAY.S_DEN * P, base + LAY.S_LO * P, base + LAY.S_HI * P, base + LAY.S_H * P
    SX = X.shape[0] // B
    for row in range(SX):
        for n in range(P):
            X[b * SX + row, n] = S[src + n]
    if SX > 1:
        for n in range(P):
            p = S[src + n]
            eps = _eps(p, S[ho + n], rel, dt)
            if SX == 2 * P + 1:  # central (eq. 24)
                rp = b * SX + 1 + 2 * n
                X[rp, n] = ti.min(p + eps, S[hio + n])
                X[rp + 1, n] = ti.max(p - eps, S[loo + n])
                S[deno + n] = ti.cast(X[rp, n], dt) - ti.cast(X[rp + 1, n], dt)
            else:  # forward: +eps, or -eps where +eps would leave the box
                rp = b * SX + 1 + n
                up = p + eps
                if up > S[hio + n]:
                    up = ti.max(p - eps, S[loo + n])
                X[rp, n] = up
                S[deno + n] = ti.cast(X[rp, n], dt) - ti.cast(X[b * SX, n], dt)
    else:
        for n in range(P):
            S[deno + n] = ti.cast(0, dt)


@ti.func
def _export(S: ti.template(), I: ti.template(), Out: ti.template(), b, P):
    """Out[b] = x, F, C, status, iterations, reason."""
    base = b * _sb(P)
    ib = _ib(b, P)
    for n in range(P):
        Out[b, n] = S[base + LAY.S_X * P + n]
    Out[b, P + LAY.O_F] = S[base + LAY.S_NVEC * P + LAY.SC_F]
    Out[b, P + LAY.O_C] = S[base + LAY.S_NVEC * P + LAY.SC_C]
    Out[b, P + LAY.O_STATUS] = I[ib + LAY.I_STATUS]
    Out[b, P + LAY.O_ITER] = I[ib + LAY.I_ITER]
    Out[b, P + LAY.O_REASON] = I[ib + LAY.I_REASON]


@ti.kernel
def _init(X0: nd, K: nd, S: nd, I: nd, X: nd, dt: ti.template()):
    """S and I from the start points X0 and the constants K (gputrack.ops.lm.Layout); the
    first points to evaluate into X. taichi:cpu; the parallel archs run ``_init_tasks``."""
    B, P = X0.shape[0], X0.shape[1]
    SB = _sb(P)
    KB = LAY.K_NVEC * P + 1
    kh = B * KB
    kg = kh + P
    nk = K.shape[0] - kg  # globals and mask
    G = B * SB
    ti.loop_config(serialize=True)  # one task: B is small, the work is O(B P + M P)
    for b in range(B):
        rel = K[kg + LAY.G_REL]
        if b == 0:
            for t in range(LAY.NIGLOB):
                I[t] = 0
            I[LAY.IG_B] = B
            I[LAY.IG_HAS_MASK] = ti.i32(nk > LAY.NGLOB)
            I[LAY.IG_P] = P
            for t in range(nk):
                S[G + t] = K[kg + t]
        _init_problem(X0, K, S, I, b, B, P, dt)
        _points(S, X, b, b * SB + LAY.S_X * P, B, P, rel, dt)


@ti.func
def _init_problem(X0: ti.template(), K: ti.template(), S: ti.template(), I: ti.template(), b, B, P, dt: ti.template()):
    """Problem b's blocks of S and I from its start point X0[b] and the constants K."""
    KB = LAY.K_NVEC * P + 1
    kh = B * KB
    for t in range(LAY.I_NFIX + P):
        I[_ib(b, P) + t] = 0
    base = b * _sb(P)
    for n in range(P):
        x = ti.cast(X0[b, n], dt)
        S[base + LAY.S_X * P + n] = x
        S[base + LAY.S_XT * P + n] = x
        S[base + LAY.S_G * P + n] = ti.cast(0, dt)
        S[base + LAY.S_LO * P + n] = K[b * KB + LAY.K_LO * P + n]
        S[base + LAY.S_HI * P + n] = K[b * KB + LAY.K_HI * P + n]
        S[base + LAY.S_H * P + n] = K[kh + n]
    for k in range(LAY.NSCAL):
        S[base + LAY.S_NVEC * P + k] = ti.cast(0, dt)
    S[base + LAY.S_NVEC * P + LAY.SC_C] = K[b * KB + LAY.K_NVEC * P]  # C
    S[base + LAY.S_NVEC * P + LAY.SC_NU] = ti.cast(2, dt)  # nu


def _update_kernel(jg, lanes, name):
    """The solver's taichi:cpu iteration (a Taichi kernel named ``name``), its Jacobian argument
    annotated as ``jg``, whose elements have ``lanes`` columns (``_gram_static``'s V)."""

    def update(
        S: nd,
        I: nd,
        W: nd,
        X: nd,
        R: nd,
        Jg: jg,
        Out: nd,
        first: ti.i32,
        final: ti.i32,
        dt: ti.template(),
        use_jac: ti.template(),
        fused: ti.template(),
        SP: ti.template(),
    ):
        """One solver iteration on taichi:cpu (the parallel archs run ``_update_tasks``); ``Jg`` is the
        user's Jacobian when ``use_jac``, else unused (pass R). ``fused`` (central differences without a
        mask): J^T J and J^T r straight from the stacked residuals, J^T never stored (on taichi:cpu
        storing it cost as much as the products). With ``use_jac``, J^T J and J^T r at the trial come
        straight from Jg as stored into the factor's block L and the first P values of J^T (J^T never
        stored) and move to A and g if the trial is accepted (J is finite iff the diagonal of J^T J
        is): ``SP`` is P as a compile-time value (``_gram_static``) or TILES (``_gram_tiles``)."""
        ti.static_assert(not use_jac or SP != 0, "the solver's Jacobian path on taichi:cpu needs SP (_static_p)")
        B, P, M = I[LAY.IG_B], I[LAY.IG_P], R.shape[1]
        NPR = (P + 1) // 2  # row pairs
        ti.loop_config(serialize=True)
        for b in range(B):  # every phase of problem b, in order
            if final == 0 and I[_ib(b, P) + LAY.I_STATUS] == RUNNING:
                if ti.static(fused):
                    _phase_finite(S, I, R, b, dt)
                elif ti.static(use_jac):
                    A = b * _wb(P, M) + LAY.W_A * P * P
                    L = A + (LAY.W_L - LAY.W_A) * P * P
                    jt = b * _wb(P, M) + LAY.W_NSQ * P * P
                    if ti.static(SP > 0):
                        _gram_static(Jg, R, b, M, W, L, jt, SP, dt, lanes)  # eq. 22 at the trial
                    else:
                        # the rest of the J^T block holds the row blocks that _gram_tile skips
                        z = ti.select(P * M - P >= M * ((P + GRAM_SEG - 1) // GRAM_SEG), jt + P, -1)
                        _gram_tiles(Jg, R, b, M, P, W, L, jt, dt, z)  # eq. 22 at the trial
                    for n in range(P):
                        I[_ib(b, P) + LAY.I_FIN + n] = _finite(W[L + n * P + n], dt)
                else:
                    for n in range(P):
                        _phase_jacobian(S, I, W, R, Jg, b, n, dt, use_jac)
            _phase_accept(S, I, W, R, b, dt, first, final)
            if final == 0:
                if ti.static(use_jac):
                    if I[_ib(b, P) + LAY.I_ACCEPTED]:
                        A = b * _wb(P, M) + LAY.W_A * P * P
                        L = A + (LAY.W_L - LAY.W_A) * P * P
                        jt = b * _wb(P, M) + LAY.W_NSQ * P * P
                        for k in range(P * P):
                            W[A + k] = W[L + k]
                        for n in range(P):
                            S[b * _sb(P) + LAY.S_G * P + n] = W[jt + n]
                else:
                    for i2 in range(NPR):
                        _phase_normal(S, I, W, R, b, 2 * i2, dt, fused)
                _phase_step(S, I, W, X, b, M, dt)
            _export(S, I, Out, b, P)

    update.__name__ = update.__qualname__ = name
    return ti.kernel(update)


_update = _update_kernel(nd, 1, "_update")
#: the user's float64 Jacobian (B, M, P) in pairs of columns (B, M, P / 2, 2), as NumPy stores it
JAC_PAIRS = ti.types.ndarray(dtype=ti.types.vector(2, ti.f64), ndim=3)
_update_pairs = _update_kernel(JAC_PAIRS, 2, "_update_pairs")


# ------------------------------------------------------------------------------------------------
# the parallel archs (Vulkan, CUDA): every task bounded in loop passes per invocation
#
# lavapipe (Vulkan on a CPU) stops every loop of a shader invocation after 65535 passes in total
# (runtime.LLVMPIPE_LOOP_LIMIT) and goes on with wrong numbers: one invocation per problem running
# the whole damped Cholesky factorisation (~P^3 / 6 inner passes) returned wrong steps with ok = 1
# from P = 70. So on these archs an invocation of a task (a top-level loop: its own shader) gets
# work whose loop passes are known in advance: a row of J^T, a 2 x 4 block of J^T J (M / GRAM_U
# passes), one problem's acceptance or next points; and the factorisation is a resumable
# per-problem state machine that each launch advances by at most ``ncol`` columns, launched NT
# times (``_tasks_plan`` plans both; on lavapipe NT = 1 up to P = 218 for the ops, P = 132 for the
# solver, which plans room for CHOL_TRIES_PLANNED tries). Inner products take DOT_U terms per pass
# and the factor CHOL_R rows per pass: one launch factors a P = 128 matrix ~5 times over. Sizes
# whose tasks cannot fit (on lavapipe: P above 659 for the ops, 462 for the solver, or ~60000
# residuals per problem) raise ValueError. Where the device has no such limit one launch
# does it all. The unrolled bodies are kept small: Taichi's compile time grows with them (a cold
# compile of ``_lm_step_tasks`` ~2 s with 8 x 8 terms per pass, ~12 s with 16 x 8 and separate
# tails).

DOT_U = 8  # terms per loop pass of the inner products (_dot_acc, _dot_diff, _chol_col)
CHOL_R = 8  # rows of the factor per loop pass of _chol_col
GRAM_U = 4  # residuals per loop pass of _gram_block
LOOP_BUDGET = 60000  # loop passes a task plans per invocation under runtime.LLVMPIPE_LOOP_LIMIT (the rest: margin)
CHOL_TRIES_PLANNED = 4  # full-depth factorisations (tries of the damping) the solver's launches have room for, at least
# the factorisation's state between the launches of one step: next column (-1: none pending, -2:
# failed) and tries so far, in the two spare scalars of the problem's S block (exact as floats; 0
# again after the step's last launch)
SC_COL, SC_TRIES = LAY.NSCAL - 2, LAY.NSCAL - 1
if max(LAY.SC_F, LAY.SC_C, LAY.SC_NU, LAY.SC_PRED, LAY.SC_FT, LAY.SC_SNORM) >= SC_COL:
    raise RuntimeError("gputrack.abi.LMLayout: the taichi solver needs its last two scalar slots spare")


@ti.func
def _dot_acc(v, X: ti.template(), a, sa, Y: ti.template(), c, sc, n, dt: ti.template()):
    """v - sum_{k<n} X[a + k sa] Y[c + k sc], term after term in order of k; DOT_U terms per loop pass
    (ceil(n / DOT_U) passes)."""
    s = ti.cast(v, dt)
    k = 0
    while k < n:
        for e in ti.static(range(DOT_U)):
            if k + e < n:
                s -= X[a + (k + e) * sa] * Y[c + (k + e) * sc]
        k += DOT_U
    return s


@ti.func
def _dot_diff(W: ti.template(), a, S: ti.template(), xo, yo, n, dt: ti.template()):
    """sum_{k<n} W[a + k] (S[xo + k] - S[yo + k]) in order of k; DOT_U terms per loop pass."""
    s = ti.cast(0, dt)
    k = 0
    while k < n:
        for e in ti.static(range(DOT_U)):
            if k + e < n:
                s += W[a + k + e] * (S[xo + k + e] - S[yo + k + e])
        k += DOT_U
    return s


@ti.func
def _chol_col(W: ti.template(), A, L, j, P, C, dt: ti.template(), S: ti.template(), xo, loo, hio, go,
              bounds: ti.template(), wd) -> ti.i32:  # fmt: skip
    """Column j of the Cholesky factor of A + C I (the P x P matrix at W[A], lower triangle read) into
    W[L] (L may be A: in place), from its columns 0..j-1: left-looking, the operations of
    ``_chol_solve`` / ``_phase_step`` in their order. With ``bounds`` a parameter held at a bound by
    the gradient (``_active``) gets a unit row and column, as in ``_phase_step``. Returns 0 if the
    pivot is not positive and finite. Rows j .. P - 1 in blocks of CHOL_R (the first block gives the
    pivot; the last repeats row P - 1), each one pass over k per DOT_U: ``_col_passes`` loop passes."""
    ok = 1
    aj = 0
    if ti.static(bounds):
        aj = _active(S, xo, loo, hio, go, j)
    d = ti.cast(1, dt)
    i = j
    while i < P and ok:
        row = ti.Vector([ti.min(i + r, P - 1) for r in ti.static(range(CHOL_R))])
        v = ti.Vector([W[A + row[r] * P + j] for r in ti.static(range(CHOL_R))], dt=dt)
        if ti.static(bounds):
            for r in ti.static(range(CHOL_R)):
                if aj or _active(S, xo, loo, hio, go, row[r]):
                    v[r] = ti.cast(0, dt)
        if i == j:
            cj = C
            if ti.static(bounds):
                cj = ti.select(aj, C, C * W[wd + j])  # the solver: the damping's scale D (1 for C I)
            v[0] = ti.select(aj, ti.cast(1, dt), W[A + j * P + j]) + cj  # the pivot's row
        k = 0
        while k < j:
            for e in ti.static(range(DOT_U)):
                if k + e < j:
                    lj = W[L + j * P + k + e]
                    for r in ti.static(range(CHOL_R)):
                        v[r] -= W[L + row[r] * P + k + e] * lj
            k += DOT_U
        if i == j:
            if v[0] <= 0 or not _finite(v[0], dt):
                ok = 0
            else:
                d = ti.sqrt(v[0])
                W[L + j * P + j] = d
        if ok:
            for r in ti.static(range(CHOL_R)):
                if i + r < P and i + r > j:
                    W[L + (i + r) * P + j] = v[r] / d
        i += CHOL_R
    return ok


@ti.func
def _substitute(W: ti.template(), L, X: ti.template(), x, P, dt: ti.template()):
    """X[x : x + P] (the right-hand side) -> (L L^T)^-1 X[x : x + P], L the factor at W[L]: forward, then
    backward substitution (the operations of ``_chol_solve``). ``_subst_passes`` loop passes."""
    for ph in range(2):
        for ii in range(P):
            i, a, sa, c, n = ii, L + ii * P, 1, x, ii  # L[i, :i] . X[:i]
            if ph == 1:
                i = P - 1 - ii
                a, sa, c, n = L + (i + 1) * P + i, P, x + i + 1, P - 1 - i  # L[i+1:, i] . X[i+1:]
            X[x + i] = _dot_acc(X[x + i], W, a, sa, X, c, 1, n, dt) / W[L + i * P + i]


@ti.func
def _ops_factor(W: ti.template(), a, g, C, ok: ti.template(), delta: ti.template(), b, P, ncol, t, last,
                dt: ti.template()):  # fmt: skip
    """Launch t of the ops' factorisation of problem b: columns t*ncol .. of A + C I (at W[a], in place),
    ok[b] = 0 at a pivot that is not positive definite; the ``last`` launch solves for the right-hand
    side at W[g] into delta[b] (0 where not ok) (eq. 22)."""
    if t == 0:
        ok[b] = 1
    if ok[b]:
        j = t * ncol
        end = ti.min(P, j + ncol)
        while j < end:
            if not _chol_col(W, a, a, j, P, C, dt, W, 0, 0, 0, 0, False, 0):
                ok[b] = 0
                j = end
            j += 1
    if last:
        if ok[b]:
            _substitute(W, a, W, g, P, dt)
            for i in range(P):
                delta[b, i] = W[g + i]
        else:
            for i in range(P):
                delta[b, i] = ti.cast(0, dt)


@ti.func
def _gram_block(W: ti.template(), jt, a, R: ti.template(), rrow, G: ti.template(), goff, i, q, M, P,
                dt: ti.template()):  # fmt: skip
    """One item of the normal equations (eq. 22) on the parallel archs: rows i and k = min(i + 1, P - 1)
    of J^T J against columns 4q .. 4q + 3 (the entries on or below the diagonal, both triangles) into
    W[a + i*P + j], or with 4q >= P rows i and k of J^T r into G[goff + i]; J^T in rows of M at W[jt],
    r = R[rrow, :]. ceil(M / GRAM_U) loop passes."""
    k = ti.min(i + 1, P - 1)
    j0 = 4 * q
    ri, rk = jt + i * M, jt + k * M
    if j0 >= P:  # J^T r
        s = ti.cast(0, dt)
        t = ti.cast(0, dt)
        m = 0
        while m < M:
            for u in ti.static(range(GRAM_U)):
                if m + u < M:
                    v = ti.cast(R[rrow, m + u], dt)
                    s += W[ri + m + u] * v
                    t += W[rk + m + u] * v
            m += GRAM_U
        G[goff + i] = s
        G[goff + k] = t
    elif j0 <= k:
        c = ti.Vector([jt + ti.min(j0 + e, P - 1) * M for e in ti.static(range(4))])
        s = ti.Vector([0.0] * 4, dt=dt)
        t = ti.Vector([0.0] * 4, dt=dt)
        m = 0
        while m < M:
            for u in ti.static(range(GRAM_U)):
                if m + u < M:
                    x = W[ri + m + u]
                    y = W[rk + m + u]
                    for e in ti.static(range(4)):
                        w = W[c[e] + m + u]
                        s[e] += x * w
                        t[e] += y * w
            m += GRAM_U
        for e in ti.static(range(4)):
            j = j0 + e
            if j <= i:
                W[a + i * P + j] = s[e]
                W[a + j * P + i] = s[e]
            if j <= k:
                W[a + k * P + j] = t[e]
                W[a + j * P + k] = t[e]


@ti.func
def _copy_rows(W: ti.template(), WB, JtJ: ti.template(), Jtr: ti.template(), b, i, P, back: ti.template()):
    """Row i of problem b: JtJ[b, i, :] and Jtr[b, i] from W (``back``) or the lower triangle of that
    row and Jtr[b, i] into W (J^T J at b*WB, J^T r at b*WB + WB - P)."""
    if ti.static(back):
        for j in range(P):
            JtJ[b, i, j] = W[b * WB + i * P + j]
        Jtr[b, i] = W[b * WB + WB - P + i]
    else:
        for j in range(i + 1):
            W[b * WB + i * P + j] = JtJ[b, i, j]
        W[b * WB + WB - P + i] = Jtr[b, i]


@ti.kernel
def _normal_equations_tasks(J: nd, r: nd, JtJ: nd, Jtr: nd, W: nd, dt: ti.template(), NI: ti.template()):
    """``_normal_equations`` on the parallel archs: J^T, then one 2 x 4 block of J^T J (or two entries of
    J^T r) per item, then the rows out. NI: the grid of every task (``_grid``)."""
    B, M, P = J.shape[0], J.shape[1], J.shape[2]
    WB = _ops_block(P, M)
    NPR, NQ = (P + 1) // 2, (P + 3) // 4 + 1
    for u in range(NI):
        t = u
        while t < B * P:
            _transpose(J, W, t // P, t % P, (t // P) * WB + P * P, M)
            t += NI
    for u in range(NI):
        t = u
        while t < B * NPR * NQ:
            b, v = t // (NPR * NQ), t % (NPR * NQ)
            a = b * WB
            _gram_block(W, a + P * P, a, r, b, W, a + P * P + P * M, 2 * (v // NQ), v % NQ, M, P, dt)  # eq. 22
            t += NI
    for u in range(NI):
        t = u
        while t < B * P:
            _copy_rows(W, WB, JtJ, Jtr, t // P, t % P, P, True)
            t += NI


@ti.kernel
def _lm_step_tasks(JtJ: nd, Jtr: nd, damping: nd, delta: nd, ok: nd, W: nd, ncol: ti.i32, it: ti.i32, nt: ti.i32,
                   dt: ti.template(), NI: ti.template()):  # fmt: skip
    """``_lm_step`` on the parallel archs, launch ``it`` of nt (``_tasks_plan``): the first copies the
    lower triangle and J^T r into W (B * (P*P + P),), each factors ``ncol`` columns, the last solves."""
    B, P = Jtr.shape[0], Jtr.shape[1]
    WB = P * P + P
    for u in range(NI):
        t = u
        while t < ti.select(it == 0, B * P, 0):
            _copy_rows(W, WB, JtJ, Jtr, t // P, t % P, P, False)
            t += NI
    for u in range(NI):
        b = u
        while b < B:
            _ops_factor(W, b * WB, b * WB + P * P, damping[b], ok, delta, b, P, ncol, it, it == nt - 1, dt)  # eq. 22
            b += NI


@ti.kernel
def _lm_solve_tasks(J: nd, r: nd, damping: nd, delta: nd, ok: nd, W: nd, ncol: ti.i32, it: ti.i32, nt: ti.i32,
                    dt: ti.template(), NI: ti.template()):  # fmt: skip
    """``_lm_solve`` on the parallel archs, launch ``it`` of nt: the first computes J^T J and J^T r as
    ``_normal_equations_tasks`` does, then as ``_lm_step_tasks``; W: (B * _ops_block(P, M),)."""
    B, M, P = J.shape[0], J.shape[1], J.shape[2]
    WB = _ops_block(P, M)
    NPR, NQ = (P + 1) // 2, (P + 3) // 4 + 1
    for u in range(NI):
        t = u
        while t < ti.select(it == 0, B * P, 0):
            _transpose(J, W, t // P, t % P, (t // P) * WB + P * P, M)
            t += NI
    for u in range(NI):
        t = u
        while t < ti.select(it == 0, B * NPR * NQ, 0):
            b, v = t // (NPR * NQ), t % (NPR * NQ)
            a = b * WB
            _gram_block(W, a + P * P, a, r, b, W, a + P * P + P * M, 2 * (v // NQ), v % NQ, M, P, dt)  # eq. 22
            t += NI
    for u in range(NI):
        b = u
        while b < B:
            a = b * WB
            _ops_factor(W, a, a + P * P + P * M, damping[b], ok, delta, b, P, ncol, it, it == nt - 1, dt)  # eq. 22
            b += NI


@ti.func
def _step_factor(S: ti.template(), I: ti.template(), W: ti.template(), Out: ti.template(), b, M, ncol, first, last,
                 dt: ti.template()):  # fmt: skip
    """``_phase_step`` in launches on the parallel archs. The ``first`` makes the gtol test and starts
    the damped factorisation; each advances it by at most ``ncol`` columns (raising C tenfold and
    starting again at a pivot that is not positive definite, as ``_phase_step``); the ``last`` solves
    for the trial point and its predicted reduction, and exports. A factorisation not finished by
    then (more full-depth tries than the launches had room for, at least CHOL_TRIES_PLANNED) fails
    as one that runs out of tries does (FAILED, NOT_PD)."""
    P, B = I[LAY.IG_P], I[LAY.IG_B]
    base = b * _sb(P)
    sc = base + LAY.S_NVEC * P
    ib = _ib(b, P)
    G = B * _sb(P)
    A = b * _wb(P, M) + LAY.W_A * P * P
    L = A + (LAY.W_L - LAY.W_A) * P * P
    xo, xto, go = base + LAY.S_X * P, base + LAY.S_XT * P, base + LAY.S_G * P
    loo, hio = base + LAY.S_LO * P, base + LAY.S_HI * P
    scale = ti.cast(S[G + G_SCALE], ti.i32)
    wd = _wd(b, P, M)
    if first:
        if I[ib + LAY.I_STATUS] == RUNNING and I[ib + LAY.I_ACCEPTED]:
            _gtol_test(S, I, W, b, A, P, G, scale, dt)  # projected gradient (active bounds removed)
        if I[ib + LAY.I_STATUS] == RUNNING:
            _damping_scale(I, W, b, A, wd, P, scale, dt)
        S[sc + SC_COL] = ti.cast(ti.select(I[ib + LAY.I_STATUS] == RUNNING, 0, -1), dt)
        S[sc + SC_TRIES] = ti.cast(0, dt)
    col = ti.cast(S[sc + SC_COL], ti.i32)
    if col >= 0 and col < P:
        tries = ti.cast(S[sc + SC_TRIES], ti.i32)
        C = S[sc + LAY.SC_C]
        dmax = _cref(W, A, P, scale, dt)
        steps = 0
        while steps < ncol and col >= 0 and col < P:
            if _chol_col(W, A, L, col, P, C, dt, S, xo, loo, hio, go, True, wd):  # eq. 22: J^T J + C D
                col += 1
            elif C > S[G + LAY.G_CMAX] * dmax:
                col = -2
            else:
                C = ti.max(10 * C, S[G + LAY.G_CTINY] * dmax)  # not PD: raise C tenfold and try again
                tries += 1
                col = ti.select(tries <= MAX_CHOL_TRIES, 0, -2)
            steps += 1
        S[sc + SC_COL] = ti.cast(col, dt)
        S[sc + SC_TRIES] = ti.cast(tries, dt)
        S[sc + LAY.SC_C] = C
    if last:
        if I[ib + LAY.I_STATUS] == RUNNING:
            if col != P:
                I[ib + LAY.I_STATUS] = FAILED
                I[ib + LAY.I_REASON] = R_NOTPD
            else:
                # delta = (J^T J + C I)^-1 J^T r in the xt slots, then the step projected into the box
                for i in range(P):
                    S[xto + i] = ti.select(_active(S, xo, loo, hio, go, i), ti.cast(0, dt), S[go + i])
                _substitute(W, L, S, xto, P, dt)
                for i in range(P):
                    S[xto + i] = ti.min(ti.max(S[xo + i] - S[xto + i], S[loo + i]), S[hio + i])  # paper 003 eq. 8-9
                # predicted reduction of the model ||r - J s||^2 for s = x - xt
                pr = ti.cast(0, dt)
                for i in range(P):
                    si = S[xo + i] - S[xto + i]
                    pr += 2 * si * S[go + i] - si * _dot_diff(W, A + i * P, S, xo, xto, P, dt)
                S[sc + LAY.SC_PRED] = pr
        S[sc + SC_COL] = ti.cast(0, dt)  # spare again between iterations (as the layout says)
        S[sc + SC_TRIES] = ti.cast(0, dt)
        _export(S, I, Out, b, P)


@ti.func
def _point_pair(S: ti.template(), X: ti.template(), b, n, src, B, P, rel, dt: ti.template()):
    """One item of ``_points`` on the parallel archs: rows b*SX + 1 + 2n and + 2 + 2n of X (the point
    S[src : src + P] moved by +-eps in parameter n, eq. 24) and den[n]; n = P: row b*SX, the point."""
    base = b * _sb(P)
    SX = X.shape[0] // B
    if n == P:
        for m in range(P):
            X[b * SX, m] = S[src + m]
    elif SX == 2 * P + 1:  # central (eq. 24)
        rp = b * SX + 1 + 2 * n
        for m in range(P):
            if m != n:
                X[rp, m] = S[src + m]
                X[rp + 1, m] = S[src + m]
        p = S[src + n]
        eps = _eps(p, S[base + LAY.S_H * P + n], rel, dt)
        X[rp, n] = ti.min(p + eps, S[base + LAY.S_HI * P + n])
        X[rp + 1, n] = ti.max(p - eps, S[base + LAY.S_LO * P + n])
        S[base + LAY.S_DEN * P + n] = ti.cast(X[rp, n], dt) - ti.cast(X[rp + 1, n], dt)
    elif SX > 1:  # forward: +eps, or -eps where +eps would leave the box
        rp = b * SX + 1 + n
        for m in range(P):
            if m != n:
                X[rp, m] = S[src + m]
        p = S[src + n]
        eps = _eps(p, S[base + LAY.S_H * P + n], rel, dt)
        up = p + eps
        if up > S[base + LAY.S_HI * P + n]:
            up = ti.max(p - eps, S[base + LAY.S_LO * P + n])
        # the point's row b*SX is written by item n = P of the same launch: p as stored, read back here
        X[rp, n] = p
        ps = ti.cast(X[rp, n], dt)
        X[rp, n] = up
        S[base + LAY.S_DEN * P + n] = ti.cast(X[rp, n], dt) - ps
    else:
        S[base + LAY.S_DEN * P + n] = ti.cast(0, dt)


@ti.kernel
def _init_tasks(X0: nd, K: nd, S: nd, I: nd, X: nd, dt: ti.template(), NI: ti.template()):
    """``_init`` on the parallel archs: the problems, the globals and mask, the points: one item each."""
    B, P = X0.shape[0], X0.shape[1]
    KB = LAY.K_NVEC * P + 1
    kg = B * KB + P
    nk = K.shape[0] - kg  # globals and mask
    for u in range(NI):
        b = u
        while b < B:
            _init_problem(X0, K, S, I, b, B, P, dt)
            b += NI
    for u in range(NI):
        t = u
        while t < nk:
            if t == 0:
                for g in range(LAY.NIGLOB):
                    I[g] = 0
                I[LAY.IG_B] = B
                I[LAY.IG_HAS_MASK] = ti.i32(nk > LAY.NGLOB)
                I[LAY.IG_P] = P
            S[B * _sb(P) + t] = K[kg + t]
            t += NI
    for u in range(NI):
        t = u
        while t < B * (P + 1):
            b = t // (P + 1)
            _point_pair(S, X, b, t % (P + 1), b * _sb(P) + LAY.S_X * P, B, P, K[kg + LAY.G_REL], dt)
            t += NI


@ti.kernel
def _update_tasks(
    S: nd,
    I: nd,
    W: nd,
    R: nd,
    Jg: nd,
    Out: nd,
    dt: ti.template(),
    first: ti.template(),
    final: ti.template(),
    use_jac: ti.template(),
    NI: ti.template(),
):
    """``_update`` on the parallel archs up to the normal equations: the rows of J^T, acceptance, the
    blocks of J^T J and J^T r; ``_step_tasks`` launches follow (but after the ``final`` acceptance)."""
    B, P, M = I[LAY.IG_B], I[LAY.IG_P], R.shape[1]
    SR = R.shape[0] // B
    NPR, NQ = (P + 1) // 2, (P + 3) // 4 + 1
    if ti.static(not final):
        for u in range(NI):
            t = u
            while t < B * P:
                b, n = t // P, t % P
                if I[_ib(b, P) + LAY.I_STATUS] == RUNNING:
                    _phase_jacobian(S, I, W, R, Jg, b, n, dt, use_jac)
                t += NI
    for u in range(NI):
        b = u
        while b < B:
            _phase_accept(S, I, W, R, b, dt, first, final)
            if ti.static(final):
                _export(S, I, Out, b, P)
            b += NI
    if ti.static(not final):
        for u in range(NI):
            t = u
            while t < B * NPR * NQ:
                b, v = t // (NPR * NQ), t % (NPR * NQ)
                if I[_ib(b, P) + LAY.I_ACCEPTED]:
                    a = b * _wb(P, M) + LAY.W_A * P * P
                    jt = b * _wb(P, M) + LAY.W_NSQ * P * P
                    g = b * _sb(P) + LAY.S_G * P
                    _gram_block(W, jt, a, R, b * SR, S, g, 2 * (v // NQ), v % NQ, M, P, dt)  # eq. 22
                t += NI


@ti.kernel
def _step_tasks(S: nd, I: nd, W: nd, X: nd, Out: nd, M: ti.i32, ncol: ti.i32, it: ti.i32, nt: ti.i32,
                dt: ti.template(), NI: ti.template()):  # fmt: skip
    """Launch ``it`` of nt of the step on the parallel archs (``_step_factor``); the last also writes
    the next points (the trial and its perturbed copies, or the accepted x when stopped)."""
    B, P = I[LAY.IG_B], I[LAY.IG_P]
    for u in range(NI):
        b = u
        while b < B:
            _step_factor(S, I, W, Out, b, M, ncol, it == 0, it == nt - 1, dt)
            b += NI
    for u in range(NI):
        t = u
        while t < ti.select(it == nt - 1, B * (P + 1), 0):
            b = t // (P + 1)
            base = b * _sb(P)
            src = base + LAY.S_XT * P
            if I[_ib(b, P) + LAY.I_STATUS] != RUNNING:
                src = base + LAY.S_X * P  # stopped: the accepted x
            _point_pair(S, X, b, t % (P + 1), src, B, P, S[B * _sb(P) + LAY.G_REL], dt)
            t += NI


#: threads per problem of ``_step_block`` (CUDA): the trailing triangle of column j, (P - j)^2 / 2
#: entries, shared out over them
BLOCK_STEP = 256


def _block_step() -> bool:
    """Whether the step runs as ``_step_block``, a CUDA block per problem with block barriers
    (``ti.simt.block.sync``, which Taichi compiles for CUDA only), rather than ``_step_tasks``'s
    thread per problem: one thread's O(P^3) factorisation took ~3 ms a launch for the face bundle's
    P = 92 on an H100."""
    return current_arch() == "cuda"


@ti.func
def _tri(q):
    """Entry q of a lower triangle, row by row: (i, k) with k <= i."""
    i = ti.cast((ti.sqrt(8.0 * q + 1.0) - 1.0) * 0.5, ti.i32)
    while i * (i + 1) // 2 > q:
        i -= 1
    while (i + 1) * (i + 2) // 2 <= q:
        i += 1
    return ti.Vector([i, q - i * (i + 1) // 2])


@ti.func
def _chol_block(W: ti.template(), L, P, lid, BLK: ti.template(), flag: ti.template(), dt: ti.template()) -> ti.i32:
    """In place, by the problem's block: the lower triangle of W[L] (P x P) -> its Cholesky factor,
    right-looking (column j scaled, then the trailing triangle updated by its outer product, each
    shared out over the threads). Returns 1 if positive definite, the same on every thread (flag[1]);
    every barrier is reached by every thread."""
    if lid == 0:
        flag[1] = 1
    for j in range(P):
        ti.simt.block.sync()
        if lid == 0 and flag[1]:
            s = W[L + j * P + j]
            if s <= 0 or not _finite(s, dt):
                flag[1] = 0
            else:
                W[L + j * P + j] = ti.sqrt(s)
        ti.simt.block.sync()
        if flag[1]:
            d = W[L + j * P + j]
            i = j + 1 + lid
            while i < P:
                W[L + i * P + j] /= d
                i += BLK
        ti.simt.block.sync()
        if flag[1]:
            n = P - j - 1
            q = lid
            while q < n * (n + 1) // 2:
                ik = _tri(q)
                i, k = j + 1 + ik[0], j + 1 + ik[1]
                W[L + i * P + k] -= W[L + i * P + j] * W[L + k * P + j]
                q += BLK
    ti.simt.block.sync()
    return flag[1]


@ti.kernel
def _step_block(S: nd, I: nd, W: nd, X: nd, Out: nd, M: ti.i32, dt: ti.template(), BLK: ti.template()):
    """``_step_factor`` and the next points (``_step_tasks``) by a CUDA block of BLK threads per
    problem: the gtol test and the damping's scale on thread 0; the damped matrix, its factor
    (``_chol_block``), the triangular solves a column at a time and the predicted reduction's rows
    shared out; raising C tenfold at a pivot that is not positive definite, as ``_phase_step``."""
    B, P = I[LAY.IG_B], I[LAY.IG_P]
    ti.loop_config(block_dim=BLK)
    for t in range(B * BLK):
        flag = ti.simt.block.SharedArray((3,), ti.i32)  # go, positive definite, give up
        val = ti.simt.block.SharedArray((2,), dt)  # C, what the damping's limits are relative to
        b, lid = t // BLK, t % BLK
        base = b * _sb(P)
        sc = base + LAY.S_NVEC * P
        ib = _ib(b, P)
        G = B * _sb(P)
        A = b * _wb(P, M) + LAY.W_A * P * P
        L = A + (LAY.W_L - LAY.W_A) * P * P
        tmp = b * _wb(P, M) + LAY.W_NSQ * P * P  # J^T's first P entries: free after the normal equations
        xo, xto, go = base + LAY.S_X * P, base + LAY.S_XT * P, base + LAY.S_G * P
        loo, hio = base + LAY.S_LO * P, base + LAY.S_HI * P
        scale = ti.cast(S[G + G_SCALE], ti.i32)
        wd = _wd(b, P, M)
        if lid == 0:
            flag[0] = 0
            if I[ib + LAY.I_STATUS] == RUNNING and I[ib + LAY.I_ACCEPTED]:
                _gtol_test(S, I, W, b, A, P, G, scale, dt)  # projected gradient (active bounds removed)
            if I[ib + LAY.I_STATUS] == RUNNING:
                _damping_scale(I, W, b, A, wd, P, scale, dt)
                flag[0] = 1
                val[0] = S[sc + LAY.SC_C]
                val[1] = _cref(W, A, P, scale, dt)
        ti.simt.block.sync()
        ok = 0
        if flag[0]:
            tries = 0
            while tries <= MAX_CHOL_TRIES:
                C = val[0]
                q = lid
                while q < P * (P + 1) // 2:  # J^T J + C D, held parameters' rows and columns unit
                    ij = _tri(q)
                    i, j = ij[0], ij[1]
                    ai = _active(S, xo, loo, hio, go, i)
                    if j < i:
                        W[L + i * P + j] = ti.select(ai or _active(S, xo, loo, hio, go, j), ti.cast(0, dt),
                                                     W[A + i * P + j])  # fmt: skip
                    else:
                        W[L + i * P + i] = ti.select(ai, 1 + C, W[A + i * P + i] + C * W[wd + i])
                    q += BLK
                i = lid
                while i < P:
                    S[xto + i] = ti.select(_active(S, xo, loo, hio, go, i), ti.cast(0, dt), S[go + i])
                    i += BLK
                ok = _chol_block(W, L, P, lid, BLK, flag, dt)  # eq. 22
                if ok:
                    break
                if lid == 0:
                    flag[2] = ti.i32(C > S[G + LAY.G_CMAX] * val[1])
                    if not flag[2]:
                        val[0] = ti.max(10 * C, S[G + LAY.G_CTINY] * val[1])  # not PD: raise C tenfold
                ti.simt.block.sync()
                if flag[2]:
                    break
                tries += 1
            if ok:
                for j in range(P):  # forward, a column at a time
                    if lid == 0:
                        S[xto + j] /= W[L + j * P + j]
                    ti.simt.block.sync()
                    i = j + 1 + lid
                    while i < P:
                        S[xto + i] -= W[L + i * P + j] * S[xto + j]
                        i += BLK
                    ti.simt.block.sync()
                for jj in range(P):  # backward
                    j = P - 1 - jj
                    if lid == 0:
                        S[xto + j] /= W[L + j * P + j]
                    ti.simt.block.sync()
                    i = lid
                    while i < j:
                        S[xto + i] -= W[L + j * P + i] * S[xto + j]
                        i += BLK
                    ti.simt.block.sync()
                i = lid
                while i < P:
                    S[xto + i] = ti.min(ti.max(S[xo + i] - S[xto + i], S[loo + i]), S[hio + i])  # paper 003 eq. 8-9
                    i += BLK
                ti.simt.block.sync()
                i = lid
                while i < P:  # row i's term of the predicted reduction of ||r - J s||^2, s = x - xt
                    si = S[xo + i] - S[xto + i]
                    W[tmp + i] = 2 * si * S[go + i] - si * _dot_diff(W, A + i * P, S, xo, xto, P, dt)
                    i += BLK
                ti.simt.block.sync()
        if lid == 0:
            if flag[0]:
                S[sc + LAY.SC_C] = val[0]
                if not ok:
                    I[ib + LAY.I_STATUS] = FAILED
                    I[ib + LAY.I_REASON] = R_NOTPD
                else:
                    pr = ti.cast(0, dt)
                    for i in range(P):
                        pr += W[tmp + i]
                    S[sc + LAY.SC_PRED] = pr
            _export(S, I, Out, b, P)
        ti.simt.block.sync()
        src = xto
        if I[ib + LAY.I_STATUS] != RUNNING:
            src = xo  # stopped: the accepted x
        n = lid
        while n <= P:
            _point_pair(S, X, b, n, src, B, P, S[G + LAY.G_REL], dt)
            n += BLK


GRIDS = (256, 1024, 4096, 16384, 65536, SPIRV_GRID_ITEMS)


def _grid(items: int) -> int:
    """Invocations of every task of a parallel-arch kernel whose largest task has ``items`` items: a
    compile-time size from GRIDS (few variants to compile), each invocation taking the items u, u + NI,
    .... A loop over a size known only at run time would dispatch SPIRV_GRID_ITEMS invocations
    whatever it holds: ~1-5 ms per task on lavapipe for the idle ones (more the larger the shader),
    against ~0.1 ms for a grid of 256."""
    return next((g for g in GRIDS if g >= items), GRIDS[-1])


def _col_passes(P: int) -> np.ndarray:
    """Loop passes of ``_chol_col`` for each column j of a P x P factor. A loop of n iterations takes
    n + 1 passes on llvmpipe (the last one finds the loop done)."""
    j = np.arange(P)
    return -(-(P - j) // CHOL_R) * (2 + -(-j // DOT_U)) + 1


def _subst_passes(P: int) -> int:
    """Loop passes of ``_substitute``."""
    return 3 + 2 * (P + 1) + 2 * (P + int((-(-np.arange(P) // DOT_U)).sum()))


def _tasks_plan(device, B: int, P: int, M: int, kind: str) -> tuple[int, int]:
    """(ncol, NT) for the parallel archs' launches of ``kind`` ("normal": normal_equations, "ops":
    lm_step and lm_solve, "solver"): columns of the factorisation per launch, launches. Where the
    device bounds the loop passes of an invocation (runtime.loop_limit) every task stays within
    LOOP_BUDGET: the ops plan one factorisation, the solver room for CHOL_TRIES_PLANNED of them (each
    launch has room for ncol / P). Elsewhere one launch does it all. Raises ValueError where a task
    would need more passes for (B, P, M) than the device runs."""
    limit = loop_limit(device)
    tries = MAX_CHOL_TRIES + 1 if kind == "solver" else 1
    if limit is None:
        return P * tries, 1

    def per_item(items):  # items of a task that one invocation runs
        return -(-items // _grid(items))

    # passes per item (a loop of n iterations takes n + 1, the parallel loop's own included)
    k = per_item(B)
    step = int(_col_passes(P).max()) + 1  # a column and its pass of the launch's column loop
    gram = per_item(B * ((P + 1) // 2) * ((P + 3) // 4 + 1)) * (-(-M // GRAM_U) + 3)
    if kind == "solver":
        # gtol test, 1 + max diag, the column loop's end; right-hand side, substitution, box,
        # predicted reduction, export
        fixed = 3 * (P + 1) + 3 + (P + 1) + _subst_passes(P) + 2 * (P + 1) + P * (-(-P // DOT_U) + 1) + (P + 1)
        need = {
            "Jacobian rows": per_item(B * P) * (M + 3),
            "acceptance": k * (M + 4 * P + 8),
            "normal equations": gram,
            "points": per_item(B * (P + 1)) * (P + 3),
        }
    else:
        fixed = 3 + _subst_passes(P) + (P + 1)  # the column loop's end, substitution, delta
        need = {
            "transpose": per_item(B * P) * (M // 8 + 10),
            "normal equations": gram,
            "rows": per_item(B * P) * (P + 4),
        }
    if kind != "normal":
        need["factorisation"] = k * (fixed + step)
    worst = max(need, key=need.get)
    if need[worst] > LOOP_BUDGET:
        raise ValueError(
            f"{device.spec} ({device.info.name}) runs at most {limit} loop passes per kernel invocation; the LM "
            f"kernels' {worst} would need {need[worst]} for B={B}, P={P}, M={M}: use fewer parameters or "
            "residuals per problem, or another device (taichi:cpu, opencl)"
        )
    if kind == "normal":
        return 0, 0
    ncol = (LOOP_BUDGET // k - fixed) // step
    planned = CHOL_TRIES_PLANNED if kind == "solver" else 1
    return ncol, max(1, -(-planned * P // ncol))


class State:
    """Arrays of one solve (gputrack.ops.lm.Layout); W is set by ``solver_workspace``."""

    def __init__(self, device, lay, S, I, Out):
        self.device, self.lay, self.S, self.I, self.Out = device, lay, S, I, Out
        self.W = None
        self.dt = _ti_dtype(S.dtype)
        self.plan = None  # (ncol, launches) of the parallel archs' step (``_tasks_plan``)
        self.fused = 0  # ``_update``'s fused template value of the solve's calls (``solver_update``)


def upload_into(device, arr, host, asynchronous=False):
    """Copy ``host`` into the existing device array ``arr`` (same shape and dtype); the caller counts it."""
    if current_arch() == "cpu":
        copy(host, arr.buffer)  # a host-memory copy (arrays.copy); ``from_numpy`` takes ~0.1 ms
    else:
        arr.buffer.from_numpy(host)


def download_into(device, arr, host):
    """Copy the device array ``arr`` into the NumPy array ``host``; the caller counts it."""
    if current_arch() == "cpu":
        copy(arr.buffer, host)
    else:
        host[...] = arr.buffer.to_numpy()


def reads_host(device) -> bool:
    """taichi:cpu kernels read and write NumPy arrays in place (the solver's host callables' points and
    results are then never copied); elsewhere Taichi would copy them per launch."""
    return current_arch() == "cpu"


def _buf(a):
    """What a kernel takes for an array of the solver: a DeviceArray's ndarray, or a NumPy array itself."""
    return a if isinstance(a, np.ndarray) else a.buffer


def solver_state(device, lay, S, I, Out):
    return State(device, lay, S, I, Out)


def solver_workspace(state, lay, W):
    state.lay, state.W = lay, W
    if not _per_problem():  # raises where the device cannot run the parallel tasks for these sizes
        state.plan = _tasks_plan(state.device, lay.B, lay.P, lay.M, "solver")


def solver_init(state, X0, K, X):
    args = (X0.buffer, K.buffer, state.S.buffer, state.I.buffer, _buf(X))
    if _per_problem():
        launch(_init, args, (state.dt,))
    else:
        B, P = X0.shape
        launch(_init_tasks, args, (state.dt, _grid(max(B * (P + 1), K.shape[0] - B * (2 * P + 1) - P))))


def solver_update(state, R, X, *, first, final, jac=None):
    S, I, W, Out = state.S.buffer, state.I.buffer, state.W.buffer, state.Out.buffer
    Jg = R if jac is None else jac  # unused without a Jacobian callable
    args = (S, I, W, _buf(X), _buf(R), _buf(Jg), Out)
    if _per_problem():
        kernel = _update
        if jac is not None and _in_pairs(jac):
            kernel = _update_pairs
            args = (*args[:5], jac.reshape(*jac.shape[:2], -1, 2), Out)
        # central / forward differences without a mask: 1 / 2 (``_phase_normal``); the final call
        # (residuals at the last points only) takes the solve's other calls' kernel, whose J^T J it skips
        if not final:
            state.fused = 0
            if jac is None and not state.lay.has_mask:
                state.fused = 1 if R.shape[0] == state.lay.B * (2 * state.lay.P + 1) else 2
        SP = _static_p(state.lay.P) if jac is not None else 0
        launch(kernel, args, (state.dt, jac is not None, state.fused, SP), scalars=(int(first), int(final)),
               scalarize=jac is None, ir_passes=False)  # fmt: skip
    else:
        B, P = state.lay.B, state.lay.P
        NI = _grid(B * ((P + 1) // 2) * ((P + 3) // 4 + 1))
        launch(_update_tasks, (S, I, W, R.buffer, Jg.buffer, Out), (state.dt, bool(first), bool(final), jac is not None,
                                                                    NI))  # fmt: skip
        if not final and _block_step():
            launch(_step_block, (S, I, W, X.buffer, Out), (state.dt, BLOCK_STEP), scalars=(state.lay.M,))
        elif not final:
            ncol, nt = state.plan
            for it in range(nt):
                launch(_step_tasks, (S, I, W, X.buffer, Out), (state.dt, _grid(B * (P + 1))),
                       scalars=(state.lay.M, ncol, it, nt))  # fmt: skip


def _download(arr):
    """``arr.numpy()`` (counted in the device's transfers); on taichi:cpu one host-memory copy
    (``arrays.copy``)."""
    if current_arch() != "cpu":
        return arr.numpy()
    out = np.empty(arr.shape, arr.dtype)
    copy(arr.buffer, out)
    arr.device.transfers.d2h += out.nbytes
    return out


def solver_active(state) -> int:
    I = _download(state.I)
    return int(np.count_nonzero(state.lay.iblock(I)[:, LAY.I_STATUS] == RUNNING))


def solver_result(state):
    return _download(state.Out)

"""Taichi kernels of :mod:`gputrack.ops.model_template` (the rule: the op's docstring; the NumPy
reference: gputrack/backends/reference/model_template.py).

* :func:`render` (step 1), one launch: a thread per pixel of the crop (on the CPU arch in float64,
  :func:`_render_lanes`: RENDER_LANES pixels of a row per thread as SIMD lanes, the same arithmetic
  with its branches as masks: 2.0-2.5 -> 0.74-0.91 ms for the body at rest, three runs in turn,
  2026-12-06; the picks still the reference's); every part whose box holds
  the pixel is intersected (the shapes of :func:`gputrack.models.render.intersect`; the
  discriminants in the cross-product form a - (o x d)^2, which keeps the accuracy for a camera far
  from the part; a ray missing the infinite cylinder is rejected before any division), the nearest
  hit wins (strict ``<``: ties to the lower part). It computes in :func:`render_dtype`: float64
  where the device has it (the op's float64 inputs; the texture's double sines by
  :func:`gputrack.backends.taichi.trig.sincos64`, within ~2e-14 of NumPy's: the render and the
  templates equal the reference's, tested), else float32 (the sines a polynomial, :func:`_sin`,
  ~1e-7 off plus the argument's own float32 rounding); the outputs round to float32 at the store.
* :func:`classify` (steps 2-4), one launch of three or four top-level loops (Taichi's barrier
  between them): the statistics zeroed (serial); the per-pixel step 3: the interior flag, q =
  floor(v s) (the float32 product, an integer below 2**40), the window's count, sum and extremes
  in 64-bit integers (the strength numerator |c q - S| < 2**47 into the int64 ``num``; ``window``
  and ``border`` are template values, unrolled), the extremum strength numerator; step 4's per-part
  counts and ranges by atomics on the runs of a part's pixels in a row; the candidates (pool
  extrema) binned per part by an atomic counter (bin order is the atomics' order: only the set
  matters). Elsewhere (GPUs, Vulkan), :func:`_classify`: a thread per crop pixel (an interior pixel with border >=
  window // 2 skips the same-part tests), then a thread per start of a run (per-pixel atomics on
  the few shared statistics cost ~2 ms on a CPU; on lavapipe Vulkan a loop over rows lost every
  row past the 128th, cause not found). On the CPU arch, :func:`_classify_rows`: a task per chunk
  of rows, each row walked column by column with the window's statistics from its columns' shares
  (:func:`_column`: each column's part range, sums and extremes over the window's rows, kept in a
  ring shifted a column a step; exact in float64 and float32), the pixels of a window that holds
  another part one by one, and the runs flushed where they end: 1.6-1.7 -> 0.53-0.59 ms for the
  body at rest (the per-pixel loop's neighbour reads compile to gathers there), the same outputs.
* :func:`emit` (steps 6-7). On the CPU arch one launch of a thread per kind and part (each its own
  task of Taichi's thread pool: a loop over 2 J CPU_TASK indices, every CPU_TASK-th working, as
  Taichi 1.7 gives a CPU task at least 512 indices), as the op's docstring describes: the greedy
  extrema by a partial heap sort of the part's bin, then the farthest-point fill over the part's
  pool (listed in the bin, the candidates being done with) by rows, best first
  (:func:`_farthest_new`): each row starts with a bound of its distances from the extrema taken
  (to the nearest of them of its farther end); the row of the largest bound is brought up to date
  and its bound made exact, until the row of the largest bound is exact (distances only shrink, so
  a bound stays a bound); a new point makes inexact only the rows it can reach. A row far from
  every new point is never computed again (the depth template's torso at rest, 11354 pool pixels:
  1.14 -> 0.79 ms; every pick the same).
  Elsewhere (Vulkan, CUDA) one thread's loops must stay bounded (lavapipe's llvmpipe runs at most
  65535 loop passes per invocation and then silently goes on with wrong numbers): one launch for
  the extrema, the fill's first point and the pool's distances (a thread per pixel), then one
  launch per fill point (the largest tier-and-distance key by atomic max, the first pixel holding
  it by atomic min), as many as the most fill points of a kind and part (one small download).

Every comparison after q is integer arithmetic, so the picks equal the reference's on the same
images (Taichi's CPU backend compiles with fast math: no float tie-breaking is relied on; misses
are flags, not infinities).
"""

import math

import numpy as np

from ...uploads import constant
from .launch import launch
from .particles import _pcg
from .runtime import scratch, ti
from .tasks import CPU_TASK, chunk, cpu_chunks
from .trig import sin64_lanes, sincos64

nd1 = ti.types.ndarray(ndim=1)
nd2 = ti.types.ndarray(ndim=2)
nd3 = ti.types.ndarray(ndim=3)
NO_ROW = 1 << 30


# -- step 1: render -------------------------------------------------------------------------------
PI_A = 3.140625  # pi = PI_A + PI_B (Cody-Waite: n PI_A is exact for the texture's n)
PI_B = math.pi - 3.140625
SIN_TAYLOR = [(-1) ** m / math.factorial(2 * m + 1) for m in range(1, 6)]  # x^3 .. x^11


@ti.func
def _ifloor(x):
    """floor(x) as an int32 (|x| < 2**31; one instruction on the CPU, faster than a truncation
    with a correction, measured)."""
    return ti.cast(ti.floor(x), ti.i32)


@ti.func
def _qfloor(x):
    """floor(x) as an int64 (|x| < 2**40: step 2's q from the float32 product v s, exact)."""
    return ti.cast(ti.floor(x), ti.i64)


@ti.func
def _sin(x):
    """sin(x) in float32 to ~1e-7 (+ |x| eps of the reduction): x - n pi in [-pi/2, pi/2], its
    Taylor polynomial to x^11; ~3x faster than libm's sinf on the CPU arch."""
    ni = _ifloor(x * (1.0 / math.pi) + 0.5)
    n = ti.cast(ni, ti.f32)
    r = (x - n * PI_A) - n * PI_B
    r2 = r * r
    poly = ti.f32(SIN_TAYLOR[4])
    for m in ti.static(range(3, -1, -1)):
        poly = poly * r2 + ti.f32(SIN_TAYLOR[m])
    y = r + r * r2 * poly
    return ti.select((ni & 1) != 0, -y, y)


@ti.func
def _first_root(a, bh, disc):
    """The smaller root t of a t^2 + 2 bh t + c = 0 given its discriminant bh^2 - a c >= 0, a > 0."""
    return (-bh - ti.sqrt(disc)) / a


@ti.func
def _axes(k, v):
    """(v[k], v[u], v[w]): the axis component and the two others in increasing axis order."""
    return (ti.select(k == 0, v[0], ti.select(k == 1, v[1], v[2])), ti.select(k == 0, v[1], v[0]),
            ti.select(k == 2, v[1], v[2]))  # fmt: skip


@ti.func
def _side(ou, ov, du, dv, ra, rb, real: ti.template()):
    """The side of an (elliptic) cylinder in the coordinates scaled to a unit circle (a capsule: ra =
    rb = r): (u, v of o, u, v of d, a, the discriminant as a - (o x d)^2: no cancellation of the large
    |o|^2 |d|^2 terms); d scalars or lanes."""
    ia = 1.0 / ra
    ib = 1.0 / rb
    ua = ou * ia
    va = ov * ib
    ea = du * ia
    eb = dv * ib
    a = ea * ea + eb * eb
    cr = ua * eb - va * ea
    return ua, va, ea, eb, a, ti.max(a - cr * cr, ti.cast(0.0, real))


@ti.func
def _cap_sphere(o, d, k, end, dd, r, real: ti.template()):
    """A capsule's cap: the sphere of radius r at ``end`` on the axis k, and the ray o + t d (d one
    ray, or three vectors of lanes; dd = d . d): (dd r^2 - |oc x d|^2, d . oc), oc = o - end e_k (the
    discriminant without the cancellation of (d . oc)^2 - dd (|oc|^2 - r^2), Lagrange's identity)."""
    oc = ti.Vector([o[0], o[1], o[2]], dt=real)
    for m in ti.static(range(3)):
        if k == m:
            oc[m] = o[m] - end
    x = oc[1] * d[2] - oc[2] * d[1]
    y = oc[2] * d[0] - oc[0] * d[2]
    z = oc[0] * d[1] - oc[1] * d[0]
    return dd * r * r - (x * x + y * y + z * z), d[0] * oc[0] + d[1] * oc[1] + d[2] * oc[2]


@ti.func
def _intersect(table: ti.template(), j, o, d, real: ti.template()):
    """First hit of the ray o + t d (part coordinates) with part j's shape: (hit, t, which) as
    gputrack.models.render.intersect (which: 0 the side or a capsule, 1/2 a cylinder's start/end
    cap), in ``real``. A ray that misses the infinite (elliptic) cylinder misses the shape (the
    caps lie inside it); one that enters it within [start, end] hits there first (t > 0 checked
    after, as the reference's min over the surfaces): only the rest needs the caps."""
    kind = table[j, 16]
    k = ti.cast(table[j, 17], ti.i32)
    s0 = table[j, 18]
    s1 = table[j, 19]
    ok, ou, ov = _axes(k, o)
    dk, du, dv = _axes(k, d)
    hit = False
    t = real(0.0)
    which = 0
    ra = table[j, 20]
    rb = table[j, 21]
    # a ray that misses the infinite cylinder misses the shape: tested without a division first
    # (the discriminant below times ra^2 rb^2)
    x0 = ou * dv - ov * du
    if du * du * rb * rb + dv * dv * ra * ra - x0 * x0 >= 0.0:
        ua, va, ea, eb, a, disc = _side(ou, ov, du, dv, ra, rb, real)
        inside = False
        if a > 0.0:
            t0 = _first_root(a, ua * ea + va * eb, disc)
            s = ok + t0 * dk
            if (s >= s0) & (s <= s1):
                hit = True
                inside = True
                t = t0
        if not inside:
            if kind == 0.0:  # capsule: the spheres of the two caps
                r = table[j, 20]
                dd = d.dot(d)
                for e in ti.static(range(2)):
                    ds, bh = _cap_sphere(o, d, k, s1 if ti.static(e == 1) else s0, dd, r, real)
                    if ds >= 0.0:
                        ts = _first_root(dd, bh, ds)
                        if (not hit) | (ts < t):
                            hit = True
                            t = ts
            elif dk != 0.0:  # cylinder: the flat caps
                idk = 1.0 / dk
                for e in ti.static(range(2)):
                    tc = ((s1 if ti.static(e == 1) else s0) - ok) * idk
                    pu = ua + tc * ea
                    pv = va + tc * eb
                    if (pu * pu + pv * pv <= 1.0) & ((not hit) | (tc < t)):
                        hit = True
                        t = tc
                        which = e + 1
    return hit & (t > 0.0), t, which


@ti.func
def _normal(table: ti.template(), j, p, which, real: ti.template()):
    """The unit outward normal at the hit p of part j's shape (``which`` from :func:`_intersect`)."""
    k = ti.cast(table[j, 17], ti.i32)
    s0 = table[j, 18]
    s1 = table[j, 19]
    ra = table[j, 20]
    rb = table[j, 21]
    n = ti.Vector([0.0, 0.0, 0.0], dt=real)
    if table[j, 16] == 0.0:  # capsule: from the closest point of the axis segment, / r
        n = ti.Vector([p[0], p[1], p[2]], dt=real)
        for m in ti.static(range(3)):
            if k == m:
                n[m] = p[m] - ti.min(ti.max(p[m], s0), s1)
        n = n / ra
    else:
        for m in ti.static(range(3)):
            if k == m:
                n[m] = ti.select(which == 1, -1.0, ti.select(which == 2, 1.0, 0.0))
            elif which == 0:
                n[m] = p[m] / ti.select(m == ti.select(k == 0, 1, 0), ra * ra, rb * rb)
        n = n / ti.max(n.norm(), real(1e-12))
    return n


@ti.kernel
def _render(table: nd2, waves: nd3, consts: nd1, part: nd2, values: nd3, local: nd3, r0: ti.i32, r1: ti.i32,
            c0: ti.i32, c1: ti.i32, real: ti.template()):  # fmt: skip
    """Step 1 over the crop in ``real`` (table, waves and consts of that type; float literals that
    are not exact in float32 written real(x): Taichi's literals take the default float32 type)."""
    J = table.shape[0]
    fx, fy, cx, cy, amp, shading = consts[0], consts[1], consts[2], consts[3], consts[4], consts[5]
    w = c1 - c0
    for i in range((r1 - r0) * w):
        r = r0 + i // w
        c = c0 + i % w
        dc = ti.Vector([(ti.cast(c, real) - cx) / fx, (ti.cast(r, real) - cy) / fy, 1.0], dt=real)
        best = -1
        bt = real(0.0)
        bwhich = 0
        bd = ti.Vector([0.0, 0.0, 1.0], dt=real)
        for j in range(J):
            if (r >= ti.cast(table[j, 12], ti.i32)) & (r < ti.cast(table[j, 13], ti.i32)) & \
                    (c >= ti.cast(table[j, 14], ti.i32)) & (c < ti.cast(table[j, 15], ti.i32)):  # fmt: skip
                d = ti.Vector([0.0, 0.0, 0.0], dt=real)
                o = ti.Vector([table[j, 9], table[j, 10], table[j, 11]], dt=real)
                for m in ti.static(range(3)):
                    d[m] = table[j, 3 * m] * dc[0] + table[j, 3 * m + 1] * dc[1] + table[j, 3 * m + 2] * dc[2]
                hit, t, which = _intersect(table, j, o, d, real)
                if hit & ((best < 0) | (t < bt)):
                    best = j
                    bt = t
                    bwhich = which
                    bd = d
        gray = real(0.0)
        x = ti.Vector([0.0, 0.0, 0.0], dt=real)
        if best >= 0:
            x = ti.Vector([table[best, 9], table[best, 10], table[best, 11]], dt=real) + bt * bd
            s = real(0.0)
            for q in range(waves.shape[1]):
                arg = waves[best, q, 0] * x[0] + waves[best, q, 1] * x[1] + waves[best, q, 2] * x[2] + waves[best, q, 3]
                if ti.static(real == ti.f64):
                    s += sincos64(arg)[0]
                else:
                    s += _sin(arg)
            tex = ti.min(ti.max(0.5 + amp * s, real(0.02)), real(0.98))
            cosv = ti.abs(bd.dot(_normal(table, best, x, bwhich, real))) / bd.norm()
            gray = tex * (1.0 - shading + shading * cosv)
        part[r, c] = best
        values[0, r, c] = ti.cast(gray, ti.f32)
        values[1, r, c] = ti.cast(bt, ti.f32)
        for m in ti.static(range(3)):
            local[r, c, m] = ti.cast(x[m], ti.f32)


#: pixels of a crop row per thread of :func:`_render_lanes` (8 float64: one AVX-512 register)
RENDER_LANES = 8


@ti.func
def _lanes_v(x, L: ti.template()):
    """The value x in every one of L float64 lanes."""
    return ti.Vector([x] * L, dt=ti.f64)


@ti.func
def _intersect_lanes(table: ti.template(), j, o, d, L: ti.template()):
    """:func:`_intersect` for L rays at once (d: three L-lane vectors, o the part's origin): the same
    arithmetic lane by lane, its branches as masks (hit, t, which)."""
    f64 = ti.f64
    kind = table[j, 16]
    k = ti.cast(table[j, 17], ti.i32)
    s0 = table[j, 18]
    s1 = table[j, 19]
    ra = table[j, 20]
    rb = table[j, 21]
    ok, ou, ov = _axes(k, o)
    dk = d[2]  # _axes(k, d) by a branch: a select of vectors on a scalar condition does not compile here
    du = d[0]
    dv = d[1]
    if k == 0:
        dk = d[0]
        du = d[1]
        dv = d[2]
    elif k == 1:
        dk = d[1]
        du = d[0]
        dv = d[2]
    zero = _lanes_v(f64(0.0), L)
    t = zero
    which = ti.Vector([0] * L, dt=ti.i32)
    x0 = ou * dv - ov * du
    near = du * du * rb * rb + dv * dv * ra * ra - x0 * x0 >= 0.0  # the infinite cylinder
    ua, va, ea, eb, a, disc = _side(ou, ov, du, dv, ra, rb, f64)
    positive = a > 0.0
    # (-b - sqrt) / a as _first_root; 0 - x for -x: a unary minus of a value that came through a
    # select trips an LLVM assertion in Taichi 1.7 with scalarisation off
    t0 = (f64(0.0) - (ua * ea + va * eb) - ti.sqrt(disc)) / ti.select(positive, a, _lanes_v(f64(1.0), L))
    s = ok + t0 * dk
    inside = near & positive & (s >= s0) & (s <= s1)
    hit = inside
    t = ti.select(inside, t0, t)
    rest = near & ~inside
    if kind == 0.0:  # capsule: the spheres of the two caps
        r = ra
        dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        for e in ti.static(range(2)):
            ds, bh = _cap_sphere(o, d, k, s1 if ti.static(e == 1) else s0, dd, r, f64)
            ts = (f64(0.0) - bh - ti.sqrt(ti.max(ds, f64(0.0)))) / dd
            take = rest & (ds >= 0.0) & (~hit | (ts < t))
            hit = hit | take
            t = ti.select(take, ts, t)
    else:  # cylinder: the flat caps
        moving = dk != 0.0
        idk = 1.0 / ti.select(moving, dk, _lanes_v(f64(1.0), L))
        for e in ti.static(range(2)):
            tc = ((s1 if ti.static(e == 1) else s0) - ok) * idk
            pu = ua + tc * ea
            pv = va + tc * eb
            take = rest & moving & (pu * pu + pv * pv <= 1.0) & (~hit | (tc < t))
            hit = hit | take
            t = ti.select(take, tc, t)
            which = ti.select(take, ti.Vector([e + 1] * L, dt=ti.i32), which)
    return hit & (t > 0.0), t, which


@ti.kernel
def _render_lanes(table: nd2, waves: nd3, consts: nd1, part: nd2, values: nd3, local: nd3, r0: ti.i32, r1: ti.i32,
                  c0: ti.i32, c1: ti.i32, L: ti.template()):  # fmt: skip
    """:func:`_render` in float64 for L consecutive pixels of a crop row per thread (the CPU arch,
    compiled with scalarisation off: each value a SIMD vector of L lanes; the same arithmetic, lane
    by lane, its branches as masks). The shading runs once per part that won a lane."""
    f64 = ti.f64
    J = table.shape[0]
    fx, fy, cx, cy, amp, shading = consts[0], consts[1], consts[2], consts[3], consts[4], consts[5]
    ng = (c1 - c0 + L - 1) // L
    for i in range((r1 - r0) * ng):
        r = r0 + i // ng
        c = c0 + (i % ng) * L
        cf = ti.Vector([ti.cast(c + e, f64) for e in ti.static(range(L))], dt=f64)
        fr = ti.cast(r, f64)
        dc0 = (cf - cx) / fx
        dc1 = (fr - cy) / fy
        dc2 = f64(1.0)
        best = ti.Vector([-1] * L, dt=ti.i32)
        bt = _lanes_v(f64(0.0), L)
        bwhich = ti.Vector([0] * L, dt=ti.i32)
        bd0 = _lanes_v(f64(0.0), L)
        bd1 = _lanes_v(f64(0.0), L)
        bd2 = _lanes_v(f64(1.0), L)
        for j in range(J):
            if (fr >= table[j, 12]) & (fr < table[j, 13]) & (ti.cast(c + L - 1, f64) >= table[j, 14]) & \
                    (ti.cast(c, f64) < table[j, 15]):  # fmt: skip
                inbox = (cf >= table[j, 14]) & (cf < table[j, 15])
                d = [table[j, 3 * m] * dc0 + table[j, 3 * m + 1] * dc1 + table[j, 3 * m + 2] * dc2 for m in ti.static(range(3))]
                o = ti.Vector([table[j, 9], table[j, 10], table[j, 11]], dt=f64)
                hit, t, which = _intersect_lanes(table, j, o, d, L)
                take = inbox & hit & ((best < 0) | (t < bt))
                best = ti.select(take, ti.Vector([j] * L, dt=ti.i32), best)
                bt = ti.select(take, t, bt)
                bwhich = ti.select(take, which, bwhich)
                bd0 = ti.select(take, d[0], bd0)
                bd1 = ti.select(take, d[1], bd1)
                bd2 = ti.select(take, d[2], bd2)
        gray = _lanes_v(f64(0.0), L)
        x0 = _lanes_v(f64(0.0), L)
        x1 = _lanes_v(f64(0.0), L)
        x2 = _lanes_v(f64(0.0), L)
        for j in range(J):  # the shading of each part that won a lane
            mine = best == j
            won = 0
            for e in ti.static(range(L)):
                won = won | ti.cast(best[e] == j, ti.i32)
            if won != 0:
                p0 = table[j, 9] + bt * bd0
                p1 = table[j, 10] + bt * bd1
                p2 = table[j, 11] + bt * bd2
                sm = _lanes_v(f64(0.0), L)
                for q in range(waves.shape[1]):
                    arg = waves[j, q, 0] * p0 + waves[j, q, 1] * p1 + waves[j, q, 2] * p2 + waves[j, q, 3]
                    sm += sin64_lanes(arg)
                tex = ti.min(ti.max(f64(0.5) + amp * sm, f64(0.02)), f64(0.98))
                # the unit outward normal (_normal) at the hit
                k = ti.cast(table[j, 17], ti.i32)
                s0 = table[j, 18]
                s1 = table[j, 19]
                ra = table[j, 20]
                rb = table[j, 21]
                pv = [p0, p1, p2]
                nv = [p0 * 0.0, p1 * 0.0, p2 * 0.0]
                if table[j, 16] == 0.0:  # capsule: from the closest point of the axis segment, / r
                    for m in ti.static(range(3)):
                        nv[m] = pv[m] / ra
                        if k == m:
                            nv[m] = (pv[m] - ti.min(ti.max(pv[m], s0), s1)) / ra
                else:
                    cap = ti.select(bwhich == 1, _lanes_v(f64(-1.0), L),
                                    ti.select(bwhich == 2, _lanes_v(f64(1.0), L), _lanes_v(f64(0.0), L)))  # fmt: skip
                    for m in ti.static(range(3)):
                        den = ti.select(m == ti.select(k == 0, 1, 0), ra * ra, rb * rb)
                        nv[m] = ti.select(bwhich == 0, pv[m] / den, _lanes_v(f64(0.0), L))
                        if k == m:
                            nv[m] = cap
                    nn = ti.max(ti.sqrt(nv[0] * nv[0] + nv[1] * nv[1] + nv[2] * nv[2]), f64(1e-12))
                    for m in ti.static(range(3)):
                        nv[m] = nv[m] / nn
                dn = bd0 * nv[0] + bd1 * nv[1] + bd2 * nv[2]
                cosv = ti.max(dn, f64(0.0) - dn) / ti.sqrt(bd0 * bd0 + bd1 * bd1 + bd2 * bd2)  # |dn| (ti.abs: "not supported")
                g = tex * (f64(1.0) - shading + shading * cosv)
                gray = ti.select(mine, g, gray)
                x0 = ti.select(mine, p0, x0)
                x1 = ti.select(mine, p1, x1)
                x2 = ti.select(mine, p2, x2)
        for e in ti.static(range(L)):
            if c + e < c1:
                part[r, c + e] = best[e]
                values[0, r, c + e] = ti.cast(gray[e], ti.f32)
                values[1, r, c + e] = ti.cast(bt[e], ti.f32)
                local[r, c + e, 0] = ti.cast(x0[e], ti.f32)
                local[r, c + e, 1] = ti.cast(x1[e], ti.f32)
                local[r, c + e, 2] = ti.cast(x2[e], ti.f32)


def render_dtype(device):
    """The type the render computes in: np.float64 where the device has it (the reference's float64,
    so the templates are the reference's), else np.float32. The texture's double sines are
    :func:`gputrack.backends.taichi.trig.sincos64` on every arch (SPIR-V has no double sine,
    "Instruction Sin does not 64bits operation"; on the CPU it is inlined where the C library's is a
    call: render 11.6 -> 9.7 ms for the body at rest, measured): within ~2e-14 of NumPy's for the
    texture's arguments, far below the float32 rounding of the gray value."""
    return np.float64 if device.fp64 else np.float32


def render(device, chain, transforms, texture, table, waves, consts, crop, part, values, local):
    """Step 1 into ``part``, ``values``, ``local`` at the pixels of ``crop`` (computed in
    :func:`render_dtype`, stored float32)."""
    r0, r1, c0, c1 = (int(x) for x in crop)
    if r1 <= r0 or c1 <= c0:
        return
    dt = render_dtype(device)  # the op's tables are float64
    table = np.ascontiguousarray(table, dt)
    waves = np.ascontiguousarray(waves, dt)
    consts = np.ascontiguousarray(consts, dt)
    real = ti.f64 if dt == np.float64 else ti.f32
    if device.arch == "cpu":  # read in place
        tab, wv, cs = table, waves, consts
    else:
        tab = scratch(device, "mt table", table.shape, real)
        tab.from_numpy(table)
        wv = constant(device, waves).buffer
        cs = constant(device, consts).buffer
    arrays = (tab, wv, cs, part.buffer, values.buffer, local.buffer)
    if device.arch == "cpu" and real == ti.f64:
        launch(_render_lanes, arrays, (RENDER_LANES,), scalars=(r0, r1, c0, c1), scalarize=False)
    else:
        launch(_render, arrays, (real,), scalars=(r0, r1, c0, c1))


# -- steps 2-5: classify ----------------------------------------------------------------------------
@ti.func
def _stronger(num_a, cnt_a, idx_a, num_b, cnt_b, idx_b):
    """a stronger than b: |c q - S| / c larger (cross-multiplied in 64 bits), ties by the pcg hash of
    the pixel index, then by the index (the op's step 3)."""
    lhs = ti.cast(num_a, ti.i64) * ti.cast(cnt_b, ti.i64)
    rhs = ti.cast(num_b, ti.i64) * ti.cast(cnt_a, ti.i64)
    ha = _pcg(ti.cast(idx_a, ti.u32))
    hb = _pcg(ti.cast(idx_b, ti.u32))
    return (lhs > rhs) | ((lhs == rhs) & ((ha < hb) | ((ha == hb) & (idx_a < idx_b))))


@ti.func
def _at(r, c, r0, r1, c0, c1):
    """(in the crop, r and c clamped into the crop): branch-free neighbour reads."""
    inside = (r >= r0) & (r < r1) & (c >= c0) & (c < c1)
    return inside, ti.min(ti.max(r, r0), r1 - 1), ti.min(ti.max(c, c0), c1 - 1)


@ti.func
def _flush(stats: ti.template(), j, count, base, r, a, b):
    """A run of part j's pixels (or interior pixels) in row r, columns a .. b, into the statistics."""
    ti.atomic_add(stats[j, count], b - a + 1)
    if r < stats[j, base]:
        ti.atomic_min(stats[j, base], r)
    if r > stats[j, base + 1]:
        ti.atomic_max(stats[j, base + 1], r)
    if a < stats[j, base + 2]:
        ti.atomic_min(stats[j, base + 2], a)
    if b > stats[j, base + 3]:
        ti.atomic_max(stats[j, base + 3], b)


@ti.func
def _zero_stats(stats: ti.template(), surv: ti.template()):
    """The per-part statistics and candidate counters reset (a serial loop: a few values)."""
    ti.loop_config(serialize=True)
    for j in range(stats.shape[0]):
        stats[j, 0] = 0
        stats[j, 1] = 0
        for e in ti.static(range(4)):
            stats[j, 2 + 2 * e] = NO_ROW
            stats[j, 3 + 2 * e] = -1
        surv[0, j] = 0
        surv[1, j] = 0


@ti.func
def _strength(count, q, S, hi, lo):
    """Step 3's extremum strength numerator |c q - S| (int64), -1 where q is not an extremum."""
    e = ti.cast(count, ti.i64) * q - S
    return ti.select((hi > lo) & ((q == hi) | (q == lo)), ti.select(e < 0, -e, e), ti.i64(-1))


@ti.func
def _window(part: ti.template(), values: ti.template(), r, c, p, r0, r1, c0, c1, s0, s1, half: ti.template(),
            masked: ti.template()):  # fmt: skip
    """Step 3 over the window of pixel (r, c) of part p: (count, num0, num1). ``masked``: only the
    window's pixels of part p count (branch-free reads clamped into the crop); else the whole window
    is of part p (read as it is)."""
    q0 = _qfloor(values[0, r, c] * s0)
    q1 = _qfloor(values[1, r, c] * s1)
    count = 1
    S0 = q0
    S1 = q1
    hi0 = q0
    lo0 = q0
    hi1 = q1
    lo1 = q1
    for dy in ti.static(range(-half, half + 1)):
        for dx in ti.static(range(-half, half + 1)):
            if ti.static(dy != 0 or dx != 0):
                same = True
                y = r + dy
                x = c + dx
                if ti.static(masked):
                    inside, y, x = _at(r + dy, c + dx, r0, r1, c0, c1)
                    same = inside & (part[y, x] == p)
                a0 = _qfloor(values[0, y, x] * s0)
                a1 = _qfloor(values[1, y, x] * s1)
                count += ti.cast(same, ti.i32)
                S0 += ti.select(same, a0, ti.i64(0))
                S1 += ti.select(same, a1, ti.i64(0))
                hi0 = ti.select(same, ti.max(hi0, a0), hi0)
                lo0 = ti.select(same, ti.min(lo0, a0), lo0)
                hi1 = ti.select(same, ti.max(hi1, a1), hi1)
                lo1 = ti.select(same, ti.min(lo1, a1), lo1)
    return count, _strength(count, q0, S0, hi0, lo0), _strength(count, q1, S1, hi1, lo1)


@ti.func
def _bin(part: ti.template(), interior: ti.template(), num: ti.template(), stats: ti.template(), surv: ti.template(),
         bins: ti.template(), r, c):  # fmt: skip
    """Pixel (r, c) into its part's bins of candidates if it is a pool extremum (the pool: every
    pixel of a part without interior)."""
    p = part[r, c]
    if p >= 0:  # noqa: SIM102 - the inner test reads stats[p]
        if (stats[p, 1] == 0) | (interior[r, c] != 0):
            for k in ti.static(range(2)):
                if num[k, r, c] >= 0:
                    start = 0
                    for jj in range(p):
                        start += stats[jj, 0]
                    bins[k, start + ti.atomic_add(surv[k, p], 1)] = r * part.shape[1] + c


@ti.kernel
def _classify(part: nd2, values: nd3, interior: nd2, num: nd3, cnt: nd2, bins: nd2, stats: nd2, surv: nd2,
              r0: ti.i32, r1: ti.i32, c0: ti.i32, c1: ti.i32, s0: ti.f32, s1: ti.f32, half: ti.template(),
              border: ti.template()):  # fmt: skip
    w = c1 - c0
    n = (r1 - r0) * w
    _zero_stats(stats, surv)
    for i in range(n):  # 3. per pixel: interior flag, window statistics, extremum strength (branch-free)
        r = r0 + i // w
        c = c0 + i % w
        p = part[r, c]
        inner = 0
        count = 0
        num0 = ti.i64(-1)
        num1 = ti.i64(-1)
        if p >= 0:
            same_all = True
            for dy in ti.static(range(-border, border + 1)):
                for dx in ti.static(range(-border, border + 1)):
                    if ti.static(dy != 0 or dx != 0):
                        inside, y, x = _at(r + dy, c + dx, r0, r1, c0, c1)
                        same_all = same_all & inside & (part[y, x] == p)
            inner = ti.cast(same_all, ti.i32)
            if ti.static(border >= half) and same_all:  # an interior pixel: its whole window is of its part
                count, num0, num1 = _window(part, values, r, c, p, r0, r1, c0, c1, s0, s1, half, False)
            else:
                count, num0, num1 = _window(part, values, r, c, p, r0, r1, c0, c1, s0, s1, half, True)
        interior[r, c] = inner
        num[0, r, c] = num0
        num[1, r, c] = num1
        cnt[r, c] = count
    for i in range(n):  # 4. a thread per start of a run of a part's (interior) pixels in a row flushes it
        r = r0 + i // w
        c = c0 + i % w
        p = part[r, c]
        if p >= 0:
            q = ti.select(interior[r, c] != 0, p, -1)
            before = -1
            qbefore = -1
            if c > c0:
                before = part[r, c - 1]
                qbefore = ti.select(interior[r, c - 1] != 0, before, -1)
            if before != p:
                e = c + 1
                while (e < c1) and (part[r, e] == p):
                    e += 1
                _flush(stats, p, 0, 6, r, c, e - 1)
            if (q >= 0) & (qbefore != q):
                e = c + 1
                while (e < c1) and (part[r, e] == p) and (interior[r, e] != 0):
                    e += 1
                _flush(stats, p, 1, 2, r, c, e - 1)
    for i in range(n):  # the candidates (pool extrema) binned per part
        _bin(part, interior, num, stats, surv, bins, r0 + i // w, c0 + i % w)


@ti.func
def _column(part: ti.template(), values: ti.template(), r, x, r0, r1, c0, c1, s0, s1, half: ti.template(),
            border: ti.template()):  # fmt: skip
    """Column x's share of the windows centred in row r: the smallest and largest part id over the
    window's rows (r - half .. r + half) and over the border's, a pixel outside the crop counting as
    -1 ((4,) int32); the sums of q over the window's rows ((2,) float64: integers below 2**43,
    exact) and their extremes ((4,) float32: hi0, lo0, hi1, lo1; q = floor(v s) is an integer
    below 2**40 that float32 holds exactly)."""
    xin = (x >= c0) & (x < c1)
    xc = ti.min(ti.max(x, c0), c1 - 1)
    pmin_h = NO_ROW
    pmax_h = -1
    pmin_b = NO_ROW
    pmax_b = -1
    S0 = ti.f64(0.0)
    S1 = ti.f64(0.0)
    hi0 = ti.f32(-3e38)
    lo0 = ti.f32(3e38)
    hi1 = ti.f32(-3e38)
    lo1 = ti.f32(3e38)
    for dy in ti.static(range(-max(half, border), max(half, border) + 1)):
        y = r + dy
        yc = ti.min(ti.max(y, r0), r1 - 1)
        p = ti.select(xin & (y >= r0) & (y < r1), part[yc, xc], -1)
        if ti.static(-half <= dy <= half):
            pmin_h = ti.min(pmin_h, p)
            pmax_h = ti.max(pmax_h, p)
            a0 = ti.floor(values[0, yc, xc] * s0)
            a1 = ti.floor(values[1, yc, xc] * s1)
            S0 += ti.cast(a0, ti.f64)
            S1 += ti.cast(a1, ti.f64)
            hi0 = ti.max(hi0, a0)
            lo0 = ti.min(lo0, a0)
            hi1 = ti.max(hi1, a1)
            lo1 = ti.min(lo1, a1)
        if ti.static(-border <= dy <= border):
            pmin_b = ti.min(pmin_b, p)
            pmax_b = ti.max(pmax_b, p)
    return ti.Vector([pmin_h, pmax_h, pmin_b, pmax_b]), ti.Vector([S0, S1]), ti.Vector([hi0, lo0, hi1, lo1])


@ti.kernel
def _classify_rows(part: nd2, values: nd3, interior: nd2, num: nd3, cnt: nd2, bins: nd2, stats: nd2, surv: nd2,
                   r0: ti.i32, r1: ti.i32, c0: ti.i32, c1: ti.i32, s0: ti.f32, s1: ti.f32, half: ti.template(),
                   border: ti.template(), chunks: ti.template()):  # fmt: skip
    """:func:`_classify` on the CPU arch, its rows cut into ``chunks`` (each a task of Taichi's thread
    pool) and each row walked column by column: the window's statistics from the aggregates of its
    2R + 1 columns (:func:`_column`, R = max(half, border); a ring shifted one column a step), the
    window's pixels one by one only where it holds another part; the runs of step 4 flushed where
    they end. Every pixel's outputs equal :func:`_classify`'s."""
    h = r1 - r0
    R = ti.static(max(half, border))
    NC = ti.static(2 * max(half, border) + 1)
    _zero_stats(stats, surv)
    for it in range(chunks * CPU_TASK):
        begin, end = chunk(it, h, chunks)
        for rr in range(begin, end):
            r = r0 + rr
            Pc = ti.Matrix([[0] * 4 for _ in ti.static(range(NC))], ti.i32)  # columns c - R .. c + R
            Sc = ti.Matrix([[0.0] * 2 for _ in ti.static(range(NC))], ti.f64)
            Ec = ti.Matrix([[0.0] * 4 for _ in ti.static(range(NC))], ti.f32)
            for k in ti.static(range(1, NC)):  # the columns left of c0 + R + 1
                pv, sv, ev = _column(part, values, r, c0 - R - 1 + k, r0, r1, c0, c1, s0, s1, half, border)
                for m in ti.static(range(4)):
                    Pc[k, m] = pv[m]
                    Ec[k, m] = ev[m]
                for m in ti.static(range(2)):
                    Sc[k, m] = sv[m]
            run = -1  # the part of the run of pixels that ends at c - 1, and where it started
            run_c = c0
            irun = -1  # the same for its interior pixels
            irun_c = c0
            for c in range(c0, c1):
                pv, sv, ev = _column(part, values, r, c + R, r0, r1, c0, c1, s0, s1, half, border)
                for k in ti.static(range(NC)):
                    for m in ti.static(range(4)):
                        Pc[k, m] = Pc[k + 1, m] if ti.static(k + 1 < NC) else pv[m]
                        Ec[k, m] = Ec[k + 1, m] if ti.static(k + 1 < NC) else ev[m]
                    for m in ti.static(range(2)):
                        Sc[k, m] = Sc[k + 1, m] if ti.static(k + 1 < NC) else sv[m]
                p = part[r, c]
                inner = 0
                count = 0
                num0 = ti.i64(-1)
                num1 = ti.i64(-1)
                if p >= 0:
                    bmin, bmax, wmin, wmax = NO_ROW, -1, NO_ROW, -1
                    for k in ti.static(range(R - border, R + border + 1)):
                        bmin = ti.min(bmin, Pc[k, 2])
                        bmax = ti.max(bmax, Pc[k, 3])
                    for k in ti.static(range(R - half, R + half + 1)):
                        wmin = ti.min(wmin, Pc[k, 0])
                        wmax = ti.max(wmax, Pc[k, 1])
                    inner = ti.cast((bmin == p) & (bmax == p), ti.i32)
                    if (wmin == p) & (wmax == p):  # the window is all of part p
                        count = (2 * half + 1) * (2 * half + 1)
                        q0 = ti.floor(values[0, r, c] * s0)
                        q1 = ti.floor(values[1, r, c] * s1)
                        S0 = ti.f64(0.0)
                        S1 = ti.f64(0.0)
                        hi0, lo0, hi1, lo1 = q0, q0, q1, q1
                        for k in ti.static(range(R - half, R + half + 1)):
                            S0 += Sc[k, 0]
                            S1 += Sc[k, 1]
                            hi0 = ti.max(hi0, Ec[k, 0])
                            lo0 = ti.min(lo0, Ec[k, 1])
                            hi1 = ti.max(hi1, Ec[k, 2])
                            lo1 = ti.min(lo1, Ec[k, 3])
                        i64 = ti.i64  # every value an integer: exact in int64 as in the per-pixel kernel
                        num0 = _strength(count, ti.cast(q0, i64), ti.cast(S0, i64), ti.cast(hi0, i64), ti.cast(lo0, i64))
                        num1 = _strength(count, ti.cast(q1, i64), ti.cast(S1, i64), ti.cast(hi1, i64), ti.cast(lo1, i64))
                    else:
                        count, num0, num1 = _window(part, values, r, c, p, r0, r1, c0, c1, s0, s1, half, True)
                interior[r, c] = inner
                num[0, r, c] = num0
                num[1, r, c] = num1
                cnt[r, c] = count
                iq = ti.select(inner != 0, p, -1)  # 4. a run (of interior pixels) ends where the part changes
                if p != run:
                    if run >= 0:
                        _flush(stats, run, 0, 6, r, run_c, c - 1)
                    run = p
                    run_c = c
                if iq != irun:
                    if irun >= 0:
                        _flush(stats, irun, 1, 2, r, irun_c, c - 1)
                    irun = iq
                    irun_c = c
            if run >= 0:
                _flush(stats, run, 0, 6, r, run_c, c1 - 1)
            if irun >= 0:
                _flush(stats, irun, 1, 2, r, irun_c, c1 - 1)
    for it in range(chunks * CPU_TASK):  # the candidates (pool extrema) binned per part
        begin, end = chunk(it, h, chunks)
        for rr in range(begin, end):
            for c in range(c0, c1):
                _bin(part, interior, num, stats, surv, bins, r0 + rr, c)


def classify(device, part, values, crop, scales, window, border, interior, num, cnt, bins, stats, surv):
    """Steps 2-4: stats (J, 10), surv (2, J) candidates per kind and part, bins (unordered), the
    interior flag, num (int64: the extrema's strength numerators, -1 elsewhere), cnt."""
    r0, r1, c0, c1 = (int(x) for x in crop)
    sc = np.asarray(scales, np.float32)
    arrays = (part.buffer, values.buffer, interior.buffer, num.buffer, cnt.buffer, bins.buffer, stats.buffer,
              surv.buffer)  # fmt: skip
    scalars = (r0, r1, c0, c1, float(sc[0]), float(sc[1]))
    if device.arch == "cpu":
        launch(_classify_rows, arrays, (int(window) // 2, int(border), cpu_chunks(device)), scalars=scalars,
               ir_passes=False)
    else:
        launch(_classify, arrays, (int(window) // 2, int(border)), scalars=scalars)


# -- steps 6-7: emit --------------------------------------------------------------------------------
@ti.func
def _stronger_px(num: ti.template(), cnt: ti.template(), k, W, a, b):
    """Candidate pixel a (index r W + c) stronger than b for value k."""
    ra = a // W
    ca = a - ra * W
    rb = b // W
    cb = b - rb * W
    return _stronger(num[k, ra, ca], cnt[ra, ca], a, num[k, rb, cb], cnt[rb, cb], b)


@ti.func
def _sift(bins: ti.template(), num: ti.template(), cnt: ti.template(), k, W, start, i0, size):
    """Sift bins[k, start + i0] down the max-heap (by strength) of ``size`` entries at ``start``."""
    i = i0
    while True:
        l = 2 * i + 1
        if l >= size:
            break
        m = l
        if l + 1 < size:  # noqa: SIM102 - the inner test reads past the heap otherwise
            if _stronger_px(num, cnt, k, W, bins[k, start + l + 1], bins[k, start + l]):
                m = l + 1
        if not _stronger_px(num, cnt, k, W, bins[k, start + m], bins[k, start + i]):
            break
        t = bins[k, start + i]
        bins[k, start + i] = bins[k, start + m]
        bins[k, start + m] = t
        i = m


@ti.func
def _put(out0: ti.template(), out1: ti.template(), k, o, local: ti.template(), values: ti.template(), r, c):
    """Point o of template k: the part-local point and value of pixel (r, c)."""
    if k == 0:
        for m in ti.static(range(3)):
            out0[o, m] = local[r, c, m]
        out0[o, 3] = values[0, r, c]
    else:
        for m in ti.static(range(3)):
            out1[o, m] = local[r, c, m]
        out1[o, 3] = values[1, r, c]


@ti.func
def _greedy(bins: ti.template(), num: ti.template(), cnt: ti.template(), surv: ti.template(), taken: ti.template(),
            k, j, W, start, quota, d2max):  # fmt: skip
    """Step 6 for kind k, part j: the candidates strongest first (a partial heap sort of their bin),
    each taken unless a taken one lies at d^2 <= d2max; their pixels (r << 16 | c) into taken[k, j];
    returns how many."""
    size = surv[k, j]
    for e in range(size // 2):
        _sift(bins, num, cnt, k, W, start, size // 2 - 1 - e, size)
    T = 0
    while (T < quota) & (size > 0):
        top = bins[k, start]
        size -= 1
        bins[k, start] = bins[k, start + size]
        _sift(bins, num, cnt, k, W, start, 0, size)
        r = top // W
        c = top - r * W
        ok = True
        for t in range(T):
            tr = taken[k, j, t] >> 16
            tc = taken[k, j, t] & 0xFFFF
            if (r - tr) * (r - tr) + (c - tc) * (c - tc) <= d2max:
                ok = False
                break
        if ok:
            taken[k, j, T] = (r << 16) | c
            T += 1
    return T


@ti.func
def _pool_range(stats: ti.template(), j):
    every = stats[j, 1] == 0
    b = ti.select(every, 6, 2)
    return every, stats[j, b], stats[j, b + 1], stats[j, b + 2], stats[j, b + 3]


@ti.func
def _centroid_pixel(part: ti.template(), interior: ti.template(), j, every, pr0, pr1, pc0, pc1):
    """The pool pixel nearest the pool's centroid (n r - sum r, n c - sum c; the first among ties)."""
    P = ti.i64(0)
    sr = ti.i64(0)
    sc = ti.i64(0)
    for y in range(pr0, pr1 + 1):
        for x in range(pc0, pc1 + 1):
            if (part[y, x] == j) & (every | (interior[y, x] != 0)):
                P += 1
                sr += y
                sc += x
    best = ti.i64(-1)
    fr = 0
    fc = 0
    for y in range(pr0, pr1 + 1):
        for x in range(pc0, pc1 + 1):
            if (part[y, x] == j) & (every | (interior[y, x] != 0)):
                ey = P * y - sr
                ex = P * x - sc
                v = ey * ey + ex * ex
                if (best < 0) | (v < best):
                    best = v
                    fr = y
                    fc = x
    return fr, fc


@ti.func
def _pool_part(part: ti.template(), stats: ti.template(), interior: ti.template(), y, x):
    """The part whose pool holds pixel (y, x) (its interior pixels, or all its pixels for a part with
    no interior pixel: step 4), else -1."""
    p = part[y, x]
    q = -1
    if p >= 0:  # noqa: SIM102 - the inner test reads stats[p]
        if (stats[p, 1] == 0) | (interior[y, x] != 0):
            q = p
    return q


@ti.func
def _nearest_d2(taken: ti.template(), k, j, y, x, t0, t1, d):
    """min(d, the squared distance from pixel (y, x) to points t0 .. t1 - 1 taken for kind k, part j)."""
    for t in range(t0, t1):
        tr = taken[k, j, t] >> 16
        tc = taken[k, j, t] & 0xFFFF
        d = ti.min(d, (y - tr) * (y - tr) + (x - tc) * (x - tc))
    return d


@ti.func
def _seed_fill(part: ti.template(), interior: ti.template(), used: ti.template(), taken: ti.template(),
               out0: ti.template(), out1: ti.template(), local: ti.template(), values: ti.template(), k, j, H, offset,
               T, m, every, pr0, pr1, pc0, pc1):  # fmt: skip
    """The fill's seeds (step 7): the pool's rows and columns marked unused, then the first fill point
    at the pool's centroid when no extremum was taken, then the rows and columns of the T points
    taken marked used. Returns (T, m) after the centroid point."""
    for y in range(pr0, pr1 + 1):
        used[k, j, y] = 0
    for x in range(pc0, pc1 + 1):
        used[k, j, H + x] = 0
    if T == 0:  # the first: nearest the pool's centroid
        fr, fc = _centroid_pixel(part, interior, j, every, pr0, pr1, pc0, pc1)
        taken[k, j, 0] = (fr << 16) | fc
        _put(out0, out1, k, offset, local, values, fr, fc)
        T = 1
        m -= 1
    for t in range(T):
        used[k, j, taken[k, j, t] >> 16] = 1
        used[k, j, H + (taken[k, j, t] & 0xFFFF)] = 1
    return T, m


#: rows[k, j] of :func:`_emit_serial`: the pool's first entry of each row (H + 1 values), then per row
#: (H values each, at slot * H + 1): a bound of its distances, how many taken points they have seen,
#: whether the bound is the exact best over the unused columns, and that best's column
ROW_BOUND, ROW_SEEN, ROW_EXACT, ROW_BEST = 1, 2, 3, 4
ROW_SLOTS = 5


@ti.kernel
def _emit_serial(part: nd2, values: nd3, local: nd3, plan: nd3, stats: nd2, surv: nd2, bins: nd2, interior: nd2,
                 num: nd3, cnt: nd2, dist: nd3, used: nd3, taken: nd3, rows: nd3, out0: nd2, out1: nd2,
                 d2max: ti.i32):  # fmt: skip
    """Steps 6-7 with one thread per kind k and part j (the CPU arch: no limit on a thread's loops):
    the greedy extrema, then the farthest-point fill over the part's pool, listed (its columns, in
    pixel order; rows[k, j, y] the first of row y) in the part's bin (its candidates are done with),
    the distances at the pixels in dist[k], the points taken in taken[k, j] (r << 16 | c)."""
    J = stats.shape[0]
    H = part.shape[0]
    W = part.shape[1]
    for it in range(2 * J * CPU_TASK):  # a task of Taichi's thread pool per kind and part
        if it % CPU_TASK != 0:
            continue
        g = it // CPU_TASK
        k = 1 - g // J  # the depth template first: its fill (few depth extrema) takes longest
        j = g % J
        offset = plan[k, j, 0]
        quota = plan[k, j, 1]
        start = plan[k, j, 2]
        if quota > 0:
            T = _greedy(bins, num, cnt, surv, taken, k, j, W, start, quota, d2max)
            for t in range(T):
                _put(out0, out1, k, offset + t, local, values, taken[k, j, t] >> 16, taken[k, j, t] & 0xFFFF)
            m = quota - T
            if m > 0:  # 7. the fill
                every, pr0, pr1, pc0, pc1 = _pool_range(stats, j)
                T, m = _seed_fill(part, interior, used, taken, out0, out1, local, values, k, j, H, offset, T, m, every,
                                  pr0, pr1, pc0, pc1)  # fmt: skip
                # the pool into the bin (pixel order); per row its first entry and a bound of its
                # distances to the points taken (to the nearest of them of the row's farther end);
                # the distances themselves wait until the search needs the row (seen: none yet)
                P = 0
                for y in range(pr0, pr1 + 1):
                    rows[k, j, y] = P
                    xa = -1
                    xb = -1
                    for x in range(pc0, pc1 + 1):
                        if (part[y, x] == j) & (every | (interior[y, x] != 0)):
                            bins[k, start + P] = x
                            P += 1
                            dist[k, y, x] = 1 << 30
                            xa = ti.select(xa < 0, x, xa)
                            xb = x
                    bound = 0
                    if xa >= 0:
                        bound = 1 << 30
                        for t in range(T):
                            tr = taken[k, j, t] >> 16
                            tc = taken[k, j, t] & 0xFFFF
                            ex = ti.max((xa - tc) * (xa - tc), (xb - tc) * (xb - tc))
                            bound = ti.min(bound, (y - tr) * (y - tr) + ex)
                    rows[k, j, ROW_BOUND * H + 1 + y] = bound
                    rows[k, j, ROW_SEEN * H + 1 + y] = 0
                    rows[k, j, ROW_EXACT * H + 1 + y] = 0
                rows[k, j, pr1 + 1] = P
                for _ in range(m):
                    p1 = _farthest_new(rows, bins, dist, used, taken, k, j, H, start, pr0, pr1, T)
                    px = p1
                    if p1 < 0:  # none: the farthest with a new row or column, else any
                        b2 = 0
                        b3 = -1
                        p2 = -1
                        p3 = -1
                        for y in range(pr0, pr1 + 1):
                            _row_update(rows, bins, dist, taken, k, j, H, start, y, T)
                            nr = used[k, j, y] == 0
                            for e in range(rows[k, j, y], rows[k, j, y + 1]):
                                x = bins[k, start + e]
                                d = dist[k, y, x]
                                if (nr | (used[k, j, H + x] == 0)) & (d > b2):
                                    b2 = d
                                    p2 = (y << 16) | x
                                if d > b3:
                                    b3 = d
                                    p3 = (y << 16) | x
                        px = ti.select(p2 >= 0, p2, p3)
                    lr = px >> 16
                    lc = px & 0xFFFF
                    used[k, j, lr] = 1
                    used[k, j, H + lc] = 1
                    taken[k, j, T] = px
                    _put(out0, out1, k, offset + T, local, values, lr, lc)
                    T += 1
                    for y in range(pr0, pr1 + 1):  # the rows whose best the new point may change
                        if (rows[k, j, ROW_EXACT * H + 1 + y] != 0) & (
                                (rows[k, j, ROW_BEST * H + 1 + y] == lc)
                                | ((y - lr) * (y - lr) < rows[k, j, ROW_BOUND * H + 1 + y])):  # fmt: skip
                            rows[k, j, ROW_EXACT * H + 1 + y] = 0


@ti.func
def _row_update(rows: ti.template(), bins: ti.template(), dist: ti.template(), taken: ti.template(), k, j, H, start,
                y, T):  # fmt: skip
    """Row y of the pool's distances brought up to the T points taken, and its bound (over all its
    pixels: no longer the exact best of :func:`_farthest_new`)."""
    seen = rows[k, j, ROW_SEEN * H + 1 + y]
    if seen < T:
        rmax = 0
        for e in range(rows[k, j, y], rows[k, j, y + 1]):
            x = bins[k, start + e]
            d = _nearest_d2(taken, k, j, y, x, seen, T, dist[k, y, x])
            dist[k, y, x] = d
            rmax = ti.max(rmax, d)
        rows[k, j, ROW_BOUND * H + 1 + y] = rmax
        rows[k, j, ROW_SEEN * H + 1 + y] = T
        rows[k, j, ROW_EXACT * H + 1 + y] = 0


@ti.func
def _farthest_new(rows: ti.template(), bins: ti.template(), dist: ti.template(), used: ti.template(),
                  taken: ti.template(), k, j, H, start, pr0, pr1, T):  # fmt: skip
    """The pool pixel farthest from the T points taken among those with a new row and a new column
    (d > 0; the first in pixel order among ties) as r << 16 | c, or -1. Best first: the unused row of
    the largest bound (the first among ties) is brought up to date, its bound made its exact best over
    the unused columns (and that pixel kept); once the row of the largest bound is exact, its best is
    the answer (every row before it is bounded below it, every row after it comes later)."""
    p1 = -1
    while True:
        yb = -1
        bb = 0
        for y in range(pr0, pr1 + 1):
            if (used[k, j, y] == 0) & (rows[k, j, ROW_BOUND * H + 1 + y] > bb):
                bb = rows[k, j, ROW_BOUND * H + 1 + y]
                yb = y
        if yb < 0:
            break
        if rows[k, j, ROW_EXACT * H + 1 + yb] != 0:
            p1 = (yb << 16) | rows[k, j, ROW_BEST * H + 1 + yb]
            break
        _row_update(rows, bins, dist, taken, k, j, H, start, yb, T)
        best = 0
        bx = -1
        for e in range(rows[k, j, yb], rows[k, j, yb + 1]):
            x = bins[k, start + e]
            d = dist[k, yb, x]
            if (used[k, j, H + x] == 0) & (d > best):
                best = d
                bx = x
        rows[k, j, ROW_BOUND * H + 1 + yb] = best
        rows[k, j, ROW_BEST * H + 1 + yb] = bx
        rows[k, j, ROW_EXACT * H + 1 + yb] = 1
    return p1


#: the device path's per-(kind, part) state: next output slot, fill points left, last point, best key, best pixel
ST_SLOT, ST_LEFT, ST_LAST, ST_KEY, ST_IDX = range(5)
NO_IDX = 0x7FFFFFFF


@ti.kernel
def _emit_prep(part: nd2, values: nd3, local: nd3, plan: nd3, stats: nd2, surv: nd2, bins: nd2, interior: nd2,
               num: nd3, cnt: nd2, dist: nd3, used: nd3, taken: nd3, state: nd3, out0: nd2, out1: nd2, r0: ti.i32,
               r1: ti.i32, c0: ti.i32, c1: ti.i32, d2max: ti.i32):  # fmt: skip
    """The device path (bounded loops per thread: lavapipe's llvmpipe runs at most 65535 loop passes
    per invocation): per kind and part the greedy extrema and the fill's first point; then per pixel
    the pool's distances to the points taken. The fill's steps follow in :func:`_emit_step`."""
    J = stats.shape[0]
    H = part.shape[0]
    W = part.shape[1]
    for g in range(2 * J):
        k = g // J
        j = g - k * J
        offset = plan[k, j, 0]
        quota = plan[k, j, 1]
        start = plan[k, j, 2]
        state[k, j, ST_LEFT] = 0
        state[k, j, ST_KEY] = -1
        state[k, j, ST_IDX] = NO_IDX
        state[k, j, 5] = 0
        if quota > 0:
            T = _greedy(bins, num, cnt, surv, taken, k, j, W, start, quota, d2max)
            for t in range(T):
                _put(out0, out1, k, offset + t, local, values, taken[k, j, t] >> 16, taken[k, j, t] & 0xFFFF)
            m = quota - T
            if m > 0:
                every, pr0, pr1, pc0, pc1 = _pool_range(stats, j)
                T, m = _seed_fill(part, interior, used, taken, out0, out1, local, values, k, j, H, offset, T, m, every,
                                  pr0, pr1, pc0, pc1)  # fmt: skip
            state[k, j, ST_SLOT] = offset + T
            state[k, j, ST_LEFT] = m
            state[k, j, 5] = T
    w = c1 - c0
    for i in range((r1 - r0) * w):
        y = r0 + i // w
        x = c0 + i % w
        p = _pool_part(part, stats, interior, y, x)
        if p >= 0:
            for k in ti.static(range(2)):
                if state[k, p, ST_LEFT] > 0:
                    d = _nearest_d2(taken, k, p, y, x, 0, state[k, p, 5], 1 << 30)
                    dist[k, y, x] = d


@ti.func
def _fill_key(used: ti.template(), H, k, p, y, x, d):
    """The fill's order as one integer: the tier (2: a new row and a new column, 1: either, 0: neither;
    only with d > 0) above d (< 2**20)."""
    nr = used[k, p, y] == 0
    nc = used[k, p, H + x] == 0
    tier = ti.select(nr & nc, 2, ti.select(nr | nc, 1, 0))
    return ti.select(d > 0, tier, 0) * (1 << 20) + d


@ti.kernel
def _emit_step(part: nd2, values: nd3, local: nd3, stats: nd2, interior: nd2, dist: nd3, used: nd3, state: nd3,
               out0: nd2, out1: nd2, r0: ti.i32, r1: ti.i32, c0: ti.i32, c1: ti.i32, first: ti.i32):  # fmt: skip
    """One fill point of every kind and part with points left: the distances updated with the last
    point, the largest key (atomic max), the first pixel holding it (atomic min), the point."""
    J = stats.shape[0]
    H = part.shape[0]
    W = part.shape[1]
    w = c1 - c0
    n = (r1 - r0) * w
    for i in range(n):
        y = r0 + i // w
        x = c0 + i % w
        p = _pool_part(part, stats, interior, y, x)
        if p >= 0:
            for k in ti.static(range(2)):
                if state[k, p, ST_LEFT] > 0:
                    d = dist[k, y, x]
                    if first == 0:
                        last = state[k, p, ST_LAST]
                        ly = last // W
                        lx = last - ly * W
                        d = ti.min(d, (y - ly) * (y - ly) + (x - lx) * (x - lx))
                        dist[k, y, x] = d
                    key = _fill_key(used, H, k, p, y, x, d)
                    if key > state[k, p, ST_KEY]:  # few atomics: the pool's pixels share one word
                        ti.atomic_max(state[k, p, ST_KEY], key)
    for i in range(n):
        y = r0 + i // w
        x = c0 + i % w
        p = _pool_part(part, stats, interior, y, x)
        if p >= 0:
            for k in ti.static(range(2)):
                if state[k, p, ST_LEFT] > 0:  # noqa: SIM102 - the inner test reads dist where this part has a fill
                    if _fill_key(used, H, k, p, y, x, dist[k, y, x]) == state[k, p, ST_KEY]:
                        ti.atomic_min(state[k, p, ST_IDX], y * W + x)
    ti.loop_config(serialize=True)
    for g in range(2 * J):
        k = g // J
        j = g - k * J
        if state[k, j, ST_LEFT] > 0:
            px = state[k, j, ST_IDX]
            y = px // W
            x = px - y * W
            _put(out0, out1, k, state[k, j, ST_SLOT], local, values, y, x)
            used[k, j, y] = 1
            used[k, j, H + x] = 1
            state[k, j, ST_LAST] = px
            state[k, j, ST_SLOT] += 1
            state[k, j, ST_LEFT] -= 1
            state[k, j, ST_KEY] = -1
            state[k, j, ST_IDX] = NO_IDX


def emit(device, part, values, local, crop, plan, stats, surv, bins, interior, num, cnt, dist, used, s2, out0, out1):
    """Steps 6-7 into out0 (RGB) and out1 (depth): on the CPU arch one kernel (a thread per kind and
    part); elsewhere a kernel for the extrema and the fill's start, then one per fill point."""
    r0, r1, c0, c1 = (int(x) for x in crop)
    d2max = math.ceil(float(s2)) - 1  # d^2 < s2 for an integer d^2
    J = stats.shape[0]
    o0 = out0.buffer if out0.buffer is not None else scratch(device, "mt empty", (1, 4), ti.f32)
    o1 = out1.buffer if out1.buffer is not None else scratch(device, "mt empty", (1, 4), ti.f32)
    nt = max(int(out0.shape[0]), int(out1.shape[0]), 1)
    taken = scratch(device, "mt taken", (2, J, nt), ti.i32)
    common = (part.buffer, values.buffer, local.buffer, plan.buffer, stats.buffer, surv.buffer, bins.buffer,
              interior.buffer, num.buffer, cnt.buffer, dist.buffer, used.buffer, taken)  # fmt: skip
    if device.arch == "cpu":
        rows = scratch(device, "mt rows", (2, J, ROW_SLOTS * part.shape[0] + 1), ti.i32)
        launch(_emit_serial, (*common, rows, o0, o1), scalars=(d2max,), ir_passes=False)
        return
    state = scratch(device, "mt state", (2, J, 6), ti.i32)
    launch(_emit_prep, (*common, state, o0, o1), scalars=(r0, r1, c0, c1, d2max))
    steps = int(state.to_numpy()[:, :, ST_LEFT].max())
    for step in range(steps):
        launch(_emit_step, (part.buffer, values.buffer, local.buffer, stats.buffer, interior.buffer, dist.buffer,
                            used.buffer, state, o0, o1), scalars=(r0, r1, c0, c1, int(step == 0)))  # fmt: skip

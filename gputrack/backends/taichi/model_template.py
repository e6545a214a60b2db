"""Taichi kernels of :mod:`gputrack.ops.model_template`: three launches (the rule: the op's docstring;
the NumPy reference: gputrack/backends/reference/model_template.py).

* :func:`render` (step 1): one thread per pixel of the crop; every part whose box holds the pixel is
  intersected in float32 (the shapes of :func:`gputrack.models.render.intersect`; the
  discriminants in the cross-product form |d|^2 r^2 - |o x d|^2, which keeps float32's accuracy
  for a camera far from the part), the nearest hit wins (strict ``<``: ties to the lower part).
* :func:`classify` (steps 2-5), one kernel of three top-level loops (Taichi's barrier between
  them): the statistics zeroed; one thread per crop pixel: interior flag, q = floor(v s) (integers
  from here on), the window's count, sum, extremes, the extremum strength numerator, the per-part
  counts and ranges by atomics; one thread per crop pixel: the suppression (exact 64-bit
  cross-multiplied strengths, ties by pixel index) and the survivors binned per part by an atomic
  counter (bin order is the atomics' order: only the set matters).
* :func:`emit` (steps 7-9), one kernel of two loops: one thread per survivor ranks it among its
  part's survivors (counting stronger ones, stopping at the part's extrema count), writes it if it
  ranks below that count and stamps the fill mask around it; then one thread per fill point runs
  step 8 (rows t, t + 1, t - 1, ...; the golden in-row rank; a second pass without the mask).

Every comparison after q is integer arithmetic, so the picks equal the reference's on the same
images (Taichi's CPU backend compiles with fast math: no float tie-breaking is relied on; misses
are flags, not infinities).
"""

import math

import numpy as np

from ...uploads import constant
from .launch import launch
from .runtime import scratch, ti

nd1 = ti.types.ndarray(ndim=1)
nd2 = ti.types.ndarray(ndim=2)
nd3 = ti.types.ndarray(ndim=3)
BIG = 3.0e38
NO_ROW = 1 << 30


# -- step 1: render -------------------------------------------------------------------------------
PI_A = 3.140625  # pi = PI_A + PI_B (Cody-Waite: n PI_A is exact for the texture's n)
PI_B = math.pi - 3.140625
SIN_TAYLOR = [(-1) ** m / math.factorial(2 * m + 1) for m in range(1, 6)]  # x^3 .. x^11


@ti.func
def _sin(x):
    """sin(x) in float32 to ~1e-7 (+ |x| eps of the reduction): x - n pi in [-pi/2, pi/2], its
    Taylor polynomial to x^11; ~3x faster than libm's sinf on the CPU arch."""
    n = ti.floor(x * (1.0 / math.pi) + 0.5)
    r = (x - n * PI_A) - n * PI_B
    r2 = r * r
    poly = ti.f32(SIN_TAYLOR[4])
    for m in ti.static(range(3, -1, -1)):
        poly = poly * r2 + ti.f32(SIN_TAYLOR[m])
    y = r + r * r2 * poly
    return ti.select((ti.cast(n, ti.i32) & 1) != 0, -y, y)


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
def _intersect(table: ti.template(), j, o, d):
    """First hit of the ray o + t d (part coordinates) with part j's shape: (hit, t, which) as
    gputrack.models.render.intersect (which: 0 the side or a capsule, 1/2 a cylinder's start/end
    cap). A ray that misses the infinite (elliptic) cylinder misses the shape (the caps lie inside
    it); one that enters it within [start, end] hits there first (t > 0 checked after, as the
    reference's min over the surfaces): only the rest needs the caps."""
    kind = table[j, 16]
    k = ti.cast(table[j, 17], ti.i32)
    s0 = table[j, 18]
    s1 = table[j, 19]
    ia = 1.0 / table[j, 20]
    ib = 1.0 / table[j, 21]
    ok, ou, ov = _axes(k, o)
    dk, du, dv = _axes(k, d)
    # the side, in the coordinates scaled to a unit circle (a capsule: ra = rb = r); the
    # discriminant as a - (o x d)^2 (no cancellation of the large |o|^2 |d|^2 terms in float32)
    ua = ou * ia
    va = ov * ib
    ea = du * ia
    eb = dv * ib
    a = ea * ea + eb * eb
    cr = ua * eb - va * ea
    disc = a - cr * cr
    hit = False
    t = 0.0
    which = 0
    if disc >= 0.0:
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
                    end = s0
                    if ti.static(e == 1):
                        end = s1
                    oc = ti.Vector([o[0], o[1], o[2]])
                    for m in ti.static(range(3)):
                        if k == m:
                            oc[m] = o[m] - end
                    x = oc[1] * d[2] - oc[2] * d[1]
                    y = oc[2] * d[0] - oc[0] * d[2]
                    z = oc[0] * d[1] - oc[1] * d[0]
                    ds = dd * r * r - (x * x + y * y + z * z)
                    if ds >= 0.0:
                        ts = _first_root(dd, d.dot(oc), ds)
                        if (not hit) | (ts < t):
                            hit = True
                            t = ts
            elif dk != 0.0:  # cylinder: the flat caps
                idk = 1.0 / dk
                for e in ti.static(range(2)):
                    end = s0
                    if ti.static(e == 1):
                        end = s1
                    tc = (end - ok) * idk
                    pu = ua + tc * ea
                    pv = va + tc * eb
                    if (pu * pu + pv * pv <= 1.0) & ((not hit) | (tc < t)):
                        hit = True
                        t = tc
                        which = e + 1
    return hit & (t > 0.0), t, which


@ti.func
def _normal(table: ti.template(), j, p, which):
    """The unit outward normal at the hit p of part j's shape (``which`` from :func:`_intersect`)."""
    k = ti.cast(table[j, 17], ti.i32)
    s0 = table[j, 18]
    s1 = table[j, 19]
    ra = table[j, 20]
    rb = table[j, 21]
    n = ti.Vector([0.0, 0.0, 0.0])
    if table[j, 16] == 0.0:  # capsule: from the closest point of the axis segment, / r
        n = ti.Vector([p[0], p[1], p[2]])
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
        n = n / ti.max(n.norm(), 1e-12)
    return n


@ti.kernel
def _render(table: nd2, waves: nd3, part: nd2, values: nd3, local: nd3, r0: ti.i32, c0: ti.i32, w: ti.i32,
            n: ti.i32, fx: ti.f32, fy: ti.f32, cx: ti.f32, cy: ti.f32, amp: ti.f32, shading: ti.f32):  # fmt: skip
    J = table.shape[0]
    for i in range(n):
        r = r0 + i // w
        c = c0 + i % w
        dc = ti.Vector([(ti.cast(c, ti.f32) - cx) / fx, (ti.cast(r, ti.f32) - cy) / fy, 1.0])
        best = -1
        bt = 0.0
        bwhich = 0
        bo = ti.Vector([0.0, 0.0, 0.0])
        bd = ti.Vector([0.0, 0.0, 1.0])
        for j in range(J):
            if (r >= ti.cast(table[j, 12], ti.i32)) & (r < ti.cast(table[j, 13], ti.i32)) & \
                    (c >= ti.cast(table[j, 14], ti.i32)) & (c < ti.cast(table[j, 15], ti.i32)):  # fmt: skip
                d = ti.Vector([0.0, 0.0, 0.0])
                o = ti.Vector([table[j, 9], table[j, 10], table[j, 11]])
                for m in ti.static(range(3)):
                    d[m] = table[j, 3 * m] * dc[0] + table[j, 3 * m + 1] * dc[1] + table[j, 3 * m + 2] * dc[2]
                hit, t, which = _intersect(table, j, o, d)
                if hit & ((best < 0) | (t < bt)):
                    best = j
                    bt = t
                    bwhich = which
                    bo = o
                    bd = d
        gray = 0.0
        x = ti.Vector([0.0, 0.0, 0.0])
        if best >= 0:
            x = bo + bt * bd
            s = 0.0
            for q in range(waves.shape[1]):
                s += _sin(waves[best, q, 0] * x[0] + waves[best, q, 1] * x[1] + waves[best, q, 2] * x[2]
                          + waves[best, q, 3])  # fmt: skip
            tex = ti.min(ti.max(0.5 + amp * s, 0.02), 0.98)
            cosv = ti.abs(bd.dot(_normal(table, best, x, bwhich))) / bd.norm()
            gray = tex * (1.0 - shading + shading * cosv)
        part[r, c] = best
        values[0, r, c] = gray
        values[1, r, c] = bt
        for m in ti.static(range(3)):
            local[r, c, m] = x[m]


def render(device, chain, transforms, texture, table, waves, consts, crop, part, values, local):
    """Step 1 into ``part``, ``values``, ``local`` at the pixels of ``crop``."""
    r0, r1, c0, c1 = (int(x) for x in crop)
    if r1 <= r0 or c1 <= c0:
        return
    table = np.ascontiguousarray(table, np.float32)
    if device.arch == "cpu":
        tab = table  # read in place
    else:
        tab = scratch(device, "mt table", table.shape, ti.f32)
        tab.from_numpy(table)
    wv = constant(device, np.ascontiguousarray(waves, np.float32)).buffer
    fx, fy, cx, cy, amp, shading = (float(x) for x in np.asarray(consts, np.float32))
    w = c1 - c0
    launch(_render, (tab, wv, part.buffer, values.buffer, local.buffer),
           scalars=(r0, c0, w, (r1 - r0) * w, fx, fy, cx, cy, amp, shading))  # fmt: skip


# -- steps 2-5: classify ----------------------------------------------------------------------------
@ti.func
def _part_at(part: ti.template(), r, c, r0, r1, c0, c1):
    """The part of pixel (r, c); -1 outside the crop."""
    p = -1
    if (r >= r0) & (r < r1) & (c >= c0) & (c < c1):
        p = part[r, c]
    return p


@ti.func
def _stronger(num_a, cnt_a, idx_a, num_b, cnt_b, idx_b):
    """a stronger than b: |c q - S| / c larger (cross-multiplied in 64 bits), ties by pixel index."""
    lhs = ti.cast(num_a, ti.i64) * ti.cast(cnt_b, ti.i64)
    rhs = ti.cast(num_b, ti.i64) * ti.cast(cnt_a, ti.i64)
    return (lhs > rhs) | ((lhs == rhs) & (idx_a < idx_b))


@ti.func
def _at(r, c, r0, r1, c0, c1):
    """(in the crop, r and c clamped into the crop): branch-free neighbour reads."""
    inside = (r >= r0) & (r < r1) & (c >= c0) & (c < c1)
    return inside, ti.min(ti.max(r, r0), r1 - 1), ti.min(ti.max(c, c0), c1 - 1)


@ti.kernel
def _classify(part: nd2, values: nd3, cls: nd3, cnt: nd2, bins: nd2, stats: nd2, surv: nd2, r0: ti.i32, r1: ti.i32,
              c0: ti.i32, c1: ti.i32, s0: ti.f32, s1: ti.f32, rad: ti.i32, d2max: ti.i32, half: ti.template(),
              border: ti.template()):  # fmt: skip
    J = stats.shape[0]
    W = part.shape[1]
    w = c1 - c0
    h = r1 - r0
    n = h * w
    ti.loop_config(serialize=True)
    for j in range(J):
        stats[j, 0] = 0
        stats[j, 1] = 0
        for e in ti.static(range(4)):
            stats[j, 2 + 2 * e] = NO_ROW
            stats[j, 3 + 2 * e] = -1
        surv[0, j] = 0
        surv[1, j] = 0
    for i in range(n):  # 3. per pixel: interior flag, window statistics, extremum strength (branch-free)
        r = r0 + i // w
        c = c0 + i % w
        p = part[r, c]
        inner = 0
        count = 0
        num0 = -1
        num1 = -1
        if p >= 0:
            same_all = True
            for dy in ti.static(range(-border, border + 1)):
                for dx in ti.static(range(-border, border + 1)):
                    if ti.static(dy != 0 or dx != 0):
                        inside, y, x = _at(r + dy, c + dx, r0, r1, c0, c1)
                        same_all = same_all & inside & (part[y, x] == p)
            inner = ti.cast(same_all, ti.i32)
            q0 = ti.cast(ti.floor(values[0, r, c] * s0), ti.i32)
            q1 = ti.cast(ti.floor(values[1, r, c] * s1), ti.i32)
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
                        inside, y, x = _at(r + dy, c + dx, r0, r1, c0, c1)
                        same = inside & (part[y, x] == p)
                        a0 = ti.cast(ti.floor(values[0, y, x] * s0), ti.i32)
                        a1 = ti.cast(ti.floor(values[1, y, x] * s1), ti.i32)
                        count += ti.cast(same, ti.i32)
                        S0 += ti.select(same, a0, 0)
                        S1 += ti.select(same, a1, 0)
                        hi0 = ti.select(same, ti.max(hi0, a0), hi0)
                        lo0 = ti.select(same, ti.min(lo0, a0), lo0)
                        hi1 = ti.select(same, ti.max(hi1, a1), hi1)
                        lo1 = ti.select(same, ti.min(lo1, a1), lo1)
            num0 = ti.select((hi0 > lo0) & ((q0 == hi0) | (q0 == lo0)), ti.abs(count * q0 - S0), -1)
            num1 = ti.select((hi1 > lo1) & ((q1 == hi1) | (q1 == lo1)), ti.abs(count * q1 - S1), -1)
        cls[0, r, c] = inner
        cls[1, r, c] = num0
        cls[2, r, c] = num1
        cnt[r, c] = count
    for e in range(J * h):  # 4. per part and row: the counts and ranges (few atomics, no contention per pixel)
        j = e // h
        r = r0 + e - j * h
        na = 0
        ni = 0
        a_lo = c1
        a_hi = -1
        i_lo = c1
        i_hi = -1
        for c in range(c0, c1):
            mine = part[r, c] == j
            inner = mine & (cls[0, r, c] != 0)
            na += ti.cast(mine, ti.i32)
            ni += ti.cast(inner, ti.i32)
            a_lo = ti.select(mine, ti.min(a_lo, c), a_lo)
            a_hi = ti.select(mine, c, a_hi)
            i_lo = ti.select(inner, ti.min(i_lo, c), i_lo)
            i_hi = ti.select(inner, c, i_hi)
        if na > 0:
            ti.atomic_add(stats[j, 0], na)
            ti.atomic_min(stats[j, 6], r)
            ti.atomic_max(stats[j, 7], r)
            ti.atomic_min(stats[j, 8], a_lo)
            ti.atomic_max(stats[j, 9], a_hi)
        if ni > 0:
            ti.atomic_add(stats[j, 1], ni)
            ti.atomic_min(stats[j, 2], r)
            ti.atomic_max(stats[j, 3], r)
            ti.atomic_min(stats[j, 4], i_lo)
            ti.atomic_max(stats[j, 5], i_hi)
    for i in range(n):  # 5. suppression; the survivors binned per part
        r = r0 + i // w
        c = c0 + i % w
        p = part[r, c]
        if p >= 0:
            every = stats[p, 1] == 0  # the pool: every pixel of a part without interior
            if every | (cls[0, r, c] != 0):
                me = r * W + c
                mc = cnt[r, c]
                for k in ti.static(range(2)):
                    num = cls[1 + k, r, c]
                    if num >= 0:
                        alive = True
                        for dy in range(-rad, rad + 1):
                            for dx in range(-rad, rad + 1):
                                d2 = dy * dy + dx * dx
                                if alive & (d2 > 0) & (d2 <= d2max):
                                    y = r + dy
                                    x = c + dx
                                    if _part_at(part, y, x, r0, r1, c0, c1) == p:
                                        if every | (cls[0, y, x] != 0):
                                            nb = cls[1 + k, y, x]
                                            if nb >= 0:
                                                if _stronger(nb, cnt[y, x], y * W + x, num, mc, me):
                                                    alive = False
                        if alive:
                            start = 0
                            for jj in range(p):
                                start += stats[jj, 0]
                            bins[k, start + ti.atomic_add(surv[k, p], 1)] = me


def classify(device, part, values, crop, scales, window, border, rad, s2, cls, cnt, bins, stats, surv):
    """Steps 2-5: stats (J, 10), surv (2, J), bins, cls, cnt (as the reference, bins unordered)."""
    r0, r1, c0, c1 = (int(x) for x in crop)
    sc = np.asarray(scales, np.float32)
    d2max = int(math.ceil(float(s2))) - 1  # d^2 < s2 for an integer d^2
    launch(_classify, (part.buffer, values.buffer, cls.buffer, cnt.buffer, bins.buffer, stats.buffer, surv.buffer),
           (int(window) // 2, int(border)),
           scalars=(r0, r1, c0, c1, float(sc[0]), float(sc[1]), int(rad), d2max))  # fmt: skip


# -- steps 7-9: emit --------------------------------------------------------------------------------
@ti.func
def _write(out: ti.template(), o, local: ti.template(), values: ti.template(), k, r, c):
    for m in ti.static(range(3)):
        out[o, m] = local[r, c, m]
    out[o, 3] = values[k, r, c]


@ti.func
def _pool(part: ti.template(), cls: ti.template(), r, c, j, every):
    return (part[r, c] == j) & (every | (cls[0, r, c] != 0))


@ti.kernel
def _emit(part: nd2, values: nd3, local: nd3, plan: nd3, stats: nd2, surv: nd2, bins: nd2, cls: nd3, cnt: nd2,
          mask: nd3, out0: nd2, out1: nd2, r0: ti.i32, r1: ti.i32, c0: ti.i32, c1: ti.i32, stamp: ti.i32,
          rad: ti.i32, d2max: ti.i32, n0: ti.i32, n1: ti.i32, total: ti.i32, serial: ti.template()):  # fmt: skip
    J = stats.shape[0]
    W = part.shape[1]
    for e in range(2 * total):  # 7. the extrema: each survivor's rank among its part's survivors
        k = e // total
        i = e - k * total
        j = -1
        for jj in range(J):
            if (i >= plan[k, jj, 3]) & (i < plan[k, jj, 3] + surv[k, jj]):
                j = jj
        if j >= 0:
            n_ext = plan[k, j, 1]
            if n_ext > 0:
                start = plan[k, j, 3]
                me = bins[k, i]
                r = me // W
                c = me - r * W
                num = cls[1 + k, r, c]
                mc = cnt[r, c]
                rank = 0
                for b in range(start, start + surv[k, j]):
                    if rank < n_ext:
                        o = bins[k, b]
                        y = o // W
                        x = o - y * W
                        if _stronger(cls[1 + k, y, x], cnt[y, x], o, num, mc, me):
                            rank += 1
                if rank < n_ext:
                    if k == 0:
                        _write(out0, plan[k, j, 0] + rank, local, values, k, r, c)
                    else:
                        _write(out1, plan[k, j, 0] + rank, local, values, k, r, c)
                    for dy in range(-rad, rad + 1):
                        for dx in range(-rad, rad + 1):
                            if dy * dy + dx * dx <= d2max:
                                y = r + dy
                                x = c + dx
                                if (y >= r0) & (y < r1) & (x >= c0) & (x < c1):
                                    if part[y, x] == j:
                                        mask[k, y, x] = stamp
    ti.loop_config(serialize=serial)
    for e in range(n0 + n1):  # 8. the fill points
        k = 0
        s = e
        if e >= n0:
            k = 1
            s = e - n0
        j = -1
        for jj in range(J):
            if (s >= plan[k, jj, 0]) & (s < plan[k, jj, 0] + plan[k, jj, 2]):
                j = jj
        if j >= 0:
            n_ext = plan[k, j, 1]
            i = s - plan[k, j, 0] - n_ext
            if i >= 0:
                m = plan[k, j, 2] - n_ext
                every = stats[j, 1] == 0
                b = ti.select(every, 6, 2)
                pr0 = stats[j, b]
                pr1 = stats[j, b + 1]
                pc0 = stats[j, b + 2]
                pc1 = stats[j, b + 3]
                R = pr1 - pr0 + 1
                t = pr0 + ((2 * i + 1) * R) // (2 * m)
                h = (ti.cast(i, ti.u32) * ti.u32(2654435769) + ti.u32(0x80000000)) >> ti.u32(16)
                hr = ti.cast(h, ti.i32)
                found_r = -1
                found_c = -1
                for strict in range(2):
                    if found_r < 0:
                        for step in range(2 * R + 1):
                            if found_r < 0:
                                row = t + ti.select(step % 2 == 1, (step + 1) // 2, -(step // 2))
                                if (row >= pr0) & (row <= pr1):
                                    count = 0
                                    for x in range(pc0, pc1 + 1):
                                        if _pool(part, cls, row, x, j, every) & ((strict == 1) | (mask[k, row, x] != stamp)):
                                            count += 1
                                    if count > 0:
                                        want = (hr * count) >> 16
                                        seen = 0
                                        for x in range(pc0, pc1 + 1):
                                            if found_r < 0:
                                                if _pool(part, cls, row, x, j, every) & ((strict == 1) | (mask[k, row, x] != stamp)):
                                                    if seen == want:
                                                        found_r = row
                                                        found_c = x
                                                    seen += 1
                if found_r >= 0:
                    if k == 0:
                        _write(out0, s, local, values, k, found_r, found_c)
                    else:
                        _write(out1, s, local, values, k, found_r, found_c)


def emit(device, part, values, local, crop, plan, stats, surv, bins, cls, cnt, mask, stamp, rad, s2, n0, n1,
         total_area, out0, out1):  # fmt: skip
    """Steps 7-9 into out0 (RGB) and out1 (depth)."""
    r0, r1, c0, c1 = (int(x) for x in crop)
    d2max = int(math.ceil(float(s2))) - 1
    o0 = out0.buffer if out0.buffer is not None else scratch(device, "mt empty", (1, 4), ti.f32)
    o1 = out1.buffer if out1.buffer is not None else scratch(device, "mt empty", (1, 4), ti.f32)
    launch(_emit, (part.buffer, values.buffer, local.buffer, plan.buffer, stats.buffer, surv.buffer, bins.buffer,
                   cls.buffer, cnt.buffer, mask.buffer, o0, o1),
           (device.arch == "cpu",),
           scalars=(r0, r1, c0, c1, int(stamp), int(rad), d2max, int(n0), int(n1), int(total_area)))  # fmt: skip

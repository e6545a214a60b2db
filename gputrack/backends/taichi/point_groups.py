"""Taichi kernel of :mod:`gputrack.ops.point_groups`: one launch, four loops.

1. one thread per group: the inverse Cholesky factors of the position and velocity blocks of
   Sigma (symmetrised), their log-determinants, the group's position and a cull radius, into a
   (T, 20) scratch array;
2. one thread per point: the gate (eq. 8) and score (eq. 9-11) of the groups that can gate it,
   the best kept. A group farther than its cull radius, sqrt(gamma trace Sigma_p), cannot (d2 >=
   |d|^2 / trace >= gamma): the groups are sorted by x once (one thread, T is small) and a point
   visits only those within the largest cull radius in x (a binary search, then a strip);
3. one thread: the points of each group listed in point order (counts, starts, a scatter: O(N));
4. one thread per group: two passes over its own points, in point order: their mean (shifted by
   the group's mean), then the covariance about it (no cancellation in float32).

Taichi runs the top-level loops of one kernel one after the other.
"""

import numpy as np

from .launch import launch
from .lm import _finite
from .runtime import ti

nd = ti.types.ndarray()
G = 23
# scratch per group j: [W_p (6), logdet_p, pd_p, W_v (6), logdet_v, pd_v, x, y, z, cull radius^2,
# x of the group of rank j in x order, that group's slot, (row 0) the largest cull radius]
#: a point farther than sqrt(CULL gamma trace(Sigma_p)) from a group is outside its gate (d2 >=
#: |d|^2 / trace): the full test is skipped; the margin keeps rounding from ever changing the answer
CULL = 1.0001


@ti.func
def _factor(S: ti.template(), j, idx: ti.template(), g: ti.template(), base: ti.template()):
    """Inverse Cholesky factor W (lower, 6 entries) of the 3x3 block S[j][idx, idx], log det, pd flag."""
    a00 = S[j, idx[0], idx[0]]
    a10 = 0.5 * (S[j, idx[1], idx[0]] + S[j, idx[0], idx[1]])
    a11 = S[j, idx[1], idx[1]]
    a20 = 0.5 * (S[j, idx[2], idx[0]] + S[j, idx[0], idx[2]])
    a21 = 0.5 * (S[j, idx[2], idx[1]] + S[j, idx[1], idx[2]])
    a22 = S[j, idx[2], idx[2]]
    ok = 0
    w = ti.Vector.zero(ti.f32, 6)
    ld = 0.0
    if a00 > 0:
        l00 = ti.sqrt(a00)
        l10 = a10 / l00
        l20 = a20 / l00
        r11 = a11 - l10 * l10
        if r11 > 0:
            l11 = ti.sqrt(r11)
            l21 = (a21 - l20 * l10) / l11
            r22 = a22 - l20 * l20 - l21 * l21
            if r22 > 0:
                l22 = ti.sqrt(r22)
                w00 = 1.0 / l00
                w11 = 1.0 / l11
                w22 = 1.0 / l22
                w10 = -l10 * w00 / l11
                w21 = -l21 * w11 / l22
                w20 = -(l20 * w00 + l21 * w10) / l22
                w = ti.Vector([w00, w10, w11, w20, w21, w22])
                ld = 2.0 * (ti.log(l00) + ti.log(l11) + ti.log(l22))
                ok = 1
    for k in ti.static(range(6)):
        g[j, base + k] = w[k]
    g[j, base + 6] = ld
    g[j, base + 7] = ti.cast(ok, ti.f32)


@ti.func
def _d2(g: ti.template(), j, base: ti.template(), d0, d1, d2):
    """|W d|^2, W the factor stored at g[j, base:base+6]."""
    e0 = g[j, base] * d0
    e1 = g[j, base + 1] * d0 + g[j, base + 2] * d1
    e2 = g[j, base + 3] * d0 + g[j, base + 4] * d1 + g[j, base + 5] * d2
    return e0 * e0 + e1 * e1 + e2 * e2


@ti.kernel
def _assign(y: nd, lam: nd, xi: nd, S: nd, active: nd, g: nd, idx: nd, labels: nd, counts: nd, mean: nd, cov: nd,
            n: ti.i32, gamma: ti.f32, has_active: ti.template()):  # fmt: skip
    T = xi.shape[0]
    N = labels.shape[0]
    for j in range(T):
        _factor(S, j, ti.static((0, 2, 4)), g, 0)
        _factor(S, j, ti.static((1, 3, 5)), g, 8)
        r2 = ti.static(CULL) * gamma * (S[j, 0, 0] + S[j, 2, 2] + S[j, 4, 4])
        if g[j, 7] < 0.5:
            r2 = -1.0  # not positive definite: gates nothing
        if ti.static(has_active):
            if active[j] == 0:
                r2 = -1.0  # an empty slot
        g[j, 16], g[j, 17], g[j, 18], g[j, 19] = xi[j, 0], xi[j, 2], xi[j, 4], r2
    ti.loop_config(serialize=True)
    for _ in range(1):  # the groups in x order (insertion sort: T is small) and the largest cull radius
        rmax = 0.0
        for j in range(T):
            key = g[j, 16]
            k = j
            while k > 0 and g[k - 1, 20] > key:
                g[k, 20], g[k, 21] = g[k - 1, 20], g[k - 1, 21]
                k -= 1
            g[k, 20], g[k, 21] = key, ti.cast(j, ti.f32)
            if g[j, 19] > 0:
                rmax = ti.max(rmax, ti.sqrt(g[j, 19]))
        g[0, 22] = rmax
    for i in range(labels.shape[0]):
        best = -1
        if i < n:
            p0, p1, p2 = y[i, 0], y[i, 1], y[i, 2]
            v0, v1, v2 = lam[i, 0], lam[i, 1], lam[i, 2]
            fin = _finite(p0, ti.f32) & _finite(p1, ti.f32) & _finite(p2, ti.f32)
            fin &= _finite(v0, ti.f32) & _finite(v1, ti.f32) & _finite(v2, ti.f32)
            if fin:
                top = 0.0
                lo, hi = 0, T  # the first rank with x >= p0 - rmax: only the strip |x - p0| <= rmax can gate
                while lo < hi:
                    mid = (lo + hi) // 2
                    if g[mid, 20] < p0 - g[0, 22]:
                        lo = mid + 1
                    else:
                        hi = mid
                r = lo
                while r < T and g[r, 20] <= p0 + g[0, 22]:
                    j = ti.cast(g[r, 21], ti.i32)
                    r += 1
                    e0, e1, e2 = p0 - g[j, 16], p1 - g[j, 17], p2 - g[j, 18]
                    if e0 * e0 + e1 * e1 + e2 * e2 < g[j, 19]:  # else d2 >= |d|^2 / trace >= gamma (or no gate)
                        d2p = _d2(g, j, 0, e0, e1, e2)  # eq. 8
                        if d2p < gamma:
                            s = -(d2p + g[j, 6])  # eq. 9 (log)
                            if g[j, 15] > 0.5:
                                s -= _d2(g, j, 8, v0 - xi[j, 1], v1 - xi[j, 3], v2 - xi[j, 5]) + g[j, 14]  # eq. 10
                            if best < 0 or s > top or (s == top and j < best):  # eq. 11; ties to the lowest slot
                                top = s
                                best = j
        labels[i] = best
    ti.loop_config(serialize=True)
    for _ in range(1):  # the points of each group, in point order: counts, starts, then a scatter
        for j in range(T):
            idx[N + j] = 0
        for i in range(n):
            if labels[i] >= 0:
                idx[N + labels[i]] += 1
        c = 0
        for j in range(T):
            k = idx[N + j]
            idx[N + T + j] = c  # the group's first position in idx[:N]
            idx[N + j] = c  # its cursor
            c += k
        for i in range(n):
            if labels[i] >= 0:
                idx[idx[N + labels[i]]] = i
                idx[N + labels[i]] += 1
    for j in range(T):
        a, b = idx[N + T + j], idx[N + j]  # the group's points: idx[a:b]
        c = b - a
        s1 = ti.Vector.zero(ti.f32, 6)
        for k in range(a, b):
            i = idx[k]
            s1 += ti.Vector([y[i, 0] - xi[j, 0], lam[i, 0] - xi[j, 1], y[i, 1] - xi[j, 2],
                             lam[i, 1] - xi[j, 3], y[i, 2] - xi[j, 4], lam[i, 2] - xi[j, 5]])  # fmt: skip
        counts[j] = c
        m = ti.Vector.zero(ti.f32, 6)
        if c > 0:
            m = s1 / c
        mu = ti.Vector([xi[j, 0] + m[0], xi[j, 1] + m[1], xi[j, 2] + m[2], xi[j, 3] + m[3], xi[j, 4] + m[4],
                        xi[j, 5] + m[5]])  # fmt: skip
        s2 = ti.Matrix.zero(ti.f32, 6, 6)
        for k in range(a, b):  # second pass about the mean: no cancellation in float32
            i = idx[k]
            d = ti.Vector([y[i, 0] - mu[0], lam[i, 0] - mu[1], y[i, 1] - mu[2],
                           lam[i, 1] - mu[3], y[i, 2] - mu[4], lam[i, 2] - mu[5]])  # fmt: skip
            s2 += d.outer_product(d)
        for u in ti.static(range(6)):
            mean[j, u] = mu[u]
            for w in ti.static(range(6)):
                v = 0.0
                if c > 0:
                    v = s2[u, w] / c  # eq. 7: cov(C_y)
                cov[j, u, w] = v

def assign_points(device, points, velocities, means, spreads, active, gamma, N, out):
    labels, counts, mean, cov = out
    T = means.shape[0]
    g = device.empty((T, G), np.float32)
    idx = device.empty((labels.shape[0] + 2 * T,), np.int32)
    act = active.buffer if active is not None else counts.buffer
    arrays = (points.buffer, velocities.buffer, means.buffer, spreads.buffer, act, g.buffer, idx.buffer, labels.buffer,
              counts.buffer, mean.buffer, cov.buffer)  # fmt: skip
    launch(_assign, arrays, (active is not None,), scalars=(int(N), float(gamma)))
    return out

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

import math

import numpy as np

from .launch import launch
from .lm import _finite
from .runtime import current_arch, scratch, ti

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
    _factor_values(a00, a10, a11, a20, a21, a22, g, j, base)


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


# -- group_frame: a whole frame of the group table (gputrack/ops/point_groups.py) -----------------
#
# One launch, six loops: (1) one thread: every slot predicted (eq. 2-3) and its gate factors from
# Sigma + diag(min_spread^2); (2) one thread: the gating groups listed in K buckets along x (a
# group in every bucket its cull interval [x - r, x + r], with a margin, touches: a point visits
# only the groups of its own bucket; K <= 16384 / T keeps the passes of this loop bounded);
# (3) one thread per point: surface offset, gate and score (as _assign); (4) one thread: each
# group's points in point order; (5) one thread per group: moments, eq. 7, the stereo EKF update
# (eq. 4-6, Joseph form, as ekf_update_stereo); (6) one thread per group: the merge pre-test.
# On taichi:cpu, up to SERIAL_POINTS points, (5) and (6) run on one thread too: only the gate's
# loop wakes the thread pool.

GC = 32  # scratch per slot: _assign's 23, then the merge centre (6) and radii (2)
PD_EPS = 4.0 * float(np.finfo(np.float32).eps)  # the Kalman ops' pivot test (PD_EPS_FACTOR eps)
SUM_BUCKET_LIMIT = 16384  # buckets x slots
#: taichi:cpu runs loops 5 and 6 on one thread up to this many points: waking the pool's threads
#: for a loop (~0.1 ms after the host's work between frames) costs more than those loops save
SERIAL_POINTS = 16384


@ti.func
def _point(pts: ti.template(), i, off, nan):
    """Point i moved ``off`` mm further along its viewing ray (NaN where it has no ray)."""
    p = ti.Vector([pts[i, 0], pts[i, 1], pts[i, 2]])
    if off > 0:
        r = ti.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
        s = nan
        if r > 0:
            s = 1.0 + off / r
        p = p * s
    return p


@ti.func
def _bound3(tab: ti.template(), j, base: ti.template(), idx: ti.template(), fl):
    """An upper bound of the largest eigenvalue of the 3x3 block idx of tab[j, base:base+36] +
    fl I: min(trace, largest absolute row sum)."""
    tr = 0.0
    rows = 0.0
    for a in ti.static(range(3)):
        s = 0.0
        for k in ti.static(range(3)):
            v = tab[j, base + idx[a] * 6 + idx[k]]
            if ti.static(a == k):
                v += fl
                tr += v
            s += ti.abs(v)
        rows = ti.max(rows, s)
    return ti.min(tr, rows)


@ti.kernel
def _frame(tab: nd, pts: nd, vel: nd, c: nd, g: nd, idx: nd, labels: nd, n: ti.i32, K: ti.i32, nan: ti.f32,
           serial_groups: ti.template()):  # fmt: skip
    T = tab.shape[0]
    N = labels.shape[0]
    gamma, fp, fv, off = c[79], c[82], c[83], c[84]
    # 1. predict every slot (x = F x, P = sym(F sym(P) F^T + sym(Q))), the gate factors
    ti.loop_config(serialize=True)
    for j in range(T):
        F = ti.Matrix.zero(ti.f32, 6, 6)
        Q = ti.Matrix.zero(ti.f32, 6, 6)
        Pm = ti.Matrix.zero(ti.f32, 6, 6)
        xv = ti.Vector.zero(ti.f32, 6)
        for a in ti.static(range(6)):
            xv[a] = tab[j, a]
            for k in ti.static(range(6)):
                F[a, k] = c[a * 6 + k]
                Q[a, k] = c[36 + a * 6 + k]
                Pm[a, k] = tab[j, 6 + a * 6 + k]
        Pm = 0.5 * (Pm + Pm.transpose())
        Q = 0.5 * (Q + Q.transpose())
        xv = F @ xv
        Pm = F @ Pm @ F.transpose() + Q
        Pm = 0.5 * (Pm + Pm.transpose())
        for a in ti.static(range(6)):
            tab[j, a] = xv[a]
            for k in ti.static(range(6)):
                tab[j, 6 + a * 6 + k] = Pm[a, k]
        _factor_fl(tab, j, ti.static((0, 2, 4)), fp, g, 0)
        _factor_fl(tab, j, ti.static((1, 3, 5)), fv, g, 8)
        r2 = ti.static(CULL) * gamma * (tab[j, 42] + tab[j, 42 + 14] + tab[j, 42 + 28] + 3.0 * fp)
        if g[j, 7] < 0.5 or tab[j, 78] < 0.5:
            r2 = -1.0  # not positive definite, or a free slot: gates nothing
        g[j, 16], g[j, 17], g[j, 18], g[j, 19] = xv[0], xv[2], xv[4], r2
    # 2. the gating groups in K buckets along x: idx[N + 2T + k] the start of bucket k's list
    #    (K + 1 entries), the lists after them
    ti.loop_config(serialize=True)
    for _ in range(1):
        lo, hi = 3.4e38, -3.4e38
        for j in range(T):
            if g[j, 19] > 0:
                r = 1.001 * ti.sqrt(g[j, 19]) + 1e-4 * ti.abs(g[j, 16])
                lo, hi = ti.min(lo, g[j, 16] - r), ti.max(hi, g[j, 16] + r)
        w = (hi - lo) / K
        if not (w > 0):
            w = 1.0
        g[0, 20], g[0, 21] = lo, w  # the buckets' origin and width
        base = N + 2 * T
        for k in range(K + 1):
            idx[base + k] = 0
        for j in range(T):
            if g[j, 19] > 0:
                r = 1.001 * ti.sqrt(g[j, 19]) + 1e-4 * ti.abs(g[j, 16])
                k0 = ti.max(0, ti.min(K - 1, ti.cast(ti.floor((g[j, 16] - r - lo) / w), ti.i32)))
                k1 = ti.max(0, ti.min(K - 1, ti.cast(ti.floor((g[j, 16] + r - lo) / w), ti.i32)))
                for k in range(k0, k1 + 1):
                    idx[base + k + 1] += 1
        for k in range(K):
            idx[base + k + 1] += idx[base + k]
        for k in range(K):
            idx[base + K + 1 + k] = idx[base + k]  # cursors
        for j in range(T):  # in slot order: each bucket's list ascends
            if g[j, 19] > 0:
                r = 1.001 * ti.sqrt(g[j, 19]) + 1e-4 * ti.abs(g[j, 16])
                k0 = ti.max(0, ti.min(K - 1, ti.cast(ti.floor((g[j, 16] - r - lo) / w), ti.i32)))
                k1 = ti.max(0, ti.min(K - 1, ti.cast(ti.floor((g[j, 16] + r - lo) / w), ti.i32)))
                for k in range(k0, k1 + 1):
                    idx[base + 2 * K + 1 + idx[base + K + 1 + k]] = j
                    idx[base + K + 1 + k] += 1
    # 3. one thread per point: the gate (eq. 8) and score (eq. 9-11) of its bucket's groups
    for i in range(N):
        best = -1
        if i < n:
            p = _point(pts, i, off, nan)
            v0, v1, v2 = vel[i, 0], vel[i, 1], vel[i, 2]
            fin = _finite(p[0], ti.f32) & _finite(p[1], ti.f32) & _finite(p[2], ti.f32)
            fin &= _finite(v0, ti.f32) & _finite(v1, ti.f32) & _finite(v2, ti.f32)
            kf = (p[0] - g[0, 20]) / g[0, 21]
            if fin and kf >= 0 and kf < K:
                base = N + 2 * T
                k = ti.cast(kf, ti.i32)
                top = 0.0
                for q in range(idx[base + k], idx[base + k + 1]):
                    j = idx[base + 2 * K + 1 + q]
                    e0, e1, e2 = p[0] - g[j, 16], p[1] - g[j, 17], p[2] - g[j, 18]
                    if e0 * e0 + e1 * e1 + e2 * e2 < g[j, 19]:
                        d2p = _d2(g, j, 0, e0, e1, e2)  # eq. 8
                        if d2p < gamma:
                            s = -(d2p + g[j, 6])  # eq. 9 (log)
                            if g[j, 15] > 0.5:
                                s -= _d2(g, j, 8, v0 - tab[j, 1], v1 - tab[j, 3], v2 - tab[j, 5]) + g[j, 14]  # eq. 10
                            if best < 0 or s > top or (s == top and j < best):  # eq. 11; ties to the lowest slot
                                top = s
                                best = j
        labels[i] = best
    # 4. the points of each group, in point order
    ti.loop_config(serialize=True)
    for _ in range(1):
        for j in range(T):
            idx[N + j] = 0
        for i in range(n):
            if labels[i] >= 0:
                idx[N + labels[i]] += 1
        s = 0
        for j in range(T):
            k = idx[N + j]
            idx[N + T + j] = s
            idx[N + j] = s
            s += k
        for i in range(n):
            if labels[i] >= 0:
                idx[idx[N + labels[i]]] = i
                idx[N + labels[i]] += 1
    # 5. one thread per group: moments, eq. 7, the stereo EKF update
    if ti.static(serial_groups):
        ti.loop_config(serialize=True)
    for j in range(T):
        a, b = idx[N + T + j], idx[N + j]
        cnt = b - a
        xi = ti.Vector([tab[j, 0], tab[j, 1], tab[j, 2], tab[j, 3], tab[j, 4], tab[j, 5]])
        s1 = ti.Vector.zero(ti.f32, 6)
        for k in range(a, b):
            i = idx[k]
            p = _point(pts, i, off, nan)
            s1 += ti.Vector([p[0] - xi[0], vel[i, 0] - xi[1], p[1] - xi[2], vel[i, 1] - xi[3], p[2] - xi[4],
                             vel[i, 2] - xi[5]])  # fmt: skip
        m = ti.Vector.zero(ti.f32, 6)
        if cnt > 0:
            m = s1 / cnt
        mu = xi + m
        s2 = ti.Matrix.zero(ti.f32, 6, 6)
        for k in range(a, b):
            i = idx[k]
            p = _point(pts, i, off, nan)
            d = ti.Vector([p[0] - mu[0], vel[i, 0] - mu[1], p[1] - mu[2], vel[i, 1] - mu[3], p[2] - mu[4],
                           vel[i, 2] - mu[5]])  # fmt: skip
            s2 += d.outer_product(d)
        seen = tab[j, 78] > 0.5 and cnt >= ti.cast(c[81], ti.i32) and mu[4] > 0
        S = ti.Matrix.zero(ti.f32, 6, 6)
        for u in ti.static(range(6)):
            for w in ti.static(range(6)):
                S[u, w] = tab[j, 42 + u * 6 + w]
        if seen:  # eq. 7
            S = c[80] * S + (1.0 - c[80]) * (s2 / cnt)
        S = 0.5 * (S + S.transpose())
        xo = xi
        if seen:
            xo, Po, ok = _ekf_stereo(tab, j, xi, mu, c)
            if ok:
                for u in ti.static(range(6)):
                    for w in ti.static(range(6)):
                        tab[j, 6 + u * 6 + w] = Po[u, w]
            else:
                xo = xi
        for u in ti.static(range(6)):
            tab[j, u] = xo[u]
            tab[j, 80 + u] = mu[u]
            for w in ti.static(range(6)):
                tab[j, 42 + u * 6 + w] = S[u, w]
        tab[j, 79] = ti.cast(cnt, ti.f32)
        tab[j, 86] = ti.cast(seen, ti.f32)
        # the merge regions' centre (velocity: the points' mean where there are enough) and radii
        vc = ti.Vector([xo[1], xo[3], xo[5]])
        if cnt >= ti.cast(c[81], ti.i32):
            vc = ti.Vector([mu[1], mu[3], mu[5]])
        g[j, 23], g[j, 24], g[j, 25], g[j, 26], g[j, 27], g[j, 28] = xo[0], xo[2], xo[4], vc[0], vc[1], vc[2]
        g[j, 29] = ti.sqrt(c[85] * _bound3(tab, j, 42, ti.static((0, 2, 4)), fp))
        g[j, 30] = ti.sqrt(c[85] * _bound3(tab, j, 42, ti.static((1, 3, 5)), fv))
    # 6. one thread per group: the merge pre-test against the groups after it
    if ti.static(serial_groups):
        ti.loop_config(serialize=True)
    for i in range(T):
        nc = 0
        for k in ti.static(range(4)):
            tab[i, 88 + k] = -1.0
        if tab[i, 78] > 0.5:
            for j in range(i + 1, T):
                if tab[j, 78] > 0.5:
                    dp = ti.Vector([g[i, 23] - g[j, 23], g[i, 24] - g[j, 24], g[i, 25] - g[j, 25]]).norm()
                    dv = ti.Vector([g[i, 26] - g[j, 26], g[i, 27] - g[j, 27], g[i, 28] - g[j, 28]]).norm()
                    if dp <= g[i, 29] + g[j, 29] and dv <= g[i, 30] + g[j, 30]:
                        if nc < 4:
                            tab[i, 88 + nc] = ti.cast(j, ti.f32)
                        nc += 1
        tab[i, 87] = ti.cast(nc, ti.f32)


@ti.func
def _factor_fl(tab: ti.template(), j, idx: ti.template(), fl, g: ti.template(), base: ti.template()):
    """_factor of the block idx of the spread at tab[j, 42:78] plus fl I."""
    a00 = tab[j, 42 + idx[0] * 7] + fl
    a10 = 0.5 * (tab[j, 42 + idx[1] * 6 + idx[0]] + tab[j, 42 + idx[0] * 6 + idx[1]])
    a11 = tab[j, 42 + idx[1] * 7] + fl
    a20 = 0.5 * (tab[j, 42 + idx[2] * 6 + idx[0]] + tab[j, 42 + idx[0] * 6 + idx[2]])
    a21 = 0.5 * (tab[j, 42 + idx[2] * 6 + idx[1]] + tab[j, 42 + idx[1] * 6 + idx[2]])
    a22 = tab[j, 42 + idx[2] * 7] + fl
    _factor_values(a00, a10, a11, a20, a21, a22, g, j, base)


@ti.func
def _factor_values(a00, a10, a11, a20, a21, a22, g: ti.template(), j, base: ti.template()):
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
def _ekf_stereo(tab: ti.template(), j, xv, mu, c: ti.template()):
    """The stereo EKF update of slot j (predicted state xv, covariance in tab) from the points'
    mean mu as z = [u v d] (eq. 4-6): Joseph form, as ekf_update_stereo; ok = 0 where the state is
    behind the camera or the innovation covariance is not positive definite."""
    f, b, cx, cy = c[75], c[76], c[77], c[78]
    z = ti.Vector([f * mu[0] / mu[4] + cx, f * mu[2] / mu[4] + cy, f * b / mu[4]])  # eq. 6
    Pm = ti.Matrix.zero(ti.f32, 6, 6)
    for u in ti.static(range(6)):
        for w in ti.static(range(6)):
            Pm[u, w] = tab[j, 6 + u * 6 + w]
    Pm = 0.5 * (Pm + Pm.transpose())
    X, Y, Z = xv[0], xv[2], xv[4]
    ok = Z > 0
    Zs = Z
    if not ok:
        Zs = 1.0
    h = ti.Vector([f * X / Zs + cx, f * Y / Zs + cy, f * b / Zs])
    H = ti.Matrix.zero(ti.f32, 3, 6)
    H[0, 0] = f / Zs
    H[0, 4] = -f * X / (Zs * Zs)
    H[1, 2] = f / Zs
    H[1, 4] = -f * Y / (Zs * Zs)
    H[2, 4] = -f * b / (Zs * Zs)
    Rm = ti.Matrix([[c[72], 0.0, 0.0], [0.0, c[73], 0.0], [0.0, 0.0, c[74]]])
    HP = H @ Pm
    S = HP @ H.transpose() + Rm
    L = ti.Matrix.zero(ti.f32, 3, 3)
    for a in ti.static(range(3)):
        d = S[a, a]
        for k in ti.static(range(a)):
            d -= L[a, k] * L[a, k]
        good = d > ti.static(PD_EPS) * S[a, a]
        if not good:
            ok = False
            d = 1.0
        L[a, a] = ti.sqrt(d)
        for r in ti.static(range(a + 1, 3)):
            v = S[r, a]
            for k in ti.static(range(a)):
                v -= L[r, k] * L[a, k]
            L[r, a] = v / L[a, a]
    Wm = ti.Matrix.zero(ti.f32, 3, 6)  # L W = HP
    for a in ti.static(range(3)):
        for col in ti.static(range(6)):
            v = HP[a, col]
            for k in ti.static(range(a)):
                v -= L[a, k] * Wm[k, col]
            Wm[a, col] = v / L[a, a]
    Kt = ti.Matrix.zero(ti.f32, 3, 6)  # L^T Kt = W
    for a in ti.static((2, 1, 0)):
        for col in ti.static(range(6)):
            v = Wm[a, col]
            for k in ti.static(range(a + 1, 3)):
                v -= L[k, a] * Kt[k, col]
            Kt[a, col] = v / L[a, a]
    K = Kt.transpose()
    x1 = xv + K @ (z - h)
    B = Pm - K @ HP
    P1 = B - (B @ H.transpose()) @ K.transpose() + K @ Rm @ K.transpose()
    return x1, 0.5 * (P1 + P1.transpose()), ok


def _buckets(T: int) -> int:
    return max(1, min(2 * T, SUM_BUCKET_LIMIT // T))


def group_frame(device, table, points, velocities, constants, n, labels):
    from .runtime import loop_limit

    T = table.shape[0]
    N = labels.shape[0]
    K = _buckets(T)
    limit = loop_limit(device)
    if limit is not None and max(2 * n + 2 * T, 4 * T + 3 * K + 2 * T * K) > limit:
        raise ValueError(f"points: at most {(limit - 2 * T) // 2} points and a few thousand groups a frame on "
                         f"{device.spec} (its shader invocations run at most {limit} loop passes), got {n} points "
                         f"and {T} slots")  # fmt: skip
    g = scratch(device, "group_frame g", (T, GC), ti.f32)
    idx = scratch(device, "group_frame idx", (N + 2 * T + 2 * K + 1 + T * K,), ti.i32)
    serial = current_arch() == "cpu" and n <= SERIAL_POINTS
    launch(_frame, (table.buffer, points.buffer, velocities.buffer, constants.buffer, g, idx, labels.buffer), (serial,),
           scalars=(int(n), int(K), math.nan))
    return table, labels

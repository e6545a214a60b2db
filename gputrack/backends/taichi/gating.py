"""Taichi kernel of :mod:`gputrack.ops.gating`: one thread per track.

Each thread builds its track's S = H Ps H^T + Rs and Cholesky factor (as the NumPy reference,
gputrack/backends/reference/kalman.py: symmetrised P and R, pivot test d_j > 4 eps S_jj), then
scans the detections, all of them or, with ``sorted_z``, the strip |z_0 - (H x)_0| <=
sqrt(threshold S_00) found by a binary search, and appends each d2 < threshold to its own row of
the outputs (so the order is the detection order, as in the reference). The small matrices
(n <= 12, m <= 6) are unrolled at compile time; one variant is compiled per (dtype, n, m,
active, sorted_z).
"""

import dataclasses

import numpy as np

from .launch import launch
from .runtime import ti

nd = ti.types.ndarray()
PD_EPS_FACTOR = 4.0
#: the sweep strip is widened by this relative margin (and by one tiny absolute one) so that a
#: pair at the gate's edge is never skipped by rounding; the d2 test decides
STRIP_SLACK = 1e-3

#: a scan of at most this many (track, detection) pairs, and any sorted sweep (a few detections
#: per track), runs on the calling thread: a parallel loop's dispatch costs ~60 us on a CPU and
#: far more on a busy one
SERIAL_PAIRS = 1 << 15

_REAL = {"float32": ti.f32, "float64": ti.f64}


@dataclasses.dataclass(frozen=True)
class _Variant:
    real: str
    n: int
    m: int
    active: bool
    sorted_z: bool
    serial: bool  # one thread runs the loop over tracks (small work: no thread-pool dispatch)


@ti.kernel
def _gate(x: nd, P: nd, H: nd, R: nd, z: nd, active: nd, cnt: nd, det: nd, d2: nd, tr: nd,
          D: ti.i32, thr_in: ti.f64, v: ti.template()):  # fmt: skip
    real = _REAL[v.real]
    n = ti.static(v.n)
    m = ti.static(v.m)
    tol = ti.static(float(np.finfo(v.real).eps) * PD_EPS_FACTOR)
    K = det.shape[1]
    thr = ti.cast(thr_in, real)
    ti.loop_config(serialize=v.serial)
    for t in range(x.shape[0]):
        Ps = ti.Matrix.zero(real, n, n)
        for i in ti.static(range(n)):
            for j in ti.static(range(n)):
                Ps[i, j] = 0.5 * (P[t, i, j] + P[t, j, i])
        hx = ti.Vector.zero(real, m)
        HP = ti.Matrix.zero(real, m, n)
        for a in ti.static(range(m)):
            for k in ti.static(range(n)):
                hx[a] += H[a, k] * x[t, k]
                for j in ti.static(range(n)):
                    HP[a, j] += H[a, k] * Ps[k, j]
        S = ti.Matrix.zero(real, m, m)
        trace = ti.cast(0.0, real)
        for a in ti.static(range(m)):
            for c in ti.static(range(m)):
                acc = ti.cast(0.0, real)
                for k in ti.static(range(n)):
                    acc += HP[a, k] * H[c, k]
                if ti.static(a == c):
                    trace += acc  # trace(H P H^T)
                S[a, c] = acc + 0.5 * (R[a, c] + R[c, a])
        L = ti.Matrix.zero(real, m, m)  # S = L L^T
        inv = ti.Vector.zero(real, m)
        ok = 1
        for j in ti.static(range(m)):
            dj = S[j, j]
            for k in ti.static(range(j)):
                dj -= L[j, k] * L[j, k]
            good = dj > tol * S[j, j]
            if not good:
                ok = 0
                dj = 1.0
            L[j, j] = ti.sqrt(dj)
            inv[j] = 1.0 / L[j, j]
            for i in ti.static(range(j + 1, m)):
                s = S[i, j]
                for k in ti.static(range(j)):
                    s -= L[i, k] * L[j, k]
                L[i, j] = s * inv[j]
        if ti.static(v.active):
            if active[t] == 0:
                ok = 0
        c = 0
        if ok != 0:
            lo = 0
            top = ti.cast(0.0, real)
            if ti.static(v.sorted_z):  # the strip |z_0 - (H x)_0| <= sqrt(thr S_00)
                w = ti.sqrt(thr * S[0, 0]) * (1.0 + STRIP_SLACK) + 1e-30
                bottom = hx[0] - w
                top = hx[0] + w
                hi = D
                while lo < hi:  # first detection with z_0 >= bottom
                    mid = (lo + hi) // 2
                    if z[mid, 0] < bottom:
                        lo = mid + 1
                    else:
                        hi = mid
            d = lo
            while d < D:
                if ti.static(v.sorted_z):
                    if z[d, 0] > top:
                        break
                wv = ti.Vector.zero(real, m)  # L^-1 (z_d - H x)
                acc = ti.cast(0.0, real)
                for i in ti.static(range(m)):
                    s = z[d, i] - hx[i]
                    for k in ti.static(range(i)):
                        s -= L[i, k] * wv[k]
                    wv[i] = s * inv[i]
                    acc += wv[i] * wv[i]
                if acc < thr:  # eq. 8 gate
                    if c < K:
                        det[t, c] = d
                        d2[t, c] = acc
                    c += 1
                d += 1
        cnt[t] = c
        tr[t] = trace


def gate_pairs(device, x, P, H, R, z, D, threshold, active, sorted_z, out):
    count, det, d2, trace = out
    serial = sorted_z or x.shape[0] * max(int(D), 1) <= SERIAL_PAIRS
    v = _Variant(x.dtype.name, x.shape[1], H.shape[0], active is not None, sorted_z, serial)
    act = active.buffer if active is not None else count.buffer
    arrays = (x.buffer, P.buffer, H.buffer, R.buffer, z.buffer, act, count.buffer, det.buffer, d2.buffer, trace.buffer)
    launch(_gate, arrays, (v,), scalars=(int(D), float(threshold)))
    return out

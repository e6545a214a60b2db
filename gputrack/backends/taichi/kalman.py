"""Taichi kernels of the batched Kalman filter ops: one thread per track, one launch per call.

The small matrix algebra (n <= 12, m <= 6) is unrolled at compile time (n, m are template
arguments), so each (n, m, dtype, shared/per-track layout, options) combination compiles once.
Shared matrices are (n,n) ndarrays and per-track ones (T,n,n); the kernel reads either through
:func:`_get`, chosen at compile time from the ndarray's dimension. The known zero entries of a
shared F, Q, H and R (bitmask template arguments ``fpat`` .. ``rpat``, -1 = dense) are left out
at compile time: the constant-velocity F and Q, a selection H and a diagonal R are mostly zeros,
which removes about half of the work. Run-time branches on zero entries were tried and were
slower (they keep LLVM from optimising the unrolled code).
The numerics follow gputrack/backends/reference/kalman.py step for step (see its docstring).
Arguments an op does not use are passed as ``x`` (never read). Note: a whole local matrix
re-assigned inside an ``if ti.static(...)`` block did not reach the code after the block in
Taichi 1.7.4; results computed in such blocks are copied element by element.
"""

import numpy as np

from .runtime import ti

UPDATED, SKIPPED, NOT_PD, BAD_DEPTH = 0, 1, 2, 3
PD_EPS_FACTOR = 4.0
MODE_PREDICT, MODE_LINEAR, MODE_STEREO = 0, 1, 2

nd = ti.types.ndarray()


@ti.func
def _get(A: ti.template(), t, i: ti.template(), j: ti.template()):
    """A[i, j] of a shared (r,c) matrix or A[t, i, j] of a per-track (T,r,c) one."""
    if ti.static(len(A.shape) == 3):
        return A[t, i, j]
    else:
        return A[i, j]


@ti.func
def _nonfinite(v, real: ti.template()):
    """True for NaN or +-inf, from the bits (robust under fast math)."""
    r = False
    if ti.static(real == ti.f64):
        r = (ti.bit_cast(v, ti.u64) & ti.u64(0x7FF0000000000000)) == ti.u64(0x7FF0000000000000)
    else:
        r = (ti.bit_cast(v, ti.u32) & ti.u32(0x7F800000)) == ti.u32(0x7F800000)
    return r


def _nz(pat, n, i, k):
    """Whether entry (i, k) of a matrix with n columns may be non-zero (pat: bitmask, -1 = dense)."""
    return (pat >> (i * n + k)) & 1 == 1


STEREO_PATTERN = sum(1 << (i * 6 + k) for i, k in ((0, 0), (0, 4), (1, 2), (1, 4), (2, 4)))


def _make(real, eps):
    """Kernels for one float type (scalar arguments need a fixed annotation)."""

    @ti.func
    def load_sym(A: ti.template(), t, r: ti.template(), pat: ti.template()):
        """(A + A^T)/2 of the (r,r) matrix A (shared or per track); known zeros are not read."""
        S = ti.Matrix.zero(real, r, r)
        for i in ti.static(range(r)):
            if ti.static(_nz(pat, r, i, i)):
                S[i, i] = _get(A, t, i, i)
            for j in ti.static(range(i + 1, r)):
                if ti.static(_nz(pat, r, i, j) or _nz(pat, r, j, i)):
                    v = ti.cast(0, real)
                    if ti.static(_nz(pat, r, i, j)):
                        v += _get(A, t, i, j)
                    if ti.static(_nz(pat, r, j, i)):
                        v += _get(A, t, j, i)
                    S[i, j] = 0.5 * v
                    S[j, i] = 0.5 * v
        return S

    @ti.func
    def predict_x(F: ti.template(), t, xv, n: ti.template(), fpat: ti.template()):
        xn = ti.Vector.zero(real, n)
        for i in ti.static(range(n)):
            s = ti.cast(0, real)
            for k in ti.static(range(n)):
                if ti.static(_nz(fpat, n, i, k)):
                    s += _get(F, t, i, k) * xv[k]
            xn[i] = s
        return xn

    @ti.func
    def predict_P(
        F: ti.template(), Q: ti.template(), t, Ps, n: ti.template(), fpat: ti.template(), qpat: ti.template()
    ):
        """F Ps F^T + (Q + Q^T)/2 for symmetric Ps, known zeros of F skipped; exactly symmetric."""
        FP = ti.Matrix.zero(real, n, n)
        for i in ti.static(range(n)):
            for k in ti.static(range(n)):
                if ti.static(_nz(fpat, n, i, k)):
                    a = _get(F, t, i, k)
                    for j in ti.static(range(n)):
                        FP[i, j] += a * Ps[k, j]
        Qs = load_sym(Q, t, n, qpat)
        Pn = ti.Matrix.zero(real, n, n)
        for j in ti.static(range(n)):
            for k in ti.static(range(n)):
                if ti.static(_nz(fpat, n, j, k)):
                    a = _get(F, t, j, k)
                    for i in ti.static(range(j + 1)):
                        Pn[i, j] += FP[i, k] * a
        for i in ti.static(range(n)):
            for j in ti.static(range(i, n)):
                v = Pn[i, j] + Qs[i, j]
                Pn[i, j] = v
                Pn[j, i] = v
        return Pn

    @ti.func
    def update(xv, Ps, y, Hm, Rs, s, n: ti.template(), m: ti.template(), hpat: ti.template()):
        """Joseph-form update with innovation y; returns (x+, P+, ok) packed as a tuple matrix."""
        # H P (m,n), zero entries of H skipped
        HP = ti.Matrix.zero(real, m, n)
        for a in ti.static(range(m)):
            for k in ti.static(range(n)):
                if ti.static(_nz(hpat, n, a, k)):
                    for j in ti.static(range(n)):
                        HP[a, j] += Hm[a, k] * Ps[k, j]
        # S = H P H^T + R (lower triangle)
        S = ti.Matrix.zero(real, m, m)
        for c in ti.static(range(m)):
            for k in ti.static(range(n)):
                if ti.static(_nz(hpat, n, c, k)):
                    for a in ti.static(range(c, m)):
                        S[a, c] += HP[a, k] * Hm[c, k]
        for a in ti.static(range(m)):
            for c in ti.static(range(a + 1)):
                S[a, c] += Rs[a, c]
        # Cholesky S = L L^T with the positive-definiteness test of the reference
        L = ti.Matrix.zero(real, m, m)
        inv = ti.Vector.zero(real, m)
        ok = 1
        for j in ti.static(range(m)):
            d = S[j, j]
            for k in ti.static(range(j)):
                d -= L[j, k] * L[j, k]
            if not (d > PD_EPS_FACTOR * eps * S[j, j]):
                ok = 0
                d = ti.cast(1, real)
            d = ti.sqrt(d)
            L[j, j] = d
            inv[j] = 1.0 / d
            for i in ti.static(range(j + 1, m)):
                v = S[i, j]
                for k in ti.static(range(j)):
                    v -= L[i, k] * L[j, k]
                L[i, j] = v * inv[j]
        # K^T = S^-1 (H P): forward then backward substitution, column by column
        Kt = HP
        for c in ti.static(range(n)):
            for i in ti.static(range(m)):
                v = Kt[i, c]
                for k in ti.static(range(i)):
                    v -= L[i, k] * Kt[k, c]
                Kt[i, c] = v * inv[i]
            for ii in ti.static(range(m)):
                i = ti.static(m - 1 - ii)
                v = Kt[i, c]
                for k in ti.static(range(i + 1, m)):
                    v -= L[k, i] * Kt[k, c]
                Kt[i, c] = v * inv[i]
        K = s * Kt.transpose()  # (n,m), scaled gain (paper 002 eq. 4-6)
        xn = xv + K @ y
        # Joseph form: B = (I - K H) P = P - K (H P); P+ = B - (B H^T) K^T + K R K^T
        B = Ps - K @ HP
        C = K @ Rs  # (n,m)
        for i in ti.static(range(n)):
            for a in ti.static(range(m)):
                for k in ti.static(range(n)):
                    if ti.static(_nz(hpat, n, a, k)):
                        C[i, a] -= B[i, k] * Hm[a, k]
        Pn = ti.Matrix.zero(real, n, n)
        for i in ti.static(range(n)):
            for j in ti.static(range(i, n)):
                v = B[i, j]
                for a in ti.static(range(m)):
                    v += C[i, a] * K[j, a]
                Pn[i, j] = v
                Pn[j, i] = v
        return xn, Pn, ok

    @ti.kernel
    def kf(
        x: nd,
        P: nd,
        z: nd,
        F: nd,
        Q: nd,
        H: nd,
        R: nd,
        mask: nd,
        gain: nd,
        xo: nd,
        Po: nd,
        st: nd,
        f: real,
        b: real,
        cx: real,
        cy: real,
        n: ti.template(),
        m: ti.template(),
        mode: ti.template(),
        do_predict: ti.template(),
        has_mask: ti.template(),
        has_gain: ti.template(),
        fpat: ti.template(),
        qpat: ti.template(),
        hpat: ti.template(),
        rpat: ti.template(),
    ):
        for t in range(x.shape[0]):
            xv = ti.Vector.zero(real, n)
            Pm = ti.Matrix.zero(real, n, n)
            for i in ti.static(range(n)):
                xv[i] = x[t, i]
                for j in ti.static(range(n)):
                    Pm[i, j] = P[t, i, j]
            if ti.static(do_predict):
                xp = predict_x(F, t, xv, n, fpat)
                for i in ti.static(range(n)):
                    xv[i] = xp[i]
                Pp = predict_P(F, Q, t, 0.5 * (Pm + Pm.transpose()), n, fpat, qpat)
                for i in ti.static(range(n)):
                    for j in ti.static(range(n)):
                        Pm[i, j] = Pp[i, j]
            if ti.static(mode != MODE_PREDICT):
                xn = xv
                Pn = Pm
                code = UPDATED
                if ti.static(has_mask):  # noqa: SIM102 - a compile-time branch around a run-time one
                    if mask[t] == 0:
                        code = SKIPPED
                zv = ti.Vector.zero(real, m)
                for a in ti.static(range(m)):
                    zv[a] = z[t, a]
                    if _nonfinite(zv[a], real):
                        code = SKIPPED
                if ti.static(mode == MODE_STEREO):  # noqa: SIM102 - compile-time around run-time
                    if code == UPDATED and not (xv[4] > 0):
                        code = BAD_DEPTH
                if code == UPDATED:
                    s = ti.cast(1, real)
                    if ti.static(has_gain):
                        s = gain[t]
                    Ps = Pm  # exactly symmetric after a prediction
                    if ti.static(not do_predict):
                        for i in ti.static(range(n)):
                            for j in ti.static(range(i + 1, n)):
                                v = 0.5 * (Pm[i, j] + Pm[j, i])
                                Ps[i, j] = v
                                Ps[j, i] = v
                    Rs = load_sym(R, t, m, rpat)
                    Hm = ti.Matrix.zero(real, m, n)
                    y = ti.Vector.zero(real, m)
                    if ti.static(mode == MODE_STEREO):
                        iz = 1.0 / xv[4]  # eq. 6 and its Jacobian at the predicted state
                        Hm[0, 0] = f * iz
                        Hm[0, 4] = -f * xv[0] * iz * iz
                        Hm[1, 2] = f * iz
                        Hm[1, 4] = -f * xv[2] * iz * iz
                        Hm[2, 4] = -f * b * iz * iz
                        y[0] = zv[0] - (f * xv[0] * iz + cx)
                        y[1] = zv[1] - (f * xv[2] * iz + cy)
                        y[2] = zv[2] - f * b * iz
                    else:
                        for a in ti.static(range(m)):
                            v = zv[a]
                            for k in ti.static(range(n)):
                                if ti.static(_nz(hpat, n, a, k)):
                                    h = _get(H, t, a, k)
                                    Hm[a, k] = h
                                    v -= h * xv[k]
                            y[a] = v
                    xu, Pu, ok = update(xv, Ps, y, Hm, Rs, s, n, m, hpat)
                    if ok:
                        xn = xu
                        Pn = Pu
                    else:
                        code = NOT_PD
                for i in ti.static(range(n)):
                    xo[t, i] = xn[i]
                    for j in ti.static(range(n)):
                        Po[t, i, j] = Pn[i, j]
                st[t] = ti.cast(code, ti.u8)
            if ti.static(mode == MODE_PREDICT):
                for i in ti.static(range(n)):
                    xo[t, i] = xv[i]
                    for j in ti.static(range(n)):
                        Po[t, i, j] = Pm[i, j]

    @ti.kernel
    def gate(
        x: nd,
        P: nd,
        H: nd,
        R: nd,
        z: nd,
        out: nd,
        n: ti.template(),
        m: ti.template(),
        hpat: ti.template(),
        rpat: ti.template(),
    ):
        for t in range(x.shape[0]):
            Ps = ti.Matrix.zero(real, n, n)
            for i in ti.static(range(n)):
                for j in ti.static(range(n)):
                    Ps[i, j] = 0.5 * (P[t, i, j] + P[t, j, i])
            Rs = load_sym(R, t, m, rpat)
            Hm = ti.Matrix.zero(real, m, n)
            hx = ti.Vector.zero(real, m)
            for a in ti.static(range(m)):
                v = ti.cast(0, real)
                for k in ti.static(range(n)):
                    if ti.static(_nz(hpat, n, a, k)):
                        h = _get(H, t, a, k)
                        Hm[a, k] = h
                        v += h * x[t, k]
                hx[a] = v
            HP = ti.Matrix.zero(real, m, n)
            for a in ti.static(range(m)):
                for k in ti.static(range(n)):
                    if ti.static(_nz(hpat, n, a, k)):
                        for j in ti.static(range(n)):
                            HP[a, j] += Hm[a, k] * Ps[k, j]
            S = ti.Matrix.zero(real, m, m)
            for c in ti.static(range(m)):
                for k in ti.static(range(n)):
                    if ti.static(_nz(hpat, n, c, k)):
                        for a in ti.static(range(c, m)):
                            S[a, c] += HP[a, k] * Hm[c, k]
            L = ti.Matrix.zero(real, m, m)
            inv = ti.Vector.zero(real, m)
            ok = 1
            for j in ti.static(range(m)):
                d = S[j, j] + Rs[j, j]
                for k in ti.static(range(j)):
                    d -= L[j, k] * L[j, k]
                if not (d > PD_EPS_FACTOR * eps * (S[j, j] + Rs[j, j])):
                    ok = 0
                    d = ti.cast(1, real)
                d = ti.sqrt(d)
                L[j, j] = d
                inv[j] = 1.0 / d
                for i in ti.static(range(j + 1, m)):
                    v = S[i, j] + Rs[i, j]
                    for k in ti.static(range(j)):
                        v -= L[i, k] * L[j, k]
                    L[i, j] = v * inv[j]
            for d_ in range(z.shape[0]):
                w = ti.Vector.zero(real, m)
                acc = ti.cast(0, real)
                for i in ti.static(range(m)):
                    v = z[d_, i] - hx[i]
                    for k in ti.static(range(i)):
                        v -= L[i, k] * w[k]
                    w[i] = v * inv[i]
                    acc += w[i] * w[i]
                if ok == 0:
                    acc = ti.math.inf
                out[t, d_] = acc

    return kf, gate


_KERNELS = {
    "float32": _make(ti.f32, float(np.finfo(np.float32).eps)),
    "float64": _make(ti.f64, float(np.finfo(np.float64).eps)),
}


def _run(device, x, P, z, F, Q, H, R, mask, gain_scale, mode, out, pats, cam=(0.0, 0.0, 0.0, 0.0)):
    T, n = x.shape
    m = z.shape[1] if z is not None else 1
    dt = x.dtype
    if out is None:
        out = (device.empty((T, n), dt), device.empty((T, n, n), dt))
        if mode != MODE_PREDICT:
            out += (device.empty((T,), np.uint8),)
    xo, Po = out[0], out[1]
    st = out[2] if mode != MODE_PREDICT else None
    d = x.buffer
    kf, _ = _KERNELS[dt.name]

    def buf(a):
        return a.buffer if a is not None else d

    fpat, qpat, hpat, rpat = pats
    kf(
        d,
        P.buffer,
        buf(z),
        buf(F),
        buf(Q),
        buf(H),
        buf(R),
        buf(mask),
        buf(gain_scale),
        xo.buffer,
        Po.buffer,
        buf(st),
        *cam,
        n,
        m,
        mode,
        F is not None,
        mask is not None,
        gain_scale is not None,
        fpat if F is not None else -1,
        qpat if F is not None else -1,
        hpat if mode == MODE_LINEAR else (STEREO_PATTERN if mode == MODE_STEREO else -1),
        rpat if mode != MODE_PREDICT else -1,
    )
    return (xo, Po) if mode == MODE_PREDICT else (xo, Po, st)


def kf_predict(device, x, P, F, Q, out=None, pats=(-1, -1, -1, -1)):
    return _run(device, x, P, None, F, Q, None, None, None, None, MODE_PREDICT, out, pats)


def kf_update(device, x, P, z, H, R, mask=None, gain_scale=None, predict=None, out=None, pats=(-1, -1, -1, -1)):
    F, Q = predict if predict is not None else (None, None)
    return _run(device, x, P, z, F, Q, H, R, mask, gain_scale, MODE_LINEAR, out, pats)


def ekf_update_stereo(
    device, x, P, z, R, f, b, cx=0.0, cy=0.0, mask=None, gain_scale=None, predict=None, out=None, pats=(-1, -1, -1, -1)
):
    F, Q = predict if predict is not None else (None, None)
    return _run(device, x, P, z, F, Q, None, R, mask, gain_scale, MODE_STEREO, out, pats, (f, b, cx, cy))


def mahalanobis(device, x, P, H, R, z, out=None, pats=(-1, -1, -1, -1)):
    T, n = x.shape
    out = out if out is not None else device.empty((T, z.shape[0]), x.dtype)
    _, gate = _KERNELS[x.dtype.name]
    gate(x.buffer, P.buffer, H.buffer, R.buffer, z.buffer, out.buffer, n, z.shape[1], pats[2], pats[3])
    return out

"""Taichi kernels of the batched Kalman filter ops: one launch per call, L tracks per thread.

The per-track math (n <= 12, m <= 6) is traced at compile time by the plain Python functions of
:class:`_Tracer`: every matrix is a Python list of Taichi values, every loop over its entries
is unrolled, and the known zero entries of a shared F, Q, H and R (bitmask ``pats``, -1 =
dense; the constant-velocity F and Q, a selection H and a diagonal R are mostly zeros) are left
out of the traced code. The code has no branches: every track computes its update and a
per-track select keeps the input where the status is not UPDATED (run-time branches were
tried and were slower: they keep LLVM from optimising the unrolled code).

Lanes. On taichi:cpu a value is a ``ti.types.vector(L, real)`` holding L tracks (L = 8 for
float32, 4 for float64) and the kernels are compiled with ``real_matrix_scalarize`` off, so
that LLVM emits SIMD instructions across the L tracks (each lane's loads and stores stay
per track in the (T,n,n) layout). The last group of a batch repeats track T-1 in its spare
lanes; every lane loads its inputs before any lane stores, and the repeated lanes store the
same values. On the GPU archs (vulkan, cuda) L = 1: one scalar track per thread.

The numerics follow gputrack/backends/reference/kalman.py step for step (see its docstring).
Launch cost on taichi:cpu is about 30 us plus about 8 us per ndarray argument, so the common
call of a tracker (in place, no mask, no gain_scale) has a kernel with 8 ndarray arguments
instead of 12, the compile-time options travel as one hashable :class:`_Variant`, kernels are
launched directly after their first call (gputrack/backends/taichi/launch.py, compiled with
``scalarize=False``), and batches of up to SERIAL_MAX tracks run on the calling thread.
"""

import dataclasses

import numpy as np

from ...abi import KalmanStatus
from .launch import launch
from .runtime import ti

# status codes (gputrack/abi.py), folded into the kernels at compile time
UPDATED, SKIPPED, NOT_PD, BAD_DEPTH = (int(s) for s in (KalmanStatus.UPDATED, KalmanStatus.SKIPPED,
                                                         KalmanStatus.NOT_PD, KalmanStatus.BAD_DEPTH))
PD_EPS_FACTOR = 4.0
MODE_PREDICT, MODE_LINEAR, MODE_STEREO = 0, 1, 2
#: batches of at most this many tracks run on the calling thread (a thread-pool wake-up costs
#: more than the work: ~10-30 us on a busy 2-core CPU)
SERIAL_MAX = 1024

nd = ti.types.ndarray()
_impl = ti.lang.impl

STEREO_PATTERN = sum(1 << (i * 6 + k) for i, k in ((0, 0), (0, 4), (1, 2), (1, 4), (2, 4)))


@dataclasses.dataclass(frozen=True)
class _Variant:
    """Compile-time options of one kernel variant (one template argument, hashed by value)."""

    real: str  # "float32" or "float64"
    lanes: int
    n: int
    m: int
    mode: int
    predict: bool = False
    mask: bool = False
    gain: bool = False
    pats: tuple = (-1, -1, -1, -1)  # F, Q, H, R zero patterns (-1 = dense)
    serial: bool = False  # one thread runs the whole loop (small batches: no thread-pool wake-up)


def _nz(pat, cols, i, k):
    """Whether entry (i, k) of a matrix with ``cols`` columns may be non-zero (pat -1 = dense)."""
    return (pat >> (i * cols + k)) & 1 == 1


def _sum(terms):
    """Sum of a list of traced values; None for an empty list (a structural zero)."""
    acc = None
    for t in terms:
        acc = t if acc is None else acc + t
    return acc


class _Tracer:
    """Traces the per-track algebra of one kernel variant for a group of L tracks.

    Values are Taichi scalars (L = 1) or L-lane vectors; ``None`` stands for a known zero.
    Called from the kernels inside ``ti.static(...)`` (plain Python run at compile time).
    """

    def __init__(self, v: _Variant, g, T):
        self.v = v
        self.real = ti.f64 if v.real == "float64" else ti.f32
        self.eps = float(np.finfo(v.real).eps)
        self.L = v.lanes
        if self.L == 1:
            self.ts = [g]
        else:
            self.ts = [self.init(ti.min(g * self.L + lane, T - 1)) for lane in range(self.L)]

    # -- values ------------------------------------------------------------------------------
    @staticmethod
    def init(e):
        """A new local variable holding e (so that it is computed once)."""
        return _impl.expr_init(e)

    def lanes(self, per_track, dtype=None):
        """One value from per_track(t) of each lane's track t."""
        dtype = dtype or self.real
        if self.L == 1:
            return self.init(ti.cast(per_track(self.ts[0]), dtype))
        return self.init(ti.types.vector(self.L, dtype)([per_track(t) for t in self.ts]))

    def splat(self, c, dtype=None):
        dtype = dtype or self.real
        if self.L == 1:
            return self.init(ti.cast(c, dtype))
        return self.init(ti.types.vector(self.L, dtype)([c] * self.L))

    def lane(self, val, k):
        return val if self.L == 1 else _impl.subscript(None, val, k)

    def sel(self, cond, a, b):
        """Per lane a where cond else b (Python numbers are splat to the type of the other)."""
        if isinstance(a, (int, float)):
            a = self.splat(a, ti.i32 if isinstance(a, int) else None)
        if isinstance(b, (int, float)):
            b = self.splat(b, ti.i32 if isinstance(b, int) else None)
        return self.init(ti.select(cond, a, b))

    def zero(self, v, like):
        """v, or a zero of like's shape where v is None (a structural zero)."""
        return v if v is not None else self.init(0.0 * like)

    @staticmethod
    def at(A, *idx):
        return _impl.subscript(None, A, *idx)

    def mat(self, A, i, j, pat, cols):
        """Entry (i, j) of a shared (r,c) or per-track (T,r,c) matrix; None for a known zero."""
        if len(A.shape) == 3:
            return self.lanes(lambda t: self.at(A, t, i, j))
        if not _nz(pat, cols, i, j):
            return None
        return self.init(self.at(A, i, j))

    def nonfinite(self, A, i):
        """Per lane: A[t, i] is NaN or +-inf (all exponent bits set; robust under fast math)."""
        itype, shift, ones = (ti.u64, 52, 0x7FF) if self.real == ti.f64 else (ti.u32, 23, 0xFF)
        return self.lanes(lambda t: ((ti.bit_cast(self.at(A, t, i), itype) >> shift) & ones) == ones, ti.i32)

    # -- loads and stores --------------------------------------------------------------------
    def load_state(self, x, P):
        n = self.v.n
        xv = [self.lanes(lambda t, i=i: self.at(x, t, i)) for i in range(n)]
        Pm = [[self.lanes(lambda t, i=i, j=j: self.at(P, t, i, j)) for j in range(n)] for i in range(n)]
        return xv, Pm

    def store(self, xo, Po, st, xv, Pm, code):
        n = self.v.n
        for k, t in enumerate(self.ts):
            for i in range(n):
                self.at(xo, t, i)._assign(self.lane(xv[i], k))
                for j in range(n):
                    self.at(Po, t, i, j)._assign(self.lane(Pm[i][j], k))
            if code is not None:
                self.at(st, t)._assign(ti.cast(self.lane(code, k), ti.u8))

    def sym(self, A, r, pat=-1, get=None):
        """(A + A^T)/2 of an (r,r) matrix given as a list (get None) or read by get(i, j)."""
        get = get or (lambda i, j: A[i][j])
        S = [[None] * r for _ in range(r)]
        for i in range(r):
            S[i][i] = get(i, i) if _nz(pat, r, i, i) else None
            for j in range(i + 1, r):
                a = get(i, j) if _nz(pat, r, i, j) else None
                b = get(j, i) if _nz(pat, r, j, i) else None
                v = _sum([e for e in (a, b) if e is not None])
                S[i][j] = S[j][i] = None if v is None else self.init(0.5 * v)
        return S

    def shared_sym(self, A, r, pat):
        """(A + A^T)/2 of a shared or per-track (r,r) matrix, known zeros as None."""
        if len(A.shape) == 3:
            pat = -1
        return self.sym(None, r, pat, lambda i, j: self.mat(A, i, j, -1, r))

    # -- eq. 2-3: prediction -----------------------------------------------------------------
    def predict(self, F, Q, xv, Ps):
        """x' = F x, P' = F Ps F^T + (Q + Q^T)/2 for a symmetric Ps; P' exactly symmetric."""
        n, fpat = self.v.n, self.v.pats[0]
        Fm = [[self.mat(F, i, k, fpat, n) for k in range(n)] for i in range(n)]
        xp = [self.init(self.zero(_sum([Fm[i][k] * xv[k] for k in range(n) if Fm[i][k] is not None]), xv[i]))
              for i in range(n)]  # fmt: skip
        FP = [[_sum([Fm[i][k] * Ps[k][j] for k in range(n) if Fm[i][k] is not None]) for j in range(n)]
              for i in range(n)]  # fmt: skip
        FP = [[None if e is None else self.init(e) for e in row] for row in FP]
        Qs = self.shared_sym(Q, n, self.v.pats[1])
        Pn = [[None] * n for _ in range(n)]
        for i in range(n):
            for j in range(i, n):
                terms = [FP[i][k] * Fm[j][k] for k in range(n) if Fm[j][k] is not None and FP[i][k] is not None]
                if Qs[i][j] is not None:
                    terms.append(Qs[i][j])
                Pn[i][j] = Pn[j][i] = self.init(self.zero(_sum(terms), xv[0]))
        return xp, Pn

    # -- S = H P H^T + R and its Cholesky factor ---------------------------------------------
    def innovation(self, Ps, Hm, Rs):
        """H Ps (m,n), the lower triangle of S = H Ps H^T + R, and S's Cholesky factor.

        Returns (HP, Lf, inv, ok): Lf lower triangular, inv[j] = 1 / Lf[j][j], ok per lane 1
        where S is positive definite (pivot d_j > PD_EPS_FACTOR eps S_jj)."""
        n, m = self.v.n, len(Hm)
        zero = self.init(0.0 * Ps[0][0])
        HP = [[self.init(self.zero(_sum([Hm[a][k] * Ps[k][j] for k in range(n) if Hm[a][k] is not None]), zero))
               for j in range(n)] for a in range(m)]  # fmt: skip
        S = [[None] * m for _ in range(m)]
        for a in range(m):
            for c in range(a + 1):
                terms = [HP[a][k] * Hm[c][k] for k in range(n) if Hm[c][k] is not None]
                if Rs[a][c] is not None:
                    terms.append(Rs[a][c])
                S[a][c] = self.init(self.zero(_sum(terms), zero))
        Lf = [[None] * m for _ in range(m)]
        inv = [None] * m
        ok = None
        tol = PD_EPS_FACTOR * self.eps
        for j in range(m):
            d = self.init(S[j][j] - _sum([Lf[j][k] * Lf[j][k] for k in range(j)]) if j else S[j][j])
            good = self.init(d > tol * S[j][j])
            ok = good if ok is None else self.init(ok & good)
            Lf[j][j] = self.init(ti.sqrt(self.sel(good, d, 1.0)))
            inv[j] = self.init(1.0 / Lf[j][j])
            for i in range(j + 1, m):
                v = S[i][j] - _sum([Lf[i][k] * Lf[j][k] for k in range(j)]) if j else S[i][j]
                Lf[i][j] = self.init(v * inv[j])
        return HP, Lf, inv, ok

    def forward(self, Lf, inv, b):
        """Solve Lf w = b (m-vector)."""
        w = []
        for i in range(len(b)):
            v = b[i] - _sum([Lf[i][k] * w[k] for k in range(i)]) if i else b[i]
            w.append(self.init(v * inv[i]))
        return w

    def backward(self, Lf, inv, w):
        """Solve Lf^T u = w (m-vector)."""
        m = len(w)
        u = [None] * m
        for i in reversed(range(m)):
            v = w[i] - _sum([Lf[k][i] * u[k] for k in range(i + 1, m)]) if i < m - 1 else w[i]
            u[i] = self.init(v * inv[i])
        return u

    # -- Joseph-form update ------------------------------------------------------------------
    def update(self, xv, Ps, y, Hm, Rs, s):
        """x+ = x + K y, P+ = (I - K H) Ps (I - K H)^T + K R K^T with K = s P H^T S^-1.

        Returns (x+, P+, ok). As in the reference: B = Ps - K (H Ps), C = K R - B H^T,
        P+ = B + C K^T (upper triangle, mirrored)."""
        n, m = self.v.n, len(y)
        HP, Lf, inv, ok = self.innovation(Ps, Hm, Rs)
        Kt = [[None] * n for _ in range(m)]  # K^T = S^-1 (H P), column by column
        for c in range(n):
            col = self.backward(Lf, inv, self.forward(Lf, inv, [HP[a][c] for a in range(m)]))
            for a in range(m):
                Kt[a][c] = col[a]
        K = [[self.init(Kt[a][i] * s) if s is not None else Kt[a][i] for a in range(m)] for i in range(n)]
        xn = [self.init(xv[i] + _sum([K[i][a] * y[a] for a in range(m)])) for i in range(n)]
        B = [[self.init(Ps[i][j] - _sum([K[i][a] * HP[a][j] for a in range(m)])) for j in range(n)] for i in range(n)]
        C = [[None] * m for _ in range(n)]
        for i in range(n):
            for a in range(m):
                kr = _sum([K[i][b] * Rs[b][a] for b in range(m) if Rs[b][a] is not None])
                bh = _sum([B[i][k] * Hm[a][k] for k in range(n) if Hm[a][k] is not None])
                C[i][a] = self.init(self.zero(kr, xv[0]) - self.zero(bh, xv[0]))
        Pn = [[None] * n for _ in range(n)]
        for i in range(n):
            for j in range(i, n):
                Pn[i][j] = Pn[j][i] = self.init(B[i][j] + _sum([C[i][a] * K[j][a] for a in range(m)]))
        return xn, Pn, ok

    # -- whole kernels -----------------------------------------------------------------------
    def filter(self, x, P, z, F, Q, H, R, mask, gain, xo, Po, st, cam):
        """kf_predict / kf_update / ekf_update_stereo of this group of tracks."""
        v = self.v
        n, m = v.n, v.m
        xv, Pm = self.load_state(x, P)
        if v.predict:
            xv, Pm = self.predict(F, Q, xv, self.sym(Pm, n))
            Ps = Pm  # exactly symmetric after a prediction
        elif v.mode != MODE_PREDICT:
            Ps = self.sym(Pm, n)
        if v.mode == MODE_PREDICT:
            self.store(xo, Po, st, xv, Pm, None)
            return
        zv = [self.lanes(lambda t, a=a: self.at(z, t, a)) for a in range(m)]
        bad = [self.nonfinite(z, a) for a in range(m)]
        if v.mask:
            bad.append(self.lanes(lambda t: self.at(mask, t) == 0, ti.i32))
        code = self.sel(_sum(bad) > 0, SKIPPED, UPDATED)
        s = self.lanes(lambda t: self.at(gain, t)) if v.gain else None
        Rs = self.shared_sym(R, m, v.pats[3])
        if v.mode == MODE_STEREO:  # eq. 6 and its Jacobian at the predicted state
            f, b, cx, cy = (self.init(ti.cast(c, self.real)) for c in cam)
            good_z = self.init(xv[4] > 0)
            code = self.sel(good_z == 0, self.sel(code == UPDATED, BAD_DEPTH, code), code)
            iz = self.init(1.0 / self.sel(good_z, xv[4], 1.0))
            fz = self.init(f * iz)
            nfz = self.init((-f) * iz * iz)  # (no unary minus on lane vectors: it does not compile)
            Hm = [[None] * 6 for _ in range(3)]
            Hm[0][0] = Hm[1][2] = fz
            Hm[0][4] = self.init(nfz * xv[0])
            Hm[1][4] = self.init(nfz * xv[2])
            Hm[2][4] = self.init(nfz * b)
            y = [self.init(zv[0] - (fz * xv[0] + cx)), self.init(zv[1] - (fz * xv[2] + cy)),
                 self.init(zv[2] - fz * b)]  # fmt: skip
        else:
            Hm = [[self.mat(H, a, k, v.pats[2], n) for k in range(n)] for a in range(m)]
            y = [self.init(zv[a] - self.zero(_sum([Hm[a][k] * xv[k] for k in range(n) if Hm[a][k] is not None]), xv[0]))
                 for a in range(m)]  # fmt: skip
        xn, Pn, ok = self.update(xv, Ps, y, Hm, Rs, s)
        code = self.sel(code == UPDATED, self.sel(ok, code, NOT_PD), code)
        upd = self.init(code == UPDATED)
        xs = [self.sel(upd, xn[i], xv[i]) for i in range(n)]
        Pn = [[self.sel(upd, Pn[i][j], Pm[i][j]) for j in range(n)] for i in range(n)]
        self.store(xo, Po, st, xs, Pn, code)

    def gate_prepare(self, x, P, H, R):
        """Per group: (self, H x, Cholesky factor of S, 1/diagonal, ok) for the gating kernel."""
        v = self.v
        n = v.n
        xv = [self.lanes(lambda t, i=i: self.at(x, t, i)) for i in range(n)]
        Ps = self.sym(None, n, -1, lambda i, j: self.lanes(lambda t: self.at(P, t, i, j)))
        Hm = [[self.mat(H, a, k, v.pats[2], n) for k in range(n)] for a in range(v.m)]
        hx = [self.init(self.zero(_sum([Hm[a][k] * xv[k] for k in range(n) if Hm[a][k] is not None]), xv[0]))
              for a in range(v.m)]  # fmt: skip
        _, Lf, inv, ok = self.innovation(Ps, Hm, self.shared_sym(R, v.m, v.pats[3]))
        return self, hx, Lf, inv, ok

    def gate_detection(self, pre, z, out, d):
        """Squared Mahalanobis distance of detection d to every track of the group (eq. 8)."""
        hx, Lf, inv, ok = pre
        w = self.forward(Lf, inv, [self.init(self.at(z, d, a) - hx[a]) for a in range(len(hx))])
        acc = self.init(_sum([e * e for e in w]))
        acc = self.sel(ok, acc, float("inf"))
        for k, t in enumerate(self.ts):
            self.at(out, t, d)._assign(self.lane(acc, k))


@ti.kernel
def _kf(x: nd, P: nd, z: nd, F: nd, Q: nd, H: nd, R: nd, mask: nd, gain: nd, xo: nd, Po: nd, st: nd,
        f: ti.f64, b: ti.f64, cx: ti.f64, cy: ti.f64, v: ti.template()):  # fmt: skip
    """Every op of the filter, outputs xo, Po, st (unused arguments are never read)."""
    ti.loop_config(serialize=v.serial)
    for g in range((x.shape[0] + v.lanes - 1) // v.lanes):
        ti.static(_Tracer(v, g, x.shape[0]).filter(x, P, z, F, Q, H, R, mask, gain, xo, Po, st, (f, b, cx, cy)))


@ti.kernel
def _kf_inplace(x: nd, P: nd, z: nd, F: nd, Q: nd, H: nd, R: nd, st: nd,
                f: ti.f64, b: ti.f64, cx: ti.f64, cy: ti.f64, v: ti.template()):  # fmt: skip
    """The same in place (outputs x, P) without mask and gain_scale: 8 ndarray arguments."""
    ti.loop_config(serialize=v.serial)
    for g in range((x.shape[0] + v.lanes - 1) // v.lanes):
        ti.static(_Tracer(v, g, x.shape[0]).filter(x, P, z, F, Q, H, R, x, x, x, P, st, (f, b, cx, cy)))


@ti.kernel
def _gate(x: nd, P: nd, H: nd, R: nd, z: nd, out: nd, v: ti.template()):
    for g in range((x.shape[0] + v.lanes - 1) // v.lanes):
        pre = ti.static(_Tracer(v, g, x.shape[0]).gate_prepare(x, P, H, R))
        for d in range(z.shape[0]):
            ti.static(pre[0].gate_detection(pre[1:], z, out, d))




def _lanes(dt) -> int:
    if _impl.current_cfg().arch not in (ti.x64, ti.arm64):
        return 1
    return 4 if dt == np.float64 else 8


_VARIANTS: dict = {}


def _variant(*key) -> _Variant:
    v = _VARIANTS.get(key)
    if v is None:
        v = _VARIANTS.setdefault(key, _Variant(*key))
    return v


def _run(device, x, P, z, F, Q, H, R, mask, gain_scale, mode, out, pats, cam=(0.0, 0.0, 0.0, 0.0)):
    cam = tuple(float(c) for c in cam)  # the kernels' f64 scalars
    T, n = x.shape
    m = z.shape[1] if z is not None else 1
    dt = x.dtype
    if out is None:
        out = (device.empty((T, n), dt), device.empty((T, n, n), dt))
        if mode != MODE_PREDICT:
            out += (device.empty((T,), np.uint8),)
    xo, Po = out[0], out[1]
    st = out[2] if mode != MODE_PREDICT else None
    predict = F is not None
    if mode == MODE_STEREO:
        pats = (pats[0], pats[1], STEREO_PATTERN, pats[3])
    if not predict:
        pats = (-1, -1) + tuple(pats[2:])
    if mode == MODE_PREDICT:
        pats = pats[:2] + (-1, -1)
    v = _variant(
        dt.name, _lanes(dt), n, m, mode, predict, mask is not None, gain_scale is not None, tuple(pats), T <= SERIAL_MAX
    )
    d = x.buffer
    zb, Fb, Qb = (a.buffer if a is not None else d for a in (z, F, Q))
    Hb, Rb, sb = (a.buffer if a is not None else d for a in (H, R, st))
    if mask is None and gain_scale is None and xo is x and Po is P:
        launch(_kf_inplace, (d, P.buffer, zb, Fb, Qb, Hb, Rb, sb), (v,), scalars=cam, scalarize=False)
    else:
        mb, gb = (a.buffer if a is not None else d for a in (mask, gain_scale))
        arrays = (d, P.buffer, zb, Fb, Qb, Hb, Rb, mb, gb, xo.buffer, Po.buffer, sb)
        launch(_kf, arrays, (v,), scalars=cam, scalarize=False)
    return (xo, Po) if mode == MODE_PREDICT else (xo, Po, st)


def kf_predict(device, x, P, F, Q, out=None, pats=(-1, -1, -1, -1)):
    return _run(device, x, P, None, F, Q, None, None, None, None, MODE_PREDICT, out, pats)


def kf_update(device, x, P, z, H, R, mask=None, gain_scale=None, F=None, Q=None, out=None, pats=(-1, -1, -1, -1)):
    return _run(device, x, P, z, F, Q, H, R, mask, gain_scale, MODE_LINEAR, out, pats)


def ekf_update_stereo(
    device,
    x,
    P,
    z,
    R,
    f,
    b,
    cx=0.0,
    cy=0.0,
    mask=None,
    gain_scale=None,
    F=None,
    Q=None,
    out=None,
    pats=(-1, -1, -1, -1),
):
    return _run(device, x, P, z, F, Q, None, R, mask, gain_scale, MODE_STEREO, out, pats, (f, b, cx, cy))


def mahalanobis(device, x, P, H, R, z, out=None, pats=(-1, -1, -1, -1)):
    T, n = x.shape
    out = out if out is not None else device.empty((T, z.shape[0]), x.dtype)
    v = _variant(
        x.dtype.name, _lanes(x.dtype), n, z.shape[1], MODE_LINEAR, False, False, False, (-1, -1) + tuple(pats[2:])
    )
    launch(_gate, (x.buffer, P.buffer, H.buffer, R.buffer, z.buffer, out.buffer), (v,), scalarize=False)
    return out

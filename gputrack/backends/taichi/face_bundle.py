"""Taichi: the landmark residuals and Jacobian of gputrack/ops/face_bundle.py as one kernel launch.

One loop over (parameter vector, landmark or prior row): a landmark item poses its model point
(eq. 4-5), writes its two residual rows and their non-zero Jacobian entries (frame i's columns and
the identity's, each times its scale); a prior item writes its row and diagonal entry. The model's
sizes A and S are compile-time values (small matrices). On a CPU the loop runs on the calling
thread: a face bundle is ~70 items of ~1 us, and a parallel loop's dispatch costs more.
"""

from .launch import launch
from .runtime import current_arch, ti
from .trig import sincos64

nd = ti.types.ndarray()


@ti.func
def _rotation(r, dt: ti.template()):
    """R = I + a [r]x + b [r]x^2 and J_l = I + b [r]x + c [r]x^2 of a Rodrigues vector r, with
    a, b, c = sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3 (series below t = 1e-3), as
    gputrack.models.pose.rotation_coefficients."""
    t2 = r.dot(r)
    t = ti.sqrt(t2)
    small = t < 1e-3
    ts = ti.select(small, ti.cast(1, dt), t)
    sn, cs = ts * 0, ts * 0
    if ti.static(dt == ti.f64):
        sn, cs = sincos64(ts)  # SPIR-V has no 64-bit sin and cos
    else:
        sn, cs = ti.sin(ts), ti.cos(ts)
    a = ti.select(small, 1 - t2 / 6 + t2 * t2 / 120, sn / ts)
    b = ti.select(small, 0.5 - t2 / 24 + t2 * t2 / 720, (1 - cs) / (ts * ts))
    c = ti.select(small, 1.0 / 6.0 - t2 / 120 + t2 * t2 / 5040, (ts - sn) / (ts * ts * ts))
    Kx = ti.Matrix([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]], dt=dt)
    K2 = Kx @ Kx
    eye = ti.Matrix.identity(dt, 3)
    return eye + a * Kx + b * K2, eye + b * Kx + c * K2


@ti.func
def _landmark(Y: ti.template(), C: ti.template(), D: ti.template(), R: ti.template(), J: ti.template(), b, i, k,
              n, K, dt: ti.template(), A: ti.template(), S: ti.template(), jac: ti.template()):  # fmt: skip
    F = 6 + A
    base = i * F
    nF = n * F
    sc = 3 * n * K  # the scale's offset in D
    cm, cl = 5, 5 + 3 * K  # offsets of mean, L0 and G in C
    cg = cl + 3 * K * A
    r = ti.Vector([ti.cast(Y[b, base + c], dt) * D[sc + base + c] for c in ti.static(range(3))], dt=dt)
    t = ti.Vector([ti.cast(Y[b, base + 3 + c], dt) * D[sc + base + 3 + c] for c in ti.static(range(3))], dt=dt)
    ex = ti.Vector([ti.cast(Y[b, base + 6 + q], dt) * D[sc + base + 6 + q] for q in ti.static(range(A))], dt=dt)
    Bs = ti.Matrix.zero(dt, 3, A)  # eq. 4: the expression basis of identity s, L0 + sum_p s_p G_p
    for c in ti.static(range(3)):
        for q in ti.static(range(A)):
            v = C[cl + (k * 3 + c) * A + q]
            for p in ti.static(range(S)):
                v += ti.cast(Y[b, nF + p], dt) * D[sc + nF + p] * C[cg + ((k * 3 + c) * S + p) * A + q]
            Bs[c, q] = v
    X = ti.Vector([C[cm + k * 3 + c] for c in ti.static(range(3))], dt=dt) + Bs @ ex  # eq. 4
    Rm, Jl = _rotation(r, dt)
    RX = Rm @ X
    Yc = RX + t
    fx, fy, cx, cy = C[0], C[1], C[2], C[3]
    iz = 1 / ti.max(Yc[2], C[4])  # eq. 5
    q0 = i * K + k
    w = D[2 * n * K + q0]
    R[b, 2 * q0] = (fx * Yc[0] * iz + cx - D[2 * q0]) * w  # eq. 6, weighted
    R[b, 2 * q0 + 1] = (fy * Yc[1] * iz + cy - D[2 * q0 + 1]) * w
    if ti.static(jac):
        aw = w * iz
        Dp = ti.Matrix([[fx * aw, 0.0, -fx * Yc[0] * iz * aw], [0.0, fy * aw, -fy * Yc[1] * iz * aw]], dt=dt)
        RXx = ti.Matrix([[0.0, -RX[2], RX[1]], [RX[2], 0.0, -RX[0]], [-RX[1], RX[0], 0.0]], dt=dt)
        Dr = -(Dp @ (RXx @ Jl))  # d(RX)/dr = -[RX]x J_l(r)
        DpR = Dp @ Rm
        Da = DpR @ Bs  # dY/da = R Bs
        for e in ti.static(range(2)):
            row = 2 * q0 + e
            for c in ti.static(range(3)):
                J[b, row, base + c] = Dr[e, c] * D[sc + base + c]
                J[b, row, base + 3 + c] = Dp[e, c] * D[sc + base + 3 + c]  # dY/dt = I
            for q in ti.static(range(A)):
                J[b, row, base + 6 + q] = Da[e, q] * D[sc + base + 6 + q]
        if ti.static(S > 0):
            Ga = ti.Matrix.zero(dt, 3, S)  # dX/ds = G a
            for c in ti.static(range(3)):
                for p in ti.static(range(S)):
                    v = ti.cast(0, dt)
                    for q in ti.static(range(A)):
                        v += C[cg + ((k * 3 + c) * S + p) * A + q] * ex[q]
                    Ga[c, p] = v
            Ds = DpR @ Ga
            for e in ti.static(range(2)):
                for p in ti.static(range(S)):
                    J[b, 2 * q0 + e, nF + p] = Ds[e, p] * D[sc + nF + p]


@ti.kernel
def _landmarks(Y: nd, C: nd, D: nd, R: nd, J: nd, n: ti.i32, K: ti.i32, prior: ti.i32, dt: ti.template(),
               A: ti.template(), S: ti.template(), jac: ti.template(), serial: ti.template()):  # fmt: skip
    items = n * K + S
    F = 6 + A
    P = n * F + S
    sc = 3 * n * K
    if ti.static(serial):
        ti.loop_config(serialize=True)
    for t in range(Y.shape[0] * items):
        b, q = t // items, t % items
        if q < n * K:
            _landmark(Y, C, D, R, J, b, q // K, q % K, n, K, dt, A, S, jac)
        elif prior:
            p = q - n * K
            col = n * F + p
            row = 2 * n * K + p
            w = D[sc + P + p]
            R[b, row] = (ti.cast(Y[b, col], dt) * D[sc + col] - D[sc + P + S + p]) * w
            if ti.static(jac):
                J[b, row, col] = w * D[sc + col]


def landmark_residuals(device, points, model, frames, consts, values, jacobian, out):
    R, J = out
    dt = ti.f64 if R.dtype.itemsize == 8 else ti.f32
    launch(_landmarks, (points.buffer, consts.buffer, values.buffer, R.buffer, J.buffer),
           (dt, model.A, model.S, bool(jacobian), current_arch() == "cpu"),
           scalars=(frames.n, model.K, int(frames.prior is not None)), ir_passes=False)  # fmt: skip

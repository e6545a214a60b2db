"""Taichi kernels: sparse-template cost and residuals (paper 000 eq. 17-21), NCC patches (paper 003).

One launch per op call. The outermost loop runs over hypotheses (one thread each) with a serial
inner loop over the points, summed in blocks of ``CHUNK`` (two-level sums: the error grows with
CHUNK + N / CHUNK, not with N). RGB needs two passes (alpha and beta are sums over the valid
points): the first stores each point's sample and validity in a per-hypothesis scratch row.
Conventions: gputrack/ops/template.py.
"""

import weakref

import numpy as np

from .runtime import DTYPES, ti

CHUNK = 64
TINY = 1e-12
FLT_BIG = 3.0e38
FLAT = 1e-6

# per-device scratch buffers (raw Taichi ndarrays), dropped with the device
_scratch = weakref.WeakKeyDictionary()


@ti.func
def _point(tf: ti.types.ndarray(dtype=ti.f32, ndim=4), b, j, x, y, z, fx, fy, cx, cy, wm1, hm1):
    """Camera-frame Z, pixel (u, v), and whether the point is inside the image (Z > 0)."""
    X = tf[b, j, 0, 0] * x + tf[b, j, 0, 1] * y + tf[b, j, 0, 2] * z + tf[b, j, 0, 3]  # eq. 4
    Y = tf[b, j, 1, 0] * x + tf[b, j, 1, 1] * y + tf[b, j, 1, 2] * z + tf[b, j, 1, 3]
    Z = tf[b, j, 2, 0] * x + tf[b, j, 2, 1] * y + tf[b, j, 2, 2] * z + tf[b, j, 2, 3]
    u = ti.f32(0.0)
    v = ti.f32(0.0)
    ok = 0
    if Z > 0.0 and Z < FLT_BIG:
        u = fx * (X / Z) + cx  # eq. 5
        v = fy * (Y / Z) + cy
        if u >= 0.0 and u <= wm1 and v >= 0.0 and v <= hm1:
            ok = 1
    return Z, u, v, ok


@ti.func
def _measured(d):
    return d > 0.0 and d < FLT_BIG  # a measurement: > 0 and finite (NaN fails both)


@ti.kernel
def _rgbd_kernel(
    tf: ti.types.ndarray(dtype=ti.f32, ndim=4),
    rpts: ti.types.ndarray(dtype=ti.f32, ndim=2),
    rpart: ti.types.ndarray(dtype=ti.i32, ndim=1),
    dpts: ti.types.ndarray(dtype=ti.f32, ndim=2),
    dpart: ti.types.ndarray(dtype=ti.i32, ndim=1),
    gray: ti.types.ndarray(dtype=ti.f32, ndim=2),
    dimg: ti.types.ndarray(dtype=ti.f32, ndim=2),
    fx: ti.f32,
    fy: ti.f32,
    cx: ti.f32,
    cy: ti.f32,
    lam: ti.f32,
    c_rgb: ti.f32,
    c_depth: ti.f32,
    sample: ti.types.ndarray(dtype=ti.f32, ndim=2),
    valid: ti.types.ndarray(dtype=ti.u8, ndim=2),
    total: ti.types.ndarray(dtype=ti.f32, ndim=1),
    eps_c: ti.types.ndarray(dtype=ti.f32, ndim=1),
    eps_d: ti.types.ndarray(dtype=ti.f32, ndim=1),
    residuals: ti.types.ndarray(dtype=ti.f32, ndim=2),
    want_residuals: ti.template(),
):
    nb = tf.shape[0]
    n = rpts.shape[0]
    m = dpts.shape[0]
    h = gray.shape[0]
    w = gray.shape[1]
    wm1 = ti.f32(w - 1)
    hm1 = ti.f32(h - 1)
    cc = c_rgb * c_rgb
    cd = c_depth * c_depth
    wc = ti.sqrt(1.0 - lam)
    wd = ti.sqrt(lam)
    for b in range(nb):
        # pass 1 (RGB): samples I_i and the sums over the valid points (eq. 17)
        sT = ti.f32(0.0)
        sTT = ti.f32(0.0)
        sTI = ti.f32(0.0)
        for c0 in range((n + CHUNK - 1) // CHUNK):
            bT = ti.f32(0.0)
            bTT = ti.f32(0.0)
            bTI = ti.f32(0.0)
            for i in range(c0 * CHUNK, ti.min(n, c0 * CHUNK + CHUNK)):
                Z, u, v, ok = _point(tf, b, rpart[i], rpts[i, 0], rpts[i, 1], rpts[i, 2], fx, fy, cx, cy, wm1, hm1)
                I = ti.f32(0.0)
                if ok:
                    x0 = ti.min(ti.cast(u, ti.i32), w - 2)
                    y0 = ti.min(ti.cast(v, ti.i32), h - 2)
                    a = u - ti.cast(x0, ti.f32)
                    bw = v - ti.cast(y0, ti.f32)
                    i00 = gray[y0, x0]
                    i01 = gray[y0, x0 + 1]
                    i10 = gray[y0 + 1, x0]
                    i11 = gray[y0 + 1, x0 + 1]
                    top = i00 + a * (i01 - i00)
                    bot = i10 + a * (i11 - i10)
                    I = top + bw * (bot - top)  # sec. 3.5: bilinear
                    T = rpts[i, 3]
                    bT += T
                    bTT += T * T
                    bTI += T * I
                sample[b, i] = I
                valid[b, i] = ti.cast(ok, ti.u8)
            sT += bT
            sTT += bTT
            sTI += bTI
        alpha = ti.f32(0.0)
        beta = ti.f32(0.0)
        if sT > TINY:
            alpha = 1.0 / sT  # eq. 17
        if sTI > TINY:
            beta = alpha * sTT / sTI  # eq. 17
        # pass 2 (RGB): eps_C = sum rho_c(d_i)
        eC = ti.f32(0.0)
        for c0 in range((n + CHUNK - 1) // CHUNK):
            blk = ti.f32(0.0)
            for i in range(c0 * CHUNK, ti.min(n, c0 * CHUNK + CHUNK)):
                rho = ti.f32(1.0)
                r = wc
                if valid[b, i] != 0:
                    d = beta * sample[b, i] - alpha * rpts[i, 3]  # eq. 17: d_i
                    rho = d * d / (cc + d * d)
                    r = wc * d / ti.sqrt(cc + d * d)  # eq. 20-21: r_i
                blk += rho
                if ti.static(want_residuals):
                    residuals[b, i] = r
            eC += blk
        # depth: eps_D = sum rho_c'(d'_i) (eq. 18)
        eD = ti.f32(0.0)
        for c0 in range((m + CHUNK - 1) // CHUNK):
            blk = ti.f32(0.0)
            for i in range(c0 * CHUNK, ti.min(m, c0 * CHUNK + CHUNK)):
                Z, u, v, ok = _point(tf, b, dpart[i], dpts[i, 0], dpts[i, 1], dpts[i, 2], fx, fy, cx, cy, wm1, hm1)
                rho = ti.f32(1.0)
                r = wd
                if ok:
                    x0 = ti.min(ti.cast(u, ti.i32), w - 2)
                    y0 = ti.min(ti.cast(v, ti.i32), h - 2)
                    d00 = dimg[y0, x0]
                    d01 = dimg[y0, x0 + 1]
                    d10 = dimg[y0 + 1, x0]
                    d11 = dimg[y0 + 1, x0 + 1]
                    if _measured(d00) and _measured(d01) and _measured(d10) and _measured(d11):
                        a = u - ti.cast(x0, ti.f32)
                        bw = v - ti.cast(y0, ti.f32)
                        top = d00 + a * (d01 - d00)
                        bot = d10 + a * (d11 - d10)
                        dd = top + bw * (bot - top) - Z  # eq. 18: d'_i = Zhat - Z
                        rho = dd * dd / (cd + dd * dd)
                        r = wd * dd / ti.sqrt(cd + dd * dd)  # eq. 20-21: r'_i
                blk += rho
                if ti.static(want_residuals):
                    residuals[b, n + i] = r
            eD += blk
        if ti.static(not want_residuals):
            total[b] = (1.0 - lam) * eC + lam * eD  # eq. 19
            eps_c[b] = eC
            eps_d[b] = eD


def _buffer(device, name, shape, dtype):
    """A scratch Taichi ndarray of ``shape`` kept per device (reallocated when the shape changes)."""
    per_device = _scratch.setdefault(device, {})
    found = per_device.get(name)
    if found is None or found[0] != shape:
        found = (shape, ti.ndarray(DTYPES[np.dtype(dtype).name], shape))
        per_device[name] = found
    return found[1]


def _run(device, tf, rgb, depth, gray, dimg, camera, lam, c_rgb, c_depth, residuals):
    nb = tf.shape[0]
    n = rgb["pts"].shape[0]
    m = depth["pts"].shape[0]
    sample = _buffer(device, "sample", (nb, n), np.float32)
    valid = _buffer(device, "valid", (nb, n), np.uint8)
    if residuals:
        res = device.empty((nb, n + m), np.float32)
        dummy = _buffer(device, "dummy1", (1,), np.float32)
        outs = (dummy, dummy, dummy)
        res_buf = res.buffer
    else:
        res = tuple(device.empty((nb,), np.float32) for _ in range(3))
        outs = tuple(r.buffer for r in res)
        res_buf = _buffer(device, "dummy2", (1, 1), np.float32)
    fx, fy, cx, cy = (float(c) for c in camera)
    _rgbd_kernel(
        tf.buffer, rgb["pts"].buffer, rgb["part"].buffer, depth["pts"].buffer, depth["part"].buffer,
        gray.buffer, dimg.buffer, fx, fy, cx, cy, lam, c_rgb, c_depth, sample, valid,
        outs[0], outs[1], outs[2], res_buf, residuals,
    )
    return res


def rgbd_cost(device, tf, rgb, depth, gray, dimg, camera, *, lam, c_rgb, c_depth):
    return _run(device, tf, rgb, depth, gray, dimg, camera, lam, c_rgb, c_depth, False)


def rgbd_residuals(device, tf, rgb, depth, gray, dimg, camera, *, lam, c_rgb, c_depth):
    return _run(device, tf, rgb, depth, gray, dimg, camera, lam, c_rgb, c_depth, True)

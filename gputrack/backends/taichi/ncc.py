"""Taichi kernels: zero-mean NCC of templates with bilinear image patches (paper 003 eq. 13).

One launch per op call: first the templates' shifted values and sums (a thread per template; on a
CPU one serial loop; they are the same for every hypothesis: precomputed, the face tracker's
score call of 1000 x 10 patches took 2.18-2.60 ms against 2.66-2.99 ms, taichi:cpu, three runs in
turn, 2026-12-06), then one thread per (hypothesis, point) for the per-point scores, one per
hypothesis for their sum N(u). Conventions: gputrack/ops/ncc.py.

On the CPU arch, templates of S = 4, 8 or 16 (the face tracker's) take a row of the patch at a
time as one SIMD vector of S lanes (:func:`_ncc_lanes`, compiled with scalarisation off): each
image row of the patch is loaded and interpolated across once (S + 1 pixels: one vector load, its
lanes shifted by one and the next pixel), the template rows are vectors of their own array, and
the sums are per lane until the end. The face tracker's score call (1000 x 10 patches of 16 x 16,
``perf/bench_face.py``'s score case) took 1.00-1.35 ms against 2.02-2.68 ms for the scalar loop,
three runs in turn (2026-12-06).
"""

import numpy as np

from ...abi import INTENSITY_MAX
from .launch import launch
from .runtime import current_arch, scratch, ti

#: a patch or template whose standard deviation is at most FLAT (|mean| + 1) is flat (scores 0)
FLAT = 1e-6
#: template sizes S whose patch rows are SIMD vectors of S lanes on the CPU arch (_ncc_lanes), and
#: the element type of their template rows (one object per size: the scratch arrays are kept by it)
LANE_ROWS = {s: ti.types.vector(s, ti.f32) for s in (4, 8, 16)}


@ti.func
def _clamp(x):
    """A pixel or template value clamped to [-INTENSITY_MAX, INTENSITY_MAX] (gputrack/abi.py;
    gputrack/ops/ncc.py); NaN stays NaN."""
    m = ti.f32(float(INTENSITY_MAX))
    return ti.select(x > m, m, ti.select(x < -m, -m, x))


@ti.func
def _px(img: ti.template(), y, x):
    return _clamp(img[y, x])


@ti.func
def _sample(img: ti.template(), uu, vv, h, w):
    x0 = ti.min(ti.cast(uu, ti.i32), w - 2)
    y0 = ti.min(ti.cast(vv, ti.i32), h - 2)
    a = uu - ti.cast(x0, ti.f32)
    bw = vv - ti.cast(y0, ti.f32)
    i00 = _px(img, y0, x0)
    i10 = _px(img, y0 + 1, x0)
    top = i00 + a * (_px(img, y0, x0 + 1) - i00)
    bot = i10 + a * (_px(img, y0 + 1, x0 + 1) - i10)
    return top + bw * (bot - top)  # bilinear


@ti.func
def _finish(n, p0, t0, sp, st, spp, stt, spt):
    """The NCC of the shifted sums (see _ncc_one): 0 for a flat patch or template."""
    out = ti.f32(0.0)
    # centred sums (each product of a sum with a mean: no float32 overflow below 2**48 per value)
    vp = spp - sp * (sp / n)
    vt = stt - st * (st / n)
    cv = spt - sp * (st / n)
    mp = p0 + sp / n
    mt = t0 + st / n
    # a flat patch or template (standard deviation <= 1e-6 (|mean| + 1)) scores 0
    fp = FLAT * (ti.abs(mp) + 1.0)
    ft = FLAT * (ti.abs(mt) + 1.0)
    if vp > n * fp * fp and vt > n * ft * ft:
        out = ti.min(ti.max(cv / (ti.sqrt(vp) * ti.sqrt(vt)), -1.0), 1.0)
    return out


@ti.func
def _template_sums(tpl: ti.template(), ts: ti.template(), tstat: ti.template(), tv: ti.template(), k,
                   lanes: ti.template()):  # fmt: skip
    """Template k's values shifted by its first one (each clamped, as _ncc_one's patch pixels) into
    ts[k] (with ``lanes`` also its rows as vectors into tv[k]), and their sums t0, st, stt into
    tstat[k], in the order _ncc_one adds its patch's sums: computed once per call instead of once per
    hypothesis."""
    s = tpl.shape[1]
    t0 = _clamp(tpl[k, 0, 0])
    st = ti.f32(0.0)
    stt = ti.f32(0.0)
    for i in range(s):
        rt = ti.f32(0.0)
        rtt = ti.f32(0.0)
        for jj in range(s):
            t = _clamp(tpl[k, i, jj]) - t0
            ts[k, i, jj] = t
            rt += t
            rtt += t * t
        st += rt
        stt += rtt
        if ti.static(lanes):
            tv[k, i] = ti.Vector([ts[k, i, e] for e in ti.static(range(lanes))], dt=ti.f32)
    tstat[k, 0] = t0
    tstat[k, 1] = st
    tstat[k, 2] = stt


@ti.func
def _ncc_one(pts: ti.template(), ts: ti.template(), tstat: ti.template(), img: ti.template(), b, k):
    s = ts.shape[1]
    h = img.shape[0]
    w = img.shape[1]
    u = pts[b, k, 0]
    v = pts[b, k, 1]
    ctr = 0.5 * ti.cast(s - 1, ti.f32)
    out = ti.f32(0.0)
    # the whole patch must lie inside the image (NaN fails the tests)
    if u - ctr >= 0.0 and u + ctr <= ti.cast(w - 1, ti.f32) and v - ctr >= 0.0 and v + ctr <= ti.cast(h - 1, ti.f32):
        n = ti.cast(s * s, ti.f32)
        # one pass; sums of values shifted by the first patch and template values (so the centred
        # sums do not cancel), accumulated per row then over the rows (the template's: tstat)
        t0, st, stt = tstat[k, 0], tstat[k, 1], tstat[k, 2]
        p0 = ti.f32(0.0)
        sp = ti.f32(0.0)
        spp = ti.f32(0.0)
        spt = ti.f32(0.0)
        if s < w and s < h:
            # inside the image every patch pixel has the same bilinear weights: one base pixel (the
            # last column and row start one pixel in with weight 1 where the patch touches the
            # border, as x0 = min(floor(x), w - 2) does) and two new loads per pixel along a row
            u0 = u - ctr
            v0 = v - ctr
            xb = ti.min(ti.cast(u0, ti.i32), w - 1 - s)
            yb = ti.min(ti.cast(v0, ti.i32), h - 1 - s)
            a = u0 - ti.cast(xb, ti.f32)
            bw = v0 - ti.cast(yb, ti.f32)
            p0 = _sample(img, u0, v0, h, w)
            for i in range(s):
                y = yb + i
                lt = _px(img, y, xb)
                lb = _px(img, y + 1, xb)
                rp = ti.f32(0.0)
                rpp = ti.f32(0.0)
                rpt = ti.f32(0.0)
                for jj in range(s):
                    nt = _px(img, y, xb + jj + 1)
                    nb = _px(img, y + 1, xb + jj + 1)
                    tp = lt + a * (nt - lt)
                    bt = lb + a * (nb - lb)
                    p = tp + bw * (bt - tp) - p0  # patch pixel (i, jj), bilinear
                    lt = nt
                    lb = nb
                    t = ts[k, i, jj]
                    rp += p
                    rpp += p * p
                    rpt += p * t
                sp += rp
                spp += rpp
                spt += rpt
        else:  # a patch as large as the image: each pixel's own bilinear weights
            p0 = _sample(img, u - ctr, v - ctr, h, w)
            for i in range(s):
                vv = v + (ti.cast(i, ti.f32) - ctr)
                rp = ti.f32(0.0)
                rpp = ti.f32(0.0)
                rpt = ti.f32(0.0)
                for jj in range(s):
                    uu = u + (ti.cast(jj, ti.f32) - ctr)
                    p = _sample(img, uu, vv, h, w) - p0  # patch pixel (i, jj), bilinear
                    t = ts[k, i, jj]
                    rp += p
                    rpp += p * p
                    rpt += p * t
                sp += rp
                spp += rpp
                spt += rpt
        out = _finish(n, p0, t0, sp, st, spp, stt, spt)
    return out


@ti.func
def _row_lanes(img: ti.template(), y, xb, a, lanes: ti.template()):
    """Image row y at x = xb + a .. xb + a + lanes - 1, linearly interpolated across: one vector of
    ``lanes`` pixels from xb, the same shifted by one lane with pixel xb + lanes (each clamped)."""
    m = ti.f32(float(INTENSITY_MAX))
    left = ti.Vector([img[y, xb + e] for e in ti.static(range(lanes))], dt=ti.f32)
    left = ti.select(left > m, m, ti.select(left < -m, -m, left))
    last = _px(img, y, xb + lanes)
    right = ti.Vector([left[e + 1] for e in ti.static(range(lanes - 1))] + [last], dt=ti.f32)
    return left + a * (right - left)


@ti.func
def _ncc_lanes(pts: ti.template(), tv: ti.template(), tstat: ti.template(), img: ti.template(), b, k,
               lanes: ti.template()):  # fmt: skip
    """_ncc_one for S = ``lanes`` < H, W with a row of the patch as one SIMD vector: each image row of
    the patch interpolated across once (_row_lanes) and down between two of them, the sums per lane."""
    h = img.shape[0]
    w = img.shape[1]
    u = pts[b, k, 0]
    v = pts[b, k, 1]
    ctr = ti.static(0.5 * (lanes - 1))
    out = ti.f32(0.0)
    # the whole patch must lie inside the image (NaN fails the tests)
    if u - ctr >= 0.0 and u + ctr <= ti.cast(w - 1, ti.f32) and v - ctr >= 0.0 and v + ctr <= ti.cast(h - 1, ti.f32):
        u0 = u - ctr
        v0 = v - ctr
        xb = ti.min(ti.cast(u0, ti.i32), w - 1 - lanes)  # as _ncc_one: one base pixel for the patch
        yb = ti.min(ti.cast(v0, ti.i32), h - 1 - lanes)
        a = u0 - ti.cast(xb, ti.f32)
        bw = v0 - ti.cast(yb, ti.f32)
        p0 = _sample(img, u0, v0, h, w)
        above = _row_lanes(img, yb, xb, a, lanes)
        zero = ti.Vector([0.0] * lanes, dt=ti.f32)
        rp = zero
        rpp = zero
        rpt = zero
        for i in range(lanes):
            below = _row_lanes(img, yb + i + 1, xb, a, lanes)
            p = above + bw * (below - above) - p0  # patch row i, bilinear, shifted by p0
            rp += p
            rpp += p * p
            rpt += p * tv[k, i]
            above = below
        out = _finish(ti.static(float(lanes * lanes)), p0, tstat[k, 0], rp.sum(), tstat[k, 1], rpp.sum(),
                      tstat[k, 2], rpt.sum())  # fmt: skip
    return out


@ti.func
def _ncc_at(pts: ti.template(), ts: ti.template(), tv: ti.template(), tstat: ti.template(), img: ti.template(), b, k,
            lanes: ti.template()):  # fmt: skip
    out = ti.f32(0.0)
    if ti.static(lanes):
        out = _ncc_lanes(pts, tv, tstat, img, b, k, lanes)
    else:
        out = _ncc_one(pts, ts, tstat, img, b, k)
    return out


F2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
F3 = ti.types.ndarray(dtype=ti.f32, ndim=3)


@ti.kernel
def _ncc_points(pts: F3, tpl: F3, img: F2, out: F2, ts: F3, tstat: F2, tv: ti.types.ndarray(), serial: ti.template(),
                lanes: ti.template()):  # fmt: skip
    if ti.static(serial):
        ti.loop_config(serialize=True)
    for k in range(tpl.shape[0]):
        _template_sums(tpl, ts, tstat, tv, k, lanes)
    for b, k in ti.ndrange(pts.shape[0], pts.shape[1]):
        out[b, k] = _ncc_at(pts, ts, tv, tstat, img, b, k, lanes)


@ti.kernel
def _ncc_sum(pts: F3, tpl: F3, img: F2, out: ti.types.ndarray(dtype=ti.f32, ndim=1), ts: F3, tstat: F2,
             tv: ti.types.ndarray(), serial: ti.template(), lanes: ti.template()):  # fmt: skip
    if ti.static(serial):
        ti.loop_config(serialize=True)
    for k in range(tpl.shape[0]):
        _template_sums(tpl, ts, tstat, tv, k, lanes)
    for b in range(pts.shape[0]):
        acc = ti.f32(0.0)
        for k in range(pts.shape[1]):
            acc += _ncc_at(pts, ts, tv, tstat, img, b, k, lanes)
        out[b] = acc  # eq. 13: N(u) = sum over the K points


def patch_ncc(device, pts, tpl, img, *, per_point):
    nb, nk = pts.shape[:2]
    K, s = tpl.shape[0], tpl.shape[1]
    ts = scratch(device, "ncc_template", (K, s, s), ti.f32)
    tstat = scratch(device, "ncc_template_sums", (K, 3), ti.f32)
    serial = current_arch() == "cpu"  # K templates of s^2 values: no thread pool wake-up for them on a CPU
    lanes = s if serial and s in LANE_ROWS and s < min(img.shape) else 0
    tv = scratch(device, "ncc_template_rows", (K, s), LANE_ROWS[s]) if lanes else ts
    if per_point:
        out = device.empty((nb, nk), np.float32)
        launch(_ncc_points, (pts.buffer, tpl.buffer, img.buffer, out.buffer, ts, tstat, tv), (serial, lanes),
               scalarize=not lanes)  # fmt: skip
    else:
        out = device.empty((nb,), np.float32)
        launch(_ncc_sum, (pts.buffer, tpl.buffer, img.buffer, out.buffer, ts, tstat, tv), (serial, lanes),
               scalarize=not lanes)  # fmt: skip
    return out

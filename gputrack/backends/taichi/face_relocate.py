"""Taichi: feature-point re-localisation (gputrack/ops/face_relocate.py, paper 003 eq. 14) in float32,
one launch: a thread per feature point runs its Gauss-Newton iterations, samples its patch at the
point found and matches it with its template (on a CPU one serial loop: K ~ 10 points are too few
for the thread pool). The
patch's samples are not stored between the passes over it: each pass samples the image again
(bilinear samples of a 640 x 480 float32 image stay in the cache)."""

from ...uploads import constant
from .launch import launch
from .pixels import is_finite
from .runtime import current_arch, ti

F1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
F2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
F3 = ti.types.ndarray(dtype=ti.f32, ndim=3)


@ti.func
def _bilinear(img: ti.template(), x, y):
    """The image at (x, y), the coordinates clipped into it first (gputrack/ops/face_relocate.py)."""
    H, W = img.shape[0], img.shape[1]
    xc = ti.min(ti.max(x, 0.0), ti.cast(W - 1, ti.f32))
    yc = ti.min(ti.max(y, 0.0), ti.cast(H - 1, ti.f32))
    x0 = ti.min(ti.cast(xc, ti.i32), W - 2)  # floor: xc >= 0
    y0 = ti.min(ti.cast(yc, ti.i32), H - 2)
    fx = xc - ti.cast(x0, ti.f32)
    fy = yc - ti.cast(y0, ti.f32)
    top = img[y0, x0] + fx * (img[y0, x0 + 1] - img[y0, x0])
    bot = img[y0 + 1, x0] + fx * (img[y0 + 1, x0 + 1] - img[y0 + 1, x0])
    return top + fy * (bot - top)


@ti.func
def _normaliser(c0, s, ss, sx, sy, n, sxx, contrast, min_std, shading):
    """(mean, gain, bx, by) of n = S * S values whose sums, shifted by c0, are s, ss and, times the offsets
    x, y from the patch's centre, sx, sy: gain (v - mean - bx x - by y) has zero mean and standard
    deviation ``contrast`` (at least ``min_std``); the ramp (bx, by) is the least-squares one with
    ``shading``, else 0. sxx: the sum of x * x over the patch (the same for y)."""
    bx, by = 0.0, 0.0
    if shading != 0:
        bx, by = sx / sxx, sy / sxx
    var = ti.max(ss / n - (s / n) * (s / n) - (bx * bx + by * by) * sxx / n, 0.0)
    return c0 + s / n, contrast / ti.max(ti.sqrt(var), min_std), bx, by


@ti.func
def _stored_normaliser(p: ti.template(), k, sxx, contrast, min_std, shading):
    """:func:`_normaliser` of the stored patch p[k] (S x S; sums shifted by its first value: no
    cancellation in float32)."""
    S = p.shape[1]
    half = 0.5 * ti.cast(S - 1, ti.f32)
    p0 = p[k, 0, 0]
    s, ss, sx, sy = 0.0, 0.0, 0.0, 0.0
    for i, j in ti.ndrange(S, S):
        v = p[k, i, j] - p0
        s += v
        ss += v * v
        sx += v * (ti.cast(j, ti.f32) - half)
        sy += v * (ti.cast(i, ti.f32) - half)
    return _normaliser(p0, s, ss, sx, sy, ti.cast(S * S, ti.f32), sxx, contrast, min_std, shading)


@ti.func
def _plane_match(a: ti.template(), b: ti.template(), k, sxx):
    """The NCC of patches a[k] and b[k] (S x S), each with its least-squares plane (mean and ramp) off;
    0 where either is flat (gputrack/ops/face_relocate.py). Two passes: the planes, then the residuals."""
    S = a.shape[1]
    n = ti.cast(S * S, ti.f32)
    half = 0.5 * ti.cast(S - 1, ti.f32)
    sa, sb, xa, ya, xb, yb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    for i, j in ti.ndrange(S, S):
        va, vb = a[k, i, j], b[k, i, j]
        ox, oy = ti.cast(j, ti.f32) - half, ti.cast(i, ti.f32) - half
        sa += va
        sb += vb
        xa += va * ox
        ya += va * oy
        xb += vb * ox
        yb += vb * oy
    ma, mb = sa / n, sb / n
    bxa, bya, bxb, byb = xa / sxx, ya / sxx, xb / sxx, yb / sxx
    ab, aa, bb = 0.0, 0.0, 0.0
    for i, j in ti.ndrange(S, S):
        ox, oy = ti.cast(j, ti.f32) - half, ti.cast(i, ti.f32) - half
        ra = a[k, i, j] - ma - bxa * ox - bya * oy
        rb = b[k, i, j] - mb - bxb * ox - byb * oy
        ab += ra * rb
        aa += ra * ra
        bb += rb * rb
    fa, fb = 1e-6 * (ti.abs(ma) + 1.0), 1e-6 * (ti.abs(mb) + 1.0)
    out = 0.0
    if aa / n > fa * fa and bb / n > fb * fb:
        out = ab / ti.sqrt(aa * bb)
    return out


@ti.kernel
def _relocate(img: F2, pred: F2, prev: F3, first: F3, consts: F1, points: F2, patches: F3, match: F1,
              iterations: ti.i32, serial: ti.template()):  # fmt: skip
    rho, eps, max_step, contrast = consts[0], consts[1], consts[2], consts[3]
    tol, min_std, singular, shading = consts[4], consts[5], consts[6], consts[7]
    S = prev.shape[1]
    n = ti.cast(S * S, ti.f32)
    half = 0.5 * ti.cast(S - 1, ti.f32)
    sxx = n * ti.cast(S * S - 1, ti.f32) / 12.0  # the sum of x * x over the patch
    if ti.static(serial):
        ti.loop_config(serialize=True)
    for k in range(prev.shape[0]):
        mp, gp, bxp, byp = 0.0, 1.0, 0.0, 0.0  # (mean, gain, ramp): raw intensities
        mf, gf, bxf, byf = 0.0, 1.0, 0.0, 0.0
        if contrast > 0:
            mp, gp, bxp, byp = _stored_normaliser(prev, k, sxx, contrast, min_std, 0.0)  # no ramp off
            mf, gf, bxf, byf = _stored_normaliser(first, k, sxx, contrast, min_std, shading)
        px, py = pred[k, 0], pred[k, 1]
        mx, my = px, py
        it = 0
        while it < iterations:
            x0, y0 = mx - half, my - half  # patch pixel (0, 0)
            # the current patch's normalisers (mean, gain, ramp), its ring alike: a against the previous
            # frame's patch, b against the first frame's (its ramp off too with shading)
            ma, ga, bxa, bya = 0.0, 1.0, 0.0, 0.0
            mb, gb, bxb, byb = 0.0, 1.0, 0.0, 0.0
            if contrast > 0:
                c0 = _bilinear(img, x0, y0)
                s, ss, sx, sy = 0.0, 0.0, 0.0, 0.0
                for i, j in ti.ndrange(S, S):
                    v = _bilinear(img, x0 + j, y0 + i) - c0
                    s += v
                    ss += v * v
                    sx += v * (ti.cast(j, ti.f32) - half)
                    sy += v * (ti.cast(i, ti.f32) - half)
                ma, ga, bxa, bya = _normaliser(c0, s, ss, sx, sy, n, sxx, contrast, min_std, 0.0)
                mb, gb, bxb, byb = _normaliser(c0, s, ss, sx, sy, n, sxx, contrast, min_std, shading)
            a00, a01, a11, g0, g1 = 0.0, 0.0, 0.0, 0.0, 0.0
            for i, j in ti.ndrange(S, S):  # eq. 14's appearance terms
                x, y = x0 + j, y0 + i
                ox, oy = ti.cast(j, ti.f32) - half, ti.cast(i, ti.f32) - half
                ix = 0.5 * (_bilinear(img, x + 1, y) - _bilinear(img, x - 1, y))  # central differences
                iy = 0.5 * (_bilinear(img, x, y + 1) - _bilinear(img, x, y - 1))
                v = _bilinear(img, x, y)
                gxa, gya = ga * (ix - bxa), ga * (iy - bya)
                gxb, gyb = gb * (ix - bxb), gb * (iy - byb)
                ea = ga * (v - ma - bxa * ox - bya * oy) - gp * (prev[k, i, j] - mp - bxp * ox - byp * oy)
                eb = gb * (v - mb - bxb * ox - byb * oy) - gf * (first[k, i, j] - mf - bxf * ox - byf * oy)
                a00 += rho * gxa * gxa + gxb * gxb
                a01 += rho * gxa * gya + gxb * gyb
                a11 += rho * gya * gya + gyb * gyb
                g0 += rho * gxa * ea + gxb * eb
                g1 += rho * gya * ea + gyb * eb
            a00 += eps
            a11 += eps
            g0 += eps * (mx - px)
            g1 += eps * (my - py)
            det = a00 * a11 - a01 * a01
            dx, dy = 0.0, 0.0
            if ti.abs(det) > singular:
                dx = (a01 * g1 - a11 * g0) / det
                dy = (a01 * g0 - a00 * g1) / det
            if not (is_finite(dx) and is_finite(dy)):  # no step
                dx, dy = 0.0, 0.0
            norm = ti.sqrt(dx * dx + dy * dy)
            f = ti.min(1.0, max_step / ti.max(norm, 1e-12))
            dx *= f
            dy *= f
            mx += dx
            my += dy
            it += 1
            if ti.abs(dx) < tol and ti.abs(dy) < tol:
                it = iterations  # this point has converged
        points[k, 0] = mx
        points[k, 1] = my
        for i, j in ti.ndrange(S, S):
            patches[k, i, j] = _bilinear(img, mx - half + j, my - half + i)
        match[k] = _plane_match(patches, first, k, sxx)


def relocate_points(device, image, predicted, previous, first, consts, iterations, points, patches, match):
    c = constant(device, consts.astype("float32"))
    launch(_relocate, (image.buffer, predicted.buffer, previous.buffer, first.buffer, c.buffer, points.buffer,
                       patches.buffer, match.buffer), (current_arch() == "cpu",), scalars=(iterations,))  # fmt: skip

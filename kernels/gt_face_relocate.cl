// Feature-point re-localisation (paper 003 eq. 14): the same as
// gputrack/backends/reference/face_relocate.py, in float32. One work-item per feature point runs its
// Gauss-Newton iterations, samples its patch at the point found and matches it with its template; the
// patch's samples are not stored between the passes over it (each pass samples the image again).
// img (H, W); pred (K, 2); prev, first, patches (K, S, S); points (K, 2); match (K,);
// c: rho, eps, max_step, contrast, tol, min_std, singular, shading (gputrack/ops/face_relocate.py).

// the image at (x, y), the coordinates clipped into it first
static float gt_fr_bilinear(__global const float *img, const int H, const int W, const float x, const float y) {
    const float xc = fmin(fmax(x, 0.0f), (float)(W - 1)), yc = fmin(fmax(y, 0.0f), (float)(H - 1));
    const int x0 = min((int)xc, W - 2), y0 = min((int)yc, H - 2);  // floor: xc, yc >= 0
    const float fx = xc - (float)x0, fy = yc - (float)y0;
    __global const float *r = img + (long)y0 * W + x0;
    const float top = r[0] + fx * (r[1] - r[0]), bot = r[W] + fx * (r[W + 1] - r[W]);
    return top + fy * (bot - top);
}

// (mean, gain, bx, by) of n = S * S values whose sums, shifted by c0, are s, ss and, times the offsets
// x, y from the patch's centre, sx, sy: gain (v - mean - bx x - by y) has zero mean and standard deviation
// contrast (at least min_std); the ramp (bx, by) is the least-squares one with shading, else 0. sxx: the sum
// of x * x over the patch (the same for y; x, y, 1 are orthogonal on the square grid).
static float4 gt_fr_normaliser(const float c0, const float s, const float ss, const float sx, const float sy,
                               const float n, const float sxx, const float contrast, const float min_std,
                               const float shading) {
    const float bx = shading != 0.0f ? sx / sxx : 0.0f, by = shading != 0.0f ? sy / sxx : 0.0f;
    const float var = fmax(ss / n - (s / n) * (s / n) - (bx * bx + by * by) * sxx / n, 0.0f);
    return (float4)(c0 + s / n, contrast / fmax(sqrt(var), min_std), bx, by);
}

// gt_fr_normaliser of a stored S x S patch
static float4 gt_fr_stored(__global const float *p, const int S, const float sxx, const float contrast,
                           const float min_std, const float shading) {
    const float p0 = p[0], ctr = 0.5f * (float)(S - 1);
    float s = 0.0f, ss = 0.0f, sx = 0.0f, sy = 0.0f;
    for (int i = 0; i < S; ++i)
        for (int j = 0; j < S; ++j) {
            const float v = p[i * S + j] - p0;
            s += v;
            ss += v * v;
            sx += v * ((float)j - ctr);
            sy += v * ((float)i - ctr);
        }
    return gt_fr_normaliser(p0, s, ss, sx, sy, (float)(S * S), sxx, contrast, min_std, shading);
}

// the NCC of the S x S patches a and b, each with its least-squares plane (mean and ramp) off; 0 where
// either is flat (its residual's standard deviation at most 1e-6 (|mean| + 1)). Two passes: the planes,
// then the residuals' products.
static float gt_fr_plane_match(__global const float *a, __global const float *b, const int S, const float sxx) {
    const float ctr = 0.5f * (float)(S - 1), n = (float)(S * S);
    float sa = 0.0f, sb = 0.0f, xa = 0.0f, ya = 0.0f, xb = 0.0f, yb = 0.0f;
    for (int i = 0; i < S; ++i)
        for (int j = 0; j < S; ++j) {
            const float va = a[i * S + j], vb = b[i * S + j], ox = (float)j - ctr, oy = (float)i - ctr;
            sa += va;
            sb += vb;
            xa += va * ox;
            ya += va * oy;
            xb += vb * ox;
            yb += vb * oy;
        }
    const float ma = sa / n, mb = sb / n, bxa = xa / sxx, bya = ya / sxx, bxb = xb / sxx, byb = yb / sxx;
    float ab = 0.0f, aa = 0.0f, bb = 0.0f;
    for (int i = 0; i < S; ++i)
        for (int j = 0; j < S; ++j) {
            const float ox = (float)j - ctr, oy = (float)i - ctr;
            const float ra = a[i * S + j] - ma - bxa * ox - bya * oy, rb = b[i * S + j] - mb - bxb * ox - byb * oy;
            ab += ra * rb;
            aa += ra * ra;
            bb += rb * rb;
        }
    const float fa = 1e-6f * (fabs(ma) + 1.0f), fb = 1e-6f * (fabs(mb) + 1.0f);
    if (!(aa / n > fa * fa) || !(bb / n > fb * fb)) return 0.0f;
    return ab / sqrt(aa * bb);
}

__kernel void gt_face_relocate(__global const float *img, __global const float *pred, __global const float *prev,
                               __global const float *first, __global const float *c, __global float *points,
                               __global float *patches, __global float *match, const int K, const int S, const int H,
                               const int W, const int iterations) {
    const int k = get_global_id(0);
    if (k >= K) return;
    const float rho = c[0], eps = c[1], max_step = c[2], contrast = c[3], tol = c[4], min_std = c[5];
    const float singular = c[6], shading = c[7];
    const float n = (float)(S * S), ctr = 0.5f * (float)(S - 1);
    const float sxx = (float)S * (float)S * (float)(S * S - 1) / 12.0f;  // sum of x * x over the patch
    __global const float *pk = prev + (long)k * S * S, *fk = first + (long)k * S * S;
    float4 nprev = (float4)(0.0f, 1.0f, 0.0f, 0.0f), nfirst = nprev;  // (mean, gain, bx, by): raw intensities
    if (contrast > 0.0f) {
        nprev = gt_fr_stored(pk, S, sxx, contrast, min_std, 0.0f);  // against the previous frame: no ramp off
        nfirst = gt_fr_stored(fk, S, sxx, contrast, min_std, shading);
    }
    const float px = pred[2 * k], py = pred[2 * k + 1];
    float mx = px, my = py;
    for (int it = 0; it < iterations; ++it) {
        const float x0 = mx - ctr, y0 = my - ctr;  // patch pixel (0, 0)
        // the current patch's normalisers (mean, gain, bx, by), its ring alike: na against the previous
        // frame's patch, nb against the first frame's (its ramp off too with shading)
        float4 na = (float4)(0.0f, 1.0f, 0.0f, 0.0f), nb = na;
        if (contrast > 0.0f) {
            const float c0 = gt_fr_bilinear(img, H, W, x0, y0);
            float s = 0.0f, ss = 0.0f, sx = 0.0f, sy = 0.0f;
            for (int i = 0; i < S; ++i)
                for (int j = 0; j < S; ++j) {
                    const float v = gt_fr_bilinear(img, H, W, x0 + j, y0 + i) - c0;
                    s += v;
                    ss += v * v;
                    sx += v * ((float)j - ctr);
                    sy += v * ((float)i - ctr);
                }
            na = gt_fr_normaliser(c0, s, ss, sx, sy, n, sxx, contrast, min_std, 0.0f);
            nb = gt_fr_normaliser(c0, s, ss, sx, sy, n, sxx, contrast, min_std, shading);
        }
        float a00 = 0.0f, a01 = 0.0f, a11 = 0.0f, g0 = 0.0f, g1 = 0.0f;
        for (int i = 0; i < S; ++i)
            for (int j = 0; j < S; ++j) {  // eq. 14's appearance terms
                const float x = x0 + j, y = y0 + i, ox = (float)j - ctr, oy = (float)i - ctr;
                // the image's central differences and value there
                const float ix = 0.5f * (gt_fr_bilinear(img, H, W, x + 1, y) - gt_fr_bilinear(img, H, W, x - 1, y));
                const float iy = 0.5f * (gt_fr_bilinear(img, H, W, x, y + 1) - gt_fr_bilinear(img, H, W, x, y - 1));
                const float v = gt_fr_bilinear(img, H, W, x, y);
                const float gxa = na.y * (ix - na.z), gya = na.y * (iy - na.w);
                const float gxb = nb.y * (ix - nb.z), gyb = nb.y * (iy - nb.w);
                const float ea = na.y * (v - na.x - na.z * ox - na.w * oy)
                                 - nprev.y * (pk[i * S + j] - nprev.x - nprev.z * ox - nprev.w * oy);
                const float eb = nb.y * (v - nb.x - nb.z * ox - nb.w * oy)
                                 - nfirst.y * (fk[i * S + j] - nfirst.x - nfirst.z * ox - nfirst.w * oy);
                a00 += rho * gxa * gxa + gxb * gxb;
                a01 += rho * gxa * gya + gxb * gyb;
                a11 += rho * gya * gya + gyb * gyb;
                g0 += rho * gxa * ea + gxb * eb;
                g1 += rho * gya * ea + gyb * eb;
            }
        a00 += eps;
        a11 += eps;
        g0 += eps * (mx - px);
        g1 += eps * (my - py);
        const float det = a00 * a11 - a01 * a01;
        float dx = 0.0f, dy = 0.0f;
        if (fabs(det) > singular) {
            dx = (a01 * g1 - a11 * g0) / det;
            dy = (a01 * g0 - a00 * g1) / det;
        }
        if (!isfinite(dx) || !isfinite(dy)) dx = dy = 0.0f;
        const float f = fmin(1.0f, max_step / fmax(sqrt(dx * dx + dy * dy), 1e-12f));
        dx *= f;
        dy *= f;
        mx += dx;
        my += dy;
        if (fabs(dx) < tol && fabs(dy) < tol) break;  // this point has converged
    }
    points[2 * k] = mx;
    points[2 * k + 1] = my;
    __global float *out = patches + (long)k * S * S;
    for (int i = 0; i < S; ++i)
        for (int j = 0; j < S; ++j) out[i * S + j] = gt_fr_bilinear(img, H, W, mx - ctr + j, my - ctr + i);
    match[k] = gt_fr_plane_match(out, fk, S, sxx);
}

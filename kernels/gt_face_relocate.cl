// Feature-point re-localisation (paper 003 eq. 14): the same as
// gputrack/backends/reference/face_relocate.py, in float32. One work-item per feature point runs its
// Gauss-Newton iterations and samples its patch at the point found; the patch's samples are not
// stored between the passes over it (each pass samples the image again).
// img (H, W); pred (K, 2); prev, first, patches (K, S, S); points (K, 2);
// c: rho, eps, max_step, contrast, tol, min_std, singular (gputrack/ops/face_relocate.py).

// the image at (x, y), the coordinates clipped into it first
static float gt_fr_bilinear(__global const float *img, const int H, const int W, const float x, const float y) {
    const float xc = fmin(fmax(x, 0.0f), (float)(W - 1)), yc = fmin(fmax(y, 0.0f), (float)(H - 1));
    const int x0 = min((int)xc, W - 2), y0 = min((int)yc, H - 2);  // floor: xc, yc >= 0
    const float fx = xc - (float)x0, fy = yc - (float)y0;
    __global const float *r = img + (long)y0 * W + x0;
    const float top = r[0] + fx * (r[1] - r[0]), bot = r[W] + fx * (r[W + 1] - r[W]);
    return top + fy * (bot - top);
}

// contrast / max(std, min_std) of n values whose shifted sum and sum of squares are s, ss
static float gt_fr_gain(const float s, const float ss, const float n, const float contrast, const float min_std) {
    const float var = fmax(ss / n - (s / n) * (s / n), 0.0f);
    return contrast / fmax(sqrt(var), min_std);
}

// (mean, gain) of a stored S x S patch (sums shifted by its first value)
static float2 gt_fr_stored(__global const float *p, const int S, const float contrast, const float min_std) {
    const float n = (float)(S * S), p0 = p[0];
    float s = 0.0f, ss = 0.0f;
    for (int q = 0; q < S * S; ++q) {
        const float v = p[q] - p0;
        s += v;
        ss += v * v;
    }
    return (float2)(p0 + s / n, gt_fr_gain(s, ss, n, contrast, min_std));
}

__kernel void gt_face_relocate(__global const float *img, __global const float *pred, __global const float *prev,
                               __global const float *first, __global const float *c, __global float *points,
                               __global float *patches, const int K, const int S, const int H, const int W,
                               const int iterations) {
    const int k = get_global_id(0);
    if (k >= K) return;
    const float rho = c[0], eps = c[1], max_step = c[2], contrast = c[3], tol = c[4], min_std = c[5];
    const float singular = c[6];
    const float n = (float)(S * S), ctr = 0.5f * (float)(S - 1);
    __global const float *pk = prev + (long)k * S * S, *fk = first + (long)k * S * S;
    float2 mgp = (float2)(0.0f, 1.0f), mgf = (float2)(0.0f, 1.0f);
    if (contrast > 0.0f) {
        mgp = gt_fr_stored(pk, S, contrast, min_std);
        mgf = gt_fr_stored(fk, S, contrast, min_std);
    }
    const float px = pred[2 * k], py = pred[2 * k + 1];
    float mx = px, my = py;
    for (int it = 0; it < iterations; ++it) {
        const float x0 = mx - ctr, y0 = my - ctr;  // patch pixel (0, 0)
        float mi = 0.0f, gi = 1.0f;
        if (contrast > 0.0f) {  // the current patch's mean and gain (its ring scaled alike)
            const float c0 = gt_fr_bilinear(img, H, W, x0, y0);
            float s = 0.0f, ss = 0.0f;
            for (int i = 0; i < S; ++i)
                for (int j = 0; j < S; ++j) {
                    const float v = gt_fr_bilinear(img, H, W, x0 + j, y0 + i) - c0;
                    s += v;
                    ss += v * v;
                }
            mi = c0 + s / n;
            gi = gt_fr_gain(s, ss, n, contrast, min_std);
        }
        float a00 = 0.0f, a01 = 0.0f, a11 = 0.0f, g0 = 0.0f, g1 = 0.0f;
        for (int i = 0; i < S; ++i)
            for (int j = 0; j < S; ++j) {
                const float x = x0 + j, y = y0 + i;
                const float gx = 0.5f * gi * (gt_fr_bilinear(img, H, W, x + 1, y) - gt_fr_bilinear(img, H, W, x - 1, y));
                const float gy = 0.5f * gi * (gt_fr_bilinear(img, H, W, x, y + 1) - gt_fr_bilinear(img, H, W, x, y - 1));
                const float e = (rho + 1.0f) * gi * (gt_fr_bilinear(img, H, W, x, y) - mi)
                                - rho * mgp.y * (pk[i * S + j] - mgp.x) - mgf.y * (fk[i * S + j] - mgf.x);  // eq. 14
                a00 += gx * gx;
                a01 += gx * gy;
                a11 += gy * gy;
                g0 += gx * e;
                g1 += gy * e;
            }
        a00 = (rho + 1.0f) * a00 + eps;
        a01 = (rho + 1.0f) * a01;
        a11 = (rho + 1.0f) * a11 + eps;
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
}

// Zero-mean NCC of a template with the bilinear image patch at a point (paper 003 eq. 13).
// Conventions: gputrack/ops/ncc.py.
#define GT_FLAT 1e-6f
#ifndef GT_INTENSITY_MAX
#error "gt_ncc.cl needs the ABI defines (gputrack.abi.cl_defines)"
#endif

// A pixel or template value clamped to [-GT_INTENSITY_MAX, GT_INTENSITY_MAX] (gputrack/abi.py
// INTENSITY_MAX; gputrack/ops/ncc.py); NaN stays NaN.
inline float gt_ncc_clamp(const float x)
{
    const float m = (float)GT_INTENSITY_MAX;
    return x > m ? m : (x < -m ? -m : x);
}

// The NCC of the shifted sums (see gt_ncc_one): 0 for a flat patch or template.
inline float gt_ncc_finish(const float n, const float p0, const float t0, const float sp, const float st,
                           const float spp, const float stt, const float spt)
{
    // centred sums (each product of a sum with a mean: no float32 overflow below 2**48 per value)
    const float vp = spp - sp * (sp / n), vt = stt - st * (st / n), cv = spt - sp * (st / n);
    const float mp = p0 + sp / n, mt = t0 + st / n;
    // a flat patch or template (standard deviation <= 1e-6 (|mean| + 1)) scores 0
    const float fp = GT_FLAT * (fabs(mp) + 1.0f), ft = GT_FLAT * (fabs(mt) + 1.0f);
    if (!(vp > n * fp * fp && vt > n * ft * ft))
        return 0.0f;
    return clamp(cv / (sqrt(vp) * sqrt(vt)), -1.0f, 1.0f);
}

// The vector path of gt_ncc_one for s % W == 0 (W = 4, 8): per row, W patch pixels a step from two
// W-wide loads of each image row (left and right neighbours), with the scalar loop's bilinear weights,
// clamps (select keeps NaN, as gt_ncc_clamp), shifts (p0 the first patch pixel, t0 the first template
// value) and per-row blocking of the five sums (the W lanes summed per row, then over the rows).
#define GT_NCC_CLAMPV(W, x) select(select(x, (float##W)(-m), (x) < -m), (float##W)m, (x) > m)
#define GT_NCC_HSUM4(x) (((x).s0 + (x).s1) + ((x).s2 + (x).s3))
#define GT_NCC_HSUM8(x) GT_NCC_HSUM4((x).lo + (x).hi)
#define GT_NCC_ROWS(W)                                                                                    \
    inline float gt_ncc_rows##W(__global const float *img, const int w, const int xb, const int yb,     \
                                const float a, const float bw, __global const float *t, const int s,    \
                                const float t0, const float st, const float stt, const float n)         \
    {                                                                                                   \
        const float m = (float)GT_INTENSITY_MAX;                                                        \
        float p0 = 0.0f, sp = 0.0f, spp = 0.0f, spt = 0.0f;                                             \
        for (int i = 0; i < s; ++i) {                                                                   \
            __global const float *top = img + (size_t)(yb + i) * (size_t)w + xb;                        \
            __global const float *bot = top + w;                                                        \
            __global const float *tr = t + i * s;                                                       \
            float##W rp = 0.0f, rpp = 0.0f, rpt = 0.0f;                                                 \
            for (int jj = 0; jj < s; jj += W) {                                                         \
                const float##W lt = vload##W(0, top + jj), nt = vload##W(0, top + jj + 1);              \
                const float##W lb = vload##W(0, bot + jj), nb = vload##W(0, bot + jj + 1);              \
                const float##W clt = GT_NCC_CLAMPV(W, lt), cnt = GT_NCC_CLAMPV(W, nt);                  \
                const float##W clb = GT_NCC_CLAMPV(W, lb), cnb = GT_NCC_CLAMPV(W, nb);                  \
                const float##W T = vload##W(0, tr + jj); /* the shifted template (gt_ncc_templates) */  \
                const float##W tp = clt + a * (cnt - clt), bt = clb + a * (cnb - clb);                  \
                const float##W P0 = tp + bw * (bt - tp); /* patch pixels (i, jj .. jj + W - 1) */       \
                if (i == 0 && jj == 0)                                                                  \
                    p0 = P0.s0;                                                                         \
                const float##W P = P0 - p0;                                                             \
                rp += P;                                                                                \
                rpp += P * P;                                                                           \
                rpt += P * T;                                                                           \
            }                                                                                           \
            sp += GT_NCC_HSUM##W(rp);                                                                   \
            spp += GT_NCC_HSUM##W(rpp);                                                                 \
            spt += GT_NCC_HSUM##W(rpt);                                                                 \
        }                                                                                               \
        return gt_ncc_finish(n, p0, t0, sp, st, spp, stt, spt);                                         \
    }
GT_NCC_ROWS(4)
GT_NCC_ROWS(8)

// The vector path of gt_ncc_one for s == W (W = 4, 8, 16; the face tracker's s = 16): a row of the patch
// is one float##W. Each of the s + 1 image rows under the patch is loaded (W pixels and the next one)
// and interpolated across once, then each patch row between two of them; the sums stay per lane until
// the end. Clamps, shifts and weights as the scalar loop. The face tracker's score call (1000 x 10
// patches of 16 x 16, perf/bench_face.py's score case) took 1.15-1.25 ms on PoCL, three runs, against
// 1.12-3.03 ms through gt_ncc_rows8 (four image rows loaded per patch row; two of the three runs
// took 2.8-3.0 ms).
#define GT_NCC_NEXT4(v, e) (float4)((v).s123, e)
#define GT_NCC_NEXT8(v, e) (float8)((v).s1234, (v).s567, e)
#define GT_NCC_NEXT16(v, e) (float16)((v).s1234, (v).s5678, (v).s9abc, (v).sdef, e)
#define GT_NCC_HSUM16(x) GT_NCC_HSUM8((x).lo + (x).hi)
#define GT_NCC_LANES(W)                                                                                    \
    inline float##W gt_ncc_across##W(__global const float *row, const float a)                          \
    {                                                                                                   \
        const float m = (float)GT_INTENSITY_MAX;                                                        \
        const float##W l = vload##W(0, row);                                                            \
        const float##W cl = GT_NCC_CLAMPV(W, l);                                                        \
        const float##W cr = GT_NCC_NEXT##W(cl, gt_ncc_clamp(row[W]));                                   \
        return cl + a * (cr - cl);                                                                      \
    }                                                                                                   \
    inline float gt_ncc_lanes##W(__global const float *img, const int w, const int xb, const int yb,    \
                                 const float a, const float bw, __global const float *t, const float t0, \
                                 const float st, const float stt)                                        \
    {                                                                                                   \
        __global const float *row = img + (size_t)yb * (size_t)w + xb;                                  \
        float##W above = gt_ncc_across##W(row, a), below = gt_ncc_across##W(row + w, a);                \
        const float p0 = above.s0 + bw * (below.s0 - above.s0);                                         \
        float##W rp = 0.0f, rpp = 0.0f, rpt = 0.0f;                                                     \
        for (int i = 0; i < W; ++i) {                                                                   \
            const float##W P = above + bw * (below - above) - p0; /* patch row i, shifted by p0 */      \
            rp += P;                                                                                    \
            rpp += P * P;                                                                               \
            rpt += P * vload##W(i, t);                                                                  \
            if (i + 1 < W) { /* image rows i + 1 and i + 2 for the next patch row */                    \
                above = below;                                                                          \
                below = gt_ncc_across##W(row + (size_t)(i + 2) * (size_t)w, a);                         \
            }                                                                                           \
        }                                                                                               \
        return gt_ncc_finish((float)(W * W), p0, t0, GT_NCC_HSUM##W(rp), st, GT_NCC_HSUM##W(rpp), stt,  \
                             GT_NCC_HSUM##W(rpt));                                                      \
    }
GT_NCC_LANES(4)
GT_NCC_LANES(8)
GT_NCC_LANES(16)

// Template k's values shifted by its first one, each clamped as the patch pixels are, into ts (K, s, s),
// and t0 and their sums st, stt into tstat (K, 4) (rows summed in order, then the rows): the same
// for every hypothesis, so computed once per call. One work-item per template.
__kernel void gt_ncc_templates(__global const float *tpl, const int nk, const int s, __global float *ts,
                               __global float *tstat)
{
    const int k = get_global_id(0);
    if (k >= nk)
        return;
    __global const float *t = tpl + (size_t)k * (size_t)(s * s);
    __global float *o = ts + (size_t)k * (size_t)(s * s);
    const float t0 = gt_ncc_clamp(t[0]);
    float st = 0.0f, stt = 0.0f;
    for (int i = 0; i < s; ++i) {
        float rt = 0.0f, rtt = 0.0f;
        for (int jj = 0; jj < s; ++jj) {
            const float T = gt_ncc_clamp(t[i * s + jj]) - t0;
            o[i * s + jj] = T;
            rt += T;
            rtt += T * T;
        }
        st += rt;
        stt += rtt;
    }
    tstat[4 * k] = t0;
    tstat[4 * k + 1] = st;
    tstat[4 * k + 2] = stt;
    tstat[4 * k + 3] = 0.0f;
}

// The NCC of the patch at (u, v) with template t (shifted, from gt_ncc_templates) whose first value
// and sums are t0, st, stt.
inline float gt_ncc_one(const float u, const float v, __global const float *t, const float t0, const float st,
                        const float stt, const int s, __global const float *img, const int h, const int w)
{
    const float ctr = 0.5f * (float)(s - 1);
    const float u0 = u - ctr, v0 = v - ctr, u1 = u + ctr, v1 = v + ctr;
    // the whole patch must lie inside the image (NaN fails the tests)
    if (!(u0 >= 0.0f && u1 <= (float)(w - 1) && v0 >= 0.0f && v1 <= (float)(h - 1)))
        return 0.0f;
    const float n = (float)(s * s);
    // one pass over the patch; sums of values shifted by the first patch and template values
    // (so the centred sums below do not cancel), accumulated per row then over the rows
    float p0 = 0.0f;
    float sp = 0.0f, spp = 0.0f, spt = 0.0f;
    if (s < w && s < h) {
        // inside the image every patch pixel has the same bilinear weights: one base pixel (the
        // last column and row start one pixel in with weight 1 where the patch touches the border,
        // as x0 = min(floor(x), w - 2) does) and two new loads per pixel along a row
        const int xb = min((int)u0, w - 1 - s), yb = min((int)v0, h - 1 - s);
        const float a = u0 - (float)xb, bw = v0 - (float)yb;
        // a row of the patch in one vector where s is 4, 8 or 16 (the face tracker's); else s % 8 == 0:
        // eight pixels a step, else four (fastest on PoCL)
        if (s == 16)
            return gt_ncc_lanes16(img, w, xb, yb, a, bw, t, t0, st, stt);
        if (s == 8)
            return gt_ncc_lanes8(img, w, xb, yb, a, bw, t, t0, st, stt);
        if (s == 4)
            return gt_ncc_lanes4(img, w, xb, yb, a, bw, t, t0, st, stt);
        if ((s & 7) == 0)
            return gt_ncc_rows8(img, w, xb, yb, a, bw, t, s, t0, st, stt, n);
        if ((s & 3) == 0)
            return gt_ncc_rows4(img, w, xb, yb, a, bw, t, s, t0, st, stt, n);
        for (int i = 0; i < s; ++i) {
            __global const float *top = img + (size_t)(yb + i) * (size_t)w + xb;
            __global const float *bot = top + w;
            float lt = gt_ncc_clamp(top[0]), lb = gt_ncc_clamp(bot[0]);
            float rp = 0.0f, rpp = 0.0f, rpt = 0.0f;
            for (int jj = 0; jj < s; ++jj) {
                const float nt = gt_ncc_clamp(top[jj + 1]), nb = gt_ncc_clamp(bot[jj + 1]);
                const float tp = lt + a * (nt - lt), bt = lb + a * (nb - lb);
                const float P0 = tp + bw * (bt - tp);  // patch pixel (i, jj), bilinear
                lt = nt;
                lb = nb;
                if (i == 0 && jj == 0)
                    p0 = P0;
                const float P = P0 - p0, T = t[i * s + jj];
                rp += P;
                rpp += P * P;
                rpt += P * T;
            }
            sp += rp;
            spp += rpp;
            spt += rpt;
        }
        return gt_ncc_finish(n, p0, t0, sp, st, spp, stt, spt);
    }
    for (int i = 0; i < s; ++i) {  // a patch as large as the image: each pixel's own bilinear weights
        const float vv = v + ((float)i - ctr);
        const int y0 = min((int)vv, h - 2);
        const float bw = vv - (float)y0;
        float rp = 0.0f, rpp = 0.0f, rpt = 0.0f;
        for (int jj = 0; jj < s; ++jj) {
            const float uu = u + ((float)jj - ctr);
            const int x0 = min((int)uu, w - 2);
            const float a = uu - (float)x0;
            const int k = y0 * w + x0;
            const float i00 = gt_ncc_clamp(img[k]), i01 = gt_ncc_clamp(img[k + 1]);
            const float i10 = gt_ncc_clamp(img[k + w]), i11 = gt_ncc_clamp(img[k + w + 1]);
            const float top = i00 + a * (i01 - i00), bot = i10 + a * (i11 - i10);
            const float P0 = top + bw * (bot - top);  // patch pixel (i, jj), bilinear
            if (i == 0 && jj == 0)
                p0 = P0;
            const float P = P0 - p0, T = t[i * s + jj];
            rp += P;
            rpp += P * P;
            rpt += P * T;
        }
        sp += rp;
        spp += rpp;
        spt += rpt;
    }
    return gt_ncc_finish(n, p0, t0, sp, st, spp, stt, spt);
}

// One work-item per (hypothesis, point): ncc (B, K).
// ts, tstat: from gt_ncc_templates.
__kernel void gt_patch_ncc_points(__global const float *pts, const int nb, const int nk, __global const float *ts,
                                  __global const float *tstat, const int s, __global const float *img, const int h,
                                  const int w, __global float *ncc)
{
    const int gid = get_global_id(0);
    if (gid >= nb * nk)
        return;
    const int kk = gid % nk;
    ncc[gid] = gt_ncc_one(pts[2 * gid], pts[2 * gid + 1], ts + (size_t)kk * (size_t)(s * s), tstat[4 * kk],
                          tstat[4 * kk + 1], tstat[4 * kk + 2], s, img, h, w);
}

// One work-item per hypothesis: N(u) = sum over the K points (eq. 13), (B,).
__kernel void gt_patch_ncc(__global const float *pts, const int nb, const int nk, __global const float *ts,
                           __global const float *tstat, const int s, __global const float *img, const int h,
                           const int w, __global float *out)
{
    const int b = get_global_id(0);
    if (b >= nb)
        return;
    float acc = 0.0f;
    for (int kk = 0; kk < nk; ++kk) {
        const int p = b * nk + kk;
        acc += gt_ncc_one(pts[2 * p], pts[2 * p + 1], ts + (size_t)kk * (size_t)(s * s), tstat[4 * kk],
                          tstat[4 * kk + 1], tstat[4 * kk + 2], s, img, h, w);
    }
    out[b] = acc;
}

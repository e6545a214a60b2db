// Sparse-template RGB-D cost and residuals (paper 000 eq. 17-21). Conventions: gputrack/ops/template.py.
//
// gt_rgbd: one work-item evaluates LANES consecutive hypotheses (explicit vector lanes, see
// gt_lanes.clh) over every template point, with the points grouped by part so that each part's
// transform is loaded once. Sums are blocked (CHUNK points per partial sum) so float32 keeps its
// accuracy for thousands of points. Build options: LANES (1, 4, 8, 16), RESIDUALS (0: costs,
// 1: per-point residuals of eq. 20-21), REUSE (costs only; see below).
//
// Re-use (a particle filter's stage that samples only some parts' parameters, eq. 13-16): the nb
// hypotheses are nsrc blocks of samples (hypothesis b belongs to source b nsrc / nb, as in
// gt_sample_around), and the parts with moved[j] == 0 are posed in every sample of a block as in
// its first sample. REUSE=1 (SOURCE) evaluates the first sample of each block (lane l of work-item g:
// block s = g LANES + l) and writes cache row s: [I_i (n), valid_i (n), per RGB part j
// sum T, sum T^2, sum T I over its valid points (3 rparts), per depth part j the sum of rho_c'
// (dparts)]. REUSE=2 evaluates every hypothesis, projecting only the moved parts: the other
// parts' samples and sums come from the cache row of the hypothesis' source. The scores equal
// the full evaluation's to float rounding (the cached sums are added apart from the blocked ones).
//
// A central-difference plan (REUSE=3, residuals only; paper 000 Fig. 2, gputrack/ops/pose_residuals.py):
// the nb rows are nsrc blocks of stride = nb / nsrc rows (a problem's point, then its parameters'
// moved points); REUSE=1 has cached each problem's point. Work-item g takes the ngroups plan's
// rows order[g LANES + l], which move the same parts (moved[g nj + j]), projects only those parts
// and writes only their residuals, the other parts' sums coming from the cache (eq. 17's alpha and
// beta run over every valid point). A work-item whose rows pose an unmoved part differently from
// their problem's point (another layout) evaluates every part.
#include "gt_lanes.clh"

#ifndef RESIDUALS
#define RESIDUALS 0
#endif
#ifndef REUSE
#define REUSE 0
#endif
#define CHUNK 64
#define GT_TINY 1e-12f
#define GT_BIG 3.0e38f
#ifndef GT_INTENSITY_MAX
#error "gt_template.cl needs the ABI defines (gputrack.abi.cl_defines)"
#endif
// A gray pixel clamped to [-GT_INTENSITY_MAX, GT_INTENSITY_MAX] (gputrack/abi.py INTENSITY_MAX); NaN stays NaN.
inline realv gt_clamp_i(const realv x)
{
    const float m = (float)GT_INTENSITY_MAX;
    return select(select(x, (realv)(-m), x < -m), (realv)m, x > m);
}

// The camera-from-part transform rows of part j for the lanes' hypotheses bl.
typedef struct {
    realv r[12];
} gt_pose;

inline gt_pose gt_load_pose(__global const float *tf, const intv bl, const int nj, const int j)
{
    gt_pose p;
    const intv base = (bl * nj + j) * 12;
    for (int e = 0; e < 12; ++e)
        p.r[e] = GATHER(tf, base + e);
    return p;
}

__kernel void gt_rgbd(__global const float *tf, const int nb, const int nj,
                      __global const float *rpts, __global const int *rindex, const int rparts, const int n,
                      __global const float *dpts, __global const int *dindex, const int dparts, const int m,
                      __global const float *gray, __global const float *dimg, const int h, const int w,
                      const float fx, const float fy, const float cx, const float cy,
                      const float lam, const float c_rgb, const float c_depth, const float depth_tol,
                      __global float *sample, __global char *valid,
                      __global float *total, __global float *eps_c, __global float *eps_d, __global float *res,
                      __global const int *moved, __global float *cache, const int nsrc,
                      __global const int *order, const int ngroups)
{
    const int g = get_global_id(0);
    const int cw = 2 * n + 3 * rparts + dparts;  // a cache row (REUSE)
#if REUSE == 1
    const int b0 = g * LANES;
    if (b0 >= nsrc)
        return;
    const intv sl = min(b0 + LANE_IDS, nsrc - 1);  // the lanes' sources (past nsrc: the last one again)
    const intv bl = (sl * nb + nsrc - 1) / nsrc;    // the first sample of each block
    const intv crow = sl * cw;
#elif REUSE == 3
    if (g >= ngroups)
        return;
    const int b0 = g * LANES;
    int rows[LANES];  // the lanes' rows
    for (int l = 0; l < LANES; ++l)
        rows[l] = order[b0 + l];
    const intv bl = VLOADI(0, rows);
    const int stride = nb / nsrc;
    int every = 0;  // a row poses an unmoved part unlike its problem's point: evaluate every part
    for (int j = 0; j < nj; ++j) {
        if (moved[g * nj + j])
            continue;
        for (int l = 0; l < LANES; ++l) {
            __global const float *a = tf + ((size_t)rows[l] * (size_t)nj + (size_t)j) * 12;
            __global const float *b = tf + ((size_t)(rows[l] - rows[l] % stride) * (size_t)nj + (size_t)j) * 12;
            for (int e = 0; e < 12; ++e)
                every |= a[e] != b[e];
        }
    }
#else
    const int b0 = g * LANES;
    if (b0 >= nb)
        return;
    const intv bl = min(b0 + LANE_IDS, nb - 1);  // lanes past the batch repeat the last hypothesis
#endif
#if REUSE >= 2
    const intv crow = (bl * nsrc / nb) * cw;      // each lane's source row (nb nsrc < 2**31: the op checks)
    realv cT = 0.0f, cTT = 0.0f, cTI = 0.0f, cD = 0.0f;  // the cached parts' sums
#endif
#if REUSE == 3
#define GT_MOVED(j) (every || moved[g * nj + (j)])
#else
#define GT_MOVED(j) (moved[j])
#endif
    const float wm1 = (float)(w - 1), hm1 = (float)(h - 1);
    const float cc = c_rgb * c_rgb, cd = c_depth * c_depth;
    const float wc = sqrt(1.0f - lam), wd = sqrt(lam);
    const size_t srow = (size_t)g * (size_t)n;
    // index = [start (parts + 1), perm (points)]: part j owns points start[j]:start[j+1], and
    // (grouped) point i is the caller's point perm[i]
    __global const int *rstart = rindex, *rperm = rindex + rparts + 1;
    __global const int *dstart = dindex, *dperm = dindex + dparts + 1;

    // ---- RGB pass 1: samples I_i, validity, and the sums over the valid points (eq. 17)
    realv sT = 0.0f, sTT = 0.0f, sTI = 0.0f, bT = 0.0f, bTT = 0.0f, bTI = 0.0f;
    int cnt = 0;
    for (int j = 0; j < rparts; ++j) {
#if REUSE >= 2
        if (!GT_MOVED(j)) {
            cT += GATHER(cache, crow + (2 * n + 3 * j));
            cTT += GATHER(cache, crow + (2 * n + 3 * j + 1));
            cTI += GATHER(cache, crow + (2 * n + 3 * j + 2));
            continue;
        }
#endif
#if REUSE == 1
        sT = 0.0f; sTT = 0.0f; sTI = 0.0f; bT = 0.0f; bTT = 0.0f; bTI = 0.0f;  // part j's own sums
        cnt = 0;
#endif
        const gt_pose P = gt_load_pose(tf, bl, nj, j);
        for (int i = rstart[j]; i < rstart[j + 1]; ++i) {
            const float x = rpts[4 * i], y = rpts[4 * i + 1], z = rpts[4 * i + 2], T = rpts[4 * i + 3];
            const realv X = P.r[0] * x + P.r[1] * y + P.r[2] * z + P.r[3];  // eq. 4
            const realv Y = P.r[4] * x + P.r[5] * y + P.r[6] * z + P.r[7];
            const realv Z = P.r[8] * x + P.r[9] * y + P.r[10] * z + P.r[11];
            const realv u = fx * (X / Z) + cx;  // eq. 5
            const realv v = fy * (Y / Z) + cy;
            const intv ok = (Z > 0.0f) & (Z < GT_BIG) & (u >= 0.0f) & (u <= wm1) & (v >= 0.0f) & (v <= hm1);
            const realv uc = select((realv)0.0f, u, ok), vc = select((realv)0.0f, v, ok);
            const intv x0 = min(TO_INT(uc), w - 2), y0 = min(TO_INT(vc), h - 2);
            const intv k = y0 * w + x0;
            const realv a = uc - TO_REAL(x0), bw = vc - TO_REAL(y0);
            const realv i00 = gt_clamp_i(GATHER(gray, k)), i01 = gt_clamp_i(GATHER(gray, k + 1));
            const realv i10 = gt_clamp_i(GATHER(gray, k + w)), i11 = gt_clamp_i(GATHER(gray, k + w + 1));
            const realv top = i00 + a * (i01 - i00), bot = i10 + a * (i11 - i10);
            const realv I = top + bw * (bot - top);  // sec. 3.5: bilinear
            const realv Tv = select((realv)0.0f, (realv)T, ok);
            bT += Tv;
            bTT += Tv * T;
            bTI += Tv * I;
#if REUSE == 1
            SCATTER(cache, crow + i, I);
            SCATTER(cache, crow + (n + i), select((realv)0.0f, (realv)1.0f, ok));
#else
            VSTORER(I, srow + i, sample);
            VSTOREC(TO_CHAR(ok), srow + i, valid);
#endif
            if (++cnt == CHUNK) {
                sT += bT; sTT += bTT; sTI += bTI;
                bT = 0.0f; bTT = 0.0f; bTI = 0.0f;
                cnt = 0;
            }
        }
#if REUSE == 1
        SCATTER(cache, crow + (2 * n + 3 * j), sT + bT);
        SCATTER(cache, crow + (2 * n + 3 * j + 1), sTT + bTT);
        SCATTER(cache, crow + (2 * n + 3 * j + 2), sTI + bTI);
#endif
    }
#if REUSE >= 2
    sT += bT + cT; sTT += bTT + cTT; sTI += bTI + cTI;
#else
    sT += bT; sTT += bTT; sTI += bTI;
#endif
    const realv alpha = select((realv)0.0f, 1.0f / sT, sT > GT_TINY);              // eq. 17
    const realv beta = select((realv)0.0f, alpha * sTT / sTI, sTI > GT_TINY);      // eq. 17

    // ---- RGB pass 2: eps_C = sum rho_c(d_i) (eq. 17); residuals r_i (eq. 20-21)
    realv eC = 0.0f, blk = 0.0f;
    cnt = 0;
#if REUSE == 2
    // the lanes of a work-item nearly always share their source (blocks of nb / nsrc samples): its
    // cached samples are then loaded once for every lane
    const int c0 = LANE0(crow);
    const int same = ALL_LANES(crow == c0);
    for (int j = 0; j < rparts; ++j)
    for (int i = rstart[j]; i < rstart[j + 1]; ++i) {
        realv I;
        intv ok;
        if (moved[j]) {
            I = VLOADR(srow + i, sample);
            ok = TO_INT(VLOADC(srow + i, valid));
        } else if (same) {
            I = (realv)cache[c0 + i];
            ok = (intv)(-(cache[c0 + n + i] != 0.0f));  // every bit set: true in a vector select too
        } else {
            I = GATHER(cache, crow + i);
            ok = GATHER(cache, crow + (n + i)) != 0.0f;
        }
#elif REUSE == 3
    for (int j = 0; j < rparts; ++j)
    for (int i = (GT_MOVED(j) ? rstart[j] : rstart[j + 1]); i < rstart[j + 1]; ++i) {  // the moved parts' residuals
        const realv I = VLOADR(srow + i, sample);
        const intv ok = TO_INT(VLOADC(srow + i, valid));
#else
    for (int i = 0; i < (REUSE == 1 ? 0 : n); ++i) {  // the sources (REUSE=1) write their cache rows only
        const realv I = VLOADR(srow + i, sample);
        const intv ok = TO_INT(VLOADC(srow + i, valid));
#endif
        const realv d = beta * I - alpha * rpts[4 * i + 3];  // eq. 17: d_i
        const realv q = cc + d * d;
#if !RESIDUALS
        blk += select((realv)1.0f, d * d / q, ok);  // rho_c(d_i); an invalid point adds 1
#endif
#if RESIDUALS
        const realv r = select((realv)wc, wc * d / sqrt(q), ok);  // eq. 20-21: r_i
        float tmp[LANES];
        VSTORER(r, 0, tmp);
        const int col = rperm[i];
#if REUSE == 3
        for (int l = 0; l < LANES; ++l)
            res[(size_t)rows[l] * (size_t)(n + m) + col] = tmp[l];
#else
        for (int l = 0; l < LANES && b0 + l < nb; ++l)
            res[(size_t)(b0 + l) * (size_t)(n + m) + col] = tmp[l];
#endif
#endif
        if (++cnt == CHUNK) {
            eC += blk;
            blk = 0.0f;
            cnt = 0;
        }
    }
    eC += blk;

    // ---- depth: eps_D = sum rho_c'(d'_i) (eq. 18); residuals r'_i (eq. 20-21)
    realv eD = 0.0f;
    blk = 0.0f;
    cnt = 0;
    for (int j = 0; j < dparts; ++j) {
#if REUSE >= 2
        if (!GT_MOVED(j)) {
            cD += GATHER(cache, crow + (2 * n + 3 * rparts + j));
            continue;
        }
#endif
#if REUSE == 1
        eD = 0.0f;  // part j's own sum
        blk = 0.0f;
        cnt = 0;
#endif
        const gt_pose P = gt_load_pose(tf, bl, nj, j);
        for (int i = dstart[j]; i < dstart[j + 1]; ++i) {
            const float x = dpts[4 * i], y = dpts[4 * i + 1], z = dpts[4 * i + 2];
            const realv X = P.r[0] * x + P.r[1] * y + P.r[2] * z + P.r[3];  // eq. 4
            const realv Y = P.r[4] * x + P.r[5] * y + P.r[6] * z + P.r[7];
            const realv Z = P.r[8] * x + P.r[9] * y + P.r[10] * z + P.r[11];
            const realv u = fx * (X / Z) + cx;  // eq. 5
            const realv v = fy * (Y / Z) + cy;
            const intv ok = (Z > 0.0f) & (Z < GT_BIG) & (u >= 0.0f) & (u <= wm1) & (v >= 0.0f) & (v <= hm1);
            const realv uc = select((realv)0.0f, u, ok), vc = select((realv)0.0f, v, ok);
            const intv x0 = min(TO_INT(uc), w - 2), y0 = min(TO_INT(vc), h - 2);
            const intv k = y0 * w + x0;
            const realv d00 = GATHER(dimg, k), d01 = GATHER(dimg, k + 1);
            const realv d10 = GATHER(dimg, k + w), d11 = GATHER(dimg, k + w + 1);
            // a measurement is > 0 and finite (NaN fails both tests)
            const intv okd = ok & (fmin(fmin(d00, d01), fmin(d10, d11)) > 0.0f) & (d00 < GT_BIG) & (d01 < GT_BIG) &
                             (d10 < GT_BIG) & (d11 < GT_BIG);
            const realv a = uc - TO_REAL(x0), bw = vc - TO_REAL(y0);
            const realv top = d00 + a * (d01 - d00), bot = d10 + a * (d11 - d10);
            const realv e = top + bw * (bot - top) - Z;  // eq. 18: d'_i = Zhat - Z
            const realv dd = select((realv)0.0f, e - clamp(e, -depth_tol, depth_tol), okd);  // |e| <= depth_tol: 0
            const realv q = cd + dd * dd;
#if !RESIDUALS
            blk += select((realv)1.0f, dd * dd / q, okd);
#endif
#if RESIDUALS
            const realv r = select((realv)wd, wd * dd / sqrt(q), okd);  // eq. 20-21: r'_i
            float tmp[LANES];
            VSTORER(r, 0, tmp);
            const int col = n + dperm[i];
#if REUSE == 3
            for (int l = 0; l < LANES; ++l)
                res[(size_t)rows[l] * (size_t)(n + m) + col] = tmp[l];
#else
            for (int l = 0; l < LANES && b0 + l < nb; ++l)
                res[(size_t)(b0 + l) * (size_t)(n + m) + col] = tmp[l];
#endif
#endif
            if (++cnt == CHUNK) {
                eD += blk;
                blk = 0.0f;
                cnt = 0;
            }
        }
#if REUSE == 1
        SCATTER(cache, crow + (2 * n + 3 * rparts + j), eD + blk);
#endif
    }
#if REUSE >= 2
    eD += blk + cD;
#else
    eD += blk;
#endif

#if !RESIDUALS && REUSE != 1
    float t0[LANES], t1[LANES], t2[LANES];
    VSTORER((1.0f - lam) * eC + lam * eD, 0, t0);  // eq. 19
    VSTORER(eC, 0, t1);
    VSTORER(eD, 0, t2);
    for (int l = 0; l < LANES && b0 + l < nb; ++l) {
        total[b0 + l] = t0[l];
        eps_c[b0 + l] = t1[l];
        eps_d[b0 + l] = t2[l];
    }
#endif
}

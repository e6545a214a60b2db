// Block matching of a rectified stereo pair on the runs of a mask (gputrack/ops/stereo.py; the
// same steps as gputrack/backends/taichi/stereo.py, launched as five kernels):
//   gt_stereo_prefilter_{u8,f32}  x-Sobel clipped to [-cap, cap] plus cap, into padded GT_T
//                                 images (GT_STEREO_LANES columns on the left, Dp + LANES on
//                                 the right); NaN into the output. NDRange (H).
//   gt_stereo_left_costs          one work-item per (disparity group, tile of runs): window
//                                 column sums carried down the tile's rows, running box sums
//                                 along each run, 8 disparities in an int8 (16 in a short16).
//   gt_stereo_left_wta            one per run: winner, uniqueness, parabola vertex, marks x - d
//                                 (and its tile's marked span, by atomic min / max).
//   gt_stereo_right_costs         one per (group, tile): C_R(xr, d) at the marked positions.
//   gt_stereo_right_check         one per run: the right winners and the left-right check.
// Runs: int rows (y, x0, x1, offset, right offset); tiles: int rows (y0, y1, xa, xb, i0, i1, off, w),
// runs[order[i0 .. i1)] (gputrack/ops/stereo.py run_tiles). Cost buffers: Dp GT_T per pixel (d fastest).

// Disparities a work-item: GT_STEREO_LANES = 8 (int8, the default) or 16 (short16: the host builds
// it for uint8 input, whose costs fit in 16 bits: at most 31 * 31 * 30 = 28830). GT_T is the type
// of the prefiltered images, the column sums and the costs; comparisons are made in int.
#ifndef GT_STEREO_LANES
#define GT_STEREO_LANES 8
#endif
#if GT_STEREO_LANES == 16
typedef short GT_T;
typedef short16 GT_V;
typedef int16 GT_VI;
#define GT_VLOAD vload16
#define GT_VSTORE vstore16
#define GT_TO_VI convert_int16
#define GT_REVERSE(v) (v).sfedcba9876543210
#define GT_LANE_IDS (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15)
#else
typedef int GT_T;
typedef int8 GT_V;
typedef int8 GT_VI;
#define GT_VLOAD vload8
#define GT_VSTORE vstore8
#define GT_TO_VI(v) (v)
#define GT_REVERSE(v) (v).s76543210
#define GT_LANE_IDS (int8)(0, 1, 2, 3, 4, 5, 6, 7)
#endif

#pragma OPENCL FP_CONTRACT OFF

inline int gt_q_u8(const __global uchar *img, int i) { return (int)img[i]; }
// floor(4096 I), I clamped to [0, 1]: exact (a product by a power of two)
inline int gt_q_f32(const __global float *img, int i) { return (int)floor(fmin(fmax(img[i], 0.0f), 1.0f) * 4096.0f); }

// one work-item per row (a CPU device streams along it): NaN into the output; the prefilter on
// the rows [y0, y1) that the runs' windows read
#define GT_STEREO_PREFILTER(NAME, T, Q)                                                                  \
    __kernel void NAME(__global const T *left, __global const T *right, __global GT_T *pl, __global GT_T *pr, \
                       __global float *out, const int H, const int W, const int Wp, const int cap,        \
                       const int y0, const int y1)                                                        \
    {                                                                                                     \
        const int y = get_global_id(0);                                                                  \
        if (y >= H)                                                                                       \
            return;                                                                                       \
        for (int x = 0; x < W; ++x)                                                                       \
            out[y * W + x] = NAN;                                                                         \
        if (y < y0 || y >= y1)                                                                            \
            return;                                                                                       \
        for (int xp = 0; xp < Wp; ++xp) {                                                                 \
            const int x = xp - GT_STEREO_LANES;                                                          \
            int a = cap, b = cap;                                                                         \
            if (y >= 1 && y < H - 1 && x >= 1 && x < W - 1) {                                             \
                const int u = (y - 1) * W + x, c = y * W + x, d = (y + 1) * W + x;                        \
                int s = (Q(left, u + 1) + 2 * Q(left, c + 1) + Q(left, d + 1))                            \
                        - (Q(left, u - 1) + 2 * Q(left, c - 1) + Q(left, d - 1));                         \
                a = min(max(s, -cap), cap) + cap;                                                         \
                s = (Q(right, u + 1) + 2 * Q(right, c + 1) + Q(right, d + 1))                             \
                    - (Q(right, u - 1) + 2 * Q(right, c - 1) + Q(right, d - 1));                          \
                b = min(max(s, -cap), cap) + cap;                                                         \
            }                                                                                             \
            pl[y * Wp + xp] = (GT_T)a;                                                                    \
            pr[y * Wp + xp] = (GT_T)b;                                                                    \
        }                                                                                                 \
    }

GT_STEREO_PREFILTER(gt_stereo_prefilter_u8, uchar, gt_q_u8)
GT_STEREO_PREFILTER(gt_stereo_prefilter_f32, float, gt_q_f32)

// left costs, one work-item per (disparity group, tile): the window column sums
// V(x) = sum over the window's rows of |P_L(x) - P_R(x - d)| of the tile's columns, carried down its
// rows (the row entering added, the one leaving subtracted), then running box sums along each run
// of the row: C(x, d) = C(x - 1, d) + V(x + r) - V(x - r - 1)
__kernel void gt_stereo_left_costs(__global const GT_T *pl, __global const GT_T *pr, __global const int *runs,
                                   __global const int *tiles, __global const int *order, __global GT_T *vsum,
                                   __global GT_T *cost, const int T, const int D, const int B, const int Wp)
{
    const int g = get_global_id(0), b = get_global_id(1);
    const int G = (D + GT_STEREO_LANES - 1) / GT_STEREO_LANES, Dp = G * GT_STEREO_LANES;
    if (g >= G || b >= T)
        return;
    const __global int *tile = tiles + 8 * b;
    const int r = B / 2, d0 = g * GT_STEREO_LANES;
    const int y0 = tile[0], y1 = tile[1], xa = tile[2], xb = tile[3], i1 = tile[5], w = tile[7];
    __global GT_T *vs = vsum + ((size_t)tile[6] * G + (size_t)g * w) * GT_STEREO_LANES;  // this work-item's sums
    const int first = xa - r;
    int i = tile[4];
    for (int y = y0; y <= y1; ++y) {
        for (int j = 0; j < xb - xa + 2 * r + 1; ++j) {
            const int at = (y - r) * Wp + GT_STEREO_LANES + first + j;  // the window's top row
            GT_V v;
            if (y == y0) {
                v = (GT_V)(0);
                for (int k = 0; k < B; ++k) {
                    const int o = at + k * Wp;
                    const GT_V t = (GT_V)(pl[o]) - GT_REVERSE(GT_VLOAD(0, pr + o - d0 - (GT_STEREO_LANES - 1)));
                    v += max(t, -t);  // lane l: |P_L(x) - P_R(x - d0 - l)|
                }
            } else {
                const int add = at + (B - 1) * Wp, sub = at - Wp;
                const GT_V t1 = (GT_V)(pl[add]) - GT_REVERSE(GT_VLOAD(0, pr + add - d0 - (GT_STEREO_LANES - 1)));
                const GT_V t2 = (GT_V)(pl[sub]) - GT_REVERSE(GT_VLOAD(0, pr + sub - d0 - (GT_STEREO_LANES - 1)));
                v = GT_VLOAD(j, vs) + max(t1, -t1) - max(t2, -t2);
            }
            GT_VSTORE(v, j, vs);
        }
        for (; i < i1 && runs[5 * order[i]] == y; ++i) {
            const int q = 5 * order[i], x0 = runs[q + 1], x1 = runs[q + 2], off = runs[q + 3];
            GT_V c = (GT_V)(0);
            for (int k = 0; k < B; ++k)
                c += GT_VLOAD(x0 - r - first + k, vs);
            GT_VSTORE(c, 0, cost + (size_t)off * Dp + d0);
            for (int x = x0 + 1; x <= x1; ++x) {
                c += GT_VLOAD(x + r - first, vs) - GT_VLOAD(x - r - 1 - first, vs);
                GT_VSTORE(c, 0, cost + (size_t)(off + x - x0) * Dp + d0);
            }
        }
    }
}

// The GPU variant of the two cost kernels (gputrack/backends/opencl/stereo.py per_pixel): a
// work-item per (pixel or marked right position, disparity group), each window summed whole
// (block x block absolute differences a lane; integers, so the costs equal the carried sums of the
// kernels above). A device with few, fast cores wants the carried sums; a GPU wants the work-items.

// the run holding slot p of the offsets in column col (3: pixels, 4: right positions): the last run
// whose offset is <= p (the offsets ascend with the runs)
inline int gt_stereo_run_of(__global const int *runs, const int S, const int p, const int col)
{
    int lo = 0, hi = S - 1;
    while (lo < hi) {
        const int mid = (lo + hi + 1) >> 1;
        if (runs[5 * mid + col] <= p)
            lo = mid;
        else
            hi = mid - 1;
    }
    return lo;
}

// NDRange (P, G): C(x, d) of the runs' pixel p, lanes d0 .. d0 + LANES - 1, into cost[p]
__kernel void gt_stereo_left_costs_px(__global const GT_T *pl, __global const GT_T *pr, __global const int *runs,
                                      __global GT_T *cost, const int S, const int P, const int D, const int B,
                                      const int Wp)
{
    const int p = get_global_id(0), g = get_global_id(1);
    const int G = (D + GT_STEREO_LANES - 1) / GT_STEREO_LANES, Dp = G * GT_STEREO_LANES;
    if (p >= P || g >= G)
        return;
    const int s = gt_stereo_run_of(runs, S, p, 3), r = B / 2, d0 = g * GT_STEREO_LANES;
    const int y = runs[5 * s], x = runs[5 * s + 1] + p - runs[5 * s + 3];
    GT_V c = (GT_V)(0);
    for (int k = 0; k < B; ++k) {
        const int row = (y - r + k) * Wp + GT_STEREO_LANES + x - r;
        for (int m = 0; m < B; ++m) {
            const int o = row + m;
            const GT_V t = (GT_V)(pl[o]) - GT_REVERSE(GT_VLOAD(0, pr + o - d0 - (GT_STEREO_LANES - 1)));
            c += max(t, -t);  // lane l: |P_L(x) - P_R(x - d0 - l)|
        }
    }
    GT_VSTORE(c, 0, cost + (size_t)p * Dp + d0);
}

// NDRange (P2, G), P2 the runs' right positions: C_R(xr, d) at the marked ones (rmark), into rcost
__kernel void gt_stereo_right_costs_px(__global const GT_T *pl, __global const GT_T *pr, __global const int *runs,
                                       __global const int *rmark, __global GT_T *rcost, const int S, const int P2,
                                       const int D, const int B, const int Wp)
{
    const int q = get_global_id(0), g = get_global_id(1);
    const int G = (D + GT_STEREO_LANES - 1) / GT_STEREO_LANES, Dp = G * GT_STEREO_LANES;
    if (q >= P2 || g >= G || rmark[q] == 0)
        return;
    const int s = gt_stereo_run_of(runs, S, q, 4), r = B / 2, d0 = g * GT_STEREO_LANES;
    const int y = runs[5 * s], xr = runs[5 * s + 1] - D + 1 + q - runs[5 * s + 4];
    GT_V c = (GT_V)(0);
    for (int k = 0; k < B; ++k) {
        const int row = (y - r + k) * Wp + GT_STEREO_LANES + xr - r;
        for (int m = 0; m < B; ++m) {
            const int at = row + m;
            const GT_V t = GT_VLOAD(0, pl + at + d0) - (GT_V)(pr[at]);
            c += max(t, -t);  // lane l: |P_L(xr + d0 + l) - P_R(xr)|
        }
    }
    GT_VSTORE(c, 0, rcost + (size_t)q * Dp + d0);
}

// the smallest lane of v, by halves (.lo / .hi): log2(lanes) vector minima
#if GT_STEREO_LANES == 16
inline int gt_stereo_hmin(const int16 v)
{
    const int8 a = min(v.lo, v.hi);
    const int4 b = min(a.lo, a.hi);
    const int2 c = min(b.lo, b.hi);
    return min(c.x, c.y);
}
#else
inline int gt_stereo_hmin(const int8 v)
{
    const int4 b = min(v.lo, v.hi);
    const int2 c = min(b.lo, b.hi);
    return min(c.x, c.y);
}
#endif

// the smallest cost among c[0 .. n) (Dp slots, n <= Dp) and the smallest d that has it, a vector at a time
inline int gt_stereo_argmin(const __global GT_T *c, const int n, const int Dp, int *cost)
{
    const GT_VI lane = GT_LANE_IDS;
    GT_VI best = (GT_VI)(INT_MAX), at = (GT_VI)(0);
    for (int d0 = 0; d0 < Dp; d0 += GT_STEREO_LANES) {
        const GT_VI d = lane + d0;
        const GT_VI v = GT_TO_VI(GT_VLOAD(0, c + d0));
        const GT_VI take = (v < best) & (d < n);  // strict: each lane keeps its smallest d
        best = select(best, v, take);
        at = select(at, d, take);
    }
    // across the lanes: the smallest cost, then the smallest d among the lanes that have it
    const int cb = gt_stereo_hmin(best);
    *cost = cb;
    return gt_stereo_hmin(select((GT_VI)(INT_MAX), at, best == (GT_VI)(cb)));
}

__kernel void gt_stereo_left_wta(__global const int *runs, __global const uchar *mask, __global const GT_T *cost,
                                 __global int *ldisp, __global int *rmark, __global const int *run_tile,
                                 __global int *marked, __global float *out, const int S, const int D, const int U,
                                 const int W)
{
    const int s = get_global_id(0);
    if (s >= S)
        return;
    const int Dp = (D + GT_STEREO_LANES - 1) / GT_STEREO_LANES * GT_STEREO_LANES;
    const int y = runs[5 * s], x0 = runs[5 * s + 1], x1 = runs[5 * s + 2], off = runs[5 * s + 3],
              roff = runs[5 * s + 4];
    const int rlo = x0 - D + 1;  // the run's first right-image position
    for (int k = 0; k < x1 - x0 + D; ++k)
        rmark[roff + k] = 0;
    const GT_VI lane = GT_LANE_IDS;
    int mlo = W, mhi = -1;  // the run's marked right-image positions
    for (int x = x0; x <= x1; ++x) {
        const __global GT_T *c = cost + (size_t)(off + x - x0) * Dp;
        int ld = -1;
        if (mask[y * W + x] != 0) {
            int cb;
            const int best = gt_stereo_argmin(c, D, Dp, &cb);  // winner-take-all, the smallest d of equal costs
            GT_VI rival = (GT_VI)(0);  // uniqueness: a d more than 1 px away within (100 + U) % of the best
            for (int d0 = 0; d0 < Dp; d0 += GT_STEREO_LANES) {
                const GT_VI d = lane + d0;
                rival |= (abs(d - best) > 1) & (d < D) & (100 * GT_TO_VI(GT_VLOAD(0, c + d0)) <= (100 + U) * cb);
            }
            if (!any(rival)) {
                float val = (float)best;
                if (best > 0 && best < D - 1) {  // the parabola's vertex
                    const int cm = (int)c[best - 1], cp = (int)c[best + 1];
                    val += (float)(cm - cp) / (float)(2 * (cm - 2 * cb + cp));
                }
                out[y * W + x] = val;
                ld = best;
                rmark[roff + x - best - rlo] = 1;
                mlo = min(mlo, x - best);
                mhi = max(mhi, x - best);
            }
        }
        ldisp[off + x - x0] = ld;
    }
    if (mlo <= mhi) {  // the tile's marked span, for the right costs
        atomic_min(marked + 2 * run_tile[s], mlo);
        atomic_max(marked + 2 * run_tile[s] + 1, mhi);
    }
}

// right costs at the marked positions, the same way: V(x) = sum over the window's rows of
// |P_L(x + d) - P_R(x)| over the columns of the tile's marked span (garbage but in bounds where
// x + d >= W: such d are not candidates), C_R(xr, d) running along each run's positions in that span
__kernel void gt_stereo_right_costs(__global const GT_T *pl, __global const GT_T *pr, __global const int *runs,
                                    __global const int *tiles, __global const int *order, __global const int *marked,
                                    __global const int *rmark, __global GT_T *vsum, __global GT_T *rcost, const int T,
                                    const int D, const int B, const int Wp)
{
    const int g = get_global_id(0), b = get_global_id(1);
    const int G = (D + GT_STEREO_LANES - 1) / GT_STEREO_LANES, Dp = G * GT_STEREO_LANES;
    if (g >= G || b >= T)
        return;
    const __global int *tile = tiles + 8 * b;
    const int r = B / 2, d0 = g * GT_STEREO_LANES;
    const int y0 = tile[0], y1 = tile[1], xa = tile[2], i1 = tile[5], w = tile[7];
    const int mlo = marked[2 * b], mhi = marked[2 * b + 1];
    if (mlo > mhi)
        return;  // nothing marked in this tile
    __global GT_T *vs = vsum + ((size_t)tile[6] * G + (size_t)g * w) * GT_STEREO_LANES;
    const int first = xa - D + 1 - r;  // column sums cover [first, first + w); those of [mlo - r, mhi + r] are used
    int i = tile[4];
    for (int y = y0; y <= y1; ++y) {
        for (int j = mlo - r - first; j <= mhi + r - first; ++j) {
            const int at = (y - r) * Wp + GT_STEREO_LANES + first + j;
            GT_V v;
            if (y == y0) {
                v = (GT_V)(0);
                for (int k = 0; k < B; ++k) {
                    const GT_V t = GT_VLOAD(0, pl + at + k * Wp + d0) - (GT_V)(pr[at + k * Wp]);
                    v += max(t, -t);  // lane l: |P_L(x + d0 + l) - P_R(x)|
                }
            } else {
                const int add = at + (B - 1) * Wp, sub = at - Wp;
                const GT_V t1 = GT_VLOAD(0, pl + add + d0) - (GT_V)(pr[add]);
                const GT_V t2 = GT_VLOAD(0, pl + sub + d0) - (GT_V)(pr[sub]);
                v = GT_VLOAD(j, vs) + max(t1, -t1) - max(t2, -t2);
            }
            GT_VSTORE(v, j, vs);
        }
        for (; i < i1 && runs[5 * order[i]] == y; ++i) {
            const int q = 5 * order[i], x0 = runs[q + 1], x1 = runs[q + 2], roff = runs[q + 4];
            const int rlo = x0 - D + 1;
            const int k0 = max(0, mlo - rlo), k1 = min(x1 - x0 + D - 1, mhi - rlo);
            if (k0 > k1)
                continue;
            GT_V c = (GT_V)(0);
            for (int k = 0; k < B; ++k)
                c += GT_VLOAD(rlo + k0 - r - first + k, vs);
            for (int k = k0; k <= k1; ++k) {
                const int xr = rlo + k;
                if (k > k0)
                    c += GT_VLOAD(xr + r - first, vs) - GT_VLOAD(xr - r - 1 - first, vs);
                if (rmark[roff + k] != 0)
                    GT_VSTORE(c, 0, rcost + (size_t)(roff + k) * Dp + d0);
            }
        }
    }
}

__kernel void gt_stereo_right_check(__global const int *runs, __global const int *ldisp, __global const GT_T *rcost,
                                    __global float *out, const int S, const int D, const int B, const int W)
{
    const int s = get_global_id(0);
    if (s >= S)
        return;
    const int Dp = (D + GT_STEREO_LANES - 1) / GT_STEREO_LANES * GT_STEREO_LANES, r = B / 2;
    const int y = runs[5 * s], x0 = runs[5 * s + 1], x1 = runs[5 * s + 2], off = runs[5 * s + 3],
              roff = runs[5 * s + 4];
    const int rlo = x0 - D + 1;
    for (int x = x0; x <= x1; ++x) {
        const int ld = ldisp[off + x - x0];
        if (ld < 0)
            continue;
        const int xr = x - ld;
        int cb;  // d' whose left window is inside the image, the smallest of equal costs
        const int best = gt_stereo_argmin(rcost + (size_t)(roff + xr - rlo) * Dp, min(D, W - r - xr), Dp, &cb);
        if (abs(best - ld) > 1)
            out[y * W + x] = NAN;
    }
}

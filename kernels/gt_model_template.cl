// The sparse template of a rendered model (gputrack/ops/model_template.py, steps 1-8 of its
// docstring; the NumPy reference is gputrack/backends/reference/model_template.py). Launched in
// order on one queue:
//   gt_mt_render    NDRange (crop columns / L, crop rows): step 1, a ray per pixel, every part
//                   whose box holds the pixel intersected in float32, the nearest hit wins (strict
//                   <: ties go to the lower part index);
//   gt_mt_classify  NDRange (crop columns / L, crop rows): steps 2-3, the interior flag, the
//                   window's count c and the strength numerator |c q - S| of the extrema (-1
//                   elsewhere); work-item (0, 0) also resets the per-part stats and candidate counts;
//   gt_mt_stats     NDRange (crop rows): step 4's per-part counts and row / column ranges, a run
//                   of same-part pixels of a row at a time (a few atomics per row, not per pixel);
//   gt_mt_bin       NDRange (crop rows): step 4's candidates into their part's bin
//                   (bins[k][start_j + atomic_inc(surv[k][j])], in no particular order);
//   (the host reads the stats and plans the quotas: step 5)
//   gt_mt_emit      NDRange (J, 2), work-groups of one: per part and kind, sequentially, step 6
//                   (the greedy extrema, strongest first from a heap), step 7 (the farthest-point,
//                   rook-spread fill) and step 8 (the points).
// Every selection step works on the 64-bit integers q = floor(v s_k) (|q| < 2**40: the float32
// product v s_k, s_k a power of two, is exact on every device), their window sums and the strength
// numerators |c q - S| (< 2**47) in long; the strength comparison cross-multiplies in long (< 2**53).
// Pixels outside the crop count as no part and are never read.

#include "gt_pcg.clh"

#define GT_MT_STATS 10
#define GT_MT_NO_ROW (1 << 30)

// ---- lanes: a work-item renders / classifies GT_MT_LANES consecutive pixels of a row ------------
// (CPU devices: 8, the vector types map onto SIMD registers; GPUs and the doctor's build: 1).
// Comparisons give 1 (scalar) or -1 (vector) for true: they are combined only with & | ! and read
// only by select() and MT_ANY, which see both. lv: a long per lane (the integers q of step 2 and
// their window sums); MT_ITOL / MT_LTOI turn an int mask into a long mask and back (a long8
// comparison gives a long8 mask; a scalar one an int).
#ifndef GT_MT_LANES
#define GT_MT_LANES 1
#endif
#if GT_MT_LANES == 1
typedef float fv;
typedef int iv;
#define MT_IDS ((iv)0)
#define MT_ANY(m) ((m) != 0)
#define MT_LOADF(p) (*(p))
#define MT_LOADI(p) (*(p))
#define MT_STOREF(x, p) (*(p) = (x))
#define MT_STOREI(x, p) (*(p) = (x))
#define MT_GATHERI(p, k) ((p)[(k)])
#define MT_GATHERF(p, k) ((p)[(k)])
#define MT_TOI(x) convert_int(x)
#define MT_TOF(x) convert_float(x)
typedef long lv;
#define MT_LOADL(p) (*(p))
#define MT_STOREL(x, p) (*(p) = (x))
#define MT_TOL(x) convert_long(x)
#define MT_ITOL(m) convert_long(m)
#define MT_LTOI(m) (m)
#elif GT_MT_LANES == 8
typedef float8 fv;
typedef int8 iv;
#define MT_IDS ((iv)(0, 1, 2, 3, 4, 5, 6, 7))
#define MT_ANY(m) any(m)
#define MT_LOADF(p) vload8(0, (p))
#define MT_LOADI(p) vload8(0, (p))
#define MT_STOREF(x, p) vstore8((x), 0, (p))
#define MT_STOREI(x, p) vstore8((x), 0, (p))
#define MT_GATHERI(p, k) \
    ((iv)((p)[(k).s0], (p)[(k).s1], (p)[(k).s2], (p)[(k).s3], (p)[(k).s4], (p)[(k).s5], (p)[(k).s6], (p)[(k).s7]))
#define MT_GATHERF(p, k) \
    ((fv)((p)[(k).s0], (p)[(k).s1], (p)[(k).s2], (p)[(k).s3], (p)[(k).s4], (p)[(k).s5], (p)[(k).s6], (p)[(k).s7]))
#define MT_TOI(x) convert_int8(x)
#define MT_TOF(x) convert_float8(x)
typedef long8 lv;
#define MT_LOADL(p) vload8(0, (p))
#define MT_STOREL(x, p) vstore8((x), 0, (p))
#define MT_TOL(x) convert_long8(x)
#define MT_ITOL(m) convert_long8(m)
#define MT_LTOI(m) convert_int8(m)
#else
#error "GT_MT_LANES must be 1 or 8"
#endif
#define MT_L GT_MT_LANES
#define MT_SPAN (MT_L == 1 ? 7 : 2 * MT_L)  // a staged row: L + 2 wh columns, wh <= 3

// the lanes' ints of p[x .. x + L) of a row (x: the first lane's column); lanes outside [c0, c1): fill
inline iv mt_loadi(__global const int *row, const int x, const int c0, const int c1, const int fill)
{
    if (x >= c0 && x + MT_L <= c1)
        return MT_LOADI(row + x);
    const iv xv = x + MT_IDS;
    return select((iv)fill, MT_GATHERI(row, clamp(xv, c0, c1 - 1)), (xv >= c0) & (xv < c1));
}

inline fv mt_loadf(__global const float *row, const int x, const int c0, const int c1)
{
    if (x >= c0 && x + MT_L <= c1)
        return MT_LOADF(row + x);
    return MT_GATHERF(row, clamp(x + MT_IDS, c0, c1 - 1));
}

// store the first n lanes at p (n = L: one vector store)
inline void mt_storei(const iv v, __global int *p, const int n)
{
    if (n == MT_L) {
        MT_STOREI(v, p);
        return;
    }
    int tmp[MT_L];
    MT_STOREI(v, tmp);
    for (int l = 0; l < n; ++l)
        p[l] = tmp[l];
}

inline void mt_storel(const lv v, __global long *p, const int n)
{
    if (n == MT_L) {
        MT_STOREL(v, p);
        return;
    }
    long tmp[MT_L];
    MT_STOREL(v, tmp);
    for (int l = 0; l < n; ++l)
        p[l] = tmp[l];
}

inline void mt_storef(const fv v, __global float *p, const int n)
{
    if (n == MT_L) {
        MT_STOREF(v, p);
        return;
    }
    float tmp[MT_L];
    MT_STOREF(v, tmp);
    for (int l = 0; l < n; ++l)
        p[l] = tmp[l];
}

// ---- step 1: render -----------------------------------------------------------------------------
// The render computes in GT_MT_REAL (the ray, the intersection, the normal, the texture's sine sum,
// the shading): double where the device has fp64 (GT_MT_DOUBLE=1: the reference's float64, so
// near-ties of the integers q = floor(v s) fall as the reference's), float otherwise; its outputs
// round to float32 once, at the store (as the reference's float64 -> float32). rv: a real per lane,
// mv: the mask of a comparison of rvs (int lanes for float, long lanes for double8); MT_SEL(a, b, m):
// b where m, else a; MT_MI / MT_IM: an mv as an iv mask and back; MT_R(x): the literal x as a real.
#ifndef GT_MT_DOUBLE
#define GT_MT_DOUBLE 0
#endif
#if GT_MT_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
#define MT_R(x) (x)
#if GT_MT_LANES == 1
typedef double rv;
typedef int mv;
#define MT_MI(m) (m)
#define MT_IM(m) (m)
#define MT_TOR(x) convert_double(x)
#define MT_RTOF(x) convert_float(x)
#else
typedef double8 rv;
typedef long8 mv;
#define MT_MI(m) convert_int8(m)
#define MT_IM(m) convert_long8(m)
#define MT_TOR(x) convert_double8(x)
#define MT_RTOF(x) convert_float8(x)
#endif
#else
typedef float real;
typedef fv rv;
typedef iv mv;
#define MT_R(x) (x##f)
#define MT_MI(m) (m)
#define MT_IM(m) (m)
#define MT_TOR(x) MT_TOF(x)
#define MT_RTOF(x) (x)
#endif
#if GT_MT_LANES == 1
#define MT_SEL(a, b, m) ((m) ? (b) : (a))
#else
#define MT_SEL(a, b, m) select((a), (b), (m))
#endif

// The texture's sine. CPU builds in double (GT_MT_DOUBLE, GT_MT_LANES > 1): PoCL's double8 sin
// was two thirds of the render; this one is fma and select only (vectorised): j = rint(x 2/pi) by
// adding and removing 1.5 * 2**52 (|x| < 2**50), r = x - j pi/2 with pi/2 in three doubles (the
// first fma exact), then fdlibm's (musl's) __sin / __cos kernels on [-pi/4, pi/4] and the quadrant's
// swap and signs: within an ulp or two of libm (tests/test_model_template.py pins the render to the
// reference's np.sin). Elsewhere the device's sin.
#if GT_MT_DOUBLE && GT_MT_LANES > 1
inline rv mt_sin(const rv x)
{
    const rv j = fma(x, 0.63661977236758134308, 6755399441055744.0) - 6755399441055744.0;
    rv r = fma(-j, 1.5707963267948966, x);
    r = fma(-j, 6.123233995736766e-17, r);
    r = fma(-j, -1.4973849048591698e-33, r);
    const rv z = r * r, w = z * z;
    const rv sr = fma(z, fma(z, 2.75573137070700676789e-06, -1.98412698298579493134e-04), 8.33333333332248946124e-03) +
                  (z * w) * fma(z, 1.58969099521155010221e-10, -2.50507602534068634195e-08);
    const rv sn = fma(z * r, fma(z, sr, -1.66666666666666324348e-01), r);  // musl __sin(r, 0, 1)
    const rv cr = z * fma(z, fma(z, 2.48015872894767294178e-05, -1.38888888888741095749e-03), 4.16666666666666019037e-02) +
                  (w * w) * fma(z, fma(z, -1.13596475577881948265e-11, 2.08757232129817482790e-09),
                                -2.75573143513906633035e-07);
    const rv hz = 0.5 * z, c1 = 1.0 - hz;
    const rv cs = c1 + (((1.0 - c1) - hz) + z * cr);  // musl __cos(r, 0)
    const mv q = convert_long8(j) & 3;
    const rv s = MT_SEL(sn, cs, (q & 1) != 0);  // sin(r + q pi/2): sin r, cos r, -sin r, -cos r
    return MT_SEL(s, -s, (q & 2) != 0);
}
#else
#define mt_sin(x) sin(x)
#endif

// the smaller root of a t^2 + 2 b t + c = 0 from disc = b^2 - a c (INFINITY where none or a = 0);
// the callers compute disc without the cancellation of b^2 - a c (Lagrange's identity)
inline rv gt_mt_root(const rv a, const rv b, const rv disc)
{
    return MT_SEL((rv)INFINITY, (-b - sqrt(disc)) / a, (disc >= MT_R(0.0)) & (a > MT_R(0.0)));
}

// first hit t > 0 of the rays o + t d with the part's shape, in the frame (u, v, k) where k is the
// shape's axis (INFINITY: none); *which: 0 the side / a hemispherical cap, 1 the start cap, 2 the
// end cap (flat caps of an elliptic cylinder)
inline rv gt_mt_intersect(const int kind, const real ou, const real ov, const real ok, const rv du, const rv dv,
                          const rv dk, const real s0, const real s1, const real ra, const real rb, iv *which)
{
    *which = (iv)0;
    if (kind == 0) {  // capsule: cylinder side within [s0, s1] plus two hemispherical caps
        const real r = ra;
        const rv a = du * du + dv * dv;
        const rv cr = ou * dv - ov * du;  // b^2 - a c = a r^2 - (o x d)^2
        rv t = gt_mt_root(a, ou * du + ov * dv, a * r * r - cr * cr);
        const rv s = ok + t * dk;
        t = MT_SEL((rv)INFINITY, t, (s >= s0) & (s <= s1));
        const rv ad = du * du + dv * dv + dk * dk;
        for (int e = 0; e < 2; ++e) {
            const real ck = ok - (e == 0 ? s0 : s1);
            const rv x = ov * dk - ck * dv, y = ck * du - ou * dk, z = ou * dv - ov * du;  // oc x d
            const rv ts = gt_mt_root(ad, ou * du + ov * dv + ck * dk, ad * r * r - (x * x + y * y + z * z));
            t = MT_SEL(t, ts, ts < t);
        }
        return MT_SEL((rv)INFINITY, t, t > MT_R(0.0));
    }
    // elliptic cylinder with flat caps: the side is a unit circle in (u / ra, v / rb)
    const real us = ou / ra, vs = ov / rb;
    const rv dus = du / ra, dvs = dv / rb;
    const rv a = dus * dus + dvs * dvs;
    const rv cr = us * dvs - vs * dus;
    rv best = gt_mt_root(a, us * dus + vs * dvs, a - cr * cr);
    const rv s = ok + best * dk;
    best = MT_SEL((rv)INFINITY, best, (s >= s0) & (s <= s1));
    for (int code = 1; code <= 2; ++code) {
        const rv tc = ((code == 1 ? s0 : s1) - ok) / dk;
        const rv pu = (ou + tc * du) / ra, pv = (ov + tc * dv) / rb;
        const mv closer = (pu * pu + pv * pv <= MT_R(1.0)) & isfinite(tc) & (tc < best);
        best = MT_SEL(best, tc, closer);
        *which = MT_SEL(*which, (iv)code, MT_MI(closer));
    }
    return MT_SEL((rv)INFINITY, best, best > MT_R(0.0));
}

// NDRange (ceil((c1 - c0) / L), r1 - r0): part, gray, depth Z and the part-local point of each
// crop pixel, L pixels of a row per work-item. table (J, 24): R^T row-major, o, box (r0, r1, c0,
// c1), kind, axis, start, end, radii; waves (J, Wv, 4): (k_x, k_y, k_z, phase); consts: fx, fy, cx,
// cy, amp, shading (all reals)
__kernel void gt_mt_render(__global const real *table, __global const real *waves, __global const real *consts,
                           const int J, const int Wv, const int H, const int W, const int r0, const int r1,
                           const int c0, const int c1, __global int *part, __global float *values,
                           __global float *pts)
{
    const int c = c0 + MT_L * get_global_id(0), r = r0 + get_global_id(1);
    if (c >= c1 || r >= r1)  // the NDRange is padded to whole work-groups
        return;
    const int n = min(MT_L, c1 - c);
    const real fx = consts[0], fy = consts[1], cx = consts[2], cy = consts[3];
    const rv cf = MT_TOR(c + MT_IDS);
    const rv rx = (cf - cx) / fx;
    const real ry = ((real)r - cy) / fy, fr = (real)r;
    rv best = (rv)INFINITY;
    iv bj = (iv)-1, bwhich = (iv)0;
    for (int j = 0; j < J; ++j) {
        __global const real *tb = table + j * 24;
        if (fr < tb[12] || fr >= tb[13] || (real)(c + MT_L - 1) < tb[14] || (real)c >= tb[15])
            continue;  // no lane in the part's box
        const rv d0 = tb[0] * rx + (tb[1] * ry + tb[2]), d1 = tb[3] * rx + (tb[4] * ry + tb[5]),
                 d2 = tb[6] * rx + (tb[7] * ry + tb[8]);
        const int k = (int)tb[17];
        const real ou = k == 0 ? tb[10] : tb[9], ov = k == 2 ? tb[10] : tb[11];
        const real ok = k == 0 ? tb[9] : (k == 1 ? tb[10] : tb[11]);
        const rv du = k == 0 ? d1 : d0, dv = k == 2 ? d1 : d2, dk = k == 0 ? d0 : (k == 1 ? d1 : d2);
        iv which;
        const rv t = gt_mt_intersect((int)tb[16], ou, ov, ok, du, dv, dk, tb[18], tb[19], tb[20], tb[21], &which);
        const mv take = (t < best) & (cf >= tb[14]) & (cf < tb[15]);  // strict <: ties to the lower index
        best = MT_SEL(best, t, take);
        bj = MT_SEL(bj, (iv)j, MT_MI(take));
        bwhich = MT_SEL(bwhich, which, MT_MI(take));
    }
    const real amp = consts[4], shading = consts[5];
    rv gray = (rv)MT_R(0.0), x0 = (rv)MT_R(0.0), x1 = (rv)MT_R(0.0), x2 = (rv)MT_R(0.0);
    for (int j = 0; j < J; ++j) {  // the shading of each part that won a lane
        const iv mine = bj == j;
        if (!MT_ANY(mine))
            continue;
        const mv rmine = MT_IM(mine);
        __global const real *tb = table + j * 24;
        const rv d0 = tb[0] * rx + (tb[1] * ry + tb[2]), d1 = tb[3] * rx + (tb[4] * ry + tb[5]),
                 d2 = tb[6] * rx + (tb[7] * ry + tb[8]);
        const rv t = MT_SEL((rv)MT_R(0.0), best, rmine);
        const rv y0 = tb[9] + t * d0, y1 = tb[10] + t * d1, y2 = tb[11] + t * d2;  // the part-local hit
        const int k = (int)tb[17];
        const real s0 = tb[18], s1 = tb[19], ra = tb[20], rb = tb[21];
        const rv xu = k == 0 ? y1 : y0, xv = k == 2 ? y1 : y2, xk = k == 0 ? y0 : (k == 1 ? y1 : y2);
        const rv du = k == 0 ? d1 : d0, dv = k == 2 ? d1 : d2, dk = k == 0 ? d0 : (k == 1 ? d1 : d2);
        rv nu, nv, nk;  // the outward normal in (u, v, k): a dot product does not see the order
        if ((int)tb[16] == 0) {  // capsule: from the closest point of the axis segment, / r
            nu = xu / ra;
            nv = xv / ra;
            nk = (xk - clamp(xk, s0, s1)) / ra;
        } else {
            nu = xu / (ra * ra);
            nv = xv / (rb * rb);
            const rv len = fmax(sqrt(nu * nu + nv * nv), MT_R(1e-12));
            const mv cap = MT_IM(bwhich != 0);
            nu = MT_SEL(nu / len, (rv)MT_R(0.0), cap);
            nv = MT_SEL(nv / len, (rv)MT_R(0.0), cap);
            nk = MT_SEL((rv)MT_R(0.0), MT_SEL((rv)MT_R(1.0), (rv)MT_R(-1.0), MT_IM(bwhich == 1)), cap);
        }
        const rv cosv = fabs(du * nu + dv * nv + dk * nk) / sqrt(d0 * d0 + d1 * d1 + d2 * d2);
        __global const real *wv = waves + j * Wv * 4;
        rv sum = (rv)MT_R(0.0);
        for (int w = 0; w < Wv; ++w)
            sum += mt_sin(wv[4 * w] * y0 + (wv[4 * w + 1] * y1 + (wv[4 * w + 2] * y2 + wv[4 * w + 3])));
        const rv g = clamp(MT_R(0.5) + amp * sum, MT_R(0.02), MT_R(0.98)) * (MT_R(1.0) - shading + shading * cosv);
        gray = MT_SEL(gray, g, rmine);
        x0 = MT_SEL(x0, y0, rmine);
        x1 = MT_SEL(x1, y1, rmine);
        x2 = MT_SEL(x2, y2, rmine);
    }
    const int i = r * W + c, HW = H * W;
    const iv hit = bj >= 0;
    mt_storei(bj, part + i, n);
    mt_storef(MT_RTOF(gray), values + i, n);
    mt_storef(select((fv)0.0f, MT_RTOF(best), hit), values + HW + i, n);
    float a0[MT_L], a1[MT_L], a2[MT_L];
    MT_STOREF(MT_RTOF(x0), a0);
    MT_STOREF(MT_RTOF(x1), a1);
    MT_STOREF(MT_RTOF(x2), a2);
    __global float *o = pts + 3 * i;
    for (int l = 0; l < n; ++l) {
        o[3 * l] = a0[l];
        o[3 * l + 1] = a1[l];
        o[3 * l + 2] = a2[l];
    }
}

// ---- steps 2-5: classify, count, suppress ----------------------------------------------------------

// a stronger than b: |c q - S| / c larger (cross-multiplied in 64 bits), ties: the smaller hash of
// the pixel index, then the smaller index (the op's step 3)
inline int gt_mt_stronger(const long na, const int ca, const int ia, const long nb, const int cb, const int ib)
{
    const long lhs = na * cb, rhs = nb * ca;  // < 2**47 * 49 < 2**53
    if (lhs != rhs)
        return lhs > rhs;
    const uint ha = gt_pcg((uint)ia), hb = gt_pcg((uint)ib);
    return ha < hb || (ha == hb && ia < ib);
}

// NDRange (ceil((c1 - c0) / L), r1 - r0), L pixels of a row per work-item: interior the interior
// flag, num[k] the strength numerator |c q - S| (long) of an extremum of value k (-1: none), cnt
// the window's same-part count; work-item (0, 0) resets stats (J, 10) and surv (2, J) for gt_mt_stats and
// gt_mt_bin (launched after this kernel)
__kernel void gt_mt_classify(__global const int *part, __global const float *values, const int H, const int W,
                             const int r0, const int r1, const int c0, const int c1, const float sc0, const float sc1,
                             const int wh, const int border, const int J, __global int *interior,
                             __global long *num, __global int *cnt, __global int *stats, __global int *surv)
{
    const int gc = get_global_id(0), gr = get_global_id(1);
    if (gc == 0 && gr == 0) {
        for (int j = 0; j < J; ++j) {
            __global int *st = stats + j * GT_MT_STATS;
            st[0] = st[1] = 0;
            for (int b = 2; b < GT_MT_STATS; b += 2) {
                st[b] = GT_MT_NO_ROW;
                st[b + 1] = -1;
            }
            surv[j] = surv[J + j] = 0;
        }
    }
    const int c = c0 + MT_L * gc, r = r0 + gr;
    if (c >= c1 || r >= r1)  // the NDRange is padded to whole work-groups
        return;
    const int nl = min(MT_L, c1 - c);
    const int i = r * W + c, HW = H * W;
    const iv p = mt_loadi(part + r * W, c, c0, c1, -1);
    const iv model = p >= 0;
    iv inner = model;
    if (border > wh) {  // else the window's loop below sees every pixel of the border's square
        for (int dy = -border; dy <= border; ++dy) {
            const int y = r + dy;
            if (y < r0 || y >= r1) {
                inner = (iv)0;
                break;
            }
            for (int dx = -border; dx <= border; ++dx)
                inner = inner & (mt_loadi(part + y * W, c + dx, c0, c1, -1) == p);
        }
    }
    const lv q0 = MT_TOL(floor(mt_loadf(values + r * W, c, c0, c1) * sc0));
    const lv q1 = MT_TOL(floor(mt_loadf(values + HW + r * W, c, c0, c1) * sc1));
    iv n = (iv)0;
    lv S0 = (lv)0, S1 = (lv)0, hi0 = (lv)LONG_MIN, lo0 = (lv)LONG_MAX, hi1 = (lv)LONG_MIN, lo1 = (lv)LONG_MAX;
    // a window row's part ids and q of columns c - wh .. c + L - 1 + wh, staged once (wh <= 3)
    int sp[MT_SPAN];
    long sa[MT_SPAN], sb[MT_SPAN];
    for (int dy = -wh; dy <= wh; ++dy) {
        const int y = r + dy;
        const int inb = dy >= -border && dy <= border;
        if (y < r0 || y >= r1) {
            if (inb)
                inner = (iv)0;
            continue;
        }
        __global const int *prow = part + y * W;
        __global const float *vrow = values + y * W;
#if GT_MT_LANES == 8
        MT_STOREI(mt_loadi(prow, c - wh, c0, c1, -1), sp);
        MT_STOREI(mt_loadi(prow, c - wh + MT_L, c0, c1, -1), sp + MT_L);
        MT_STOREL(MT_TOL(floor(mt_loadf(vrow, c - wh, c0, c1) * sc0)), sa);
        MT_STOREL(MT_TOL(floor(mt_loadf(vrow, c - wh + MT_L, c0, c1) * sc0)), sa + MT_L);
        MT_STOREL(MT_TOL(floor(mt_loadf(vrow + HW, c - wh, c0, c1) * sc1)), sb);
        MT_STOREL(MT_TOL(floor(mt_loadf(vrow + HW, c - wh + MT_L, c0, c1) * sc1)), sb + MT_L);
#else
        for (int x = 0; x <= 2 * wh; ++x) {
            const int cx = c - wh + x, in = cx >= c0 && cx < c1, cc = clamp(cx, c0, c1 - 1);
            sp[x] = in ? prow[cc] : -1;
            sa[x] = convert_long(floor(vrow[cc] * sc0));
            sb[x] = convert_long(floor(vrow[HW + cc] * sc1));
        }
#endif
        for (int dx = -wh; dx <= wh; ++dx) {
            const iv same = MT_LOADI(sp + wh + dx) == p;
            const lv ls = MT_ITOL(same);
            const lv a = MT_LOADL(sa + wh + dx), b = MT_LOADL(sb + wh + dx);
            if (inb && dx >= -border && dx <= border)
                inner = inner & same;
            n += select((iv)0, (iv)1, same);
            S0 += select((lv)0, a, ls);
            S1 += select((lv)0, b, ls);
            hi0 = select(hi0, max(hi0, a), ls);
            lo0 = select(lo0, min(lo0, a), ls);
            hi1 = select(hi1, max(hi1, b), ls);
            lo1 = select(lo1, min(lo1, b), ls);
        }
    }
    const lv nl64 = MT_TOL(n);
    const lv e0 = nl64 * q0 - S0, e1 = nl64 * q1 - S1;
    const lv x0 = MT_ITOL(model & MT_LTOI((hi0 > lo0) & ((q0 == hi0) | (q0 == lo0))));
    const lv x1 = MT_ITOL(model & MT_LTOI((hi1 > lo1) & ((q1 == hi1) | (q1 == lo1))));
    mt_storei(select((iv)0, (iv)1, inner), interior + i, nl);
    mt_storel(select((lv)-1, select(e0, -e0, MT_ITOL(e0 < 0)), x0), num + i, nl);
    mt_storel(select((lv)-1, select(e1, -e1, MT_ITOL(e1 < 0)), x1), num + HW + i, nl);
    mt_storei(select((iv)0, n, model), cnt + i, nl);
}

// a run [a, b] of row r of part p into stats columns (count, rows, columns) at base
inline void gt_mt_flush(__global int *stats, const int p, const int count_col, const int base, const int r,
                        const int a, const int b)
{
    __global int *st = stats + p * GT_MT_STATS;
    atomic_add(st + count_col, b - a + 1);
    atomic_min(st + base, r);
    atomic_max(st + base + 1, r);
    atomic_min(st + base + 2, a);
    atomic_max(st + base + 3, b);
}

// NDRange (r1 - r0): per part the area, the interior count and the two (row, column) ranges, one
// flush of atomics per run of same-part (or same-part interior) pixels of a row
__kernel void gt_mt_stats(__global const int *part, __global const int *interior, const int W, const int r0,
                          const int r1, const int c0, const int c1, __global int *stats)
{
    const int r = r0 + get_global_id(0);
    if (r >= r1)  // the NDRange is padded to whole work-groups
        return;
    __global const int *pr = part + r * W;
    __global const int *ir = interior + r * W;
    int pa = -1, sa = c0, pi = -1, si = c0;  // the open runs: part and first column
    for (int c = c0; c < c1; ++c) {
        const int p = pr[c];
        const int q = p >= 0 && ir[c] ? p : -1;
        if (p != pa) {
            if (pa >= 0)
                gt_mt_flush(stats, pa, 0, 6, r, sa, c - 1);
            pa = p;
            sa = c;
        }
        if (q != pi) {
            if (pi >= 0)
                gt_mt_flush(stats, pi, 1, 2, r, si, c - 1);
            pi = q;
            si = c;
        }
    }
    if (pa >= 0)
        gt_mt_flush(stats, pa, 0, 6, r, sa, c1 - 1);
    if (pi >= 0)
        gt_mt_flush(stats, pi, 1, 2, r, si, c1 - 1);
}

// NDRange (r1 - r0): a row's candidates (pool pixels that are extrema of value k; the pool of part
// j: its interior pixels, or all its pixels when it has none) into their part's bin:
// bins[k][start_j + atomic_inc(&surv[k][j])], start_j the areas of the parts before j
__kernel void gt_mt_bin(__global const int *part, __global const int *interior, __global const long *num,
                        __global const int *stats, const int H,
                        const int W, const int r0, const int r1, const int c0, const int c1, __global int *bins,
                        __global int *surv, const int J)
{
    const int r = r0 + get_global_id(0), HW = H * W;
    if (r >= r1)  // the NDRange is padded to whole work-groups
        return;
    int pp = -1, start = 0, all = 0;  // the part of the last candidate, its bin start, its pool rule
    for (int c = c0; c < c1; ++c) {
        const int o = r * W + c;
        const int p = part[o];
        if (p < 0)
            continue;
        const int a0 = num[o] >= 0, a1 = num[HW + o] >= 0;
        if (!a0 && !a1)
            continue;
        if (p != pp) {
            pp = p;
            start = 0;
            for (int j = 0; j < p; ++j)
                start += stats[j * GT_MT_STATS];
            all = stats[p * GT_MT_STATS + 1] == 0;
        }
        if (!all && !interior[o])
            continue;
        if (a0)
            bins[start + atomic_inc(surv + p)] = o;
        if (a1)
            bins[HW + start + atomic_inc(surv + J + p)] = o;
    }
}

// ---- steps 6-8: the extrema, the fill, the points -----------------------------------------------

// candidate a stronger than b (pixel indices; num, cnt: the strength's numerator and count)
inline int gt_mt_above(__global const long *num, __global const int *cnt, const int a, const int b)
{
    return gt_mt_stronger(num[a], cnt[a], a, num[b], cnt[b], b);
}

// sift bin[i] down the max-heap bin[0 .. size) ("max": the stronger)
inline void gt_mt_sift(__global int *bin, int i, const int size, __global const long *num, __global const int *cnt)
{
    const int x = bin[i];
    for (;;) {
        int ch = 2 * i + 1;
        if (ch >= size)
            break;
        if (ch + 1 < size && gt_mt_above(num, cnt, bin[ch + 1], bin[ch]))
            ++ch;
        if (!gt_mt_above(num, cnt, bin[ch], x))
            break;
        bin[i] = bin[ch];
        i = ch;
    }
    bin[i] = x;
}

// step 8: the points of slots t0, t0 + step, ... below quota (their pixels' local point and value)
inline void gt_mt_points(__global float *out, __global const float *pts, __global const float *val, const int W,
                         const int quota, const int t0, const int step)
{
    for (int t = t0; t < quota; t += step) {
        const int rc = ((__global const int *)out)[4 * t];
        const int o = (rc >> 16) * W + (rc & 0xffff);
        out[4 * t] = pts[3 * o];
        out[4 * t + 1] = pts[3 * o + 1];
        out[4 * t + 2] = pts[3 * o + 2];
        out[4 * t + 3] = val[o];
    }
}

// step 6: the bin's size candidates strongest first (a max-heap in place), each taken into the slots
// (r << 16 | c at slot[4 t]) unless a taken one lies at d^2 <= lim, until quota are; how many were
inline int gt_mt_greedy(__global int *bin, int size, __global const long *num, __global const int *cnt,
                        __global int *slot, const int quota, const int lim, const int W)
{
    int taken = 0;
    for (int i = size / 2 - 1; i >= 0; --i)
        gt_mt_sift(bin, i, size, num, cnt);
    while (taken < quota && size > 0) {
        const int px = bin[0];
        bin[0] = bin[--size];
        gt_mt_sift(bin, 0, size, num, cnt);
        const int r = px / W, c = px - r * W;
        int ok = 1;
        for (int t = 0; t < taken && ok; ++t) {
            const int rc = slot[4 * t], dr = r - (rc >> 16), dc = c - (rc & 0xffff);
            ok = dr * dr + dc * dc > lim;
        }
        if (ok)
            slot[4 * taken++] = r << 16 | c;
    }
    return taken;
}

// the first n (<= L) ints at p, lanes past n: fill
inline iv mt_loadn(__global const int *p, const int n, const int fill)
{
    if (n >= MT_L)
        return MT_LOADI(p);
    int tmp[MT_L];
    for (int l = 0; l < MT_L; ++l)
        tmp[l] = l < n ? p[l] : fill;
    return MT_LOADI(tmp);
}

// the lane with the largest v, the smallest index ix among ties (over *bv, *bi)
inline void mt_argmax(const iv v, const iv ix, int *bv, int *bi)
{
    int a[MT_L], b[MT_L];
    MT_STOREI(v, a);
    MT_STOREI(ix, b);
    for (int l = 0; l < MT_L; ++l)
        if (a[l] > *bv || (a[l] == *bv && b[l] < *bi)) {
            *bv = a[l];
            *bi = b[l];
        }
}

// NDRange (J, 2), work-groups of one: kind k = get_global_id(1), part j = get_global_id(0); plan
// (2, J, 4): offset, quota, bin start. Step 6: the part's candidates (bins[k][start ..
// + surv[k][j])) strongest first (a max-heap in place), each taken unless a taken one lies at d^2 <=
// lim (the largest integer below spacing^2). Step 7: the pool, compacted (packed r << 16 | c, pixel
// order) over the part's bin, and dist[k][start + i] = (d^2 to the chosen points) << 2 | row used
// << 1 | column used; each fill point the tiers' argmax (rook-spread, then a new row or column,
// then any; first in pixel order among ties; used[k][j]: the seeds' row and column flags). The
// chosen pixels wait in out_k's slots (x: r << 16
// | c) until step 8 writes the points.
__kernel void gt_mt_emit(__global const int *part, __global const float *values, __global const float *pts,
                         const int H, const int W, __global const int *plan, __global const int *stats,
                         __global const int *surv, __global int *bins, __global const int *interior,
                         __global const long *nums, __global const int *cnt, __global int *dist, __global int *used, const int lim,
                         const int J,
                         __global float *out0, __global float *out1)
{
    const int j = get_global_id(0), k = get_global_id(1), HW = H * W;
    __global const int *pl = plan + (k * J + j) * 4;
    const int offset = pl[0], quota = pl[1], start = pl[2];
    if (quota <= 0)
        return;
    __global float *out = (k == 0 ? out0 : out1) + 4 * offset;
    __global int *slot = (__global int *)out;  // slot t's pixel at slot[4 t]
    __global int *bin = bins + k * HW + start;
    __global const long *num = nums + k * HW;
    const int taken = gt_mt_greedy(bin, surv[k * J + j], num, cnt, slot, quota, lim, W);  // step 6
    // step 7
    if (taken < quota) {
        __global const int *st = stats + j * GT_MT_STATS;
        const int inner = st[1] > 0, b = inner ? 2 : 6;
        __global int *pool = bin;
        __global int *dd = dist + k * HW + start;
        int n = 0;
        long sr = 0, sc = 0;
        for (int r = st[b]; r <= st[b + 1]; ++r)
            for (int c = st[b + 2]; c <= st[b + 3]; ++c) {
                const int o = r * W + c;
                if (part[o] == j && (!inner || interior[o] != 0)) {
                    pool[n++] = r << 16 | c;
                    sr += r;
                    sc += c;
                }
            }
        const int pr0 = st[b], pr1 = st[b + 1], pc0 = st[b + 2], pc1 = st[b + 3];
        int seeds = taken;
        if (seeds == 0) {  // the pool pixel nearest its centroid
            long best = LONG_MAX;
            int first = 0;
            for (int i = 0; i < n; ++i) {
                const long er = (long)n * (pool[i] >> 16) - sr, ec = (long)n * (pool[i] & 0xffff) - sc;
                const long e = er * er + ec * ec;
                if (e < best) {
                    best = e;
                    first = pool[i];
                }
            }
            slot[0] = first;
            seeds = 1;
        }
        // the seeds' rows and columns: used[k][j][r], used[k][j][H + c] (0 / 1 over the pool's box)
        __global int *urow = used + (k * J + j) * (H + W), *ucol = urow + H;
        for (int x = pr0; x <= pr1; ++x)
            urow[x] = 0;
        for (int x = pc0; x <= pc1; ++x)
            ucol[x] = 0;
        for (int t = 0; t < seeds; ++t) {
            const int src = slot[4 * t];
            urow[src >> 16] = ucol[src & 0xffff] = 1;
        }
        // the first pass: the distances to the seeds; then one pass per pick (its update)
        int pr = 0, pc = 0;
        for (int f = seeds; f < quota; ++f) {
            int b1 = 0, i1 = INT_MAX, b2 = 0, i2 = INT_MAX, b3 = -1, i3 = INT_MAX;
            iv v1 = (iv)0, x1 = (iv)INT_MAX, v2 = (iv)0, x2 = (iv)INT_MAX, v3 = (iv)-1, x3 = (iv)INT_MAX;
            for (int i = 0; i < n; i += MT_L) {
                const int nl = min(MT_L, n - i);
                const iv rc = mt_loadn(pool + i, nl, 0);
                const iv r = rc >> 16, c = rc & 0xffff;
                iv d, fl;
                if (f == seeds) {
                    d = (iv)(1 << 28);
                    for (int t = 0; t < seeds; ++t) {
                        const int src = slot[4 * t];
                        const iv dr = r - (src >> 16), dc = c - (src & 0xffff);
                        d = min(d, dr * dr + dc * dc);
                    }
                    fl = (MT_GATHERI(urow, r) << 1) | MT_GATHERI(ucol, c);  // lanes past n: masked below
                    d = select((iv)-1, d, MT_IDS < nl);
                    fl = select((iv)3, fl, MT_IDS < nl);
                } else {
                    const iv v = mt_loadn(dd + i, nl, -1);
                    const iv dr = r - pr, dc = c - pc;
                    d = min(v >> 2, dr * dr + dc * dc);
                    fl = (v & 3) | select((iv)0, (iv)2, r == pr) | select((iv)0, (iv)1, c == pc);
                    d = select((iv)-1, d, v >= 0);  // past the pool: stays out
                }
                mt_storei(d << 2 | fl, dd + i, nl);
                const iv ix = i + MT_IDS;
                const iv s1 = select((iv)0, d, fl == 0), s2 = select((iv)0, d, fl != 3);
                iv u = s1 > v1;
                v1 = select(v1, s1, u);
                x1 = select(x1, ix, u);
                u = s2 > v2;
                v2 = select(v2, s2, u);
                x2 = select(x2, ix, u);
                u = d > v3;
                v3 = select(v3, d, u);
                x3 = select(x3, ix, u);
            }
            mt_argmax(v1, x1, &b1, &i1);
            mt_argmax(v2, x2, &b2, &i2);
            mt_argmax(v3, x3, &b3, &i3);
            const int pick = b1 > 0 ? i1 : b2 > 0 ? i2 : i3;
            const int rc = pool[pick];
            slot[4 * f] = rc;
            pr = rc >> 16;
            pc = rc & 0xffff;
        }
    }
    gt_mt_points(out, pts, values + k * HW, W, quota, 0, 1);  // step 8
}

#define MT_WG_MAX 256  // the most work-items per part and kind of gt_mt_emit_wg (a power of two)

// (*v, *i) becomes (v2, i2) if that is larger: the larger value, the smaller index among ties
inline void mt_better(__local int *v, __local int *i, const int v2, const int i2)
{
    if (v2 > *v || (v2 == *v && i2 < *i)) {
        *v = v2;
        *i = i2;
    }
}

// gt_mt_emit with a work-group per part and kind (GPUs, where one work-item walking the pool once
// per fill point leaves the device idle): NDRange (J * wg, 2), work-groups (wg, 1), wg a power of
// two <= MT_WG_MAX; the same picks. Step 6 (the heap) by the first work-item; step 7's pool
// compacted in pixel order (each work-item counts a contiguous share of the pool's box, the counts
// scanned, then each writes its share), the centroid seed an argmin and each fill point an argmax
// over strided shares, reduced in local memory (larger value, then smaller pool index: the first in
// pixel order, as gt_mt_emit); step 8 a point per work-item.
__kernel void gt_mt_emit_wg(__global const int *part, __global const float *values, __global const float *pts,
                            const int H, const int W, __global const int *plan, __global const int *stats,
                            __global const int *surv, __global int *bins, __global const int *interior,
                            __global const long *nums, __global const int *cnt, __global int *dist, __global int *used,
                            const int lim, const int J, __global float *out0, __global float *out1)
{
    const int j = get_group_id(0), k = get_group_id(1), lid = get_local_id(0), wg = get_local_size(0), HW = H * W;
    __local int tv[3][MT_WG_MAX], ti[3][MT_WG_MAX], sh[4];  // sh: taken, pool size, fill row, fill column
    __local long tl[2][MT_WG_MAX];
    __global const int *pl = plan + (k * J + j) * 4;
    const int offset = pl[0], quota = pl[1], start = pl[2];  // quota <= 0: nothing to do (no early
    // return: every work-item meets every barrier, which PoCL's work-group loops need)
    __global float *out = (k == 0 ? out0 : out1) + 4 * offset;
    __global int *slot = (__global int *)out;
    __global int *bin = bins + k * HW + start;
    __global const long *num = nums + k * HW;
    // step 6
    if (lid == 0)
        sh[0] = quota > 0 ? gt_mt_greedy(bin, surv[k * J + j], num, cnt, slot, quota, lim, W) : 0;
    barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
    // step 7 where the extrema fall short of the quota; every work-item runs through every barrier
    // below, the work itself empty where there is none (PoCL 3.1 crashed on a version of this kernel
    // with barriers under such conditions)
    const int taken = sh[0], fill = taken < quota;
    {
        __global const int *st = stats + j * GT_MT_STATS;
        const int inner = st[1] > 0, b = inner ? 2 : 6;
        const int pr0 = st[b], pr1 = fill ? st[b + 1] : st[b] - 1, pc0 = st[b + 2], pc1 = st[b + 3];
        const int bw = max(0, pc1 - pc0 + 1), area = max(0, pr1 - pr0 + 1) * bw;
        __global int *pool = bin;
        __global int *dd = dist + k * HW + start;
        const int share = (area + wg - 1) / wg, a0 = min(area, lid * share), a1 = min(area, a0 + share);
        int mine = 0;
        long sr = 0, sc = 0;
        for (int a = a0; a < a1; ++a) {
            const int r = pr0 + a / bw, c = pc0 + a % bw, o = r * W + c;
            if (part[o] == j && (!inner || interior[o] != 0)) {
                ++mine;
                sr += r;
                sc += c;
            }
        }
        ti[0][lid] = mine;
        tl[0][lid] = sr;
        tl[1][lid] = sc;
        barrier(CLK_LOCAL_MEM_FENCE);
        if (lid == 0) {  // exclusive scan of the counts, and the pool's row and column sums
            int s = 0;
            long tr = 0, tc = 0;
            for (int t = 0; t < wg; ++t) {
                const int x = ti[0][t];
                ti[0][t] = s;
                s += x;
                tr += tl[0][t];
                tc += tl[1][t];
            }
            sh[1] = s;
            tl[0][0] = tr;
            tl[1][0] = tc;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        const int n = sh[1];
        const long srow = tl[0][0], scol = tl[1][0];
        for (int a = a0, w = ti[0][lid]; a < a1; ++a) {
            const int r = pr0 + a / bw, c = pc0 + a % bw, o = r * W + c;
            if (part[o] == j && (!inner || interior[o] != 0))
                pool[w++] = r << 16 | c;
        }
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);  // the pool, and every read of tl
        // no extremum taken: the seed is the pool pixel nearest the pool's centroid (the first in pixel
        // order among ties)
        {
            long best = LONG_MAX;
            int first = INT_MAX;
            const int ns = taken == 0 ? n : 0;
            for (int i = lid; i < ns; i += wg) {
                const long er = (long)n * (pool[i] >> 16) - srow, ec = (long)n * (pool[i] & 0xffff) - scol;
                const long e = er * er + ec * ec;
                if (e < best) {
                    best = e;
                    first = i;
                }
            }
            tl[0][lid] = best;
            ti[0][lid] = first;
            barrier(CLK_LOCAL_MEM_FENCE);
            for (int s = wg / 2; s > 0; s >>= 1) {
                if (lid < s && (tl[0][lid + s] < tl[0][lid] || (tl[0][lid + s] == tl[0][lid] && ti[0][lid + s] < ti[0][lid]))) {
                    tl[0][lid] = tl[0][lid + s];
                    ti[0][lid] = ti[0][lid + s];
                }
                barrier(CLK_LOCAL_MEM_FENCE);
            }
            if (lid == 0 && fill && taken == 0)
                slot[0] = n > 0 ? pool[ti[0][0]] : 0;  // 0: as gt_mt_emit with an empty pool
        }
        const int seeds = max(taken, 1), last = fill ? quota : seeds;
        // the seeds' rows and columns: used[k][j][r], used[k][j][H + c] (0 / 1 over the pool's box)
        __global int *urow = used + (k * J + j) * (H + W), *ucol = urow + H;
        for (int x = pr0 + lid; x <= pr1; x += wg)
            urow[x] = 0;
        for (int x = pc0 + lid; x <= pc1; x += wg)
            ucol[x] = 0;
        barrier(CLK_GLOBAL_MEM_FENCE);
        if (lid == 0 && fill)
            for (int t = 0; t < seeds; ++t) {
                const int src = slot[4 * t];
                urow[src >> 16] = ucol[src & 0xffff] = 1;
            }
        barrier(CLK_GLOBAL_MEM_FENCE);
        int pr = 0, pc = 0;
        for (int f = seeds; f < last; ++f) {
            int v1 = 0, x1 = INT_MAX, v2 = 0, x2 = INT_MAX, v3 = -1, x3 = INT_MAX;
            for (int i = lid; i < n; i += wg) {
                const int rc = pool[i], r = rc >> 16, c = rc & 0xffff;
                int d, fl;
                if (f == seeds) {
                    d = 1 << 28;
                    for (int t = 0; t < seeds; ++t) {
                        const int src = slot[4 * t], dr = r - (src >> 16), dc = c - (src & 0xffff);
                        d = min(d, dr * dr + dc * dc);
                    }
                    fl = urow[r] << 1 | ucol[c];
                } else {
                    const int v = dd[i], dr = r - pr, dc = c - pc;
                    d = min(v >> 2, dr * dr + dc * dc);
                    fl = (v & 3) | (r == pr ? 2 : 0) | (c == pc ? 1 : 0);
                }
                dd[i] = d << 2 | fl;
                const int s1 = fl == 0 ? d : 0, s2 = fl != 3 ? d : 0;
                if (s1 > v1) {
                    v1 = s1;
                    x1 = i;
                }
                if (s2 > v2) {
                    v2 = s2;
                    x2 = i;
                }
                if (d > v3) {
                    v3 = d;
                    x3 = i;
                }
            }
            tv[0][lid] = v1;
            ti[0][lid] = x1;
            tv[1][lid] = v2;
            ti[1][lid] = x2;
            tv[2][lid] = v3;
            ti[2][lid] = x3;
            barrier(CLK_LOCAL_MEM_FENCE);
            for (int s = wg / 2; s > 0; s >>= 1) {
                if (lid < s)
                    for (int q = 0; q < 3; ++q)
                        mt_better(&tv[q][lid], &ti[q][lid], tv[q][lid + s], ti[q][lid + s]);
                barrier(CLK_LOCAL_MEM_FENCE);
            }
            if (lid == 0) {
                const int pick = tv[0][0] > 0 ? ti[0][0] : tv[1][0] > 0 ? ti[1][0] : ti[2][0];
                const int rc = pool[pick];
                slot[4 * f] = rc;
                sh[2] = rc >> 16;
                sh[3] = rc & 0xffff;
            }
            barrier(CLK_LOCAL_MEM_FENCE);
            pr = sh[2];
            pc = sh[3];
        }
    }
    barrier(CLK_GLOBAL_MEM_FENCE);  // the slots
    gt_mt_points(out, pts, values + k * HW, W, quota, lid, wg);  // step 8
}

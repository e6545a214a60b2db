// Observation points to groups and each group's moments (gputrack/ops/point_groups.py; paper 001
// eq. 7-11). Five kernels, launched in order on one queue:
//   gt_pg_factors (T): inverse Cholesky factors of the position and velocity blocks of Sigma
//                      (symmetrised) with their log-determinants and a cull radius, into g (T, 17);
//   gt_pg_sort    (1): the groups in x order and the largest cull radius;
//   gt_pg_assign  (N): the gate (eq. 8) and score (eq. 9-11) of the groups in the point's x strip;
//   gt_pg_order   (1): each group's points listed in point order;
//   gt_pg_moments (T): one group's points summed in point order: their mean, then (a second
//                      pass) their population covariance about it, in state order.
// State order x = [x xdot y ydot z zdot] (eq. 1): positions at 0, 2, 4, velocities at 1, 3, 5.

#define G 23  // [W_p (6), logdet, pd, W_v (6), logdet, pd, x, y, z, cull r^2, sorted x, its slot, max r]
#define CULL 1.0001f  // as gputrack/backends/taichi/point_groups.py

// Inverse Cholesky factor W (lower, 6 values), log det and a positive-definite flag of the 3x3 block
// A[i, i] (+ fl on the diagonal) of a row-major 6x6 matrix, written to g[0..7].
static void gt_gf_factor(__global const float *A, int i0, int i1, int i2, float fl, __global float *g)
{
    const float a00 = A[i0 * 7] + fl, a11 = A[i1 * 7] + fl, a22 = A[i2 * 7] + fl;
    const float a10 = 0.5f * (A[i1 * 6 + i0] + A[i0 * 6 + i1]);
    const float a20 = 0.5f * (A[i2 * 6 + i0] + A[i0 * 6 + i2]);
    const float a21 = 0.5f * (A[i2 * 6 + i1] + A[i1 * 6 + i2]);
    float w[6] = {0.f, 0.f, 0.f, 0.f, 0.f, 0.f};
    float ld = 0.f, ok = 0.f;
    if (a00 > 0.f) {
        const float l00 = sqrt(a00), l10 = a10 / l00, l20 = a20 / l00;
        const float r11 = a11 - l10 * l10;
        if (r11 > 0.f) {
            const float l11 = sqrt(r11), l21 = (a21 - l20 * l10) / l11;
            const float r22 = a22 - l20 * l20 - l21 * l21;
            if (r22 > 0.f) {
                const float l22 = sqrt(r22);
                w[0] = 1.f / l00;
                w[2] = 1.f / l11;
                w[5] = 1.f / l22;
                w[1] = -l10 * w[0] / l11;
                w[4] = -l21 * w[2] / l22;
                w[3] = -(l20 * w[0] + l21 * w[1]) / l22;
                ld = 2.f * (log(l00) + log(l11) + log(l22));
                ok = 1.f;
            }
        }
    }
    for (int k = 0; k < 6; ++k)
        g[k] = w[k];
    g[6] = ld;
    g[7] = ok;
}

static void gt_pg_factor(__global const float *S, int j, int i0, int i1, int i2, __global float *g)
{
    gt_gf_factor(S + (size_t)j * 36, i0, i1, i2, 0.f, g);
}

__kernel void gt_pg_factors(__global const float *S, __global const float *xi, __global const uchar *active,
                            __global float *g, const int T, const int has_active, const float gamma)
{
    const int j = get_global_id(0);
    if (j >= T)
        return;
    __global float *gj = g + (size_t)j * G;
    gt_pg_factor(S, j, 0, 2, 4, gj);
    gt_pg_factor(S, j, 1, 3, 5, gj + 8);
    __global const float *A = S + (size_t)j * 36;
    float r2 = CULL * gamma * (A[0] + A[14] + A[28]);  // a point farther is outside the gate: d2 >= |d|^2 / trace
    if (!(gj[7] > 0.5f) || (has_active && active[j] == 0))
        r2 = -1.f;  // gates nothing
    gj[16] = xi[j * 6];
    gj[17] = xi[j * 6 + 2];
    gj[18] = xi[j * 6 + 4];
    gj[19] = r2;
}

// One work-item: the groups in x order (insertion sort: T is small), the largest cull radius.
__kernel void gt_pg_sort(__global float *g, const int T)
{
    if (get_global_id(0) != 0)
        return;
    float rmax = 0.f;
    for (int j = 0; j < T; ++j) {
        const float key = g[(size_t)j * G + 16];
        int k = j;
        while (k > 0 && g[(size_t)(k - 1) * G + 20] > key) {
            g[(size_t)k * G + 20] = g[(size_t)(k - 1) * G + 20];
            g[(size_t)k * G + 21] = g[(size_t)(k - 1) * G + 21];
            --k;
        }
        g[(size_t)k * G + 20] = key;
        g[(size_t)k * G + 21] = (float)j;
        if (g[(size_t)j * G + 19] > 0.f)
            rmax = fmax(rmax, sqrt(g[(size_t)j * G + 19]));
    }
    g[22] = rmax;
}

static float gt_pg_d2(__global const float *w, float d0, float d1, float d2)
{
    const float e0 = w[0] * d0, e1 = w[1] * d0 + w[2] * d1, e2 = w[3] * d0 + w[4] * d1 + w[5] * d2;
    return e0 * e0 + e1 * e1 + e2 * e2;
}

__kernel void gt_pg_assign(__global const float *y, __global const float *lam, __global const float *xi,
                           __global const float *g, __global int *labels, const int N, const int n, const int T,
                           const float gamma)
{
    const int i = get_global_id(0);
    if (i >= N)
        return;
    int best = -1;
    if (i < n) {
        const float p0 = y[i * 3], p1 = y[i * 3 + 1], p2 = y[i * 3 + 2];
        const float v0 = lam[i * 3], v1 = lam[i * 3 + 1], v2 = lam[i * 3 + 2];
        if (isfinite(p0) && isfinite(p1) && isfinite(p2) && isfinite(v0) && isfinite(v1) && isfinite(v2)) {
            float top = 0.f;
            const float rmax = g[22];
            int lo = 0, hi = T;  // the first rank with x >= p0 - rmax: only the strip |x - p0| <= rmax can gate
            while (lo < hi) {
                const int mid = (lo + hi) / 2;
                if (g[(size_t)mid * G + 20] < p0 - rmax)
                    lo = mid + 1;
                else
                    hi = mid;
            }
            for (int r = lo; r < T && g[(size_t)r * G + 20] <= p0 + rmax; ++r) {
                const int j = (int)g[(size_t)r * G + 21];
                __global const float *gj = g + (size_t)j * G;
                const float e0 = p0 - gj[16], e1 = p1 - gj[17], e2 = p2 - gj[18];
                if (!(e0 * e0 + e1 * e1 + e2 * e2 < gj[19]))  // d2 >= |d|^2 / trace >= gamma, or no gate
                    continue;
                const float d2p = gt_pg_d2(gj, e0, e1, e2);  // eq. 8
                if (!(d2p < gamma))
                    continue;
                __global const float *x = xi + (size_t)j * 6;
                float s = -(d2p + gj[6]);  // eq. 9 (log)
                if (gj[15] > 0.5f)
                    s -= gt_pg_d2(gj + 8, v0 - x[1], v1 - x[3], v2 - x[5]) + gj[14];  // eq. 10
                if (best < 0 || s > top || (s == top && j < best)) {  // eq. 11; ties to the lowest slot
                    top = s;
                    best = j;
                }
            }
        }
    }
    labels[i] = best;
}

// One work-item: the points of each group listed in point order in idx[:N] (counts, starts, a
// scatter); idx[N + j] ends as group j's end, idx[N + T + j] its start.
__kernel void gt_pg_order(__global const int *labels, __global int *idx, const int N, const int n, const int T)
{
    if (get_global_id(0) != 0)
        return;
    for (int j = 0; j < T; ++j)
        idx[N + j] = 0;
    for (int i = 0; i < n; ++i)
        if (labels[i] >= 0)
            ++idx[N + labels[i]];
    int c = 0;
    for (int j = 0; j < T; ++j) {
        const int k = idx[N + j];
        idx[N + T + j] = c;
        idx[N + j] = c;
        c += k;
    }
    for (int i = 0; i < n; ++i)
        if (labels[i] >= 0)
            idx[idx[N + labels[i]]++] = i;
}

__kernel void gt_pg_moments(__global const float *y, __global const float *lam, __global const float *xi,
                            __global const int *idx, __global int *counts, __global float *mean,
                            __global float *cov, const int N, const int T)
{
    const int j = get_global_id(0);
    if (j >= T)
        return;
    __global const float *x = xi + (size_t)j * 6;
    const int a = idx[N + T + j], b = idx[N + j];  // the group's points: idx[a:b]
    const int c = b - a;
    float s1[6] = {0.f, 0.f, 0.f, 0.f, 0.f, 0.f};
    for (int k = a; k < b; ++k) {
        const int i = idx[k];
        s1[0] += y[i * 3] - x[0];
        s1[1] += lam[i * 3] - x[1];
        s1[2] += y[i * 3 + 1] - x[2];
        s1[3] += lam[i * 3 + 1] - x[3];
        s1[4] += y[i * 3 + 2] - x[4];
        s1[5] += lam[i * 3 + 2] - x[5];
    }
    counts[j] = c;
    float mu[6];
    for (int u = 0; u < 6; ++u) {
        mu[u] = x[u] + (c > 0 ? s1[u] / c : 0.f);
        mean[j * 6 + u] = mu[u];
    }
    float s2[36];
    for (int k = 0; k < 36; ++k)
        s2[k] = 0.f;
    for (int k = a; k < b; ++k) {  // second pass about the mean: no cancellation in float32
        const int i = idx[k];
        const float d[6] = {y[i * 3] - mu[0],     lam[i * 3] - mu[1],     y[i * 3 + 1] - mu[2],
                            lam[i * 3 + 1] - mu[3], y[i * 3 + 2] - mu[4], lam[i * 3 + 2] - mu[5]};
        for (int u = 0; u < 6; ++u)
            for (int w = 0; w < 6; ++w)
                s2[u * 6 + w] += d[u] * d[w];
    }
    for (int k = 0; k < 36; ++k)
        cov[(size_t)j * 36 + k] = c > 0 ? s2[k] / c : 0.f;  // eq. 7: cov(C_y)
}

// ---- group_frame: a whole frame of the group table (gputrack/ops/point_groups.py) ---------------
// Six kernels in order (gputrack/backends/opencl/point_groups.py), the loops of
// gputrack/backends/taichi/point_groups.py _frame:
//   gt_gf_predict    (T): predict every slot (eq. 2-3), the gate factors of Sigma + diag(min_spread^2);
//   gt_gf_buckets    (1): the gating groups listed in K buckets along x;
//   gt_gf_assign     (N): surface offset, gate and score of the groups of the point's bucket;
//   gt_pg_order      (1): each group's points in point order (above);
//   gt_gf_update     (T): moments, eq. 7, the stereo EKF update (eq. 4-6, Joseph form);
//   gt_gf_candidates (T): the merge pre-test (bounding spheres, eq. 13).
// Table rows of TC floats: x (6) at 0, P at 6, Sigma at 42, active at 78, count 79, mean 80,
// seen 86, candidates 87 (count), 88 (4 slots). Constants: F at 0, Q at 36, R at 72, then f, b, cx,
// cy, gamma, alpha_s, min_points, min_spread^2 (2), surface offset, merge gamma at 75.

#define TC 96
#define GC 32
#define GT_PD_EPS (4.0f * FLT_EPSILON)

__kernel void gt_gf_predict(__global float *tab, __global const float *c, __global float *g, const int T)
{
    const int j = get_global_id(0);
    if (j >= T)
        return;
    __global float *t = tab + (size_t)j * TC;
    float x[6], P[36], Q[36], FP[36];
    for (int a = 0; a < 6; ++a) {
        float s = 0.f;
        for (int k = 0; k < 6; ++k)
            s += c[a * 6 + k] * t[k];
        x[a] = s;
    }
    for (int a = 0; a < 6; ++a)
        for (int k = 0; k < 6; ++k) {
            P[a * 6 + k] = 0.5f * (t[6 + a * 6 + k] + t[6 + k * 6 + a]);
            Q[a * 6 + k] = 0.5f * (c[36 + a * 6 + k] + c[36 + k * 6 + a]);
        }
    for (int a = 0; a < 6; ++a)  // F P
        for (int k = 0; k < 6; ++k) {
            float s = 0.f;
            for (int m = 0; m < 6; ++m)
                s += c[a * 6 + m] * P[m * 6 + k];
            FP[a * 6 + k] = s;
        }
    for (int a = 0; a < 6; ++a)  // F P F^T + Q
        for (int k = 0; k < 6; ++k) {
            float s = 0.f;
            for (int m = 0; m < 6; ++m)
                s += FP[a * 6 + m] * c[k * 6 + m];
            P[a * 6 + k] = s + Q[a * 6 + k];
        }
    for (int a = 0; a < 6; ++a) {
        t[a] = x[a];
        for (int k = 0; k < 6; ++k)
            t[6 + a * 6 + k] = 0.5f * (P[a * 6 + k] + P[k * 6 + a]);
    }
    __global float *gj = g + (size_t)j * GC;
    const float fp = c[82], fv = c[83];
    gt_gf_factor(t + 42, 0, 2, 4, fp, gj);
    gt_gf_factor(t + 42, 1, 3, 5, fv, gj + 8);
    float r2 = CULL * c[79] * (t[42] + t[42 + 14] + t[42 + 28] + 3.f * fp);
    if (!(gj[7] > 0.5f) || !(t[78] > 0.5f))
        r2 = -1.f;  // gates nothing
    gj[16] = x[0];
    gj[17] = x[2];
    gj[18] = x[4];
    gj[19] = r2;
}

inline float gt_gf_reach(__global const float *gj) { return 1.001f * sqrt(gj[19]) + 1e-4f * fabs(gj[16]); }

// One work-item: the buckets' origin and width into g[20], g[21]; at idx[N + 2T]: K + 1 starts,
// K cursors, the lists (slots ascending in each).
__kernel void gt_gf_buckets(__global float *g, __global int *idx, const int N, const int T, const int K)
{
    if (get_global_id(0) != 0)
        return;
    float lo = 3.4e38f, hi = -3.4e38f;
    for (int j = 0; j < T; ++j) {
        __global const float *gj = g + (size_t)j * GC;
        if (gj[19] > 0.f) {
            const float r = gt_gf_reach(gj);
            lo = fmin(lo, gj[16] - r);
            hi = fmax(hi, gj[16] + r);
        }
    }
    float w = (hi - lo) / K;
    if (!(w > 0.f))
        w = 1.f;
    g[20] = lo;
    g[21] = w;
    __global int *b = idx + N + 2 * T;
    for (int k = 0; k <= K; ++k)
        b[k] = 0;
    for (int pass = 0; pass < 2; ++pass) {
        for (int j = 0; j < T; ++j) {
            __global const float *gj = g + (size_t)j * GC;
            if (!(gj[19] > 0.f))
                continue;
            const float r = gt_gf_reach(gj);
            const int k0 = max(0, min(K - 1, (int)floor((gj[16] - r - lo) / w)));
            const int k1 = max(0, min(K - 1, (int)floor((gj[16] + r - lo) / w)));
            for (int k = k0; k <= k1; ++k) {
                if (pass == 0)
                    b[k + 1]++;
                else
                    b[2 * K + 1 + b[K + 1 + k]++] = j;
            }
        }
        if (pass == 0) {
            for (int k = 0; k < K; ++k)
                b[k + 1] += b[k];
            for (int k = 0; k < K; ++k)
                b[K + 1 + k] = b[k];
        }
    }
}

// point i moved off mm further along its viewing ray (NaN where it has none)
inline void gt_gf_point(__global const float *pts, int i, float off, float *p)
{
    p[0] = pts[i * 3];
    p[1] = pts[i * 3 + 1];
    p[2] = pts[i * 3 + 2];
    if (off > 0.f) {
        const float r = sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
        const float s = r > 0.f ? 1.f + off / r : NAN;
        p[0] *= s;
        p[1] *= s;
        p[2] *= s;
    }
}

__kernel void gt_gf_assign(__global const float *pts, __global const float *vel, __global const float *tab,
                           __global const float *c, __global const float *g, __global const int *idx,
                           __global int *labels, const int N, const int n, const int T, const int K)
{
    const int i = get_global_id(0);
    if (i >= N)
        return;
    int best = -1;
    if (i < n) {
        float p[3];
        gt_gf_point(pts, i, c[84], p);
        const float v0 = vel[i * 3], v1 = vel[i * 3 + 1], v2 = vel[i * 3 + 2];
        const float gamma = c[79];
        const float kf = (p[0] - g[20]) / g[21];
        if (isfinite(p[0]) && isfinite(p[1]) && isfinite(p[2]) && isfinite(v0) && isfinite(v1) && isfinite(v2) &&
            kf >= 0.f && kf < (float)K) {
            __global const int *b = idx + N + 2 * T;
            const int k = (int)kf;
            float top = 0.f;
            for (int q = b[k]; q < b[k + 1]; ++q) {
                const int j = b[2 * K + 1 + q];
                __global const float *gj = g + (size_t)j * GC;
                const float e0 = p[0] - gj[16], e1 = p[1] - gj[17], e2 = p[2] - gj[18];
                if (!(e0 * e0 + e1 * e1 + e2 * e2 < gj[19]))
                    continue;
                const float d2p = gt_pg_d2(gj, e0, e1, e2);  // eq. 8
                if (!(d2p < gamma))
                    continue;
                __global const float *x = tab + (size_t)j * TC;
                float s = -(d2p + gj[6]);  // eq. 9 (log)
                if (gj[15] > 0.5f)
                    s -= gt_pg_d2(gj + 8, v0 - x[1], v1 - x[3], v2 - x[5]) + gj[14];  // eq. 10
                if (best < 0 || s > top || (s == top && j < best)) {  // eq. 11; ties to the lowest slot
                    top = s;
                    best = j;
                }
            }
        }
    }
    labels[i] = best;
}

// the stereo EKF update of one slot (eq. 4-6, Joseph form, as ekf_update_stereo); 0 where the
// state is behind the camera or the innovation covariance is not positive definite
static int gt_gf_ekf(__global float *t, const float *mu, __global const float *c, float *x)
{
    const float f = c[75], b = c[76], cx = c[77], cy = c[78];
    const float z[3] = {f * mu[0] / mu[4] + cx, f * mu[2] / mu[4] + cy, f * b / mu[4]};  // eq. 6
    float P[36];
    for (int a = 0; a < 6; ++a)
        for (int k = 0; k < 6; ++k)
            P[a * 6 + k] = 0.5f * (t[6 + a * 6 + k] + t[6 + k * 6 + a]);
    const float X = x[0], Y = x[2], Z = x[4];
    int ok = Z > 0.f;
    const float Zs = ok ? Z : 1.f;
    const float h[3] = {f * X / Zs + cx, f * Y / Zs + cy, f * b / Zs};
    float H[18] = {0.f};
    H[0] = f / Zs;
    H[4] = -f * X / (Zs * Zs);
    H[6 + 2] = f / Zs;
    H[6 + 4] = -f * Y / (Zs * Zs);
    H[12 + 4] = -f * b / (Zs * Zs);
    const float R[9] = {c[72], 0.f, 0.f, 0.f, c[73], 0.f, 0.f, 0.f, c[74]};
    float HP[18], S[9], L[9] = {0.f};
    for (int a = 0; a < 3; ++a)
        for (int k = 0; k < 6; ++k) {
            float s = 0.f;
            for (int m = 0; m < 6; ++m)
                s += H[a * 6 + m] * P[m * 6 + k];
            HP[a * 6 + k] = s;
        }
    for (int a = 0; a < 3; ++a)
        for (int k = 0; k < 3; ++k) {
            float s = 0.f;
            for (int m = 0; m < 6; ++m)
                s += HP[a * 6 + m] * H[k * 6 + m];
            S[a * 3 + k] = s + R[a * 3 + k];
        }
    for (int a = 0; a < 3; ++a) {
        float d = S[a * 3 + a];
        for (int k = 0; k < a; ++k)
            d -= L[a * 3 + k] * L[a * 3 + k];
        if (!(d > GT_PD_EPS * S[a * 3 + a])) {
            ok = 0;
            d = 1.f;
        }
        L[a * 3 + a] = sqrt(d);
        for (int r = a + 1; r < 3; ++r) {
            float v = S[r * 3 + a];
            for (int k = 0; k < a; ++k)
                v -= L[r * 3 + k] * L[a * 3 + k];
            L[r * 3 + a] = v / L[a * 3 + a];
        }
    }
    if (!ok)
        return 0;
    float W[18], Kt[18];
    for (int a = 0; a < 3; ++a)
        for (int col = 0; col < 6; ++col) {
            float v = HP[a * 6 + col];
            for (int k = 0; k < a; ++k)
                v -= L[a * 3 + k] * W[k * 6 + col];
            W[a * 6 + col] = v / L[a * 3 + a];
        }
    for (int a = 2; a >= 0; --a)
        for (int col = 0; col < 6; ++col) {
            float v = W[a * 6 + col];
            for (int k = a + 1; k < 3; ++k)
                v -= L[k * 3 + a] * Kt[k * 6 + col];
            Kt[a * 6 + col] = v / L[a * 3 + a];
        }
    const float y[3] = {z[0] - h[0], z[1] - h[1], z[2] - h[2]};
    for (int a = 0; a < 6; ++a)
        x[a] += Kt[a] * y[0] + Kt[6 + a] * y[1] + Kt[12 + a] * y[2];  // K = Kt^T
    float B[36], BH[18], P1[36];
    for (int a = 0; a < 6; ++a)  // B = P - K HP
        for (int k = 0; k < 6; ++k)
            B[a * 6 + k] = P[a * 6 + k] - (Kt[a] * HP[k] + Kt[6 + a] * HP[6 + k] + Kt[12 + a] * HP[12 + k]);
    for (int a = 0; a < 6; ++a)  // B H^T
        for (int k = 0; k < 3; ++k) {
            float s = 0.f;
            for (int m = 0; m < 6; ++m)
                s += B[a * 6 + m] * H[k * 6 + m];
            BH[a * 3 + k] = s;
        }
    for (int a = 0; a < 6; ++a)  // B - (B H^T) K^T + K R K^T
        for (int k = 0; k < 6; ++k) {
            float s1 = 0.f, s2 = 0.f;
            for (int m = 0; m < 3; ++m) {
                s1 += BH[a * 3 + m] * Kt[m * 6 + k];
                float kr = 0.f;
                for (int q = 0; q < 3; ++q)
                    kr += Kt[q * 6 + a] * R[q * 3 + m];
                s2 += kr * Kt[m * 6 + k];
            }
            P1[a * 6 + k] = B[a * 6 + k] - s1 + s2;
        }
    for (int a = 0; a < 6; ++a)
        for (int k = 0; k < 6; ++k)
            t[6 + a * 6 + k] = 0.5f * (P1[a * 6 + k] + P1[k * 6 + a]);
    return 1;
}

// an upper bound of the largest eigenvalue of a 3x3 block of A (plus fl I): min(trace, largest row sum)
inline float gt_gf_bound(__global const float *A, int i0, int i1, int i2, float fl)
{
    const int id[3] = {i0, i1, i2};
    float tr = 0.f, rows = 0.f;
    for (int a = 0; a < 3; ++a) {
        float s = 0.f;
        for (int k = 0; k < 3; ++k) {
            float v = A[id[a] * 6 + id[k]];
            if (a == k) {
                v += fl;
                tr += v;
            }
            s += fabs(v);
        }
        rows = fmax(rows, s);
    }
    return fmin(tr, rows);
}

__kernel void gt_gf_update(__global const float *pts, __global const float *vel, __global float *tab,
                           __global const float *c, __global float *g, __global const int *idx, const int N,
                           const int T)
{
    const int j = get_global_id(0);
    if (j >= T)
        return;
    __global float *t = tab + (size_t)j * TC;
    const float off = c[84];
    const int a = idx[N + T + j], b = idx[N + j];  // the group's points: idx[a:b]
    const int cnt = b - a;
    float xi[6], s1[6] = {0.f, 0.f, 0.f, 0.f, 0.f, 0.f};
    for (int u = 0; u < 6; ++u)
        xi[u] = t[u];
    for (int k = a; k < b; ++k) {
        const int i = idx[k];
        float p[3];
        gt_gf_point(pts, i, off, p);
        s1[0] += p[0] - xi[0];
        s1[1] += vel[i * 3] - xi[1];
        s1[2] += p[1] - xi[2];
        s1[3] += vel[i * 3 + 1] - xi[3];
        s1[4] += p[2] - xi[4];
        s1[5] += vel[i * 3 + 2] - xi[5];
    }
    float mu[6];
    for (int u = 0; u < 6; ++u)
        mu[u] = xi[u] + (cnt > 0 ? s1[u] / cnt : 0.f);
    float s2[36];
    for (int k = 0; k < 36; ++k)
        s2[k] = 0.f;
    for (int k = a; k < b; ++k) {  // second pass about the mean: no cancellation in float32
        const int i = idx[k];
        float p[3];
        gt_gf_point(pts, i, off, p);
        const float d[6] = {p[0] - mu[0], vel[i * 3] - mu[1], p[1] - mu[2],
                            vel[i * 3 + 1] - mu[3], p[2] - mu[4], vel[i * 3 + 2] - mu[5]};
        for (int u = 0; u < 6; ++u)
            for (int w = 0; w < 6; ++w)
                s2[u * 6 + w] += d[u] * d[w];
    }
    const int enough = cnt >= (int)c[81];
    const int seen = t[78] > 0.5f && enough && mu[4] > 0.f;
    float S[36];
    for (int k = 0; k < 36; ++k)
        S[k] = seen ? c[80] * t[42 + k] + (1.f - c[80]) * (s2[k] / cnt) : t[42 + k];  // eq. 7
    for (int u = 0; u < 6; ++u)
        for (int w = 0; w < 6; ++w)
            t[42 + u * 6 + w] = 0.5f * (S[u * 6 + w] + S[w * 6 + u]);
    float x[6];
    for (int u = 0; u < 6; ++u)
        x[u] = xi[u];
    if (seen && !gt_gf_ekf(t, mu, c, x))
        for (int u = 0; u < 6; ++u)
            x[u] = xi[u];
    for (int u = 0; u < 6; ++u) {
        t[u] = x[u];
        t[80 + u] = mu[u];
    }
    t[79] = (float)cnt;
    t[86] = (float)seen;
    __global float *gj = g + (size_t)j * GC;  // the merge regions' centre and radii
    gj[23] = x[0];
    gj[24] = x[2];
    gj[25] = x[4];
    gj[26] = enough ? mu[1] : x[1];
    gj[27] = enough ? mu[3] : x[3];
    gj[28] = enough ? mu[5] : x[5];
    gj[29] = sqrt(c[85] * gt_gf_bound(t + 42, 0, 2, 4, c[82]));
    gj[30] = sqrt(c[85] * gt_gf_bound(t + 42, 1, 3, 5, c[83]));
}

__kernel void gt_gf_candidates(__global float *tab, __global const float *g, const int T)
{
    const int i = get_global_id(0);
    if (i >= T)
        return;
    __global float *t = tab + (size_t)i * TC;
    __global const float *gi = g + (size_t)i * GC;
    int nc = 0;
    for (int k = 0; k < 4; ++k)
        t[88 + k] = -1.f;
    if (t[78] > 0.5f)
        for (int j = i + 1; j < T; ++j) {
            if (!(tab[(size_t)j * TC + 78] > 0.5f))
                continue;
            __global const float *gj = g + (size_t)j * GC;
            const float a0 = gi[23] - gj[23], a1 = gi[24] - gj[24], a2 = gi[25] - gj[25];
            const float b0 = gi[26] - gj[26], b1 = gi[27] - gj[27], b2 = gi[28] - gj[28];
            const float dp = sqrt(a0 * a0 + a1 * a1 + a2 * a2), dv = sqrt(b0 * b0 + b1 * b1 + b2 * b2);
            if (dp <= gi[29] + gj[29] && dv <= gi[30] + gj[30]) {
                if (nc < 4)
                    t[88 + nc] = (float)j;
                ++nc;
            }
        }
    t[87] = (float)nc;
}

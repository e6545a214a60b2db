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

static void gt_pg_factor(__global const float *S, int j, int i0, int i1, int i2, __global float *g)
{
    __global const float *A = S + (size_t)j * 36;
    const float a00 = A[i0 * 6 + i0], a11 = A[i1 * 6 + i1], a22 = A[i2 * 6 + i2];
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

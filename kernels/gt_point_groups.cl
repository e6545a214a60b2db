// Observation points to groups and each group's moments (gputrack/ops/point_groups.py; paper 001
// eq. 7-11). Three kernels, launched in order on one queue:
//   gt_pg_factors (T): inverse Cholesky factors of the position and velocity blocks of Sigma
//                      (symmetrised) with their log-determinants, into g (T, 16);
//   gt_pg_assign  (N): every group's gate (eq. 8) and score (eq. 9-11) for one point;
//   gt_pg_moments (T): one group's points summed in point order: their mean, then (a second
//                      pass) their population covariance about it, in state order.
// State order x = [x xdot y ydot z zdot] (eq. 1): positions at 0, 2, 4, velocities at 1, 3, 5.

#define G 16

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

__kernel void gt_pg_factors(__global const float *S, __global float *g, const int T)
{
    const int j = get_global_id(0);
    if (j >= T)
        return;
    gt_pg_factor(S, j, 0, 2, 4, g + (size_t)j * G);
    gt_pg_factor(S, j, 1, 3, 5, g + (size_t)j * G + 8);
}

static float gt_pg_d2(__global const float *w, float d0, float d1, float d2)
{
    const float e0 = w[0] * d0, e1 = w[1] * d0 + w[2] * d1, e2 = w[3] * d0 + w[4] * d1 + w[5] * d2;
    return e0 * e0 + e1 * e1 + e2 * e2;
}

__kernel void gt_pg_assign(__global const float *y, __global const float *lam, __global const float *xi,
                           __global const uchar *active, __global const float *g, __global int *labels,
                           const int N, const int n, const int T, const int has_active, const float gamma)
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
            for (int j = 0; j < T; ++j) {
                __global const float *gj = g + (size_t)j * G;
                if (!(gj[7] > 0.5f) || (has_active && active[j] == 0))
                    continue;
                __global const float *x = xi + (size_t)j * 6;
                const float d2p = gt_pg_d2(gj, p0 - x[0], p1 - x[2], p2 - x[4]);  // eq. 8
                if (!(d2p < gamma))
                    continue;
                float s = -(d2p + gj[6]);  // eq. 9 (log)
                if (gj[15] > 0.5f)
                    s -= gt_pg_d2(gj + 8, v0 - x[1], v1 - x[3], v2 - x[5]) + gj[14];  // eq. 10
                if (best < 0 || s > top) {  // eq. 11: the largest m_total; ties to the lowest slot
                    top = s;
                    best = j;
                }
            }
        }
    }
    labels[i] = best;
}

__kernel void gt_pg_moments(__global const float *y, __global const float *lam, __global const float *xi,
                            __global const int *labels, __global int *counts, __global float *mean,
                            __global float *cov, const int n, const int T)
{
    const int j = get_global_id(0);
    if (j >= T)
        return;
    __global const float *x = xi + (size_t)j * 6;
    int c = 0;
    float s1[6] = {0.f, 0.f, 0.f, 0.f, 0.f, 0.f};
    for (int i = 0; i < n; ++i) {
        if (labels[i] != j)
            continue;
        ++c;
        s1[0] += y[i * 3] - x[0];
        s1[1] += lam[i * 3] - x[1];
        s1[2] += y[i * 3 + 1] - x[2];
        s1[3] += lam[i * 3 + 1] - x[3];
        s1[4] += y[i * 3 + 2] - x[4];
        s1[5] += lam[i * 3 + 2] - x[5];
    }
    counts[j] = c;
    float mu[6];
    for (int a = 0; a < 6; ++a) {
        mu[a] = x[a] + (c > 0 ? s1[a] / c : 0.f);
        mean[j * 6 + a] = mu[a];
    }
    float s2[36];
    for (int k = 0; k < 36; ++k)
        s2[k] = 0.f;
    for (int i = 0; i < n; ++i) {  // second pass about the mean: no cancellation in float32
        if (labels[i] != j)
            continue;
        const float d[6] = {y[i * 3] - mu[0],     lam[i * 3] - mu[1],     y[i * 3 + 1] - mu[2],
                            lam[i * 3 + 1] - mu[3], y[i * 3 + 2] - mu[4], lam[i * 3 + 2] - mu[5]};
        for (int a = 0; a < 6; ++a)
            for (int b = 0; b < 6; ++b)
                s2[a * 6 + b] += d[a] * d[b];
    }
    for (int k = 0; k < 36; ++k)
        cov[(size_t)j * 36 + k] = c > 0 ? s2[k] / c : 0.f;  // eq. 7: cov(C_y)
}

// Mahalanobis gating that returns only the gated pairs (gputrack/ops/gating.py; paper 001 eq. 8).
// One work-item per track: S = H Ps H^T + Rs and its Cholesky factor (as the NumPy reference:
// symmetrised P and R, pivot test d_j > PD_TOL S_jj), then a scan of the detections (with
// SORTED_Z, only the strip |z_0 - (H x)_0| <= sqrt(thr S_00), found by a binary search), appending
// each d2 < thr to the track's row. Defines: REAL, N, M, HAS_ACTIVE, SORTED_Z, PD_TOL, STRIP_SLACK.

// Defaults (a build without the launcher's defines, as host/doctor.py does): float32, the papers'
// constant-velocity state (N = 6) observed in position (M = 3), full scan, no active mask.
#ifndef REAL
#define REAL float
#endif
#ifndef N
#define N 6
#endif
#ifndef M
#define M 3
#endif
#ifndef HAS_ACTIVE
#define HAS_ACTIVE 0
#endif
#ifndef SORTED_Z
#define SORTED_Z 0
#endif
#ifndef PD_TOL
#define PD_TOL 4.7683716e-07
#endif
#ifndef STRIP_SLACK
#define STRIP_SLACK 1e-3
#endif

__kernel void gt_gate_pairs(
    __global const REAL *x, __global const REAL *P, __global const REAL *H, __global const REAL *R,
    __global const REAL *z, __global const uchar *active, __global int *cnt, __global int *det,
    __global REAL *d2, __global REAL *tr, const int T, const int D, const int K, const REAL thr)
{
    const int t = get_global_id(0);
    if (t >= T)
        return;
    REAL Ps[N][N], hx[M], HP[M][N], S[M][M], L[M][M], inv[M];
    __global const REAL *xt = x + (size_t)t * N, *Pt = P + (size_t)t * N * N;
    for (int i = 0; i < N; i++)
        for (int j = 0; j < N; j++)
            Ps[i][j] = (REAL)0.5 * (Pt[i * N + j] + Pt[j * N + i]);
    for (int a = 0; a < M; a++) {
        REAL h = 0;
        for (int j = 0; j < N; j++)
            HP[a][j] = 0;
        for (int k = 0; k < N; k++) {
            h += H[a * N + k] * xt[k];
            for (int j = 0; j < N; j++)
                HP[a][j] += H[a * N + k] * Ps[k][j];
        }
        hx[a] = h;
    }
    REAL trace = 0;
    for (int a = 0; a < M; a++)
        for (int c = 0; c < M; c++) {
            REAL acc = 0;
            for (int k = 0; k < N; k++)
                acc += HP[a][k] * H[c * N + k];
            if (a == c)
                trace += acc;  // trace(H P H^T)
            S[a][c] = acc + (REAL)0.5 * (R[a * M + c] + R[c * M + a]);
        }
    int ok = 1;
    for (int j = 0; j < M; j++) {
        REAL dj = S[j][j];
        for (int k = 0; k < j; k++)
            dj -= L[j][k] * L[j][k];
        if (!(dj > (REAL)PD_TOL * S[j][j])) {
            ok = 0;
            dj = 1;
        }
        L[j][j] = sqrt(dj);
        inv[j] = (REAL)1 / L[j][j];
        for (int i = j + 1; i < M; i++) {
            REAL s = S[i][j];
            for (int k = 0; k < j; k++)
                s -= L[i][k] * L[j][k];
            L[i][j] = s * inv[j];
        }
    }
#if HAS_ACTIVE
    if (active[t] == 0)
        ok = 0;
#endif
    int c = 0;
    if (ok) {
        int lo = 0;
#if SORTED_Z
        const REAL w = sqrt(thr * S[0][0]) * (REAL)(1 + STRIP_SLACK) + (REAL)1e-30;
        const REAL bottom = hx[0] - w, top = hx[0] + w;
        int hi = D;
        while (lo < hi) {  // first detection with z_0 >= bottom
            const int mid = (lo + hi) / 2;
            if (z[(size_t)mid * M] < bottom)
                lo = mid + 1;
            else
                hi = mid;
        }
#endif
        for (int d = lo; d < D; d++) {
            __global const REAL *zd = z + (size_t)d * M;
#if SORTED_Z
            if (zd[0] > top)
                break;
#endif
            REAL wv[M], acc = 0;  // L^-1 (z_d - H x)
            for (int i = 0; i < M; i++) {
                REAL s = zd[i] - hx[i];
                for (int k = 0; k < i; k++)
                    s -= L[i][k] * wv[k];
                wv[i] = s * inv[i];
                acc += wv[i] * wv[i];
            }
            if (acc < thr) {  // eq. 8 gate
                if (c < K) {
                    det[(size_t)t * K + c] = d;
                    d2[(size_t)t * K + c] = acc;
                }
                c++;
            }
        }
    }
    cnt[t] = c;
    tr[t] = trace;
}

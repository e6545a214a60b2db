// Batched Kalman filter (papers 001 and 002): one work-item per track.
// The numerics follow gputrack/backends/reference/kalman.py step for step.
//
// Build defines (set by gputrack/backends/opencl/kalman.py):
//   REAL          float or double
//   N, M          state and observation sizes
//   MODE          0 predict only, 1 linear update, 2 stereo EKF update (N = 6, M = 3)
//   DO_PREDICT    1: predict with F, Q before the update
//   HAS_MASK, HAS_GAIN
//   F_PT, Q_PT, H_PT, R_PT   1: per-track (T,r,c) matrix, 0: shared (r,c)
//   FPAT, QPAT, HPAT, RPAT   comma-separated row bitmasks of the possibly non-zero entries of
//                 F, Q, H and R (all ones when unknown); known zeros are skipped at compile time
//   PD_TOL        PD_EPS_FACTOR * machine epsilon of REAL

// Defaults: a plain build (no -D options, as host/doctor.py does) gives the float32 linear update
// of the papers' constant-velocity model (N = 6, M = 3, shared dense matrices).
#ifndef REAL
#define REAL float
#define REAL_IS_DOUBLE 0
#endif
#ifndef N
#define N 6
#endif
#ifndef M
#define M 3
#endif
#ifndef MODE
#define MODE 1
#endif
#ifndef DO_PREDICT
#define DO_PREDICT 0
#endif
#ifndef HAS_MASK
#define HAS_MASK 0
#endif
#ifndef HAS_GAIN
#define HAS_GAIN 0
#endif
#ifndef F_PT
#define F_PT 0
#define Q_PT 0
#define H_PT 0
#define R_PT 0
#endif
#ifndef FPAT
#define FPAT 63u, 63u, 63u, 63u, 63u, 63u
#define QPAT 63u, 63u, 63u, 63u, 63u, 63u
#define HPAT 63u, 63u, 63u
#define RPAT 7u, 7u, 7u
#endif
#ifndef PD_TOL
#define PD_TOL 4.7683716e-07
#endif

#if REAL_IS_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif

#define GT_UPDATED 0
#define GT_SKIPPED 1
#define GT_NOT_PD 2
#define GT_BAD_DEPTH 3

#define AT(A, PT, R_, C_, t, i, j) ((PT) ? (A)[((size_t)(t) * (R_) + (i)) * (C_) + (j)] : (A)[(i) * (C_) + (j)])

__constant uint gt_fpat[N] = {FPAT};
__constant uint gt_qpat[N] = {QPAT};
__constant uint gt_hpat[M] = {HPAT};
__constant uint gt_rpat[M] = {RPAT};
#define FNZ(i, k) ((gt_fpat[i] >> (k)) & 1u)
#define QNZ(i, k) ((gt_qpat[i] >> (k)) & 1u)
#define HNZ(i, k) ((gt_hpat[i] >> (k)) & 1u)
#define RNZ(i, k) ((gt_rpat[i] >> (k)) & 1u)
// (A + A^T)/2 at (i, j), reading only the entries that may be non-zero
#define SYM(A, PT, NZ, R_, t, i, j) \
    ((REAL)0.5 * ((NZ(i, j) ? AT(A, PT, R_, R_, t, i, j) : (REAL)0) + (NZ(j, i) ? AT(A, PT, R_, R_, t, j, i) : (REAL)0)))

__kernel void gt_kf(
    __global const REAL *x, __global const REAL *P, __global const REAL *z,
    __global const REAL *F, __global const REAL *Q, __global const REAL *H, __global const REAL *R,
    __global const uchar *mask, __global const REAL *gain,
    __global REAL *xo, __global REAL *Po, __global uchar *st,
    const REAL f, const REAL b, const REAL cx, const REAL cy, const int T)
{
    const int t = get_global_id(0);
    if (t >= T)
        return;
    REAL xv[N], Pm[N][N];
#pragma unroll
    for (int i = 0; i < N; i++) {
        xv[i] = x[(size_t)t * N + i];
#pragma unroll
        for (int j = 0; j < N; j++)
            Pm[i][j] = P[((size_t)t * N + i) * N + j];
    }
#if DO_PREDICT
    {
        // eq. 2-3: x' = F x, P' = F P F^T + Q (P, Q symmetrised; P' exactly symmetric)
        REAL xp[N], Ps[N][N], FP[N][N];
#pragma unroll
        for (int i = 0; i < N; i++) {
            REAL s = 0;
#pragma unroll
            for (int k = 0; k < N; k++)
                if (FNZ(i, k))
                    s += AT(F, F_PT, N, N, t, i, k) * xv[k];
            xp[i] = s;
#pragma unroll
            for (int j = 0; j < N; j++)
                Ps[i][j] = (REAL)0.5 * (Pm[i][j] + Pm[j][i]);
        }
#pragma unroll
        for (int i = 0; i < N; i++) {
#pragma unroll
            for (int j = 0; j < N; j++)
                FP[i][j] = 0;
#pragma unroll
            for (int k = 0; k < N; k++)
                if (FNZ(i, k)) {
                    const REAL a = AT(F, F_PT, N, N, t, i, k);
#pragma unroll
                    for (int j = 0; j < N; j++)
                        FP[i][j] += a * Ps[k][j];
                }
        }
#pragma unroll
        for (int i = 0; i < N; i++) {
            xv[i] = xp[i];
#pragma unroll
            for (int j = i; j < N; j++) {
                REAL s = SYM(Q, Q_PT, QNZ, N, t, i, j);
#pragma unroll
                for (int k = 0; k < N; k++)
                    if (FNZ(j, k))
                        s += FP[i][k] * AT(F, F_PT, N, N, t, j, k);
                Pm[i][j] = s;
                Pm[j][i] = s;
            }
        }
    }
#endif
#if MODE == 0
#pragma unroll
    for (int i = 0; i < N; i++) {
        xo[(size_t)t * N + i] = xv[i];
#pragma unroll
        for (int j = 0; j < N; j++)
            Po[((size_t)t * N + i) * N + j] = Pm[i][j];
    }
#else
    int code = GT_UPDATED;
#if HAS_MASK
    if (mask[t] == 0)
        code = GT_SKIPPED;
#endif
    REAL zv[M];
#pragma unroll
    for (int a = 0; a < M; a++) {
        zv[a] = z[(size_t)t * M + a];
        if (!isfinite(zv[a]))
            code = GT_SKIPPED;  // missing observation
    }
#if MODE == 2
    if (code == GT_UPDATED && !(xv[4] > 0))
        code = GT_BAD_DEPTH;
#endif
    REAL xn[N], Pn[N][N];
    if (code == GT_UPDATED) {
        const REAL s = HAS_GAIN ? gain[t] : (REAL)1;
        REAL Ps[N][N], Hm[M][N], y[M], Rs[M][M];
#pragma unroll
        for (int i = 0; i < N; i++)
#pragma unroll
            for (int j = 0; j < N; j++)
                Ps[i][j] = DO_PREDICT ? Pm[i][j] : (REAL)0.5 * (Pm[i][j] + Pm[j][i]);  // exact after a prediction
#pragma unroll
        for (int a = 0; a < M; a++)
#pragma unroll
            for (int c = 0; c < M; c++)
                Rs[a][c] = SYM(R, R_PT, RNZ, M, t, a, c);
#if MODE == 2
        // eq. 6 and its Jacobian at the (predicted) state
#pragma unroll
        for (int a = 0; a < M; a++)
#pragma unroll
            for (int k = 0; k < N; k++)
                Hm[a][k] = 0;
        const REAL iz = (REAL)1 / xv[4];
        Hm[0][0] = f * iz;
        Hm[0][4] = -f * xv[0] * iz * iz;
        Hm[1][2] = f * iz;
        Hm[1][4] = -f * xv[2] * iz * iz;
        Hm[2][4] = -f * b * iz * iz;
        y[0] = zv[0] - (f * xv[0] * iz + cx);
        y[1] = zv[1] - (f * xv[2] * iz + cy);
        y[2] = zv[2] - f * b * iz;
#else
#pragma unroll
        for (int a = 0; a < M; a++) {
            REAL v = zv[a];
#pragma unroll
            for (int k = 0; k < N; k++) {
                Hm[a][k] = HNZ(a, k) ? AT(H, H_PT, M, N, t, a, k) : (REAL)0;
                if (HNZ(a, k))
                    v -= Hm[a][k] * xv[k];
            }
            y[a] = v;
        }
#endif
        // H P (M,N) and S = H P H^T + R (lower triangle)
        REAL HP[M][N], S[M][M], L[M][M], inv[M];
#pragma unroll
        for (int a = 0; a < M; a++) {
#pragma unroll
            for (int j = 0; j < N; j++)
                HP[a][j] = 0;
#pragma unroll
            for (int k = 0; k < N; k++)
                if (HNZ(a, k)) {
#pragma unroll
                    for (int j = 0; j < N; j++)
                        HP[a][j] += Hm[a][k] * Ps[k][j];
                }
        }
#pragma unroll
        for (int a = 0; a < M; a++)
#pragma unroll
            for (int c = 0; c <= a; c++) {
                REAL v = 0;
#pragma unroll
                for (int k = 0; k < N; k++)
                    if (HNZ(c, k))
                        v += HP[a][k] * Hm[c][k];
                S[a][c] = v + Rs[a][c];
            }
        // Cholesky S = L L^T, with the reference's positive-definiteness test
        int ok = 1;
#pragma unroll
        for (int j = 0; j < M; j++) {
            REAL d = S[j][j];
#pragma unroll
            for (int k = 0; k < j; k++)
                d -= L[j][k] * L[j][k];
            if (!(d > (REAL)PD_TOL * S[j][j])) {
                ok = 0;
                d = 1;
            }
            d = sqrt(d);
            L[j][j] = d;
            inv[j] = (REAL)1 / d;
#pragma unroll
            for (int i = j + 1; i < M; i++) {
                REAL v = S[i][j];
#pragma unroll
                for (int k = 0; k < j; k++)
                    v -= L[i][k] * L[j][k];
                L[i][j] = v * inv[j];
            }
        }
        if (ok) {
            // K^T = S^-1 (H P): forward then backward substitution
            REAL Kt[M][N];
#pragma unroll
            for (int c = 0; c < N; c++) {
#pragma unroll
                for (int i = 0; i < M; i++) {
                    REAL v = HP[i][c];
#pragma unroll
                    for (int k = 0; k < i; k++)
                        v -= L[i][k] * Kt[k][c];
                    Kt[i][c] = v * inv[i];
                }
#pragma unroll
                for (int i = M - 1; i >= 0; i--) {
                    REAL v = Kt[i][c];
#pragma unroll
                    for (int k = i + 1; k < M; k++)
                        v -= L[k][i] * Kt[k][c];
                    Kt[i][c] = v * inv[i];
                }
            }
            REAL K[N][M], B[N][N], C[N][M];
#pragma unroll
            for (int i = 0; i < N; i++) {
                REAL v = xv[i];
#pragma unroll
                for (int a = 0; a < M; a++) {
                    K[i][a] = s * Kt[a][i];  // scaled gain (paper 002 eq. 4-6)
                    v += K[i][a] * y[a];
                }
                xn[i] = v;
            }
            // Joseph form: B = (I - K H) P = P - K (H P); P+ = B - (B H^T) K^T + K R K^T
#pragma unroll
            for (int i = 0; i < N; i++) {
#pragma unroll
                for (int j = 0; j < N; j++) {
                    REAL v = Ps[i][j];
#pragma unroll
                    for (int a = 0; a < M; a++)
                        v -= K[i][a] * HP[a][j];
                    B[i][j] = v;
                }
#pragma unroll
                for (int a = 0; a < M; a++) {
                    REAL v = 0;
#pragma unroll
                    for (int c = 0; c < M; c++)
                        v += K[i][c] * Rs[c][a];
#pragma unroll
                    for (int k = 0; k < N; k++)
                        if (HNZ(a, k))
                            v -= B[i][k] * Hm[a][k];
                    C[i][a] = v;
                }
            }
#pragma unroll
            for (int i = 0; i < N; i++)
#pragma unroll
                for (int j = i; j < N; j++) {
                    REAL v = B[i][j];
#pragma unroll
                    for (int a = 0; a < M; a++)
                        v += C[i][a] * K[j][a];
                    Pn[i][j] = v;
                    Pn[j][i] = v;
                }
        } else {
            code = GT_NOT_PD;
        }
    }
    if (code != GT_UPDATED) {
#pragma unroll
        for (int i = 0; i < N; i++) {
            xn[i] = xv[i];
#pragma unroll
            for (int j = 0; j < N; j++)
                Pn[i][j] = Pm[i][j];
        }
    }
#pragma unroll
    for (int i = 0; i < N; i++) {
        xo[(size_t)t * N + i] = xn[i];
#pragma unroll
        for (int j = 0; j < N; j++)
            Po[((size_t)t * N + i) * N + j] = Pn[i][j];
    }
    st[t] = (uchar)code;
#endif
}

// Squared Mahalanobis distances of D detections to every track (eq. 8): one work-item per track.
__kernel void gt_gate(
    __global const REAL *x, __global const REAL *P, __global const REAL *H, __global const REAL *R,
    __global const REAL *z, __global REAL *out, const int T, const int D)
{
    const int t = get_global_id(0);
    if (t >= T)
        return;
    REAL Ps[N][N], Hm[M][N], hx[M], HP[M][N], S[M][M], L[M][M], inv[M];
#pragma unroll
    for (int i = 0; i < N; i++)
#pragma unroll
        for (int j = 0; j < N; j++)
            Ps[i][j] = (REAL)0.5 * (P[((size_t)t * N + i) * N + j] + P[((size_t)t * N + j) * N + i]);
#pragma unroll
    for (int a = 0; a < M; a++) {
        REAL v = 0;
#pragma unroll
        for (int k = 0; k < N; k++) {
            Hm[a][k] = HNZ(a, k) ? AT(H, H_PT, M, N, t, a, k) : (REAL)0;
            if (HNZ(a, k))
                v += Hm[a][k] * x[(size_t)t * N + k];
        }
        hx[a] = v;
#pragma unroll
        for (int j = 0; j < N; j++)
            HP[a][j] = 0;
#pragma unroll
        for (int k = 0; k < N; k++)
            if (HNZ(a, k)) {
#pragma unroll
                for (int j = 0; j < N; j++)
                    HP[a][j] += Hm[a][k] * Ps[k][j];
            }
    }
#pragma unroll
    for (int a = 0; a < M; a++)
#pragma unroll
        for (int c = 0; c <= a; c++) {
            REAL v = 0;
#pragma unroll
            for (int k = 0; k < N; k++)
                if (HNZ(c, k))
                    v += HP[a][k] * Hm[c][k];
            S[a][c] = v + SYM(R, R_PT, RNZ, M, t, a, c);
        }
    int ok = 1;
#pragma unroll
    for (int j = 0; j < M; j++) {
        REAL d = S[j][j];
#pragma unroll
        for (int k = 0; k < j; k++)
            d -= L[j][k] * L[j][k];
        if (!(d > (REAL)PD_TOL * S[j][j])) {
            ok = 0;
            d = 1;
        }
        d = sqrt(d);
        L[j][j] = d;
        inv[j] = (REAL)1 / d;
#pragma unroll
        for (int i = j + 1; i < M; i++) {
            REAL v = S[i][j];
#pragma unroll
            for (int k = 0; k < j; k++)
                v -= L[i][k] * L[j][k];
            L[i][j] = v * inv[j];
        }
    }
    for (int e = 0; e < D; e++) {
        REAL w[M], acc = 0;
#pragma unroll
        for (int i = 0; i < M; i++) {
            REAL v = z[(size_t)e * M + i] - hx[i];
#pragma unroll
            for (int k = 0; k < i; k++)
                v -= L[i][k] * w[k];
            w[i] = v * inv[i];
            acc += w[i] * w[i];
        }
        out[(size_t)t * D + e] = ok ? acc : (REAL)INFINITY;
    }
}

// ---------------------------------------------------------------------------------------------
// gt_kf_v: the same filter, VW tracks per work-item in the lanes of REAL vectors (VW = 4, 8, 16).
// For CPU devices: the arithmetic runs in SIMD lanes (one track per lane), the loads and stores
// stay per track. No branches: every lane is computed and the result selected per lane.
#if defined(VW) && VW > 1
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#define REALV CAT(REAL, VW)
#if REAL_IS_DOUBLE
#define MASKV CAT(long, VW)
#else
#define MASKV CAT(int, VW)
#endif
#define LOADV(tmp) CAT(vload, VW)(0, tmp)
#define STOREV(v, tmp) CAT(vstore, VW)(v, 0, tmp)
#define INTV CAT(int, VW)

// lanes of A[t * stride + off] for tracks t0 .. t0 + VW - 1 (clamped to T - 1)
inline REALV gt_gather(__global const REAL *A, const size_t stride, const size_t off, const int t0, const int T)
{
    REAL tmp[VW];
#pragma unroll
    for (int l = 0; l < VW; l++)
        tmp[l] = A[(size_t)min(t0 + l, T - 1) * stride + off];
    return LOADV(tmp);
}

inline void gt_scatter(__global REAL *A, const size_t stride, const size_t off, const int t0, const int T, const REALV v)
{
    REAL tmp[VW];
    STOREV(v, tmp);
#pragma unroll
    for (int l = 0; l < VW; l++)
        if (t0 + l < T)
            A[(size_t)(t0 + l) * stride + off] = tmp[l];
}

// entry (i, j) of a shared (scalar, broadcast) or per-track (gathered) matrix
#define ATV(A, PT, R_, C_, t0, i, j) \
    ((PT) ? gt_gather((A), (size_t)(R_) * (C_), (size_t)(i) * (C_) + (j), (t0), T) : (REALV)((A)[(i) * (C_) + (j)]))
#define SYMV(A, PT, NZ, R_, t0, i, j) \
    ((REAL)0.5 * ((NZ(i, j) ? ATV(A, PT, R_, R_, t0, i, j) : (REALV)0) + (NZ(j, i) ? ATV(A, PT, R_, R_, t0, j, i) : (REALV)0)))

__kernel void gt_kf_v(
    __global const REAL *x, __global const REAL *P, __global const REAL *z,
    __global const REAL *F, __global const REAL *Q, __global const REAL *H, __global const REAL *R,
    __global const uchar *mask, __global const REAL *gain,
    __global REAL *xo, __global REAL *Po, __global uchar *st,
    const REAL f, const REAL b, const REAL cx, const REAL cy, const int T)
{
    const int t0 = get_global_id(0) * VW;
    if (t0 >= T)
        return;
    REALV xv[N], Pm[N][N];
#pragma unroll
    for (int i = 0; i < N; i++) {
        xv[i] = gt_gather(x, N, i, t0, T);
#pragma unroll
        for (int j = 0; j < N; j++)
            Pm[i][j] = gt_gather(P, N * N, i * N + j, t0, T);
    }
#if DO_PREDICT
    {
        REALV xp[N], Ps[N][N], FP[N][N];
#pragma unroll
        for (int i = 0; i < N; i++) {
            REALV s = 0;
#pragma unroll
            for (int k = 0; k < N; k++)
                if (FNZ(i, k))
                    s += ATV(F, F_PT, N, N, t0, i, k) * xv[k];
            xp[i] = s;
#pragma unroll
            for (int j = 0; j < N; j++)
                Ps[i][j] = (REAL)0.5 * (Pm[i][j] + Pm[j][i]);
        }
#pragma unroll
        for (int i = 0; i < N; i++) {
#pragma unroll
            for (int j = 0; j < N; j++)
                FP[i][j] = 0;
#pragma unroll
            for (int k = 0; k < N; k++)
                if (FNZ(i, k)) {
                    const REALV a = ATV(F, F_PT, N, N, t0, i, k);
#pragma unroll
                    for (int j = 0; j < N; j++)
                        FP[i][j] += a * Ps[k][j];
                }
        }
#pragma unroll
        for (int i = 0; i < N; i++) {
            xv[i] = xp[i];
#pragma unroll
            for (int j = i; j < N; j++) {
                REALV s = SYMV(Q, Q_PT, QNZ, N, t0, i, j);
#pragma unroll
                for (int k = 0; k < N; k++)
                    if (FNZ(j, k))
                        s += FP[i][k] * ATV(F, F_PT, N, N, t0, j, k);
                Pm[i][j] = s;
                Pm[j][i] = s;
            }
        }
    }
#endif
#if MODE == 0
#pragma unroll
    for (int i = 0; i < N; i++) {
        gt_scatter(xo, N, i, t0, T, xv[i]);
#pragma unroll
        for (int j = 0; j < N; j++)
            gt_scatter(Po, N * N, i * N + j, t0, T, Pm[i][j]);
    }
#else
    // lane masks (all bits set = true): valid (mask and finite z), depth ok, S positive definite
    MASKV valid = (MASKV)(-1);
#if HAS_MASK
    {
        int tmp[VW];
#pragma unroll
        for (int l = 0; l < VW; l++)
            tmp[l] = mask[min(t0 + l, T - 1)] ? -1 : 0;
        valid = CAT(convert_, MASKV)(CAT(vload, VW)(0, tmp));
    }
#endif
    REALV zv[M];
#pragma unroll
    for (int a = 0; a < M; a++) {
        zv[a] = gt_gather(z, M, a, t0, T);
        valid &= isfinite(zv[a]);  // a non-finite observation is missing
        zv[a] = select((REALV)0, zv[a], valid);
    }
    MASKV depth_ok = (MASKV)(-1);
#if MODE == 2
    depth_ok = xv[4] > 0;
#endif
    const REALV s = HAS_GAIN ? gt_gather(gain, 1, 0, t0, T) : (REALV)1;
    REALV Ps[N][N], Hm[M][N], y[M], Rs[M][M];
#pragma unroll
    for (int i = 0; i < N; i++)
#pragma unroll
        for (int j = 0; j < N; j++)
            Ps[i][j] = DO_PREDICT ? Pm[i][j] : (REAL)0.5 * (Pm[i][j] + Pm[j][i]);
#pragma unroll
    for (int a = 0; a < M; a++)
#pragma unroll
        for (int c = 0; c < M; c++)
            Rs[a][c] = SYMV(R, R_PT, RNZ, M, t0, a, c);
#if MODE == 2
#pragma unroll
    for (int a = 0; a < M; a++)
#pragma unroll
        for (int k = 0; k < N; k++)
            Hm[a][k] = 0;
    const REALV iz = (REAL)1 / select((REALV)1, xv[4], depth_ok);
    Hm[0][0] = f * iz;
    Hm[0][4] = -f * xv[0] * iz * iz;
    Hm[1][2] = f * iz;
    Hm[1][4] = -f * xv[2] * iz * iz;
    Hm[2][4] = -f * b * iz * iz;
    y[0] = zv[0] - (f * xv[0] * iz + cx);
    y[1] = zv[1] - (f * xv[2] * iz + cy);
    y[2] = zv[2] - f * b * iz;
#else
#pragma unroll
    for (int a = 0; a < M; a++) {
        REALV v = zv[a];
#pragma unroll
        for (int k = 0; k < N; k++) {
            Hm[a][k] = HNZ(a, k) ? ATV(H, H_PT, M, N, t0, a, k) : (REALV)0;
            if (HNZ(a, k))
                v -= Hm[a][k] * xv[k];
        }
        y[a] = v;
    }
#endif
    REALV HP[M][N], S[M][M], L[M][M], inv[M];
#pragma unroll
    for (int a = 0; a < M; a++) {
#pragma unroll
        for (int j = 0; j < N; j++)
            HP[a][j] = 0;
#pragma unroll
        for (int k = 0; k < N; k++)
            if (HNZ(a, k)) {
#pragma unroll
                for (int j = 0; j < N; j++)
                    HP[a][j] += Hm[a][k] * Ps[k][j];
            }
    }
#pragma unroll
    for (int a = 0; a < M; a++)
#pragma unroll
        for (int c = 0; c <= a; c++) {
            REALV v = 0;
#pragma unroll
            for (int k = 0; k < N; k++)
                if (HNZ(c, k))
                    v += HP[a][k] * Hm[c][k];
            S[a][c] = v + Rs[a][c];
        }
    MASKV pd_ok = (MASKV)(-1);
#pragma unroll
    for (int j = 0; j < M; j++) {
        REALV d = S[j][j];
#pragma unroll
        for (int k = 0; k < j; k++)
            d -= L[j][k] * L[j][k];
        const MASKV good = d > (REAL)PD_TOL * S[j][j];
        pd_ok &= good;
        d = sqrt(select((REALV)1, d, good));
        L[j][j] = d;
        inv[j] = (REAL)1 / d;
#pragma unroll
        for (int i = j + 1; i < M; i++) {
            REALV v = S[i][j];
#pragma unroll
            for (int k = 0; k < j; k++)
                v -= L[i][k] * L[j][k];
            L[i][j] = v * inv[j];
        }
    }
    REALV Kt[M][N];
#pragma unroll
    for (int c = 0; c < N; c++) {
#pragma unroll
        for (int i = 0; i < M; i++) {
            REALV v = HP[i][c];
#pragma unroll
            for (int k = 0; k < i; k++)
                v -= L[i][k] * Kt[k][c];
            Kt[i][c] = v * inv[i];
        }
#pragma unroll
        for (int i = M - 1; i >= 0; i--) {
            REALV v = Kt[i][c];
#pragma unroll
            for (int k = i + 1; k < M; k++)
                v -= L[k][i] * Kt[k][c];
            Kt[i][c] = v * inv[i];
        }
    }
    const MASKV upd = valid & depth_ok & pd_ok;
    REALV K[N][M], B[N][N], C[N][M];
#pragma unroll
    for (int i = 0; i < N; i++) {
        REALV v = xv[i];
#pragma unroll
        for (int a = 0; a < M; a++) {
            K[i][a] = s * Kt[a][i];
            v += K[i][a] * y[a];
        }
        gt_scatter(xo, N, i, t0, T, select(xv[i], v, upd));
    }
#pragma unroll
    for (int i = 0; i < N; i++) {
#pragma unroll
        for (int j = 0; j < N; j++) {
            REALV v = Ps[i][j];
#pragma unroll
            for (int a = 0; a < M; a++)
                v -= K[i][a] * HP[a][j];
            B[i][j] = v;
        }
#pragma unroll
        for (int a = 0; a < M; a++) {
            REALV v = 0;
#pragma unroll
            for (int c = 0; c < M; c++)
                v += K[i][c] * Rs[c][a];
#pragma unroll
            for (int k = 0; k < N; k++)
                if (HNZ(a, k))
                    v -= B[i][k] * Hm[a][k];
            C[i][a] = v;
        }
    }
#pragma unroll
    for (int i = 0; i < N; i++)
#pragma unroll
        for (int j = i; j < N; j++) {
            REALV v = B[i][j];
#pragma unroll
            for (int a = 0; a < M; a++)
                v += C[i][a] * K[j][a];
            gt_scatter(Po, N * N, i * N + j, t0, T, select(Pm[i][j], v, upd));
            if (j != i)
                gt_scatter(Po, N * N, j * N + i, t0, T, select(Pm[j][i], v, upd));
        }
    {
        // status: SKIPPED where not valid, else BAD_DEPTH, else NOT_PD, else UPDATED
        const INTV code = CAT(convert_, INTV)(select(select(select((MASKV)GT_NOT_PD, (MASKV)GT_UPDATED, pd_ok),
                                                           (MASKV)GT_BAD_DEPTH, depth_ok == 0),
                                                    (MASKV)GT_SKIPPED, valid == 0));
        int tmp[VW];
        CAT(vstore, VW)(code, 0, tmp);
#pragma unroll
        for (int l = 0; l < VW; l++)
            if (t0 + l < T)
                st[t0 + l] = (uchar)tmp[l];
    }
#endif
}
#endif

// Batched Kalman filter (papers 001 and 002): VW tracks per work-item (VW = 1 on a GPU: one track
// per work-item; 4, 8 or 16 on a CPU device: one track per lane of REAL vectors, SIMD arithmetic,
// per-track loads and stores). The numerics follow gputrack/backends/reference/kalman.py step
// for step. No branches on the data: every lane computes its update and the result is selected
// per lane (a lane mask is all ones for true in a vector, non-zero for true with VW = 1).
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
//   VW            tracks per work-item (1, 2, 4, 8 or 16; default 1)
//   GT_ABI, GT_KF_*  the status codes (gputrack/abi.py; every build gets them, a build without them fails)

// Defaults: a build with only the ABI defines (as host/doctor.py does) gives the float32 linear update
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
#ifndef VW
#define VW 1
#endif

#if REAL_IS_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif

// status codes: GT_KF_UPDATED, GT_KF_SKIPPED, GT_KF_NOT_PD, GT_KF_BAD_DEPTH (gputrack/abi.py KalmanStatus)
#ifndef GT_ABI
#error "build with the ABI defines of gputrack/abi.py (cl_defines; gputrack/backends/opencl/program.py)"
#endif


__constant uint gt_fpat[N] = {FPAT};
__constant uint gt_qpat[N] = {QPAT};
__constant uint gt_hpat[M] = {HPAT};
__constant uint gt_rpat[M] = {RPAT};
#define FNZ(i, k) ((gt_fpat[i] >> (k)) & 1u)
#define QNZ(i, k) ((gt_qpat[i] >> (k)) & 1u)
#define HNZ(i, k) ((gt_hpat[i] >> (k)) & 1u)
#define RNZ(i, k) ((gt_rpat[i] >> (k)) & 1u)

#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#if REAL_IS_DOUBLE
#define MASK long
#else
#define MASK int
#endif
#if VW == 1
#define REALV REAL
#define MASKV MASK
#define INTV int
#else
#define REALV CAT(REAL, VW)
#define MASKV CAT(MASK, VW)
#define INTV CAT(int, VW)
#endif

// lanes of A[t * stride + off] for tracks t0 .. t0 + VW - 1 (clamped to T - 1)
inline REALV gt_gather(__global const REAL *A, const size_t stride, const size_t off, const int t0, const int T)
{
#if VW == 1
    return A[(size_t)t0 * stride + off];
#else
    REAL tmp[VW];
#pragma unroll
    for (int l = 0; l < VW; l++)
        tmp[l] = A[(size_t)min(t0 + l, T - 1) * stride + off];
    return CAT(vload, VW)(0, tmp);
#endif
}

inline void gt_scatter(__global REAL *A, const size_t stride, const size_t off, const int t0, const int T, const REALV v)
{
#if VW == 1
    A[(size_t)t0 * stride + off] = v;
#else
    REAL tmp[VW];
    CAT(vstore, VW)(v, 0, tmp);
#pragma unroll
    for (int l = 0; l < VW; l++)
        if (t0 + l < T)
            A[(size_t)(t0 + l) * stride + off] = tmp[l];
#endif
}

// entry (i, j) of a shared (scalar, broadcast) or per-track (gathered) matrix
#define ATV(A, PT, R_, C_, t0, i, j) \
    ((PT) ? gt_gather((A), (size_t)(R_) * (C_), (size_t)(i) * (C_) + (j), (t0), T) : (REALV)((A)[(i) * (C_) + (j)]))
// (A + A^T)/2 at (i, j), reading only the entries that may be non-zero
#define SYMV(A, PT, NZ, R_, t0, i, j) \
    ((REAL)0.5 * ((NZ(i, j) ? ATV(A, PT, R_, R_, t0, i, j) : (REALV)0) + (NZ(j, i) ? ATV(A, PT, R_, R_, t0, j, i) : (REALV)0)))

// H Ps (M,N), S = H Ps H^T + Rs (lower triangle) and its Cholesky factor S = L L^T with the
// reference's positive-definiteness test; returns the lane mask of positive definite S.
// Known zeros of H (HPAT) are skipped. Used by the update and by the gating kernel.
inline MASKV gt_innovation(REALV Ps[N][N], REALV Hm[M][N], REALV Rs[M][M], REALV HP[M][N], REALV L[M][M], REALV inv[M])
{
    REALV S[M][M];
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
    return pd_ok;
}

__kernel void gt_kf(
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
        // eq. 2-3: x' = F x, P' = F P F^T + Q (P, Q symmetrised; P' exactly symmetric)
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
    // lane masks: valid (mask and finite z), depth ok, S positive definite
    MASKV valid = (MASKV)(-1);
#if HAS_MASK
#if VW == 1
    valid = mask[t0] ? -1 : 0;
#else
    {
        int tmp[VW];
#pragma unroll
        for (int l = 0; l < VW; l++)
            tmp[l] = mask[min(t0 + l, T - 1)] ? -1 : 0;
        valid = CAT(convert_, MASKV)(CAT(vload, VW)(0, tmp));
    }
#endif
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
            Ps[i][j] = DO_PREDICT ? Pm[i][j] : (REAL)0.5 * (Pm[i][j] + Pm[j][i]);  // exact after a prediction
#pragma unroll
    for (int a = 0; a < M; a++)
#pragma unroll
        for (int c = 0; c < M; c++)
            Rs[a][c] = SYMV(R, R_PT, RNZ, M, t0, a, c);
#if MODE == 2
    // eq. 6 and its Jacobian at the (predicted) state
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
    REALV HP[M][N], L[M][M], inv[M];
    const MASKV pd_ok = gt_innovation(Ps, Hm, Rs, HP, L, inv);
    // K^T = S^-1 (H P): forward then backward substitution, column by column
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
            K[i][a] = s * Kt[a][i];  // scaled gain (paper 002 eq. 4-6)
            v += K[i][a] * y[a];
        }
        gt_scatter(xo, N, i, t0, T, select(xv[i], v, upd));
    }
    // Joseph form: B = (I - K H) P = P - K (H P); P+ = B - (B H^T) K^T + K R K^T
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
        const INTV code = CAT(convert_, INTV)(select(select(select((MASKV)GT_KF_NOT_PD, (MASKV)GT_KF_UPDATED, pd_ok),
                                                           (MASKV)GT_KF_BAD_DEPTH, (MASKV)(depth_ok == 0)),
                                                    (MASKV)GT_KF_SKIPPED, (MASKV)(valid == 0)));
#if VW == 1
        st[t0] = (uchar)code;
#else
        int tmp[VW];
        CAT(vstore, VW)(code, 0, tmp);
#pragma unroll
        for (int l = 0; l < VW; l++)
            if (t0 + l < T)
                st[t0 + l] = (uchar)tmp[l];
#endif
    }
#endif
}

// Squared Mahalanobis distances of D detections to the VW tracks of a work-item (eq. 8).
__kernel void gt_gate(
    __global const REAL *x, __global const REAL *P, __global const REAL *H, __global const REAL *R,
    __global const REAL *z, __global REAL *out, const int T, const int D)
{
    const int t0 = get_global_id(0) * VW;
    if (t0 >= T)
        return;
    REALV Ps[N][N], Hm[M][N], hx[M], Rs[M][M], HP[M][N], L[M][M], inv[M];
#pragma unroll
    for (int i = 0; i < N; i++)
#pragma unroll
        for (int j = 0; j < N; j++)
            Ps[i][j] = (REAL)0.5 * (gt_gather(P, N * N, i * N + j, t0, T) + gt_gather(P, N * N, j * N + i, t0, T));
#pragma unroll
    for (int a = 0; a < M; a++) {
        REALV v = 0;
#pragma unroll
        for (int k = 0; k < N; k++) {
            Hm[a][k] = HNZ(a, k) ? ATV(H, H_PT, M, N, t0, a, k) : (REALV)0;
            if (HNZ(a, k))
                v += Hm[a][k] * gt_gather(x, N, k, t0, T);
        }
        hx[a] = v;
#pragma unroll
        for (int c = 0; c < M; c++)
            Rs[a][c] = SYMV(R, R_PT, RNZ, M, t0, a, c);
    }
    const MASKV ok = gt_innovation(Ps, Hm, Rs, HP, L, inv);
    for (int e = 0; e < D; e++) {
        REALV w[M], acc = 0;
#pragma unroll
        for (int i = 0; i < M; i++) {
            REALV v = z[(size_t)e * M + i] - hx[i];
#pragma unroll
            for (int k = 0; k < i; k++)
                v -= L[i][k] * w[k];
            w[i] = v * inv[i];
            acc += w[i] * w[i];
        }
        gt_scatter(out, D, e, t0, T, select((REALV)INFINITY, acc, ok));
    }
}

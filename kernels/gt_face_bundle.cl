// Landmark residuals of paper 003's bundle adjustment (eq. 4-6) and their Jacobian: the same as
// gputrack/backends/reference/face_bundle.py (gputrack/ops/face_bundle.py). Built with
// -DREAL=float|double (REAL_IS_DOUBLE for double), -DFB_A (deformation components) and -DFB_S
// (identity components). One work-item per (parameter vector, landmark or prior row). C: fx, fy,
// cx, cy, min_depth, mean (K, 3), L0 (K, 3, A), G (K, 3, S, A); D: target (n, K, 2), sqrt weights
// (n, K), scale (P), prior (S), prior mean (S). Only the Jacobian's entries that can be non-zero
// are written.
#ifndef REAL
#define REAL float
#endif
#ifdef REAL_IS_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif
// Without -DFB_A / -DFB_S (a build with only the ABI defines, as host/doctor.py makes) the
// multilinear face model's sizes A' = 5, S' = 15.
#ifndef FB_A
#define FB_A 5
#endif
#ifndef FB_S
#define FB_S 15
#endif
#define FB_F (6 + FB_A)

// R = I + a [r]x + b [r]x^2, J_l = I + b [r]x + c [r]x^2 (gputrack.models.pose.rotation_coefficients)
static void gt_fb_rotation(const REAL *r, REAL *R, REAL *Jl) {
    REAL t2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2];
    REAL t = sqrt(t2);
    REAL a, b, c;
    if (t < (REAL)1e-3) {
        a = 1 - t2 / 6 + t2 * t2 / 120;
        b = (REAL)0.5 - t2 / 24 + t2 * t2 / 720;
        c = (REAL)1 / 6 - t2 / 120 + t2 * t2 / 5040;
    } else {
        a = sin(t) / t;
        b = (1 - cos(t)) / (t * t);
        c = (t - sin(t)) / (t * t * t);
    }
    REAL K[9] = {0, -r[2], r[1], r[2], 0, -r[0], -r[1], r[0], 0};
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            REAL k2 = K[i * 3] * K[j] + K[i * 3 + 1] * K[3 + j] + K[i * 3 + 2] * K[6 + j];
            REAL id = (REAL)(i == j);
            R[i * 3 + j] = id + a * K[i * 3 + j] + b * k2;
            Jl[i * 3 + j] = id + b * K[i * 3 + j] + c * k2;
        }
}

__kernel void gt_face_bundle(__global const REAL *Y, __global const REAL *C, __global const REAL *D,
                             __global REAL *Rout, __global REAL *Jout, const int B, const int n, const int K,
                             const int prior, const int jac) {
    const int items = n * K + FB_S;
    const int gid = get_global_id(0);
    if (gid >= B * items) return;
    const int b = gid / items, q = gid % items;
    const int P = n * FB_F + FB_S, rows = 2 * n * K + (prior ? FB_S : 0);
    const int nF = n * FB_F, sc = 3 * n * K;
    __global const REAL *y = Y + (long)b * P;
    __global REAL *Rb = Rout + (long)b * rows;
    __global REAL *Jb = Jout + (long)b * rows * P;
    if (q >= n * K) {  // a prior row
        if (!prior) return;
        const int p = q - n * K, col = nF + p, row = 2 * n * K + p;
        const REAL w = D[sc + P + p];
        Rb[row] = (y[col] * D[sc + col] - D[sc + P + FB_S + p]) * w;
        if (jac) Jb[(long)row * P + col] = w * D[sc + col];
        return;
    }
    const int i = q / K, k = q % K, base = i * FB_F;
    const int cm = 5, cl = 5 + 3 * K, cg = 5 + 3 * K + 3 * K * FB_A;
    REAL r[3], t[3], ex[FB_A], s[FB_S > 0 ? FB_S : 1];
    for (int c = 0; c < 3; ++c) {
        r[c] = y[base + c] * D[sc + base + c];
        t[c] = y[base + 3 + c] * D[sc + base + 3 + c];
    }
    for (int a = 0; a < FB_A; ++a) ex[a] = y[base + 6 + a] * D[sc + base + 6 + a];
    for (int p = 0; p < FB_S; ++p) s[p] = y[nF + p] * D[sc + nF + p];
    REAL Bs[3 * FB_A], X[3];  // eq. 4: the expression basis of identity s, and the model point
    for (int c = 0; c < 3; ++c) {
        REAL xc = C[cm + k * 3 + c];
        for (int a = 0; a < FB_A; ++a) {
            REAL v = C[cl + (k * 3 + c) * FB_A + a];
            for (int p = 0; p < FB_S; ++p) v += s[p] * C[cg + ((k * 3 + c) * FB_S + p) * FB_A + a];
            Bs[c * FB_A + a] = v;
            xc += v * ex[a];
        }
        X[c] = xc;
    }
    REAL R[9], Jl[9], RX[3], Yc[3];
    gt_fb_rotation(r, R, Jl);
    for (int c = 0; c < 3; ++c) {
        RX[c] = R[c * 3] * X[0] + R[c * 3 + 1] * X[1] + R[c * 3 + 2] * X[2];
        Yc[c] = RX[c] + t[c];
    }
    const REAL fx = C[0], fy = C[1], cx = C[2], cy = C[3];
    const REAL iz = 1 / fmax(Yc[2], C[4]);  // eq. 5
    const int q0 = i * K + k;
    const REAL w = D[2 * n * K + q0];
    Rb[2 * q0] = (fx * Yc[0] * iz + cx - D[2 * q0]) * w;  // eq. 6, weighted
    Rb[2 * q0 + 1] = (fy * Yc[1] * iz + cy - D[2 * q0 + 1]) * w;
    if (!jac) return;
    const REAL aw = w * iz;
    const REAL Dp[6] = {fx * aw, 0, -fx * Yc[0] * iz * aw, 0, fy * aw, -fy * Yc[1] * iz * aw};
    const REAL RXx[9] = {0, -RX[2], RX[1], RX[2], 0, -RX[0], -RX[1], RX[0], 0};
    REAL M[9], Dr[6], DpR[6];
    for (int a = 0; a < 3; ++a)  // M = [RX]x J_l
        for (int c = 0; c < 3; ++c) M[a * 3 + c] = RXx[a * 3] * Jl[c] + RXx[a * 3 + 1] * Jl[3 + c] + RXx[a * 3 + 2] * Jl[6 + c];
    for (int e = 0; e < 2; ++e)
        for (int c = 0; c < 3; ++c) {
            Dr[e * 3 + c] = -(Dp[e * 3] * M[c] + Dp[e * 3 + 1] * M[3 + c] + Dp[e * 3 + 2] * M[6 + c]);  // -[RX]x J_l
            DpR[e * 3 + c] = Dp[e * 3] * R[c] + Dp[e * 3 + 1] * R[3 + c] + Dp[e * 3 + 2] * R[6 + c];
        }
    for (int e = 0; e < 2; ++e) {
        __global REAL *row = Jb + (long)(2 * q0 + e) * P;
        for (int c = 0; c < 3; ++c) {
            row[base + c] = Dr[e * 3 + c] * D[sc + base + c];
            row[base + 3 + c] = Dp[e * 3 + c] * D[sc + base + 3 + c];  // dY/dt = I
        }
        for (int a = 0; a < FB_A; ++a)  // dY/da = R Bs
            row[base + 6 + a] = (DpR[e * 3] * Bs[a] + DpR[e * 3 + 1] * Bs[FB_A + a] + DpR[e * 3 + 2] * Bs[2 * FB_A + a])
                                * D[sc + base + 6 + a];
        for (int p = 0; p < FB_S; ++p) {  // dY/ds = R G a
            REAL v = 0;
            for (int c = 0; c < 3; ++c) {
                REAL ga = 0;
                for (int a = 0; a < FB_A; ++a) ga += C[cg + ((k * 3 + c) * FB_S + p) * FB_A + a] * ex[a];
                v += DpR[e * 3 + c] * ga;
            }
            row[nF + p] = v * D[sc + nF + p];
        }
    }
}

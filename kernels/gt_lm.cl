// Batched Levenberg-Marquardt (paper 000 eq. 22-24; paper 003 eq. 8-9): the same steps as
// gputrack/backends/reference/lm.py. Built with -DREAL=float|double (solver precision),
// -DRTYPE (residual input type), -DJTYPE (Jacobian input type, with USE_JAC), -DXTYPE
// (points output type) and -DX0TYPE (start points input type); each defaults to float (a plain
// build, as host/doctor.py makes, gives the all-float32 variant).
// One work-group per problem; its work-items share the O(P^2 M) normal equations by rows.
#ifndef REAL
#define REAL float
#endif
#ifndef RTYPE
#define RTYPE REAL
#endif
#ifndef XTYPE
#define XTYPE REAL
#endif
#ifndef JTYPE
#define JTYPE RTYPE
#endif
#ifndef X0TYPE
#define X0TYPE REAL
#endif

#if defined(X0TYPE_IS_DOUBLE) || defined(REAL_IS_DOUBLE) || defined(RTYPE_IS_DOUBLE) || defined(XTYPE_IS_DOUBLE) || defined(JTYPE_IS_DOUBLE)
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif

#define RUNNING 0
#define CONVERGED 1
#define MAX_ITER 2
#define FAILED 3
#define R_FTOL 1
#define R_XTOL 2
#define R_GTOL 3
#define R_MAXIT 4
#define R_NONFINITE 5
#define R_NOTPD 6
#define R_DAMPING 7
#define MAX_CHOL_TRIES 40

// In place: W (lower triangle, P x P, row stride P) + C I -> L; rhs -> solution. 0 if not PD.
static int gt_chol_solve(__global REAL *W, __global REAL *rhs, const int P, const REAL C)
{
    for (int j = 0; j < P; ++j) {
        REAL s = W[j * P + j] + C;
        for (int k = 0; k < j; ++k)
            s -= W[j * P + k] * W[j * P + k];
        if (!(s > 0) || !isfinite(s))
            return 0;
        const REAL d = sqrt(s);
        W[j * P + j] = d;
        for (int i = j + 1; i < P; ++i) {
            REAL v = W[i * P + j];
            for (int k = 0; k < j; ++k)
                v -= W[i * P + k] * W[j * P + k];
            W[i * P + j] = v / d;
        }
    }
    for (int i = 0; i < P; ++i) {
        REAL v = rhs[i];
        for (int k = 0; k < i; ++k)
            v -= W[i * P + k] * rhs[k];
        rhs[i] = v / W[i * P + i];
    }
    for (int i = P - 1; i >= 0; --i) {
        REAL v = rhs[i];
        for (int k = i + 1; k < P; ++k)
            v -= W[k * P + i] * rhs[k];
        rhs[i] = v / W[i * P + i];
    }
    return 1;
}

// J^T J and J^T r (eq. 22); one work-item per (problem, row).
__kernel void gt_normal_equations(__global const REAL *J, __global const REAL *r, __global REAL *JtJ,
                                  __global REAL *Jtr, const int B, const int M, const int P)
{
    const int t = get_global_id(0);
    if (t >= B * P)
        return;
    const int b = t / P, i = t % P;
    __global const REAL *Jb = J + (long)b * M * P;
    for (int j = 0; j <= i; ++j) {
        REAL s = 0;
        for (int m = 0; m < M; ++m)
            s += Jb[m * P + i] * Jb[m * P + j];
        JtJ[(long)b * P * P + i * P + j] = s;
        JtJ[(long)b * P * P + j * P + i] = s;
    }
    REAL s = 0;
    for (int m = 0; m < M; ++m)
        s += Jb[m * P + i] * r[(long)b * M + m];
    Jtr[(long)b * P + i] = s;
}

// (J^T J + C I) delta = J^T r by Cholesky (eq. 22); one work-item per problem.
__kernel void gt_lm_step(__global const REAL *JtJ, __global const REAL *Jtr, __global const REAL *damping,
                         __global REAL *delta, __global int *ok, __global REAL *W, const int B, const int P)
{
    const int b = get_global_id(0);
    if (b >= B)
        return;
    __global REAL *Wb = W + (long)b * P * P;
    __global REAL *db = delta + (long)b * P;
    for (int i = 0; i < P; ++i) {
        db[i] = Jtr[(long)b * P + i];
        for (int j = 0; j <= i; ++j)
            Wb[i * P + j] = JtJ[(long)b * P * P + i * P + j];
    }
    ok[b] = gt_chol_solve(Wb, db, P, damping[b]);
    if (!ok[b])
        for (int i = 0; i < P; ++i)
            db[i] = 0;
}

// normal equations + damped Cholesky step fused: one work-group per problem.
__kernel void gt_lm_solve(__global const REAL *J, __global const REAL *r, __global const REAL *damping,
                          __global REAL *delta, __global int *ok, __global REAL *W, const int M, const int P)
{
    const int b = get_group_id(0), lid = get_local_id(0), ls = get_local_size(0);
    __global const REAL *Jb = J + (long)b * M * P;
    __global REAL *Wb = W + (long)b * P * P;
    __global REAL *db = delta + (long)b * P;
    const int npairs = P * (P + 1) / 2;
    for (int q = lid; q < npairs + P; q += ls) {
        if (q < npairs) {
            int i = (int)((sqrt(8.0f * q + 1.0f) - 1.0f) * 0.5f);
            while (i * (i + 1) / 2 > q)
                --i;
            while ((i + 1) * (i + 2) / 2 <= q)
                ++i;
            const int j = q - i * (i + 1) / 2;
            REAL s0 = 0, s1 = 0;
            int m = 0;
            for (; m + 1 < M; m += 2) {
                s0 += Jb[m * P + i] * Jb[m * P + j];  // eq. 22: J^T J
                s1 += Jb[(m + 1) * P + i] * Jb[(m + 1) * P + j];
            }
            for (; m < M; ++m)
                s0 += Jb[m * P + i] * Jb[m * P + j];
            Wb[i * P + j] = s0 + s1;
        } else {
            const int i = q - npairs;
            REAL s = 0;
            for (int m = 0; m < M; ++m)
                s += Jb[m * P + i] * r[(long)b * M + m];  // eq. 22: J^T r
            db[i] = s;
        }
    }
    barrier(CLK_GLOBAL_MEM_FENCE);
    if (lid == 0) {
        ok[b] = gt_chol_solve(Wb, db, P, damping[b]);
        if (!ok[b])
            for (int i = 0; i < P; ++i)
                db[i] = 0;
    }
}

// ------------------------------------------------------------------------------------------------
// solver: packed state (gputrack.ops.lm.Layout), one launch per iteration

// a . b over M contiguous values, four partial sums
static REAL gt_dot(__global const REAL *a, __global const REAL *b, const int M)
{
    REAL s0 = 0, s1 = 0, s2 = 0, s3 = 0;
    int m = 0;
    for (; m + 3 < M; m += 4) {
        s0 += a[m] * b[m];
        s1 += a[m + 1] * b[m + 1];
        s2 += a[m + 2] * b[m + 2];
        s3 += a[m + 3] * b[m + 3];
    }
    for (; m < M; ++m)
        s0 += a[m] * b[m];
    return (s0 + s1) + (s2 + s3);
}

#define SB_(P) (7 * (P) + 8)
#define WB_(P, M) (2 * (P) * (P) + (P) * (M))

// Rows of Xb (SX rows of P): the point src and, when SX > 1, its perturbed copies (eq. 24);
// their denominators (over the stored, possibly rounded, points) into den.
static void gt_lm_points(__global const REAL *src, __global REAL *den, __global const REAL *lo,
                         __global const REAL *hi, __global const REAL *h, __global XTYPE *Xb, const int SX,
                         const int P, const REAL rel)
{
    for (int row = 0; row < SX; ++row)
        for (int n = 0; n < P; ++n)
            Xb[row * P + n] = (XTYPE)src[n];
    if (SX > 1) {
        for (int n = 0; n < P; ++n) {
            const REAL p = src[n];
            REAL eps = h[n];
            if (eps <= 0)
                eps = rel * fmax(fabs(p), (REAL)1);
            __global XTYPE *xp = Xb + (1 + 2 * n) * P;
            xp[n] = (XTYPE)fmin(p + eps, hi[n]);
            xp[P + n] = (XTYPE)fmax(p - eps, lo[n]);
            den[n] = (REAL)xp[n] - (REAL)xp[P + n];
        }
    } else {
        for (int n = 0; n < P; ++n)
            den[n] = 0;
    }
}

// Out[b] = x, F, C, status, iterations, reason
static void gt_lm_export(__global const REAL *x, __global const REAL *sc, __global const int *ib,
                         __global REAL *Ob, const int P)
{
    for (int n = 0; n < P; ++n)
        Ob[n] = x[n];
    Ob[P] = sc[0];
    Ob[P + 1] = sc[1];
    Ob[P + 2] = (REAL)ib[0];
    Ob[P + 3] = (REAL)ib[1];
    Ob[P + 4] = (REAL)ib[3];
}

// S and I from the start points X0 (B, P) and the constants K (gputrack.ops.lm.Layout); the
// first points to evaluate into X (B*SX, P). One work-item per problem; nk = number of globals
// and mask values in K.
__kernel void gt_lm_init(__global const X0TYPE *X0, __global const REAL *K, __global REAL *S, __global int *I,
                         __global XTYPE *X, const int B, const int P, const int SX, const int nk)
{
    const int b = get_global_id(0);
    if (b >= B)
        return;
    const int SB = SB_(P), KB = 2 * P + 1;
    __global const REAL *kh = K + (long)B * KB, *kg = kh + P;
    if (b == 0) {
        for (int t = 0; t < 8; ++t)
            I[t] = 0;
        I[1] = B;
        I[2] = nk > 8;
        I[3] = P;
        for (int t = 0; t < nk; ++t)
            S[(long)B * SB + t] = kg[t];
    }
    __global int *ib = I + 8 + b * (4 + P);
    for (int t = 0; t < 4 + P; ++t)
        ib[t] = 0;
    __global REAL *Sb = S + (long)b * SB;
    __global const REAL *Kb = K + (long)b * KB;
    for (int n = 0; n < P; ++n) {
        const REAL x = (REAL)X0[(long)b * P + n];
        Sb[n] = x;
        Sb[P + n] = x;
        Sb[2 * P + n] = 0;
        Sb[4 * P + n] = Kb[n];
        Sb[5 * P + n] = Kb[P + n];
        Sb[6 * P + n] = kh[n];
    }
    __global REAL *sc = Sb + 7 * P;
    for (int k = 0; k < 8; ++k)
        sc[k] = 0;
    sc[1] = Kb[2 * P];  // C
    sc[2] = 2;  // nu
    gt_lm_points(Sb, Sb + 3 * P, Sb + 4 * P, Sb + 5 * P, Sb + 6 * P, X + (long)b * SX * P, SX, P, kg[3]);
}

// 4. gtol, damped Cholesky step, projection, next points (work-item 0 of the problem's group)
static void gt_lm_next(__global REAL *x, __global REAL *xt, __global REAL *g, __global REAL *den,
                       __global const REAL *lo, __global const REAL *hi, __global const REAL *h,
                       __global const REAL *A, __global REAL *L, __global REAL *sc, __global int *ib,
                       __global XTYPE *Xb, const int SX, const int P, const REAL gtol, const REAL rel,
                       const REAL ctiny, const REAL cmax)
{
    if (ib[0] == RUNNING && ib[2]) {
        REAL gmax = 0;
        for (int i = 0; i < P; ++i) {
            const REAL gi = g[i];
            if (!((x[i] >= hi[i] && gi < 0) || (x[i] <= lo[i] && gi > 0)))
                gmax = fmax(gmax, fabs(gi));
        }
        if (gmax <= gtol) {
            ib[0] = CONVERGED;
            ib[3] = R_GTOL;
        }
    }
    if (ib[0] == RUNNING) {
        REAL dmax = 0;
        for (int i = 0; i < P; ++i)
            dmax = fmax(dmax, A[i * P + i]);
        dmax += 1;
        REAL C = sc[1];
        int ok = 0;
        for (int tries = 0; tries <= MAX_CHOL_TRIES; ++tries) {
            // parameters held at a bound by the gradient stay there (identity rows, rhs 0)
            for (int i = 0; i < P; ++i) {
                const int ai = (x[i] >= hi[i] && g[i] < 0) || (x[i] <= lo[i] && g[i] > 0);
                xt[i] = ai ? 0 : g[i];
                for (int j = 0; j <= i; ++j) {
                    const int aj = (x[j] >= hi[j] && g[j] < 0) || (x[j] <= lo[j] && g[j] > 0);
                    L[i * P + j] = (ai || aj) ? (REAL)(i == j) : A[i * P + j];
                }
            }
            ok = gt_chol_solve(L, xt, P, C);  // eq. 22: delta into the xt slots
            if (ok || C > cmax * dmax)
                break;
            C = fmax(10 * C, ctiny * dmax);  // not PD: raise C tenfold and try again
        }
        sc[1] = C;
        if (!ok) {
            ib[0] = FAILED;
            ib[3] = R_NOTPD;
        } else {
            for (int i = 0; i < P; ++i)
                xt[i] = fmin(fmax(x[i] - xt[i], lo[i]), hi[i]);  // projected step (paper 003 eq. 8-9)
            REAL pr = 0;
            for (int i = 0; i < P; ++i) {
                const REAL si = x[i] - xt[i];
                REAL As = 0;
                for (int j = 0; j < P; ++j)
                    As += A[i * P + j] * (x[j] - xt[j]);
                pr += 2 * si * g[i] - si * As;
            }
            sc[3] = pr;
        }
    }
    gt_lm_points(ib[0] == RUNNING ? xt : x, den, lo, hi, h, Xb, SX, P, rel);
}

// One LM iteration for every running problem. R: (B*SR, M) residuals of the last call
// (SR = 2P+1: trial point and perturbed copies; SR = 1: trial point only, with Jg its Jacobian
// (B, M, P) when USE_JAC, or the last call when FINAL). X: (B*SX, P) receives the next points.
// S small state, W workspace (device only), Out (B, P + 5) the result (gputrack.ops.lm.Layout).
__kernel void gt_lm_update(__global REAL *S, __global int *I, __global REAL *W, __global XTYPE *X,
                           __global const RTYPE *R, __global const JTYPE *Jg, __global REAL *Out, const int M,
                           const int SR, const int SX, const int first, const int final_)
{
    const int b = get_group_id(0), lid = get_local_id(0), ls = get_local_size(0);
    const int B = I[1], has_mask = I[2], P = I[3];
    const int SB = SB_(P);
    __global REAL *Sb = S + (long)b * SB;
    __global REAL *x = Sb, *xt = Sb + P, *g = Sb + 2 * P, *den = Sb + 3 * P;
    __global REAL *lo = Sb + 4 * P, *hi = Sb + 5 * P, *h = Sb + 6 * P;
    __global REAL *Wb = W + (long)b * WB_(P, M);
    __global REAL *A = Wb, *L = Wb + P * P, *Jt = Wb + 2 * P * P;
    __global REAL *sc = Sb + 7 * P;  // F, C, nu, pred, Ft, snorm
    __global const REAL *G = S + (long)B * SB;
    __global const REAL *mask = G + 8;
    __global int *ib = I + 8 + b * (4 + P);  // status, iterations, accepted, reason, fin[P]
    __global const RTYPE *rt = R + (long)b * SR * M;
    const REAL ftol = G[0], xtol = G[1], gtol = G[2], rel = G[3], ctiny = G[4], cmax = G[5];
    const int running = ib[0] == RUNNING;

    // 1. Jacobian at the evaluated trial: eq. 24 over the stored points, or given
    if (running && !final_) {
        for (int n = lid; n < P; n += ls) {
            int okn = 1;
            __global REAL *row = Jt + n * M;
#ifdef USE_JAC
            for (int m = 0; m < M; ++m) {
                const REAL v = (REAL)Jg[((long)b * M + m) * P + n];
                okn &= isfinite(v) ? 1 : 0;
                row[m] = v;
            }
#else
            const REAL dn = den[n];
            __global const RTYPE *rp = R + ((long)b * SR + 1 + 2 * n) * M;
            __global const RTYPE *rm = rp + M;
            for (int m = 0; m < M; ++m) {
                REAL v = 0;
                if (!has_mask || mask[m * P + n] != 0) {
                    const REAL d = (REAL)rp[m] - (REAL)rm[m];  // r(x + eps e_n) - r(x - eps e_n)
                    okn &= isfinite(d) ? 1 : 0;
                    if (dn != 0)
                        v = d / dn;  // eq. 24
                }
                row[m] = v;
            }
#endif
            ib[4 + n] = okn;
        }
    }
    barrier(CLK_GLOBAL_MEM_FENCE);

    // 2. acceptance of the trial, damping update (Nielsen), ftol / xtol
    if (lid == 0) {
        ib[2] = 0;
        if (running) {
            int ok = 1;
            REAL Ft = 0;
            for (int m = 0; m < M; ++m) {
                const REAL v = (REAL)rt[m];
                ok &= isfinite(v) ? 1 : 0;
                Ft += v * v;  // eq. 20-21: cost = r^T r
            }
            ok &= isfinite(Ft) ? 1 : 0;
            if (!final_)
                for (int n = 0; n < P; ++n)
                    ok &= ib[4 + n];
            sc[4] = Ft;
            int acc = 0;
            if (!ok) {
                ib[0] = FAILED;
                ib[3] = R_NONFINITE;
                if (first)
                    sc[0] = INFINITY;
            } else if (first) {
                acc = 1;
            } else {
                ib[1] += 1;
                const REAL F = sc[0], pred = sc[3], dF = F - Ft;
                if (dF > 0) {
                    acc = 1;
                    const REAL rho = pred > 0 ? dF / pred : (REAL)1;
                    const REAL q = 2 * rho - 1;
                    sc[1] *= fmax((REAL)1 / 3, 1 - q * q * q);
                    sc[2] = 2;
                } else {
                    sc[1] *= sc[2];
                    sc[2] *= 2;
                    REAL dmax = 0, sn = 0, xn = 0;
                    for (int i = 0; i < P; ++i) {
                        dmax = fmax(dmax, A[i * P + i]);
                        sn += (xt[i] - x[i]) * (xt[i] - x[i]);
                        xn += x[i] * x[i];
                    }
                    if (sqrt(sn) <= xtol * (xtol + sqrt(xn))) {
                        ib[0] = CONVERGED;  // no step this small improves the cost
                        ib[3] = R_XTOL;
                    } else if (sc[1] > cmax * (1 + dmax)) {
                        ib[0] = FAILED;
                        ib[3] = R_DAMPING;
                    }
                }
            }
            if (acc) {
                ib[2] = 1;
                REAL sn = 0, xn = 0;
                for (int i = 0; i < P; ++i) {
                    const REAL d = xt[i] - x[i];
                    sn += d * d;
                    x[i] = xt[i];
                    xn += x[i] * x[i];
                }
                sn = sqrt(sn);
                sc[5] = sn;
                const REAL F_old = sc[0];
                sc[0] = Ft;
                if (!first) {
                    if (F_old - Ft <= ftol * F_old) {
                        ib[0] = CONVERGED;
                        ib[3] = R_FTOL;
                    } else if (sn <= xtol * (xtol + sqrt(xn))) {
                        ib[0] = CONVERGED;
                        ib[3] = R_XTOL;
                    }
                }
            }
            if (final_ && ib[0] == RUNNING) {
                ib[0] = MAX_ITER;
                ib[3] = R_MAXIT;
            }
        }
    }
    barrier(CLK_GLOBAL_MEM_FENCE);

    // 3. J^T J and J^T r at the accepted point (eq. 22): the P (P + 1) / 2 entries of the lower
    // triangle and the P entries of J^T r are shared out over the work-items
    if (!final_ && ib[2]) {
        const int npairs = P * (P + 1) / 2;
        for (int q = lid; q < npairs + P; q += ls) {
            if (q < npairs) {
                int i = (int)((sqrt(8.0f * q + 1.0f) - 1.0f) * 0.5f);
                while (i * (i + 1) / 2 > q)
                    --i;
                while ((i + 1) * (i + 2) / 2 <= q)
                    ++i;
                const int j = q - i * (i + 1) / 2;
                const REAL s = gt_dot(Jt + i * M, Jt + j * M, M);
                A[i * P + j] = s;
                A[j * P + i] = s;
            } else {
                const int i = q - npairs;
                __global const REAL *ri = Jt + i * M;
                REAL s0 = 0, s1 = 0;
                int m = 0;
                for (; m + 1 < M; m += 2) {
                    s0 += ri[m] * (REAL)rt[m];
                    s1 += ri[m + 1] * (REAL)rt[m + 1];
                }
                for (; m < M; ++m)
                    s0 += ri[m] * (REAL)rt[m];
                g[i] = s0 + s1;
            }
        }
    }
    barrier(CLK_GLOBAL_MEM_FENCE);
    if (lid == 0) {
        if (!final_)
            gt_lm_next(x, xt, g, den, lo, hi, h, A, L, sc, ib, X + (long)b * SX * P, SX, P, gtol, rel, ctiny, cmax);
        gt_lm_export(x, sc, ib, Out + (long)b * (P + 5), P);
    }
}

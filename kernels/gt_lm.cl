// Batched Levenberg-Marquardt (paper 000 eq. 22-24; paper 003 eq. 8-9): the same steps as
// gputrack/backends/reference/lm.py. Built with -DREAL=float|double (solver precision),
// -DRTYPE (residual input type), -DJTYPE (Jacobian input type, with USE_JAC), -DXTYPE
// (points output type) and -DX0TYPE (start points input type); each defaults to float (a build
// with only the ABI defines, as host/doctor.py makes, gives the all-float32 variant).
// One work-group per problem; its work-items share the O(P^2 M) normal equations by rows and, built
// with LM_WG_STEP (GPUs), the step's O(P^3) factorisation (gt_lm_next_wg; else work-item 0 runs it).
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

// Status and reason codes (GT_LM_RUNNING ..., GT_LM_R_FTOL ...) and the slots of the packed state
// (GT_LM_S_X ...) come from gputrack/abi.py as build defines (gputrack/backends/opencl/program.py).
#ifndef GT_ABI
#error "build with the ABI defines of gputrack/abi.py (cl_defines; gputrack/backends/opencl/program.py)"
#endif
#define MAX_CHOL_TRIES 40
#ifdef REAL_IS_DOUBLE
#define REAL2 double2
#define REAL4 double4
#define GT_TO_REAL4(v) convert_double4(v)
#else
#define REAL2 float2
#define REAL4 float4
#define GT_TO_REAL4(v) convert_float4(v)
#endif
#ifdef LM_P
#define LM_NV ((LM_P + 3) / 4)  // vectors of four in a row of J (the last padded with zeros)
#endif
#define LM_JB 16  // columns of J^T J a work-item sums at once when P is a runtime value
// GT_LM_G_SCALE (an ABI define): the global of S holding the damping's scaling, one of
// GT_LM_SCALE_IDENTITY / _MARQUARDT / _MINPACK (gputrack.abi.LMScale).

// sum_k<n a[k] b[k] in four interleaved partial sums (vectorised: the compiler may not reorder one
// running sum), the tail after them
static REAL gt_lm_dot(__global const REAL *a, __global const REAL *b, const int n)
{
    REAL4 acc = (REAL4)(0);
    int k = 0;
    for (; k + 4 <= n; k += 4)
        acc += vload4(0, a + k) * vload4(0, b + k);
    REAL s = (acc.x + acc.y) + (acc.z + acc.w);
    for (; k < n; ++k)
        s += a[k] * b[k];
    return s;
}

// env[i] = the first column of row i of the lower triangle of W (P x P, row stride P) that is not 0
// (NaN counts; i where there is none before the diagonal), as a REAL
static void gt_envelope(__global const REAL *W, __global REAL *env, const int P)
{
    for (int i = 0; i < P; ++i) {
        int f = i;
        for (int k = 0; k < i; ++k)
            if (W[i * P + k] != 0) {
                f = k;
                break;
            }
        env[i] = (REAL)f;
    }
}

// In place: W (lower triangle, P x P, row stride P) + C I -> L; rhs -> solution. 0 if not PD. env:
// 0, or each row's first entry that is not 0 (gt_envelope): the factor has no entry before it, so
// the products start there, and a row that starts after column j keeps its 0 there.
static int gt_chol_solve(__global REAL *W, __global REAL *rhs, const int P, const REAL C, __global const REAL *env)
{
    for (int j = 0; j < P; ++j) {
        __global const REAL *rj = W + j * P;
        const int fj = env ? (int)env[j] : 0;
        const REAL s = W[j * P + j] + C - gt_lm_dot(rj + fj, rj + fj, j - fj);
        if (!(s > 0) || !isfinite(s))
            return 0;
        const REAL d = sqrt(s);
        W[j * P + j] = d;
        for (int i = j + 1; i < P; ++i) {
            const int f = env ? max((int)env[i], fj) : 0;
            if (f <= j)
                W[i * P + j] = (W[i * P + j] - gt_lm_dot(W + i * P + f, rj + f, j - f)) / d;
        }
    }
    for (int i = 0; i < P; ++i) {
        const int f = env ? (int)env[i] : 0;
        rhs[i] = (rhs[i] - gt_lm_dot(W + i * P + f, rhs + f, i - f)) / W[i * P + i];
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
    ok[b] = gt_chol_solve(Wb, db, P, damping[b], 0);
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
        ok[b] = gt_chol_solve(Wb, db, P, damping[b], 0);
        if (!ok[b])
            for (int i = 0; i < P; ++i)
                db[i] = 0;
    }
}

// ------------------------------------------------------------------------------------------------
// solver: packed state (gputrack.ops.lm.Layout), one launch per iteration

// The dots of rows a0, a1 with rows b0, b1 (M contiguous values each; a . b as four partial sums,
// the lanes of a vector: lane k sums m = k mod 4, the tail into lane 0), four independent chains.
static REAL4 gt_dot22(__global const REAL *a0, __global const REAL *a1, __global const REAL *b0,
                      __global const REAL *b1, const int M)
{
    REAL4 s00 = 0, s01 = 0, s10 = 0, s11 = 0;
    int m = 0;
    for (; m + 3 < M; m += 4) {
        const REAL4 x0 = vload4(0, a0 + m), x1 = vload4(0, a1 + m);
        const REAL4 y0 = vload4(0, b0 + m), y1 = vload4(0, b1 + m);
        s00 += x0 * y0;
        s01 += x0 * y1;
        s10 += x1 * y0;
        s11 += x1 * y1;
    }
    REAL t00 = s00.x, t01 = s01.x, t10 = s10.x, t11 = s11.x;
    for (; m < M; ++m) {
        t00 += a0[m] * b0[m];
        t01 += a0[m] * b1[m];
        t10 += a1[m] * b0[m];
        t11 += a1[m] * b1[m];
    }
    return (REAL4)((t00 + s00.y) + (s00.z + s00.w), (t01 + s01.y) + (s01.z + s01.w),
                   (t10 + s10.y) + (s10.z + s10.w), (t11 + s11.y) + (s11.z + s11.w));
}

// Entry q of the lower triangle of a P x P matrix, row by row: (i, j) with j <= i.
static int2 gt_pair(const int q)
{
    int i = (int)((sqrt(8.0f * q + 1.0f) - 1.0f) * 0.5f);
    while (i * (i + 1) / 2 > q)
        --i;
    while ((i + 1) * (i + 2) / 2 <= q)
        ++i;
    return (int2)(i, q - i * (i + 1) / 2);
}

#define SB_(P) (GT_LM_S_NVEC * (P) + GT_LM_NSCAL)
#define WB_(P, M) (GT_LM_W_NSQ * (P) * (P) + (P) * (M) + (P))
#define IB_(b, P) (GT_LM_NIGLOB + (b) * (GT_LM_I_NFIX + (P)))

// Rows of Xb (SX rows of P): the point src and, when SX > 1, its perturbed copies: moved by +-eps
// (SX = 2P + 1, central differences, eq. 24) or by +eps (SX = P + 1, forward differences; -eps where
// +eps would leave the box); their denominators (over the stored, possibly rounded, points) into den.
// eps: h where given, else rel |p| (rel where p = 0, as MINPACK).
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
                eps = rel * (p != 0 ? fabs(p) : (REAL)1);
            if (SX == 2 * P + 1) {
                __global XTYPE *xp = Xb + (1 + 2 * n) * P;
                xp[n] = (XTYPE)fmin(p + eps, hi[n]);
                xp[P + n] = (XTYPE)fmax(p - eps, lo[n]);
                den[n] = (REAL)xp[n] - (REAL)xp[P + n];
            } else {
                __global XTYPE *xp = Xb + (1 + n) * P;
                const REAL up = p + eps;
                xp[n] = (XTYPE)(up <= hi[n] ? up : fmax(p - eps, lo[n]));
                den[n] = (REAL)xp[n] - (REAL)Xb[n];
            }
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
    Ob[P + GT_LM_O_F] = sc[GT_LM_SC_F];
    Ob[P + GT_LM_O_C] = sc[GT_LM_SC_C];
    Ob[P + GT_LM_O_STATUS] = (REAL)ib[GT_LM_I_STATUS];
    Ob[P + GT_LM_O_ITER] = (REAL)ib[GT_LM_I_ITER];
    Ob[P + GT_LM_O_REASON] = (REAL)ib[GT_LM_I_REASON];
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
    const int SB = SB_(P), KB = GT_LM_K_NVEC * P + 1;
    __global const REAL *kh = K + (long)B * KB, *kg = kh + P;
    if (b == 0) {
        for (int t = 0; t < GT_LM_NIGLOB; ++t)
            I[t] = 0;
        I[GT_LM_IG_B] = B;
        I[GT_LM_IG_HAS_MASK] = nk > GT_LM_NGLOB;
        I[GT_LM_IG_P] = P;
        for (int t = 0; t < nk; ++t)
            S[(long)B * SB + t] = kg[t];
    }
    __global int *ib = I + IB_(b, P);
    for (int t = 0; t < GT_LM_I_NFIX + P; ++t)
        ib[t] = 0;
    __global REAL *Sb = S + (long)b * SB;
    __global const REAL *Kb = K + (long)b * KB;
    for (int n = 0; n < P; ++n) {
        const REAL x = (REAL)X0[(long)b * P + n];
        Sb[GT_LM_S_X * P + n] = x;
        Sb[GT_LM_S_XT * P + n] = x;
        Sb[GT_LM_S_G * P + n] = 0;
        Sb[GT_LM_S_LO * P + n] = Kb[GT_LM_K_LO * P + n];
        Sb[GT_LM_S_HI * P + n] = Kb[GT_LM_K_HI * P + n];
        Sb[GT_LM_S_H * P + n] = kh[n];
    }
    __global REAL *sc = Sb + GT_LM_S_NVEC * P;
    for (int k = 0; k < GT_LM_NSCAL; ++k)
        sc[k] = 0;
    sc[GT_LM_SC_C] = Kb[GT_LM_K_NVEC * P];  // C
    sc[GT_LM_SC_NU] = 2;  // nu
    gt_lm_points(Sb + GT_LM_S_X * P, Sb + GT_LM_S_DEN * P, Sb + GT_LM_S_LO * P, Sb + GT_LM_S_HI * P,
                 Sb + GT_LM_S_H * P, X + (long)b * SX * P, SX, P, kg[GT_LM_G_REL]);
}

// What the damping's limits are relative to: 1 + max diag(J^T J) for C I, 1 when scaled.
static REAL gt_lm_cref(__global const REAL *A, const int P, const int scale)
{
    REAL dmax = 0;
    for (int i = 0; i < P; ++i)
        dmax = fmax(dmax, A[i * P + i]);
    return scale == GT_LM_SCALE_IDENTITY ? dmax + 1 : (REAL)1;
}

// Whether parameter i is held at a bound by the gradient (its row and column of the step cleared).
static int gt_lm_held(__global const REAL *x, __global const REAL *g, __global const REAL *lo,
                      __global const REAL *hi, const int i)
{
    return (x[i] >= hi[i] && g[i] < 0) || (x[i] <= lo[i] && g[i] > 0);
}

// 4a. Of a problem whose trial was accepted, the gtol test (projected gradient; scaled modes:
// MINPACK's |J_n^T r| / (||J_n|| ||r||)); then, if it is still running, the damping's scale D of its
// step: 1 (C I, eq. 22), diag(J^T J) (Marquardt) or its running maximum over the problem's
// iterations (MINPACK); 1 for a zero column. Returns whether a step is to be computed.
static int gt_lm_prepare(__global const REAL *x, __global const REAL *g, __global const REAL *lo,
                         __global const REAL *hi, __global const REAL *A, __global REAL *D,
                         __global const REAL *sc, __global int *ib, const int P, const REAL gtol, const int scale)
{
    if (ib[GT_LM_I_STATUS] == GT_LM_RUNNING && ib[GT_LM_I_ACCEPTED]) {
        REAL gmax = 0;
        for (int i = 0; i < P; ++i) {
            if (!gt_lm_held(x, g, lo, hi, i)) {
                REAL v = fabs(g[i]);
                if (scale != GT_LM_SCALE_IDENTITY) {
                    const REAL nrm = sqrt(A[i * P + i] * sc[GT_LM_SC_F]);
                    v = nrm > 0 ? v / nrm : (REAL)0;
                }
                gmax = fmax(gmax, v);
            }
        }
        if (gmax <= gtol) {
            ib[GT_LM_I_STATUS] = GT_LM_CONVERGED;
            ib[GT_LM_I_REASON] = GT_LM_R_GTOL;
        }
    }
    if (ib[GT_LM_I_STATUS] != GT_LM_RUNNING)
        return 0;
    for (int i = 0; i < P; ++i) {
        REAL d = 1;
        if (scale != GT_LM_SCALE_IDENTITY) {
            d = A[i * P + i];
            if (scale == GT_LM_SCALE_MINPACK && ib[GT_LM_I_ITER] > 0)
                d = fmax(d, D[i]);
            d = d > 0 ? d : (REAL)1;
        }
        D[i] = d;
    }
    return 1;
}

// 4. gtol, damped Cholesky step, projection, next points (work-item 0 of the problem's group). env: P
// values of scratch for the damped matrix's envelope (the factor's products start at each row's first
// entry that is not 0: a block-sparse J^T J, the face bundle's, in fewer operations).
static void gt_lm_next(__global REAL *x, __global REAL *xt, __global REAL *g, __global REAL *den,
                       __global const REAL *lo, __global const REAL *hi, __global const REAL *h,
                       __global const REAL *A, __global REAL *L, __global REAL *D, __global REAL *env, __global REAL *sc,
                       __global int *ib, __global XTYPE *Xb, const int SX, const int P, const REAL gtol,
                       const REAL rel, const REAL ctiny, const REAL cmax, const int scale)
{
    if (gt_lm_prepare(x, g, lo, hi, A, D, sc, ib, P, gtol, scale)) {
        const REAL dmax = gt_lm_cref(A, P, scale);
        REAL C = sc[GT_LM_SC_C];
        int ok = 0;
        for (int tries = 0; tries <= MAX_CHOL_TRIES; ++tries) {
            // parameters held at a bound by the gradient stay there (identity rows, rhs 0); the
            // damping C D on the diagonal
            for (int i = 0; i < P; ++i) {
                const int ai = gt_lm_held(x, g, lo, hi, i);
                xt[i] = ai ? 0 : g[i];
                for (int j = 0; j < i; ++j) {
                    const int aj = gt_lm_held(x, g, lo, hi, j);
                    L[i * P + j] = (ai || aj) ? (REAL)0 : A[i * P + j];
                }
                L[i * P + i] = ai ? 1 + C : A[i * P + i] + C * D[i];
            }
            gt_envelope(L, env, P);
            ok = gt_chol_solve(L, xt, P, 0, env);  // eq. 22: delta into the xt slots
            if (ok || C > cmax * dmax)
                break;
            C = fmax(10 * C, ctiny * dmax);  // not PD: raise C tenfold and try again
        }
        sc[GT_LM_SC_C] = C;
        if (!ok) {
            ib[GT_LM_I_STATUS] = GT_LM_FAILED;
            ib[GT_LM_I_REASON] = GT_LM_R_NOT_PD;
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
            sc[GT_LM_SC_PRED] = pr;
        }
    }
    gt_lm_points(ib[GT_LM_I_STATUS] == GT_LM_RUNNING ? xt : x, den, lo, hi, h, Xb, SX, P, rel);
}

#ifdef LM_WG_STEP
// In place, by the whole work-group: the lower triangle of W (P x P, row stride P) -> its Cholesky
// factor, column by column (the column scaled, then the trailing triangle updated by its outer
// product, each shared out over the work-items). Returns 1 if positive definite, the same on
// every work-item (flag: one local int). Every barrier is reached by every work-item.
static int gt_chol_wg(__global REAL *W, const int P, const int lid, const int ls, __local int *flag)
{
    if (lid == 0)
        *flag = 1;
    for (int j = 0; j < P; ++j) {
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
        if (lid == 0 && *flag) {
            const REAL s = W[j * P + j];
            if (!(s > 0) || !isfinite(s))
                *flag = 0;
            else
                W[j * P + j] = sqrt(s);
        }
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
        if (*flag) {
            const REAL d = W[j * P + j];
            for (int i = j + 1 + lid; i < P; i += ls)
                W[i * P + j] /= d;
        }
        barrier(CLK_GLOBAL_MEM_FENCE);
        if (*flag) {  // entries (i, k), j < k <= i: row i - j - 1 of the trailing triangle
            const int n = P - j - 1;
            for (int q = lid; q < n * (n + 1) / 2; q += ls) {
                const int2 ik = gt_pair(q);
                const int i = j + 1 + ik.x, k = j + 1 + ik.y;
                W[i * P + k] -= W[i * P + j] * W[k * P + j];
            }
        }
    }
    barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
    return *flag;
}

// 4. as gt_lm_next, by the whole work-group (GPUs, where one work-item's O(P^3) Cholesky of a
// large P left the rest of the group idle: 2.7 ms a launch for the face bundle's P = 92 on an
// H100): the factor and the two triangular solves column by column, the damped matrix and the
// predicted reduction's products shared out; work-item 0 keeps the O(P) scalar work. wi: 3 local
// ints, wr: 2 local REALs. Every work-item calls it (its barriers are reached by all); final_:
// nothing but the result.
static void gt_lm_next_wg(__global REAL *x, __global REAL *xt, __global REAL *g, __global REAL *den,
                          __global const REAL *lo, __global const REAL *hi, __global const REAL *h,
                          __global const REAL *A, __global REAL *L, __global REAL *D, __global REAL *tmp,
                          __global REAL *sc, __global int *ib, __global XTYPE *Xb, const int SX, const int P,
                          const REAL gtol, const REAL rel, const REAL ctiny, const REAL cmax, const int scale,
                          const int final_, const int lid, const int ls, __local int *wi, __local REAL *wr)
{
    if (lid == 0) {
        wi[0] = !final_ && gt_lm_prepare(x, g, lo, hi, A, D, sc, ib, P, gtol, scale);  // go: a step to compute
        if (wi[0]) {
            wr[0] = sc[GT_LM_SC_C];
            wr[1] = gt_lm_cref(A, P, scale);
        }
    }
    barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
    int ok = 0;
    if (wi[0]) {  // the same on every work-item
        for (int tries = 0; tries <= MAX_CHOL_TRIES; ++tries) {
            const REAL C = wr[0];
            for (int q = lid; q < P * (P + 1) / 2; q += ls) {  // the damped matrix, as gt_lm_next
                const int2 ij = gt_pair(q);
                const int i = ij.x, j = ij.y, ai = gt_lm_held(x, g, lo, hi, i);
                if (j < i)
                    L[i * P + j] = (ai || gt_lm_held(x, g, lo, hi, j)) ? (REAL)0 : A[i * P + j];
                else
                    L[i * P + i] = ai ? 1 + C : A[i * P + i] + C * D[i];
            }
            for (int i = lid; i < P; i += ls)
                xt[i] = gt_lm_held(x, g, lo, hi, i) ? 0 : g[i];
            ok = gt_chol_wg(L, P, lid, ls, wi + 1);
            if (ok)
                break;
            if (lid == 0) {
                wi[2] = C > cmax * wr[1];  // give up at this C
                if (!wi[2])
                    wr[0] = fmax(10 * C, ctiny * wr[1]);  // not PD: raise C tenfold and try again
            }
            barrier(CLK_LOCAL_MEM_FENCE);
            if (wi[2])
                break;
        }
        if (ok) {
            // eq. 22: L L^T delta = rhs into the xt slots, forward then back, a column at a time
            for (int j = 0; j < P; ++j) {
                if (lid == 0)
                    xt[j] /= L[j * P + j];
                barrier(CLK_GLOBAL_MEM_FENCE);
                for (int i = j + 1 + lid; i < P; i += ls)
                    xt[i] -= L[i * P + j] * xt[j];
                barrier(CLK_GLOBAL_MEM_FENCE);
            }
            for (int j = P - 1; j >= 0; --j) {
                if (lid == 0)
                    xt[j] /= L[j * P + j];
                barrier(CLK_GLOBAL_MEM_FENCE);
                for (int i = lid; i < j; i += ls)
                    xt[i] -= L[j * P + i] * xt[j];
                barrier(CLK_GLOBAL_MEM_FENCE);
            }
            for (int i = lid; i < P; i += ls)
                xt[i] = fmin(fmax(x[i] - xt[i], lo[i]), hi[i]);  // projected step (paper 003 eq. 8-9)
            barrier(CLK_GLOBAL_MEM_FENCE);
            for (int i = lid; i < P; i += ls) {  // the predicted reduction's term of row i
                const REAL si = x[i] - xt[i];
                REAL As = 0;
                for (int j = 0; j < P; ++j)
                    As += A[i * P + j] * (x[j] - xt[j]);
                tmp[i] = 2 * si * g[i] - si * As;
            }
            barrier(CLK_GLOBAL_MEM_FENCE);
        }
    }
    if (lid == 0 && !final_) {
        if (wi[0]) {
            sc[GT_LM_SC_C] = wr[0];
            if (!ok) {
                ib[GT_LM_I_STATUS] = GT_LM_FAILED;
                ib[GT_LM_I_REASON] = GT_LM_R_NOT_PD;
            } else {
                REAL pr = 0;
                for (int i = 0; i < P; ++i)
                    pr += tmp[i];
                sc[GT_LM_SC_PRED] = pr;
            }
        }
        gt_lm_points(ib[GT_LM_I_STATUS] == GT_LM_RUNNING ? xt : x, den, lo, hi, h, Xb, SX, P, rel);
    }
}
#endif

#ifdef USE_JAC
// entries j0..j0+3 of a row of J of P entries, zeros past its end
static REAL4 gt_lm_jpart4(__global const JTYPE *row, const int j0, const int P)
{
    if (j0 + 4 <= P)
        return GT_TO_REAL4(vload4(0, row + j0));
    return (REAL4)(j0 < P ? (REAL)row[j0] : (REAL)0, j0 + 1 < P ? (REAL)row[j0 + 1] : (REAL)0,
                   j0 + 2 < P ? (REAL)row[j0 + 2] : (REAL)0, (REAL)0);
}
#endif

// One LM iteration for every running problem. R: (B*SR, M) residuals of the last call
// (SR = 2P+1: trial point and perturbed copies; SR = 1: trial point only, with Jg its Jacobian
// (B, M, P) when USE_JAC, or the last call when FINAL). X: (B*SX, P) receives the next points.
// S small state, W workspace (device only), Out (B, P + 5) the result (gputrack.ops.lm.Layout).
__kernel void gt_lm_update(__global REAL *S, __global int *I, __global REAL *W, __global XTYPE *X,
                           __global const RTYPE *R, __global const JTYPE *Jg, __global REAL *Out, const int M,
                           const int SR, const int SX, const int first, const int final_)
{
    const int b = get_group_id(0), lid = get_local_id(0), ls = get_local_size(0);
    const int B = I[GT_LM_IG_B], has_mask = I[GT_LM_IG_HAS_MASK], P = I[GT_LM_IG_P];
    const int SB = SB_(P);
    __global REAL *Sb = S + (long)b * SB;
    __global REAL *x = Sb + GT_LM_S_X * P, *xt = Sb + GT_LM_S_XT * P, *g = Sb + GT_LM_S_G * P;
    __global REAL *den = Sb + GT_LM_S_DEN * P, *lo = Sb + GT_LM_S_LO * P, *hi = Sb + GT_LM_S_HI * P;
    __global REAL *h = Sb + GT_LM_S_H * P;
    __global REAL *Wb = W + (long)b * WB_(P, M);
    __global REAL *A = Wb + GT_LM_W_A * P * P, *L = Wb + GT_LM_W_L * P * P, *Jt = Wb + GT_LM_W_NSQ * P * P;
    __global REAL *sc = Sb + GT_LM_S_NVEC * P;  // F, C, nu, pred, Ft, snorm: the SC slots
    __global const REAL *G = S + (long)B * SB;
    __global const REAL *mask = G + GT_LM_NGLOB;
    __global int *ib = I + IB_(b, P);  // status, iterations, accepted, reason, fin[P]
    __global const RTYPE *rt = R + (long)b * SR * M;
    const REAL ftol = G[GT_LM_G_FTOL], xtol = G[GT_LM_G_XTOL], gtol = G[GT_LM_G_GTOL], rel = G[GT_LM_G_REL];
    const REAL ctiny = G[GT_LM_G_CTINY], cmax = G[GT_LM_G_CMAX];
    const int scale = (int)G[GT_LM_G_SCALE];
    __global REAL *D = Jt + (long)P * M;  // the damping's scale of the last step
    const int weighted = scale != GT_LM_SCALE_IDENTITY && !first;  // xtol norms as MINPACK's ||D x||
    const int running = ib[GT_LM_I_STATUS] == GT_LM_RUNNING;
#ifdef LM_WG_STEP
    __local int wg_i[3];
    __local REAL wg_r[2];
#endif

    // 1. Jacobian at the evaluated trial: eq. 24 over the stored points, or given
#ifdef USE_JAC
    // given: J^T J into L and J^T r into the first P values of Jt straight from J (M rows of P, as
    // stored; eq. 22), moved to A and g in 3. if the trial is accepted; J is finite iff the diagonal is
    if (running && !final_) {
        __global const JTYPE *Jb = Jg + (long)b * M * P;
#ifdef LM_P
        // P a build define: blocks of four rows i0..i0+3 of J^T J (and of J^T r) per work-item, in
        // registers: row m of J times its four entries at i0.., the columns from i0's vector of
        // four on (the upper triangle; the rest is their mirror), loaded four at a time, rows and
        // columns past P read as zeros. On PoCL (P = 20, M = 256) 0.04 ms against 0.16 ms for a
        // row per work-item with scalar sums (per-work-item arrays that PoCL keeps in memory).
        for (int rb = lid; rb < LM_NV; rb += ls) {
            const int i0 = 4 * rb;
            REAL4 a0[LM_NV], a1[LM_NV], a2[LM_NV], a3[LM_NV], ag = (REAL4)(0);
#pragma unroll
            for (int v = 0; v < LM_NV; ++v)
                a0[v] = a1[v] = a2[v] = a3[v] = (REAL4)(0);
            for (int m = 0; m < M; ++m) {
                __global const JTYPE *Jm = Jb + m * LM_P;
                const REAL4 x = gt_lm_jpart4(Jm, i0, LM_P);
                ag += x * (REAL)rt[m];
#pragma unroll
                for (int v = 0; v < LM_NV; ++v)
                    if (v >= rb) {
                        const REAL4 c = gt_lm_jpart4(Jm, 4 * v, LM_P);
                        a0[v] = fma((REAL4)(x.x), c, a0[v]);
                        a1[v] = fma((REAL4)(x.y), c, a1[v]);
                        a2[v] = fma((REAL4)(x.z), c, a2[v]);
                        a3[v] = fma((REAL4)(x.w), c, a3[v]);
                    }
            }
            REAL t[4][4], tg[4];
            vstore4(ag, 0, tg);
            for (int k = 0; k < 4 && i0 + k < LM_P; ++k)
                Jt[i0 + k] = tg[k];
#pragma unroll
            for (int v = 0; v < LM_NV; ++v)
                if (v >= rb) {
                    vstore4(a0[v], 0, t[0]);
                    vstore4(a1[v], 0, t[1]);
                    vstore4(a2[v], 0, t[2]);
                    vstore4(a3[v], 0, t[3]);
                    for (int k = 0; k < 4; ++k)
                        for (int e = 0; e < 4; ++e) {
                            const int i = i0 + k, j = 4 * v + e;
                            if (i < LM_P && j < LM_P && j >= i) {
                                L[i * LM_P + j] = t[k][e];
                                L[j * LM_P + i] = t[k][e];
                            }
                        }
                }
        }
#else
        // P a runtime value: per work-item a block of four rows i0.. by LM_JB columns j0.. of J^T J
        // (the blocks that reach the diagonal or beyond; the others are their mirror), its sums in
        // registers as vectors of four: row m of J times its four entries at i0, loaded four at a
        // time, rows and columns past P read as zeros (a block inside J's width takes the loop
        // without the bounds). Then J^T r by four rows. For the face bundle's P = 92 on PoCL:
        // ~0.2 ms a launch, against 0.46 ms for a row by LM_JB columns with scalar sums.
        const int nrb = (P + 3) / 4, ncb = (P + LM_JB - 1) / LM_JB;
        for (int q = lid; q < nrb * ncb + nrb; q += ls) {
            if (q < nrb * ncb) {
                const int rb = q / ncb, i0 = 4 * rb, j0 = (q - rb * ncb) * LM_JB;
                if (j0 + LM_JB <= i0)
                    continue;  // below the diagonal: the mirror of a block another work-item sums
                REAL4 acc[4][LM_JB / 4];
#pragma unroll
                for (int k = 0; k < 4; ++k)
#pragma unroll
                    for (int v = 0; v < LM_JB / 4; ++v)
                        acc[k][v] = (REAL4)(0);
                if (i0 + 4 <= P && j0 + LM_JB <= P) {
                    for (int m = 0; m < M; ++m) {
                        __global const JTYPE *Jm = Jb + (long)m * P;
                        const REAL4 x = GT_TO_REAL4(vload4(0, Jm + i0));
#pragma unroll
                        for (int v = 0; v < LM_JB / 4; ++v) {
                            const REAL4 c = GT_TO_REAL4(vload4(0, Jm + j0 + 4 * v));
                            acc[0][v] = fma((REAL4)(x.x), c, acc[0][v]);
                            acc[1][v] = fma((REAL4)(x.y), c, acc[1][v]);
                            acc[2][v] = fma((REAL4)(x.z), c, acc[2][v]);
                            acc[3][v] = fma((REAL4)(x.w), c, acc[3][v]);
                        }
                    }
                } else {
                    for (int m = 0; m < M; ++m) {
                        __global const JTYPE *Jm = Jb + (long)m * P;
                        const REAL4 x = gt_lm_jpart4(Jm, i0, P);
#pragma unroll
                        for (int v = 0; v < LM_JB / 4; ++v) {
                            const REAL4 c = gt_lm_jpart4(Jm, j0 + 4 * v, P);
                            acc[0][v] = fma((REAL4)(x.x), c, acc[0][v]);
                            acc[1][v] = fma((REAL4)(x.y), c, acc[1][v]);
                            acc[2][v] = fma((REAL4)(x.z), c, acc[2][v]);
                            acc[3][v] = fma((REAL4)(x.w), c, acc[3][v]);
                        }
                    }
                }
                REAL t[4];
#pragma unroll
                for (int k = 0; k < 4; ++k)
#pragma unroll
                    for (int v = 0; v < LM_JB / 4; ++v) {
                        vstore4(acc[k][v], 0, t);
                        for (int e = 0; e < 4; ++e) {
                            const int i = i0 + k, j = j0 + 4 * v + e;
                            if (i < P && j < P && j >= i) {
                                L[i * P + j] = t[e];
                                L[j * P + i] = t[e];
                            }
                        }
                    }
            } else {
                const int i0 = 4 * (q - nrb * ncb);
                REAL4 s = (REAL4)(0);
                for (int m = 0; m < M; ++m)
                    s = fma(gt_lm_jpart4(Jb + (long)m * P, i0, P), (REAL4)((REAL)rt[m]), s);
                REAL t[4];
                vstore4(s, 0, t);
                for (int k = 0; k < 4 && i0 + k < P; ++k)
                    Jt[i0 + k] = t[k];
            }
        }
#endif
    }
    barrier(CLK_GLOBAL_MEM_FENCE);
    if (running && !final_)
        for (int n = lid; n < P; n += ls)
            ib[GT_LM_I_FIN + n] = isfinite(L[n * P + n]) ? 1 : 0;
#else
    // the P x M entries shared out over the work-items (consecutive m: consecutive work-items); a
    // non-finite difference clears its column's flag
    if (running && !final_)
        for (int n = lid; n < P; n += ls)
            ib[GT_LM_I_FIN + n] = 1;
    barrier(CLK_GLOBAL_MEM_FENCE);
    if (running && !final_) {
        const int central = SR == 2 * P + 1;
        // a uniform loop over m with consecutive work-items on consecutive m (PoCL runs the
        // work-items of each pass as the inner, vectorised loop)
        for (int n = 0; n < P; ++n) {
            // the row moved by +eps and the one it is compared with: moved by -eps (central, eq. 24)
            // or the point's (forward)
            __global const RTYPE *rp = R + ((long)b * SR + 1 + (central ? 2 * n : n)) * M;
            __global const RTYPE *rm = central ? rp + M : R + (long)b * SR * M;
            const REAL dn = den[n];
            int fin = 1;  // a non-finite difference clears the column's flag
            for (int m0 = 0; m0 < M; m0 += ls) {
                const int m = m0 + lid;
                if (m < M) {
                    REAL v = 0;
                    if (!has_mask || mask[m * P + n] != 0) {
                        const REAL d = (REAL)rp[m] - (REAL)rm[m];  // r(x + eps e_n) - r(x -+ eps e_n)
                        fin &= isfinite(d) ? 1 : 0;
                        if (dn != 0)
                            v = d / dn;  // eq. 24
                    }
                    Jt[n * M + m] = v;
                }
            }
            if (!fin)
                atomic_and(ib + GT_LM_I_FIN + n, 0);
        }
    }
#endif
    barrier(CLK_GLOBAL_MEM_FENCE);

    // 2. acceptance of the trial, damping update (Nielsen), ftol / xtol
    if (lid == 0) {
        ib[GT_LM_I_ACCEPTED] = 0;
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
                    ok &= ib[GT_LM_I_FIN + n];
            sc[GT_LM_SC_FT] = Ft;
            int acc = 0;
            if (first && !ok) {
                ib[GT_LM_I_STATUS] = GT_LM_FAILED;
                ib[GT_LM_I_REASON] = GT_LM_R_NONFINITE;
                sc[GT_LM_SC_F] = INFINITY;  // no finite cost at x0
            } else if (first) {
                acc = 1;
            } else {
                ib[GT_LM_I_ITER] += 1;
                const REAL F = sc[GT_LM_SC_F], pred = sc[GT_LM_SC_PRED], dF = F - Ft;
                if (ok && dF > 0) {  // a trial with non-finite residuals or Jacobian is rejected (as MINPACK)
                    acc = 1;
                    const REAL rho = pred > 0 ? dF / pred : (REAL)1;
                    const REAL q = 2 * rho - 1;
                    sc[GT_LM_SC_C] *= fmax((REAL)1 / 3, 1 - q * q * q);
                    sc[GT_LM_SC_NU] = 2;
                } else {
                    sc[GT_LM_SC_C] *= sc[GT_LM_SC_NU];
                    sc[GT_LM_SC_NU] *= 2;
                    REAL sn = 0, xn = 0;
                    for (int i = 0; i < P; ++i) {
                        const REAL w = weighted ? D[i] : (REAL)1;
                        sn += w * (xt[i] - x[i]) * (xt[i] - x[i]);
                        xn += w * x[i] * x[i];
                    }
                    if (sqrt(sn) <= xtol * (xtol + sqrt(xn))) {
                        ib[GT_LM_I_STATUS] = GT_LM_CONVERGED;  // no step this small improves the cost
                        ib[GT_LM_I_REASON] = GT_LM_R_XTOL;
                    } else if (sc[GT_LM_SC_C] > cmax * gt_lm_cref(A, P, scale)) {
                        ib[GT_LM_I_STATUS] = GT_LM_FAILED;
                        ib[GT_LM_I_REASON] = GT_LM_R_DAMPING;
                    }
                }
            }
            if (acc) {
                ib[GT_LM_I_ACCEPTED] = 1;
                REAL sn = 0, xn = 0;
                for (int i = 0; i < P; ++i) {
                    const REAL w = weighted ? D[i] : (REAL)1;
                    const REAL d = xt[i] - x[i];
                    sn += w * d * d;
                    x[i] = xt[i];
                    xn += w * x[i] * x[i];
                }
                sn = sqrt(sn);
                sc[GT_LM_SC_SNORM] = sn;
                const REAL F_old = sc[GT_LM_SC_F];
                sc[GT_LM_SC_F] = Ft;
                if (!first) {
                    if (F_old - Ft <= ftol * F_old) {
                        ib[GT_LM_I_STATUS] = GT_LM_CONVERGED;
                        ib[GT_LM_I_REASON] = GT_LM_R_FTOL;
                    } else if (sn <= xtol * (xtol + sqrt(xn))) {
                        ib[GT_LM_I_STATUS] = GT_LM_CONVERGED;
                        ib[GT_LM_I_REASON] = GT_LM_R_XTOL;
                    }
                }
            }
            if (final_ && ib[GT_LM_I_STATUS] == GT_LM_RUNNING) {
                ib[GT_LM_I_STATUS] = GT_LM_MAX_ITER;
                ib[GT_LM_I_REASON] = GT_LM_R_MAX_ITER;
            }
        }
    }
    barrier(CLK_GLOBAL_MEM_FENCE);

    // 3. J^T J and J^T r at the accepted point (eq. 22): the P (P + 1) / 2 entries of the lower
    // triangle and the P entries of J^T r are shared out over the work-items
    if (!final_ && ib[GT_LM_I_ACCEPTED]) {
#ifdef USE_JAC
        for (int q = lid; q < P * P + P; q += ls) {  // computed in 1.
            if (q < P * P)
                A[q] = L[q];
            else
                g[q - P * P] = Jt[q - P * P];
        }
#else
        // by 2 x 2 blocks (rows i0, i1 of J^T J, columns j0, j1; four dots over shared loads) and
        // pairs of J^T r entries; i1 = i0 (j1 = j0) past the last row (column)
        const int nb = (P + 1) / 2, nblk = nb * (nb + 1) / 2;
        for (int q = lid; q < nblk + nb; q += ls) {
            if (q < nblk) {
                const int2 IJ = gt_pair(q);
                const int i0 = 2 * IJ.x, j0 = 2 * IJ.y, i1 = min(i0 + 1, P - 1), j1 = min(j0 + 1, P - 1);
                const REAL4 s = gt_dot22(Jt + i0 * M, Jt + i1 * M, Jt + j0 * M, Jt + j1 * M, M);
                A[i0 * P + j0] = s.x;
                A[j0 * P + i0] = s.x;
                if (j1 != j0 && j1 <= i0) {
                    A[i0 * P + j1] = s.y;
                    A[j1 * P + i0] = s.y;
                }
                if (i1 != i0) {
                    A[i1 * P + j0] = s.z;
                    A[j0 * P + i1] = s.z;
                    if (j1 != j0) {
                        A[i1 * P + j1] = s.w;
                        A[j1 * P + i1] = s.w;
                    }
                }
            } else {
                const int i0 = 2 * (q - nblk), i1 = min(i0 + 1, P - 1);
                __global const REAL *r0 = Jt + i0 * M, *r1 = Jt + i1 * M;
                REAL2 s0 = 0, s1 = 0;  // lane k sums m = k mod 2, the tail into lane 0
                int m = 0;
                for (; m + 1 < M; m += 2) {
                    const REAL2 rr = (REAL2)((REAL)rt[m], (REAL)rt[m + 1]);
                    s0 += vload2(0, r0 + m) * rr;
                    s1 += vload2(0, r1 + m) * rr;
                }
                REAL t0 = s0.x, t1 = s1.x;
                for (; m < M; ++m) {
                    t0 += r0[m] * (REAL)rt[m];
                    t1 += r1[m] * (REAL)rt[m];
                }
                g[i0] = t0 + s0.y;
                g[i1] = t1 + s1.y;
            }
        }
#endif
    }
    barrier(CLK_GLOBAL_MEM_FENCE);
#ifdef LM_WG_STEP
    // 4. by the whole work-group (Jt's first P values are free after 3.: scratch for the prediction)
    gt_lm_next_wg(x, xt, g, den, lo, hi, h, A, L, D, Jt, sc, ib, X + (long)b * SX * P, SX, P, gtol, rel, ctiny, cmax,
                  scale, final_, lid, ls, wg_i, wg_r);
    if (lid == 0)
        gt_lm_export(x, sc, ib, Out + (long)b * (P + 5), P);
#else
    if (lid == 0) {
        if (!final_)
            gt_lm_next(x, xt, g, den, lo, hi, h, A, L, D, Jt, sc, ib, X + (long)b * SX * P, SX, P, gtol, rel, ctiny,
                       cmax, scale);  // Jt's first P values are free after 3.: scratch for the envelope
        gt_lm_export(x, sc, ib, Out + (long)b * (P + 5), P);
    }
#endif
}

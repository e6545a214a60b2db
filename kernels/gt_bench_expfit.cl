// A benchmark model, not a primitive: the residuals of B fits of y = sum_k a_k exp(b_k t) to M
// samples (gputrack/benchmarks/lm.py, "device residuals"), computed on the device for a residual
// function handed to gputrack.LeastSquaresSolver. Points X (n, P) with P = 2K (a_k, b_k interleaved),
// t (M,), y (B, M); row i of X belongs to problem i / nper. Float64 (the solver's precision).
//
// One work-item per (group of GT_EXPFIT_LANES samples m, row i): global size
// (ceil(M / GT_EXPFIT_LANES), n). The group's exponentials are one exp of a double8, which PoCL
// (CPU) computes with its vector math library; one work-item per (m, i) with a scalar exp was a
// libm call per value, not vectorised across the work-items. Measured on the 2-core VM under load
// (PoCL 3.1, B = 10, P = 20, M = 256, 410 points, medians of 15 interleaved calls, 2026-11-27):
// scalar exp per (m, i) 17.0 ms, a polynomial exp of double8 3.1 ms, exp of double8 1.2 ms; the
// NumPy callable 8.0 ms.
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

#define GT_EXPFIT_LANES 8

__kernel void gt_bench_expfit(__global const double *X, __global const double *t, __global const double *y,
                              __global double *R, const int P, const int M, const int nper)
{
    const int m0 = (int)get_global_id(0) * GT_EXPFIT_LANES, i = get_global_id(1);
    if (m0 >= M)
        return;
    __global const double *x = X + (long)i * P;
    __global const double *yb = y + (long)(i / nper) * M;
    __global double *Ri = R + (long)i * M;
    if (m0 + GT_EXPFIT_LANES <= M) {
        const double8 tv = vload8(0, t + m0);
        double8 s = 0;
        for (int k = 0; k + 1 < P; k += 2)
            s += x[k] * exp(x[k + 1] * tv);
        vstore8(s - vload8(0, yb + m0), 0, Ri + m0);
    } else { // the last, short group
        for (int m = m0; m < M; m++) {
            double s = 0;
            for (int k = 0; k + 1 < P; k += 2)
                s += x[k] * exp(x[k + 1] * t[m]);
            Ri[m] = s - yb[m];
        }
    }
}

// A benchmark model, not a primitive: the residuals of B fits of y = sum_k a_k exp(b_k t) to M
// samples (gputrack/benchmarks/lm.py, "device residuals"), computed on the device for a residual
// function handed to gputrack.LeastSquaresSolver. Points X (n, P) with P = 2K (a_k, b_k interleaved),
// t (M,), y (B, M); row i of X belongs to problem i / nper. Float64 (the solver's precision).
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

__kernel void gt_bench_expfit(__global const double *X, __global const double *t, __global const double *y,
                              __global double *R, const int P, const int M, const int nper)
{
    const int m = get_global_id(0), i = get_global_id(1);
    if (m >= M)
        return;
    __global const double *x = X + (long)i * P;
    const double tm = t[m];
    double s = 0;
    for (int k = 0; k + 1 < P; k += 2)
        s += x[k] * exp(x[k + 1] * tm);
    R[(long)i * M + m] = s - y[(long)(i / nper) * M + m];
}

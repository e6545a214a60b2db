"""A benchmark model, not a primitive: the residuals of B fits of y = sum_k a_k exp(b_k t) as a Taichi
kernel (gputrack/benchmarks/lm.py, "device residuals"; the OpenCL version is kernels/gt_bench_expfit.cl).

One thread per (point i, group of LANES_CPU samples m; 1 sample off the CPU archs): the group's t
as a vector, so that on the CPU archs (compiled with ``scalarize=False``) each exponential is one
vectorised :func:`~gputrack.backends.taichi.expm.exp64` over the group; ``ti.exp`` in float64 is a call into
the C math library per value there, and has no SPIR-V (taichi:vulkan) instruction at all. Measured
on the 2-core VM under load (taichi:cpu, B = 10, P = 20, M = 256, 410 points, medians of 20
interleaved calls, 2026-11-27): one thread per (i, m) with ``ti.exp`` 8.6 ms, with the scalar
exp64 9.2 ms; 4 lanes 4.5 ms, 8 lanes 3.0 ms, 16 lanes 2.7 ms; the NumPy callable 6.1 ms.
"""

from ..backends.taichi.expm import exp64
from ..backends.taichi.launch import launch
from ..backends.taichi.runtime import current_arch, ti

nd = ti.types.ndarray()

#: samples per thread on the CPU archs (one AVX-512 register of doubles, two AVX2 ones); 1 elsewhere
LANES_CPU = 8


@ti.kernel
def _expfit(X: nd, t: nd, y: nd, R: nd, nper: ti.i32, L: ti.template()):
    """R[i, m] = sum_k X[i, 2k] exp(X[i, 2k+1] t[m]) - y[i // nper, m], float64."""
    n, P, M = X.shape[0], X.shape[1], t.shape[0]
    for i, g in ti.ndrange(n, (M + L - 1) // L):
        m0 = g * L
        # the group's t (a short last group repeats t[M - 1])
        tv = ti.Vector([t[ti.min(m0 + j, M - 1)] for j in ti.static(range(L))], ti.f64)
        s = tv * ti.f64(0.0)
        for k in range(P // 2):
            s += X[i, 2 * k] * exp64(X[i, 2 * k + 1] * tv)
        b = i // nper
        for j in ti.static(range(L)):
            if m0 + j < M:
                R[i, m0 + j] = s[j] - y[b, m0 + j]


def expfit(X, t, y, R, nper: int) -> None:
    """Taichi ndarrays X (n, P), t (M,), y (B, M), R (n, M) float64."""
    lanes = LANES_CPU if current_arch() == "cpu" else 1
    launch(_expfit, (X, t, y, R), (lanes,), scalars=(int(nper),), scalarize=False)

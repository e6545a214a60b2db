"""A benchmark model, not a primitive: the residuals of B fits of y = sum_k a_k exp(b_k t) as a Taichi
kernel (gputrack/benchmarks/lm.py, "device residuals"; the OpenCL version is kernels/gt_bench_expfit.cl)."""

from ..backends.taichi.launch import launch
from ..backends.taichi.runtime import ti

nd = ti.types.ndarray()


@ti.kernel
def _expfit(X: nd, t: nd, y: nd, R: nd, nper: ti.i32):
    """R[i, m] = sum_k X[i, 2k] exp(X[i, 2k+1] t[m]) - y[i // nper, m], float64."""
    n, P, M = X.shape[0], X.shape[1], t.shape[0]
    for i, m in ti.ndrange(n, M):
        s = ti.cast(0, ti.f64)
        tm = t[m]
        for k in range(P // 2):
            s += X[i, 2 * k] * ti.exp(X[i, 2 * k + 1] * tm)
        R[i, m] = s - y[i // nper, m]


def expfit(X, t, y, R, nper: int) -> None:
    """Taichi ndarrays X (n, P), t (M,), y (B, M), R (n, M) float64."""
    launch(_expfit, (X, t, y, R), scalars=(int(nper),))

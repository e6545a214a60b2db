"""The benchmark's device residual kernels (gputrack/benchmarks/expfit_taichi.py,
kernels/gt_bench_expfit.cl) against the NumPy callable of gputrack.benchmarks.lm.exp_fits, and the
Taichi kernels' float64 exp (gputrack/backends/taichi/expm.py) against np.exp."""

import numpy as np
import pytest

from gputrack.benchmarks.lm import device_residuals, exp_fits

B, P = 10, 20
#: |device - NumPy| per residual, relative to sum_k |a_k exp(b_k t)| + |y| (the magnitude of what
#: is summed; a residual itself may cancel to near 0)
RTOL = 1e-13


def _residual_device(device):
    if device.backend == "numpy":
        pytest.skip("numpy: the NumPy callable is the reference")
    if device.backend not in ("taichi", "opencl"):
        pytest.skip(f"{device.spec}: no device residual kernel for this backend")
    if not device.fp64:
        pytest.skip(f"{device.spec}: no float64 (the residual kernels are float64)")


def _compare(device, M, X, res):
    t, y = res.data
    dres = device_residuals(device, B, t, y)
    got = dres(device.asarray(X)).numpy()
    with np.errstate(over="ignore", invalid="ignore"):
        ref = res(X)
        terms = np.abs(X[:, 0::2, None] * np.exp(X[:, 1::2, None] * t))  # (n, K, M)
        scale = terms.sum(axis=1) + np.abs(y).repeat(X.shape[0] // B, axis=0)
    assert got.shape == ref.shape == (X.shape[0], M)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    inf = np.isinf(ref)
    np.testing.assert_array_equal(got[inf], ref[inf])  # same infinities, same signs
    fin = np.isfinite(ref)
    np.testing.assert_array_equal(np.isfinite(got), fin)
    err = np.abs(got[fin] - ref[fin]) / scale[fin]
    assert err.max() <= RTOL, f"worst relative error {err.max():.2e}"
    return got, ref


@pytest.mark.parametrize("M", [256, 250])  # 250: a last group of samples shorter than the kernels' lanes
def test_residuals_equal_numpy(device, M):
    _residual_device(device)
    rng = np.random.default_rng(3)
    res, _, x0, _, _ = exp_fits(B, P, M, rng)
    # the stacked points of a central-difference iteration, each row moved a little
    X = np.repeat(x0, 2 * P + 1, axis=0) * rng.uniform(0.9, 1.1, (B * (2 * P + 1), P))
    _compare(device, M, X, res)


def test_residuals_overflow_like_numpy(device):
    """Far trial points: exponents past exp's range give inf (not NaN) and 0 as in NumPy."""
    _residual_device(device)
    M = 256
    rng = np.random.default_rng(4)
    res, _, x0, _, _ = exp_fits(B, P, M, rng)
    X = np.repeat(x0, 3, axis=0)
    X[0, 1] = 800.0  # a_0 > 0: exp(800 t) overflows for t > 0.887 -> +inf
    X[1, 0], X[1, 1] = -X[1, 0], 720.0  # -inf
    X[2, 1] = -800.0  # underflows to 0 for t > 0.93: finite
    X[3, 1] = 709.5  # the largest finite exponents (t = 1: 1.35e308 times a_0)
    X[3, 0] = 0.5
    X[4, 1::2] = 60.0  # several large terms, finite
    X[5, 1] = np.nan  # NaN in, NaN out
    _, ref = _compare(device, M, X, res)
    assert np.isposinf(ref[0, -1]) and np.isneginf(ref[1, -1]) and np.isnan(ref[5]).all()
    assert np.isfinite(ref[2]).all() and np.isfinite(ref[3]).all()


# ------------------------------------------------------------------------------------------------
# exp64 (Taichi)


def _exp64_kernels():
    from gputrack.backends.taichi.expm import exp64
    from gputrack.backends.taichi.runtime import ti

    nd = ti.types.ndarray()

    @ti.kernel
    def scalar(x: nd, y: nd):
        for i in range(x.shape[0]):
            y[i] = exp64(x[i])

    @ti.kernel
    def lanes(x: nd, y: nd, L: ti.template()):
        for g in range(x.shape[0] // L):
            e = exp64(ti.Vector([x[g * L + j] for j in ti.static(range(L))], ti.f64))
            for j in ti.static(range(L)):
                y[g * L + j] = e[j]

    return scalar, lanes


_kernels = None
EDGES = [0.0, -0.0, 5e-324, -5e-324, 1e-300, -1e-300, 1e-17, np.nan, -np.nan, np.inf, -np.inf,
         709.78, 709.782712893384, 709.7827128933841, 709.79, 710.0, 1e300, -745.13, -745.14, -746.0, -1e300,
         -708.39, 0.34657359027997264, -0.34657359027997264, 1.0, -1.0, 88.0, -88.0]  # fmt: skip


def _check_exp(x, got):
    with np.errstate(over="ignore", under="ignore"):
        ref = np.exp(x)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    np.testing.assert_array_equal(np.isposinf(got), np.isposinf(ref))
    tiny = np.finfo(np.float64).tiny
    normal = np.isfinite(ref) & (ref >= tiny)
    rel = np.abs(got[normal] - ref[normal]) / ref[normal]
    assert rel.max() <= 2 * 2.0**-52, f"worst relative error {rel.max():.2e} at x = {x[normal][np.argmax(rel)]!r}"
    # subnormal results (or 0): within the subnormal range (the CPU may flush them to 0)
    small = np.isfinite(ref) & (ref < tiny)
    assert np.all(np.abs(got[small] - ref[small]) <= tiny)
    assert np.all(got[small] >= 0)
    # exact values
    assert np.all(got[x == 0] == 1.0)
    assert np.all(got[x == -np.inf] == 0.0)


@pytest.mark.parametrize("lanes", [0, 8])  # 0: scalar; 8: one vector of 8 lanes (SIMD on the CPU archs)
def test_exp64_matches_numpy(device, lanes):
    if device.backend != "taichi":
        pytest.skip(f"{device.spec}: exp64 is a Taichi function")
    if not device.fp64:
        pytest.skip(f"{device.spec}: no float64")
    if lanes > 1 and device.spec != "taichi:cpu":
        pytest.skip(f"{device.spec}: exp64 of a vector is for the CPU archs (the kernels use 1 lane elsewhere)")
    from gputrack.backends.taichi.launch import launch

    global _kernels
    if _kernels is None:
        _kernels = _exp64_kernels()
    scalar, vector = _kernels
    rng = np.random.default_rng(5)
    x = np.concatenate([np.array(EDGES), rng.uniform(-745.2, 709.8, 1 << 16), rng.uniform(-1, 1, 1 << 14),
                        rng.uniform(-1e-10, 1e-10, 256)])  # fmt: skip
    x = np.concatenate([x, np.zeros(-x.size % 8)])
    xd = device.asarray(x)
    yd = device.empty(x.shape, np.float64)
    if lanes:
        launch(vector, (xd.buffer, yd.buffer), (lanes,), scalarize=False)
    else:
        launch(scalar, (xd.buffer, yd.buffer))
    _check_exp(x, yd.numpy())

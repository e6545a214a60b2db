"""kernels/gt_math.clh (the OpenCL sampler's and CPU forward kinematics' sine, cosine and
logarithm) against NumPy's float64 functions on the same float32 inputs."""

import numpy as np
import pytest

from gputrack.abi import ANGLE_MAX

SOURCE = """
#include "gt_math.clh"
__kernel void gt_test_math(__global const float *x, __global float *out, const int n)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    float c;
    out[3 * i] = gt_sincosf(x[i], &c);
    out[3 * i + 1] = c;
    out[3 * i + 2] = gt_logf(fabs(x[i]));
}
"""


def _run(device, x):
    import pyopencl as cl

    from gputrack.backends.opencl.program import build_options

    kernel = cl.Kernel(cl.Program(device.context, SOURCE).build(options=build_options()), "gt_test_math")
    xs = device.asarray(x)
    out = device.empty((len(x), 3), np.float32)
    kernel(device.queue, (len(x),), None, xs.buffer.data, out.buffer.data, np.int32(len(x)))
    return out.numpy()


def test_sincos_and_log_within_an_ulp_or_two_of_float64(device):
    if device.backend != "opencl":
        pytest.skip(f"{device.spec}: gt_math.clh is an OpenCL header")
    rng = np.random.default_rng(3)
    x = np.concatenate([
        np.linspace(-8, 8, 200_001),  # every quadrant, the boundaries between them
        rng.uniform(-ANGLE_MAX, ANGLE_MAX, 200_000),  # the range FK clamps angles to
        rng.uniform(0, 1, 100_000),  # the sampler's uniforms
        2.0 ** rng.uniform(-24, 100, 100_000),  # log over many binades
        [ANGLE_MAX, -ANGLE_MAX, 1.0, 2.0**-24],
    ]).astype(np.float32)  # fmt: skip
    got = _run(device, x).astype(np.float64)
    x64 = x.astype(np.float64)
    angle = np.abs(x64) <= ANGLE_MAX  # the domain of gt_sincosf
    assert np.abs(got[angle, 0] - np.sin(x64[angle])).max() < 1.2e-7
    assert np.abs(got[angle, 1] - np.cos(x64[angle])).max() < 1.2e-7
    pos = x64 != 0
    want = np.log(np.abs(x64[pos]))
    assert (np.abs(got[pos, 2] - want) <= 1.2e-7 * np.maximum(np.abs(want), 1.0)).all()
    assert got[np.flatnonzero(x == 1.0)[0], 2] == 0.0


def test_sincos_of_inf_and_nan_is_nan(device):
    if device.backend != "opencl":
        pytest.skip(f"{device.spec}: gt_math.clh is an OpenCL header")
    got = _run(device, np.array([np.inf, -np.inf, np.nan], np.float32))
    assert np.isnan(got[:, :2]).all()

"""gputrack/backends/opencl/program.py's launch helpers: ``ndrange`` (fixed work-group shapes over a
padded range) and ``enqueue`` (a kernel's arguments set only where they changed)."""

import numpy as np
import pytest

SOURCE = """
__kernel void gt_test_axpy(__global const float *x, __global float *y, const float a, const int n)
{
    const int i = get_global_id(0);
    if (i >= n)  // the padding of ndrange
        return;
    y[i] = a * x[i] + y[i];
}
"""


def _opencl(device):
    if device.backend != "opencl":
        pytest.skip(f"{device.spec}: OpenCL launch helpers")


def test_ndrange_pads_to_whole_groups():
    from gputrack.backends.opencl.program import ndrange

    assert ndrange(1500) == ((1536,), (64,))
    assert ndrange(64) == ((64,), (64,))
    assert ndrange(0) == ((64,), (64,))  # an empty range still launches one group (the kernel skips it)
    assert ndrange(22, 169, group=(4, 8)) == ((24, 176), (4, 8))
    assert ndrange(10, 3) == ((16, 8), (8, 8))
    with pytest.raises(ValueError, match="expected 2 dimensions"):
        ndrange(10, 3, group=(64,))


def test_enqueue_sets_changed_arguments_only(device):
    _opencl(device)
    import pyopencl as cl

    from gputrack.backends.opencl.program import enqueue, ndrange, scalar_types

    sets, one = [], []

    class Counting(cl.Kernel):
        def set_args(self, *args):
            sets.append(args)
            return super().set_args(*args)

        def set_arg(self, i, value):
            one.append(i)
            return super().set_arg(i, value)

    kernel = Counting(cl.Program(device.context, SOURCE).build(), "gt_test_axpy")
    scalar_types(kernel, [None, None, np.float32, np.int32])
    n = 100
    x = device.asarray(np.arange(n, dtype=np.float32))
    y1 = device.asarray(np.zeros(n, np.float32))
    y2 = device.asarray(np.ones(n, np.float32))
    enqueue(device, kernel, *ndrange(n), x.buffer.data, y1.buffer.data, 2.0, n)
    enqueue(device, kernel, *ndrange(n), x.buffer.data, y1.buffer.data, 2.0, n)  # unchanged: not set again
    assert len(sets) == 1
    np.testing.assert_array_equal(y1.numpy(), 4.0 * np.arange(n))
    del one[:]  # (PyOpenCL's set_args may go through set_arg)
    enqueue(device, kernel, *ndrange(n), x.buffer.data, y1.buffer.data, -1.0, n)  # a scalar changes: it alone
    assert (len(sets), one) == (1, [2])
    np.testing.assert_array_equal(y1.numpy(), 3.0 * np.arange(n))
    enqueue(device, kernel, *ndrange(n), x.buffer.data, y2.buffer.data, -1.0, n)  # a buffer changes: it alone
    assert (len(sets), one) == (1, [2, 1])
    np.testing.assert_array_equal(y2.numpy(), 1.0 - np.arange(n))
    np.testing.assert_array_equal(y1.numpy(), 3.0 * np.arange(n))  # the first output untouched
    enqueue(device, kernel, *ndrange(n - 30), x.buffer.data, y2.buffer.data, 1.0, n - 30)  # fewer items
    assert (len(sets), one) == (1, [2, 1, 2, 3])
    want = 1.0 - np.arange(n)
    want[: n - 30] += np.arange(n - 30)
    np.testing.assert_array_equal(y2.numpy(), want)

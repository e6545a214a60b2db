"""The lighter Taichi frontend of gputrack/backends/taichi/runtime.py: kernels and functions still
compile to the same results, class kernels are still recognised, and compile errors still name the
file, line and code."""

import inspect

import numpy as np
import pytest


@pytest.fixture
def taichi(device):
    """The Taichi runtime module on a Taichi device (the frontend is the same on every arch)."""
    if device.backend != "taichi":
        pytest.skip("Taichi's frontend only")
    from gputrack.backends.taichi import runtime

    return device, runtime


def _inspect_inside_class(level):
    """Taichi 1.7's own test, through inspect.getframeinfo (the reference for the fast one)."""
    import re
    import sys

    frame = sys._getframe(level)
    line = inspect.getframeinfo(frame)[3][0].strip()
    return any(re.match(p, line) for p in (r"@(\w+\.)?data_oriented", r"class "))


def test_inside_class_agrees_with_taichis_own_test(taichi):
    _, runtime = taichi
    ti = runtime.ti
    # level 2: the frame that runs the class statement (0 is the test itself, 1 the class body), as
    # Taichi's decorators look at the frame around the class body they are called from

    class Plain:
        fast = runtime._inside_class(2)
        slow = _inspect_inside_class(2)

    @ti.data_oriented
    class Decorated:
        fast = runtime._inside_class(2)
        slow = _inspect_inside_class(2)

    def probe():
        return runtime._inside_class(2), _inspect_inside_class(2)

    outside = probe()
    assert (Plain.fast, Plain.slow) == (True, True)
    assert (Decorated.fast, Decorated.slow) == (True, True)
    assert outside == (False, False)
    assert runtime._inside_class(10**6) is False  # no such frame


def test_kernels_functions_and_class_kernels_compile_as_before(taichi):
    _, runtime = taichi
    ti = runtime.ti
    from taichi.lang import kernel_impl

    assert kernel_impl._inside_class is runtime._inside_class

    @ti.func
    def twice(v):
        return 2 * v

    @ti.kernel
    def apply(a: ti.types.ndarray(dtype=ti.f32, ndim=1)):
        for i in range(a.shape[0]):
            a[i] = twice(a[i]) + twice(1.0)  # the function's source looked up once, used twice

    @ti.data_oriented
    class Scaler:
        def __init__(self, k):
            self.k = k

        @ti.kernel
        def run(self, a: ti.types.ndarray(dtype=ti.f32, ndim=1)):
            for i in range(a.shape[0]):
                a[i] = a[i] * self.k

    a = np.arange(5, dtype=np.float32)
    apply(a)
    np.testing.assert_array_equal(a, 2 * np.arange(5, dtype=np.float32) + 2)
    Scaler(3.0).run(a)
    np.testing.assert_array_equal(a, 3 * (2 * np.arange(5, dtype=np.float32) + 2))


def test_compile_errors_name_file_line_and_code(taichi):
    _, runtime = taichi
    ti = runtime.ti

    @ti.kernel
    def broken(a: ti.types.ndarray(dtype=ti.f32, ndim=1)):
        for i in range(a.shape[0]):
            a[i] = not_defined_anywhere(a[i])  # noqa: F821 - the error under test

    with pytest.raises(Exception) as err:
        broken(np.zeros(3, np.float32))
    text = str(err.value)
    line = inspect.getsourcelines(test_compile_errors_name_file_line_and_code)[1] + 7
    assert __file__ in text and f"line {line}" in text
    assert "not_defined_anywhere(a[i])" in text

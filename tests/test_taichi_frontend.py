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


def test_direct_launch_of_numpy_arrays_of_vector_elements(taichi, monkeypatch):
    """launch.py's direct path passes a NumPy argument annotated with vector elements as Taichi's own
    call does (the shape without the element's dimension): the first launch compiles through
    ``kernel(...)``, the next go direct, and every launch reads and writes the right elements."""
    device, runtime = taichi
    if runtime.current_arch() != "cpu":
        pytest.skip(f"{device.spec}: NumPy arrays are passed to Taichi kernels by address on taichi:cpu only")
    from gputrack.backends.taichi import launch as L

    # a test process that ran another arch first may have turned direct launches off for its Taichi
    # program (runtime.direct_off: arrays of the stopped program still alive); this kernel touches
    # NumPy arrays only, so the direct path is turned on for it alone
    monkeypatch.setattr(runtime, "direct_off", None)
    monkeypatch.setattr(L, "_enabled", True)

    ti = runtime.ti
    pairs = ti.types.ndarray(dtype=ti.types.vector(2, ti.f64), ndim=2)

    @ti.kernel
    def swap_and_scale(a: pairs, out: ti.types.ndarray(), k: ti.f64):
        for i, j in ti.ndrange(a.shape[0], a.shape[1]):
            out[i, 2 * j] = k * a[i, j][1]
            out[i, 2 * j + 1] = k * a[i, j][0]

    rng = np.random.default_rng(3)
    for k in (1.0, 2.0, -0.5):  # the first compiles, the others launch directly
        a = rng.normal(size=(3, 8))
        out = np.zeros((3, 8))
        L.launch(swap_and_scale, (a.reshape(3, 4, 2), out), scalars=(k,))
        want = k * a.reshape(3, 4, 2)[..., ::-1].reshape(3, 8)
        np.testing.assert_array_equal(out, want)
    assert any(key[0] is swap_and_scale for key in L._cache)  # remembered for direct launches


def test_a_kernel_compiled_without_taichis_ir_passes(taichi):
    """``launch(..., ir_passes=False)`` compiles the kernel without Taichi's own IR optimisation on
    the CPU archs (``advanced_optimization``, turned back on afterwards, also when the call fails)
    and gives the results of the kernel compiled with it: the same sums, bit for bit."""
    device, runtime = taichi
    from gputrack.backends.taichi import launch as L

    ti = runtime.ti
    nd = ti.types.ndarray()

    def body(x: nd, out: nd):
        ti.loop_config(serialize=True)
        for i in range(out.shape[0]):
            s = ti.cast(0, ti.f32)
            for k in range(x.shape[1]):
                s += x[i, k] * x[i, k] - x[i, (k + 1) % x.shape[1]]
            out[i] = s

    plain, optimised = ti.kernel(body), ti.kernel(body)
    cfg = ti.lang.impl.current_cfg()
    x = device.asarray(np.random.default_rng(4).normal(size=(6, 40)).astype(np.float32))
    got = {}
    for name, kernel, passes in (("plain", plain, False), ("optimised", optimised, True)):
        out = device.empty((6,), np.float32)
        L.launch(kernel, (x.buffer, out.buffer), ir_passes=passes)
        assert cfg.advanced_optimization, "Taichi's passes must be on again after the launch"
        got[name] = out.numpy()
    np.testing.assert_array_equal(got["plain"], got["optimised"])
    want = (x.numpy() ** 2 - np.roll(x.numpy(), -1, axis=1)).sum(axis=1)
    np.testing.assert_allclose(got["plain"], want, rtol=1e-5, atol=1e-5)
    with pytest.raises(Exception):  # noqa: B017 - Taichi's own error for an array of the wrong rank
        L.launch(ti.kernel(body), (np.zeros(3, np.float32), np.zeros(6, np.float32)), ir_passes=False)
    assert cfg.advanced_optimization

import json
import os

import numpy as np
import pytest

import gputrack


def test_asarray_roundtrip_counts_bytes(device):
    x = np.arange(13 * 3, dtype=np.float32).reshape(13, 3)
    before = device.transfers.copy()
    a = device.asarray(x)
    back = gputrack.to_numpy(a)
    np.testing.assert_array_equal(back, x)
    moved = device.transfers - before
    if device.backend == "numpy":
        assert isinstance(a, np.ndarray) and (moved.h2d, moved.d2h) == (0, 0)
    else:
        assert isinstance(a, gputrack.DeviceArray)
        assert a.shape == (13, 3) and a.dtype == np.float32 and a.device is device
        assert (moved.h2d, moved.d2h) == (x.nbytes, x.nbytes)


@pytest.mark.parametrize("dtype", ["float32", "float64", "int32", "uint8"])
def test_asarray_dtypes(device, dtype):
    if dtype == "float64" and not device.fp64:
        with pytest.raises(TypeError, match="float64"):
            device.asarray(np.zeros(3))
        return
    x = (np.arange(129) % 7).astype(dtype)
    np.testing.assert_array_equal(gputrack.to_numpy(device.asarray(x)), x)


@pytest.mark.parametrize("shape", [(7,), (5, 3), (2, 3, 4), (3, 5, 3, 4), (2, 1, 3, 2, 2), (480, 640), (3, 17), (2, 2, 33)])
def test_asarray_roundtrip_shapes(device, shape):
    """Every rank round-trips exactly (ranks 1-4 take the device's copy kernels, 5 the fallback; rows
    longer than a copy's lanes with a tail)."""
    x = np.random.default_rng(1).normal(size=shape).astype(np.float32)
    np.testing.assert_array_equal(gputrack.to_numpy(device.asarray(x)), x)
    # a non-contiguous view is uploaded as its values
    y = x[..., ::-1] if x.ndim > 1 else x[::-2]
    np.testing.assert_array_equal(gputrack.to_numpy(device.asarray(y)), y)


@pytest.mark.parametrize("fast", [True, False])
def test_taichi_allocation_paths(device, fast, monkeypatch):
    """Both ways of allocating Taichi arrays (Taichi's program object, or ti.ndarray) give arrays
    that kernels write and read correctly."""
    if device.backend != "taichi":
        pytest.skip("Taichi allocation")
    from gputrack.backends.taichi import runtime

    if not fast:
        monkeypatch.setattr(runtime, "_fast_alloc", False)
    x = np.arange(3 * 129, dtype=np.float32).reshape(3, 129)
    a = device.empty(x.shape, np.float32)
    assert isinstance(a.buffer, runtime.ti.Ndarray) and a.buffer.shape == x.shape
    from gputrack.backends.taichi.arrays import copy

    assert copy(x if device.arch == "cpu" else device.asarray(x).buffer, a.buffer)  # a kernel writes a
    np.testing.assert_array_equal(a.numpy(), x)
    np.testing.assert_array_equal(device.asarray(x).numpy(), x)


@pytest.mark.parametrize("shape", [(7,), (5, 3), (2, 3, 4), (3, 5, 3, 4), (16384, 6), (3, 17)])
def test_taichi_cpu_copies_through_host_memory(device, shape, monkeypatch):
    """On taichi:cpu an upload or download is NumPy's copy into or out of the Taichi array's host
    memory (no kernel); with another dtype, or with direct launches off, the copy kernels run, and
    every path gives the same values."""
    if device.spec != "taichi:cpu":
        pytest.skip("the host-memory copies are taichi:cpu's")
    from gputrack.backends.taichi import arrays, runtime

    x = np.random.default_rng(2).normal(size=shape).astype(np.float32)
    a = device.empty(shape, np.float32)
    launched = []
    real_launch = arrays.launch
    monkeypatch.setattr(arrays, "launch", lambda *args, **kw: (launched.append(args[0]), real_launch(*args, **kw)))
    assert arrays.host_view(a.buffer, x) is not None
    assert arrays.copy(x, a.buffer)
    back = np.empty_like(x)
    assert arrays.copy(a.buffer, back)
    np.testing.assert_array_equal(back, x)
    assert launched == []  # both ways without a kernel
    # another dtype: no view; the kernel casts (float64 host into the float32 array)
    x64 = x.astype(np.float64) + 0.25
    assert arrays.host_view(a.buffer, x64) is None
    assert arrays.copy(x64, a.buffer)
    np.testing.assert_array_equal(a.numpy(), x64.astype(np.float32))
    assert launched == [arrays.COPY[len(shape)]]
    # a Taichi that cannot give an array's address: kernels from then on
    class NoAddress:
        prog = None

    monkeypatch.setattr(arrays, "_views", True)  # and True again when the test ends
    with monkeypatch.context() as m:
        m.setattr(runtime.ti.lang.impl, "get_runtime", lambda: NoAddress)
        assert arrays.host_view(a.buffer, x) is None and arrays._views is False
        assert arrays.host_view(a.buffer, x) is None
    monkeypatch.setattr(arrays, "_views", True)
    assert arrays.host_view(a.buffer, x) is not None
    # direct launches off: the copy kernels both ways, the same values
    monkeypatch.setattr(runtime, "direct_off", "test")
    assert arrays.host_view(a.buffer, x) is None
    assert arrays.copy(x, a.buffer)
    back[...] = 0
    assert arrays.copy(a.buffer, back)
    np.testing.assert_array_equal(back, x)
    assert launched[1:] == [arrays.COPY[len(shape)]] * 2


def test_asarray_into_existing_array(device):
    """asarray(x, out=a) writes x into a (counted as an upload) and returns a."""
    x = np.arange(480 * 640, dtype=np.float32).reshape(480, 640)
    a = device.asarray(np.zeros_like(x))
    before = device.transfers.copy()
    b = device.asarray(x, out=a)
    assert b is a
    np.testing.assert_array_equal(gputrack.to_numpy(a), x)
    if device.backend != "numpy":
        assert (device.transfers - before).h2d == x.nbytes
    with pytest.raises((TypeError, ValueError), match="out"):
        device.asarray(x[:10], out=a)
    with pytest.raises((TypeError, ValueError), match="out"):
        device.asarray(x.astype(np.int32), out=a)
    if device.backend != "numpy":
        with pytest.raises(TypeError, match="out"):
            device.asarray(x, out=np.zeros_like(x))


def test_asarray_rejects_bad_input(device):
    with pytest.raises(TypeError, match="expected an array of dtype .*got complex128"):
        device.asarray(np.zeros(3, dtype=complex))
    with pytest.raises(TypeError, match="astype"):
        device.asarray(np.zeros(3, dtype=bool))
    with pytest.raises(ValueError, match="at least one dimension"):
        device.asarray(np.float32(1.0))


def test_foreign_device_array_rejected(device):
    other = gputrack.device("numpy") if device.backend != "numpy" else None
    if other is None:
        # a DeviceArray-like from another device: use a fake device array to test the check
        fake = gputrack.DeviceArray(object.__new__(gputrack.Device), None, (3,), np.float32)
        fake.device.info = gputrack.DeviceInfo("opencl", "opencl", True)
        with pytest.raises(ValueError, match="expected a NumPy array for numpy, got an array on opencl"):
            device.asarray(fake)
        return
    from gputrack.ops._args import arg

    fake = gputrack.DeviceArray(object.__new__(gputrack.Device), None, (3,), np.float32)
    fake.device.info = gputrack.DeviceInfo("opencl:other", "opencl", True)
    with pytest.raises(ValueError, match=f"x: expected an array on {device.spec} or a NumPy array, got an array on opencl:other"):
        arg(device, fake, "x")


def test_device_array_is_not_implicitly_converted(device):
    if device.backend == "numpy":
        pytest.skip("the numpy device's arrays are NumPy arrays")
    a = device.asarray(np.ones(4, np.float32))
    with pytest.raises(TypeError, match=r"\.numpy\(\)"):
        np.asarray(a)


def test_same_device_object_per_spec(device):
    assert gputrack.device(device.spec) is device


def test_per_device_memoises_per_device_and_forgets_a_closed_device():
    from gputrack.backends.reference.device import NumpyDevice
    from gputrack.device import per_device

    built = []

    @per_device(maxsize=2)
    def thing(device, key):
        built.append((device, key))
        return object()

    a, b = NumpyDevice(), NumpyDevice()
    first = thing(a, 1)
    assert thing(a, 1) is first and thing(b, 1) is not first  # one value per device and arguments
    thing(a, 2)
    thing(a, 3)  # maxsize 2: the oldest (key 1) goes
    assert len(built) == 4
    assert thing(a, 1) is not first and len(built) == 5
    kept = thing(b, 1)
    a.close()
    assert a._memo == {} and thing(b, 1) is kept
    thing.cache_clear(b)
    assert thing(b, 1) is not kept


# -- sizes checked against the device before anything is allocated -------------------------------
def test_an_array_too_large_for_the_device_is_a_memory_error(device, monkeypatch):
    """512 GiB (the (2**17, 2**20) Mahalanobis table of the fuzz run, a crash on taichi:cpu) is
    refused on every device, naming the shape and the bytes; so is anything past the device's
    limit (here set low), for a new array, an upload and an op's output, before the op works."""
    shape = (2**17, 2**20)
    with pytest.raises(MemoryError, match=r"got float32 \(131072, 1048576\): .*549755813888 bytes \(512 GiB\)"):
        device.empty(shape)
    monkeypatch.setattr(device, "max_array_bytes", lambda: (1000, "a test limit"))
    want = rf"^expected an array of at most 1000 bytes on {device.spec} \(a test limit\), got float32 \(251,\): 1004 bytes\Z"
    with pytest.raises(MemoryError, match=want):
        device.empty((251,))
    with pytest.raises(MemoryError, match=want):  # a view to copy: an upload on every device
        device.asarray(np.broadcast_to(np.zeros(1, np.float32), (251,)))
    x, P = np.zeros((6, 2), np.float32), np.tile(np.eye(2, dtype=np.float32), (6, 1, 1))
    with pytest.raises(MemoryError, match=r"got float32 \(6, 42\): 1008 bytes"):
        gputrack.mahalanobis(device, x, P, np.eye(2, dtype=np.float32), np.eye(2, dtype=np.float32),
                             np.zeros((42, 2), np.float32))  # fmt: skip
    assert device.empty((250,)).shape == (250,)  # up to the limit


def test_the_device_limits_come_from_the_backend(device):
    limit, what = device.max_array_bytes()
    assert limit is None or limit > 2**26, (limit, what)
    if device.backend == "opencl":
        assert limit == min(device.cl_device.max_mem_alloc_size, device.cl_device.global_mem_size)
        # one element past the largest buffer, in a dtype whose element count stays under the 2**31 - 1
        # elements the kernels index (a device whose buffers reach 8 GiB needs float64)
        dt = np.dtype(np.float32 if limit // 4 + 1 <= device.max_elements or not device.info.fp64 else np.float64)
        n = limit // dt.itemsize + 1
        if n > device.max_elements:
            pytest.skip(f"{device.spec}: a buffer of {limit} bytes holds more elements than the kernels index")
        with pytest.raises(MemoryError, match=rf"on {device.spec} \(the OpenCL device's largest buffer\), got {dt.name} \({n},\)"):
            device.empty((n,), dt)
    if device.backend == "taichi":
        assert device.max_elements == 2**31 - 1 and device.max_ndim == 12
        with pytest.raises(MemoryError, match=r"at most 2147483647 elements on .*32-bit integers\), got uint8 \(2147483648,\)"):
            device.empty((2**31,), np.uint8)


def test_arrays_of_more_dimensions_than_the_device_has(device):
    """Taichi holds at most 12 dimensions (a 20-dimensional array gave "argument not found")."""
    if device.max_ndim is None:
        x = np.arange(2, dtype=np.float32).reshape((2,) + (1,) * 19)
        np.testing.assert_array_equal(gputrack.to_numpy(device.asarray(x)), x)
        return
    x = np.arange(2, dtype=np.float32).reshape((2,) + (1,) * (device.max_ndim - 1))
    np.testing.assert_array_equal(gputrack.to_numpy(device.asarray(x)), x)
    want = rf"^expected an array of at most 12 dimensions on {device.spec}, got 20: float32 \(1(, 1){{19}}\)\Z"
    with pytest.raises(ValueError, match=want):
        device.asarray(np.zeros((1,) * 20, np.float32))
    with pytest.raises(ValueError, match=want):
        device.empty((1,) * 20)


def test_a_ragged_list_is_not_an_array(device):
    want = r"expected a rectangular array \(nested sequences of equal lengths\), got a ragged list \(lengths \[2, 1\]\)"
    with pytest.raises(ValueError, match="^" + want):
        device.asarray([[1.0, 2.0], [3.0]])
    with pytest.raises(ValueError, match="^scores: " + want):
        gputrack.best_k(device, [[1.0, 2.0], [3.0]], 1)
    with pytest.raises(ValueError, match="^x: " + want):
        gputrack.kf_predict(device, [[1.0, 2.0], [3.0]], np.zeros((2, 2, 2)), np.eye(2), np.eye(2))


# -- closed devices -----------------------------------------------------------------------------
def _fresh(device):
    """A second device object of ``device``'s backend, closed by the caller (not the session's)."""
    if device.backend == "numpy":
        from gputrack.backends.reference.device import NumpyDevice

        return NumpyDevice()
    from gputrack.backends.opencl.device import open_opencl

    return open_opencl(device.spec.partition(":")[2])


def test_a_closed_device_and_its_arrays_are_unavailable(device):
    """Tracking on a closed device, or passing its array to another device: DeviceUnavailable.
    (Taichi runs one program per process: tests/test_registry.py closes taichi:cpu in a subprocess.)"""
    if device.backend == "taichi":
        pytest.skip("Taichi devices are closed in a subprocess (test_registry.py)")
    from gputrack.models import upper_body
    from gputrack.trackers.body import BodyTracker

    fresh = _fresh(device)
    old = fresh.asarray(np.zeros(5, np.float32))
    tracker = BodyTracker(fresh, upper_body().rest_params())
    fresh.close()
    with pytest.raises(gputrack.DeviceUnavailable, match="was closed"):
        tracker.track(np.zeros((480, 640), np.float32), np.zeros((480, 640), np.float32))
    if device.backend == "numpy":
        return  # its arrays are NumPy arrays
    want = rf"expected an array on {device.spec}, got an array of a closed {fresh.spec} device"
    with pytest.raises(gputrack.DeviceUnavailable, match="^scores: " + want):
        gputrack.best_k(device, old, 1)
    with pytest.raises(gputrack.DeviceUnavailable, match="^" + want):
        device.asarray(old)


@pytest.mark.parametrize("given", [None, "0"])
def test_pocl_defaults_apply_only_where_the_environment_has_none(given):
    """gputrack's PoCL settings (backends/opencl/device.py POCL_DEFAULTS) go into the environment
    before PoCL starts, unless the process was given its own."""
    import subprocess
    import sys

    from gputrack.backends.opencl.device import POCL_DEFAULTS

    env = {k: v for k, v in os.environ.items() if k not in POCL_DEFAULTS}
    if given is not None:
        env.update(dict.fromkeys(POCL_DEFAULTS, given))
    code = ("import os, json, gputrack.backends.opencl.device as d\n"
            "try:\n    d._enumerate()\nexcept RuntimeError:\n    pass\n"
            "print(json.dumps({k: os.environ.get(k) for k in d.POCL_DEFAULTS}))")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got == (POCL_DEFAULTS if given is None else dict.fromkeys(POCL_DEFAULTS, given))

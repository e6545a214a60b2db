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


@pytest.mark.parametrize("shape", [(7,), (5, 3), (2, 3, 4), (3, 5, 3, 4), (2, 1, 3, 2, 2), (480, 640)])
def test_asarray_roundtrip_shapes(device, shape):
    """Every rank round-trips exactly (ranks 1-4 take the device's copy kernels, 5 the fallback)."""
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

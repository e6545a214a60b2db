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

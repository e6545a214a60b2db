"""The ``numpy`` device: arrays are plain NumPy arrays on the host."""

from __future__ import annotations

import platform

import numpy as np

from ...device import Device, DeviceInfo, as_host_array


def cpu_name() -> str:
    """The CPU model name (from /proc/cpuinfo where there is one)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def probe_numpy() -> DeviceInfo:
    return DeviceInfo("numpy", "numpy", True, name=f"NumPy {np.__version__} on {cpu_name()}", fp64=True, kind="cpu")


def open_numpy(arg: str = "") -> "NumpyDevice":
    """The ``numpy`` device (``arg``: the registry's parse of the spec, always '')."""
    return NumpyDevice()


class NumpyDevice(Device):
    """Runs the reference implementation; ``asarray`` returns a contiguous NumPy array."""

    backend = "numpy"

    def __init__(self):
        super().__init__(probe_numpy())

    def asarray(self, array, dtype=None, *, out=None):
        from ...device import DeviceArray

        if out is not None:
            host = as_host_array(array, dtype=dtype)
            if not isinstance(out, np.ndarray) or host.shape != out.shape or host.dtype != out.dtype:
                raise ValueError(
                    f"out: expected a NumPy array {host.dtype.name} {host.shape} (the array's), got {out!r:.60}"
                )
            np.copyto(out, host)
            return out
        if isinstance(array, DeviceArray):
            raise ValueError(f"expected a NumPy array for numpy, got an array on {array.device.spec}")
        host = as_host_array(array, dtype=dtype)
        self.check_dtype(host.dtype)
        if host.ndim == 0:
            raise ValueError(f"expected an array with at least one dimension, got a scalar of shape {host.shape}")
        if not host.flags.c_contiguous:
            self.check_alloc(host.shape, host.dtype)  # the copy below
        return np.ascontiguousarray(host)

    def empty(self, shape, dtype=np.float32):
        self._check_open()
        shape = tuple(int(s) for s in (shape if isinstance(shape, (tuple, list)) else (shape,)))
        dt = self.check_dtype(dtype)
        self.check_alloc(shape, dt)
        return np.empty(shape, dtype=dt)

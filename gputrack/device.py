"""Backend registry, device discovery and selection, and device-resident arrays.

A *spec* names a backend: ``numpy``, ``taichi:cpu``, ``taichi:vulkan``, ``taichi:cuda``,
``opencl`` (the best OpenCL device) or ``opencl:<substring>`` (the first OpenCL device whose
platform name, device name or listed spec contains the substring, case-insensitively).

``devices()`` probes every backend and returns one :class:`DeviceInfo` per spec;
``device(spec)`` returns the :class:`Device` for a spec (one object per spec and process).
Arrays on a device are :class:`DeviceArray` objects; the ``numpy`` device's arrays are plain
NumPy arrays. Every upload and download goes through the device, which counts the bytes
moved (``Device.transfers``) so that :class:`gputrack.Pipeline` can report them per stage.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import threading
import weakref

import numpy as np

__all__ = [
    "Device",
    "DeviceArray",
    "DeviceInfo",
    "DeviceUnavailable",
    "TaichiArchConflict",
    "Transfers",
    "device",
    "devices",
    "to_numpy",
]

log = logging.getLogger("gputrack")

#: dtypes a DeviceArray may hold (bool arrays are converted by the ops that take masks).
SUPPORTED_DTYPES = tuple(np.dtype(t) for t in ("float32", "float64", "int32", "int64", "uint32", "uint8"))

TAICHI_ARCHS = ("cpu", "vulkan", "cuda")
SPEC_FORMS = "numpy, taichi:cpu, taichi:vulkan, taichi:cuda, opencl, opencl:<platform or device substring>"


class DeviceUnavailable(RuntimeError):
    """The requested backend exists but cannot run on this machine."""


class TaichiArchConflict(RuntimeError):
    """A second, different Taichi arch was requested in a process that already runs one."""


@dataclasses.dataclass(frozen=True)
class DeviceInfo:
    """What the probe found for one spec."""

    spec: str
    backend: str  # "numpy" | "taichi" | "opencl"
    available: bool
    name: str = ""  # hardware/driver name, e.g. "llvmpipe (LLVM 15.0.6, 256 bits)"
    reason: str = ""  # one line, when not available
    fp64: bool = False
    kind: str = "cpu"  # "cpu" | "gpu" | "other": what executes the kernels
    max_work_group_size: int | None = None
    driver: str = ""

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass
class Transfers:
    """Bytes moved between host and device, counted by the device."""

    h2d: int = 0
    d2h: int = 0

    def copy(self) -> "Transfers":
        return Transfers(self.h2d, self.d2h)

    def __sub__(self, other: "Transfers") -> "Transfers":
        return Transfers(self.h2d - other.h2d, self.d2h - other.d2h)


class Device:
    """One backend on one piece of hardware. Obtain it with :func:`gputrack.device`.

    Subclasses implement ``_upload``, ``_upload_into``, ``_download``, ``_empty`` and ``synchronize``.
    """

    backend: str = ""

    def __init__(self, info: DeviceInfo):
        self.info = info
        self.transfers = Transfers()
        self.closed = False

    # -- description -------------------------------------------------------------------------
    @property
    def spec(self) -> str:
        return self.info.spec

    @property
    def name(self) -> str:
        return self.info.name

    @property
    def fp64(self) -> bool:
        return self.info.fp64

    def __repr__(self) -> str:
        return f"<gputrack.Device {self.spec} ({self.name})>"

    # -- arrays ------------------------------------------------------------------------------
    def check_dtype(self, dtype) -> np.dtype:
        """Return ``dtype`` as a NumPy dtype if this device can hold it, else raise TypeError."""
        dt = dtype if isinstance(dtype, np.dtype) else np.dtype(dtype)
        if dt not in SUPPORTED_DTYPES:
            raise TypeError(
                f"expected an array of dtype {', '.join(d.name for d in SUPPORTED_DTYPES)}, got {dt.name}"
                + (" (convert boolean arrays with .astype(np.uint8))" if dt == np.bool_ else "")
            )
        if dt == np.float64 and not self.fp64:
            raise TypeError(f"expected float32 on {self.spec}: the device has no float64 support, got float64")
        return dt

    def asarray(self, array, dtype=None, *, out=None):
        """Upload a NumPy array (or anything ``numpy.asarray`` accepts) to this device.

        Returns a :class:`DeviceArray` (a NumPy array for the ``numpy`` device). A DeviceArray of
        this device is returned as it is; one of another device raises ValueError. ``out``: a
        DeviceArray of this device with the same shape and dtype to upload into (and return)
        instead of allocating, e.g. last frame's image (saves the allocation: ~1 ms for a
        640x480 float32 image on taichi:cpu, mostly the first touch of fresh memory).
        """
        self._check_open()
        if out is not None:
            host = np.ascontiguousarray(np.asarray(array, dtype=dtype))
            if not (isinstance(out, DeviceArray) and out.device is self):
                raise TypeError(f"out: expected a DeviceArray on {self.spec}, got {type(out).__name__}")
            if host.shape != out.shape or host.dtype != out.dtype:
                raise ValueError(
                    f"out: expected {host.dtype.name} {host.shape} (the array's), got {out.dtype.name} {out.shape}"
                )
            self.transfers.h2d += host.nbytes
            self._upload_into(out.buffer, host)
            return out
        if isinstance(array, DeviceArray):
            if array.device is not self:
                raise ValueError(f"expected an array on {self.spec}, got one on {array.device.spec}")
            if dtype is not None and np.dtype(dtype) != array.dtype:
                raise TypeError(f"expected dtype {np.dtype(dtype).name}, got {array.dtype.name}")
            return array
        host = np.asarray(array, dtype=dtype)
        self.check_dtype(host.dtype)
        if host.ndim == 0:
            raise ValueError(f"expected an array with at least one dimension, got a scalar of shape {host.shape}")
        host = np.ascontiguousarray(host)
        self.transfers.h2d += host.nbytes
        return self._wrap(self._upload(host), host.shape, host.dtype)

    def empty(self, shape, dtype=np.float32):
        """Allocate an uninitialised array on the device (no transfer)."""
        self._check_open()
        shape = tuple(int(s) for s in (shape if isinstance(shape, (tuple, list)) else (shape,)))
        dt = self.check_dtype(dtype)
        return DeviceArray._new(self, self._empty(shape, dt), shape, dt)

    def to_numpy(self, array) -> np.ndarray:
        """Download a DeviceArray of this device (a NumPy array is returned as it is)."""
        if isinstance(array, DeviceArray):
            return array.numpy()
        return np.asarray(array)

    def synchronize(self) -> None:
        """Wait until all work queued on the device has finished."""

    def close(self) -> None:
        """Release the device; its arrays become unusable. Needed only to switch Taichi archs."""
        self.closed = True
        _forget(self)
        with _lock:
            caches = [r() for r in _CACHES]
        for cache in caches:
            if cache is not None:
                cache.pop(self, None)

    # -- backend hooks -----------------------------------------------------------------------
    def _wrap(self, buffer, shape, dtype):
        return DeviceArray(self, buffer, shape, dtype)

    def _upload(self, host: np.ndarray):
        raise NotImplementedError

    def _upload_into(self, buffer, host: np.ndarray) -> None:
        raise NotImplementedError

    def _download(self, buffer, shape, dtype) -> np.ndarray:
        raise NotImplementedError

    def _empty(self, shape, dtype):
        raise NotImplementedError

    def _check_open(self):
        if self.closed:
            raise DeviceUnavailable(f"{self.spec} was closed; get a new device with gputrack.device({self.spec!r})")


class DeviceArray:
    """An array that lives on a device. ``.numpy()`` downloads it.

    ``buffer`` is the backend object (a ``taichi.Ndarray`` or a ``pyopencl.array.Array``);
    ops read it directly, users normally do not need it.
    """

    __slots__ = ("device", "buffer", "shape", "dtype")

    def __init__(self, device: Device, buffer, shape, dtype):
        self.device = device
        self.buffer = buffer
        self.shape = tuple(int(s) for s in shape)
        self.dtype = np.dtype(dtype)

    @classmethod
    def _new(cls, device: Device, buffer, shape: tuple, dtype: np.dtype) -> DeviceArray:
        """A DeviceArray from a checked shape (a tuple of ints) and NumPy dtype, without converting them."""
        a = cls.__new__(cls)
        a.device, a.buffer, a.shape, a.dtype = device, buffer, shape, dtype
        return a

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    @property
    def nbytes(self) -> int:
        return self.size * self.dtype.itemsize

    def __len__(self) -> int:
        return self.shape[0]

    def numpy(self) -> np.ndarray:
        """Download to a new NumPy array."""
        self.device._check_open()
        out = self.device._download(self.buffer, self.shape, self.dtype)
        self.device.transfers.d2h += out.nbytes
        return out

    def __array__(self, dtype=None, copy=None):
        raise TypeError(
            "a DeviceArray is not converted implicitly; call .numpy() to download it "
            "(so that every transfer is explicit and counted)"
        )

    def __repr__(self) -> str:
        return f"DeviceArray(shape={self.shape}, dtype={self.dtype.name}, device={self.device.spec})"


def to_numpy(array) -> np.ndarray:
    """Return a NumPy array for a NumPy array or a DeviceArray (downloading the latter)."""
    if isinstance(array, DeviceArray):
        return array.numpy()
    return np.asarray(array)


# -- registry ----------------------------------------------------------------------------------
_lock = threading.RLock()
_devices: dict[str, Device] = {}
_CACHES: list = []  # weak references to the per-device caches (per_device_cache)


def per_device_cache() -> weakref.WeakKeyDictionary:
    """A new {device: value} cache whose entry for a device goes when that device is closed.

    Caches of device arrays (scratch buffers, uploaded constants, template copies) are made with
    this: ``Device.close()`` drops their arrays while the device still runs, so that none outlives
    it (a Taichi array kept past a restart of Taichi corrupts the next program's memory).
    """
    cache = weakref.WeakKeyDictionary()
    with _lock:
        _CACHES[:] = [r for r in _CACHES if r() is not None]
        _CACHES.append(weakref.ref(cache))
    return cache


_probe_cache: list[DeviceInfo] | None = None


def _forget(dev: Device) -> None:
    with _lock:
        for key, value in list(_devices.items()):
            if value is dev:
                del _devices[key]


def devices(refresh: bool = False) -> list[DeviceInfo]:
    """Probe every backend; one DeviceInfo per spec, available or not (with the reason).

    The Taichi archs are probed in a subprocess (Taichi allows one arch per process), the
    OpenCL devices by building and running a trivial kernel. The result is cached per process;
    ``refresh=True`` probes again.
    """
    global _probe_cache
    with _lock:
        if _probe_cache is None or refresh:
            from .backends.opencl.device import probe_opencl
            from .backends.reference.device import probe_numpy
            from .backends.taichi.device import probe_taichi

            _probe_cache = [probe_numpy(), *probe_taichi(), *probe_opencl()]
        return list(_probe_cache)


def _parse(spec: str) -> tuple[str, str]:
    if not isinstance(spec, str):
        raise TypeError(f"expected a device spec string ({SPEC_FORMS}), got {type(spec).__name__}")
    s = spec.strip().lower()
    if s == "numpy":
        return "numpy", ""
    if s.startswith("taichi:") and s[7:] in TAICHI_ARCHS:
        return "taichi", s[7:]
    if s == "opencl":
        return "opencl", ""
    if s.startswith("opencl:") and len(s) > 7:
        return "opencl", spec.strip()[7:]
    raise ValueError(f"unknown device spec {spec!r}; expected one of: {SPEC_FORMS}")


def _preference(info: DeviceInfo) -> int:
    """Rank for the default device: a real GPU first, taichi:cpu last."""
    if info.spec == "taichi:cuda":
        return 0
    if info.spec == "taichi:vulkan" and info.kind == "gpu":
        return 1
    if info.backend == "opencl" and info.kind == "gpu":
        return 2
    if info.spec == "taichi:cpu":
        return 3
    return 9  # CPU OpenCL, software Vulkan and numpy are chosen only by name


def _unavailable(spec: str, reason: str) -> DeviceUnavailable:
    avail = [d.spec for d in devices() if d.available]
    return DeviceUnavailable(f"{spec} is not available: {reason}. Available: {', '.join(avail) or 'none'}")


def device(spec: str | None = None) -> Device:
    """Return the Device for ``spec``.

    With no spec, ``GPUTRACK_DEVICE`` is used if set, else the best available device
    (taichi:cuda, taichi:vulkan on a real GPU, an OpenCL GPU, then taichi:cpu).
    Raises ValueError for an unknown spec and DeviceUnavailable for one that cannot run here.
    """
    if spec is None:
        spec = os.environ.get("GPUTRACK_DEVICE") or None
    with _lock:
        if spec is None:
            ranked = sorted((d for d in devices() if d.available), key=_preference)
            ranked = [d for d in ranked if _preference(d) < 9]
            if not ranked:
                raise _unavailable("a default device", "no GPU backend and no taichi:cpu")
            spec = ranked[0].spec
        backend, arg = _parse(spec)
        key = spec.strip().lower() if backend != "opencl" else spec.strip()
        if key in _devices:
            return _devices[key]
        if backend == "numpy":
            from .backends.reference.device import NumpyDevice

            dev = NumpyDevice()
        elif backend == "taichi":
            from .backends.taichi.device import open_taichi

            dev = open_taichi(arg)
        else:
            from .backends.opencl.device import open_opencl

            dev = open_opencl(arg)
        _devices[key] = dev
        _devices.setdefault(dev.spec, dev)
        log.info("using %s (%s)", dev.spec, dev.name)
        return dev

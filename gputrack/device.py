"""The base every backend builds on: devices, device-resident arrays, errors, transfer counts,
the per-device memo and the per-device buffer pool.

This module imports no backend. The backends (``gputrack/backends/*``) subclass :class:`Device`;
the table of backends, ``device(spec)`` and ``devices()`` live in :mod:`gputrack.registry`
(``gputrack.device(...)`` and ``gputrack.devices()`` are re-exported from there).

Arrays on a device are :class:`DeviceArray` objects; the ``numpy`` device's arrays are plain
NumPy arrays. Every upload and download goes through the device, which counts the bytes
moved (``Device.transfers``) so that :class:`gputrack.Profiler` (and the Scheduler) can report them per stage.

Every allocation and upload is first checked against what the device can hold
(:meth:`Device.check_alloc`: dimensions, elements, bytes), so that an array too large for it is a
``MemoryError`` naming the shape and the bytes instead of a backend's crash or raw error. A closed
device, and an array of one given to any device, raise :class:`DeviceUnavailable`.

Everything a backend builds per device (compiled programs, kernel objects, scratch buffers,
uploaded constants) is memoised with :func:`per_device`: entries live on the device and go when
it is closed. Fresh output arrays come from the device's caching allocator (gputrack/pool.py:
freed buffers of the same size and dtype are reused; see ``Device.pool_stats``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import threading
import weakref

import numpy as np

from .pool import PoolStats, check_limit, limit_from_env

__all__ = [
    "Device",
    "DeviceArray",
    "DeviceInfo",
    "DeviceUnavailable",
    "PoolStats",
    "TaichiArchConflict",
    "Transfers",
    "per_device",
    "per_device_cache",
    "to_numpy",
    "unavailable",
]

#: dtypes a DeviceArray may hold (bool arrays are converted by the ops that take masks).
SUPPORTED_DTYPES = tuple(np.dtype(t) for t in ("float32", "float64", "int32", "int64", "uint32", "uint8"))


class DeviceUnavailable(RuntimeError):
    """The requested backend exists but cannot run on this machine."""


@functools.lru_cache(maxsize=1)
def host_memory_bytes() -> int | None:
    """The machine's physical memory in bytes (None where the system does not say)."""
    try:
        n = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return None
    return n if n > 0 else None


def _bytes(n: int) -> str:
    """``n`` bytes in words: "549755813888 bytes (512 GiB)"."""
    for unit, shift in (("TiB", 40), ("GiB", 30), ("MiB", 20), ("KiB", 10)):
        if n >= 1 << shift:
            return f"{n} bytes ({n / (1 << shift):.4g} {unit})"
    return f"{n} bytes"


def _shape(shape) -> tuple:
    return tuple(int(s) for s in shape)


def as_host_array(value, name: str = "", dtype=None) -> np.ndarray:
    """``numpy.asarray(value, dtype)``, with a clear error for a ragged nested sequence (NumPy's
    own message speaks of an "inhomogeneous shape")."""
    try:
        return np.asarray(value, dtype=dtype)
    except ValueError as e:
        if "inhomogeneous" not in str(e) and "sequence" not in str(e):
            raise
        lengths = ""
        if isinstance(value, (list, tuple)):
            lengths = f" (lengths {[len(v) if hasattr(v, '__len__') else 'scalar' for v in value[:8]]})"
        prefix = f"{name}: " if name else ""
        raise ValueError(
            f"{prefix}expected a rectangular array (nested sequences of equal lengths), got a ragged "
            f"{type(value).__name__}{lengths}"
        ) from None


def foreign_array_error(array, device, name: str = "") -> Exception:
    """The error for ``array`` (a DeviceArray) given to ``device``, which does not hold it:
    DeviceUnavailable when the array's device was closed (its memory is gone), else ValueError."""
    prefix = f"{name}: " if name else ""
    if array.device.closed:
        return DeviceUnavailable(
            f"{prefix}expected an array on {device.spec}, got an array of a closed {array.device.spec} device "
            "(its memory was released by close(); upload the data to the new device)"
        )
    return ValueError(
        f"{prefix}expected an array on {device.spec} or a NumPy array, got an array on {array.device.spec}"
    )


def unavailable(spec: str, reason: str) -> DeviceUnavailable:
    """The error a backend raises when ``spec`` cannot run here: "<spec> is not available: <reason>"
    (:func:`gputrack.registry.device` adds the specs that are available)."""
    return DeviceUnavailable(f"{spec} is not available: {reason}")


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

    Subclasses implement ``_upload``, ``_upload_into``, ``_download``, ``_empty`` and ``synchronize``,
    and, where they keep freed buffers for reuse (the caching allocator, :mod:`gputrack.pool`),
    ``pool_stats``, ``_set_pool_limit`` and ``empty_pool``.
    """

    backend: str = ""
    closed: bool = False  # set by close()
    #: most dimensions an array of this device may have (None: no limit)
    max_ndim: int | None = None
    #: most elements one array may have (None: no limit), and why
    max_elements: int | None = None
    max_elements_reason: str = ""

    def __init__(self, info: DeviceInfo):
        self.info = info
        self.transfers = Transfers()
        self.closed = False
        self._memo: dict = {}  # per_device: {function: {args: value}}
        self._pool_limit = limit_from_env()

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

    def max_array_bytes(self) -> tuple[int | None, str]:
        """The largest array this device can hold, in bytes (None: unknown), and what sets it.
        Default: the machine's memory (backends whose arrays live elsewhere override it)."""
        return host_memory_bytes(), "the machine's memory"

    def check_alloc(self, shape, dtype) -> None:
        """Check that an array of ``shape`` and ``dtype`` fits this device before it is allocated:
        ValueError past ``max_ndim`` dimensions, MemoryError past ``max_elements`` elements or
        past :meth:`max_array_bytes` (naming the shape and the bytes). Every allocation and upload
        goes through it, so an output too large for the device is an error, not a crash."""
        dt = dtype if isinstance(dtype, np.dtype) else np.dtype(dtype)
        n = math.prod(map(int, shape))  # Python ints: a product of NumPy integers could wrap around
        if self.max_ndim is not None and len(shape) > self.max_ndim:
            raise ValueError(
                f"expected an array of at most {self.max_ndim} dimensions on {self.spec}, got {len(shape)}: "
                f"{dt.name} {_shape(shape)}"
            )
        nbytes = n * dt.itemsize
        if self.max_elements is not None and n > self.max_elements:
            raise MemoryError(
                f"expected an array of at most {self.max_elements} elements on {self.spec} "
                f"({self.max_elements_reason}), got {dt.name} {_shape(shape)}: {n} elements, {_bytes(nbytes)}"
            )
        limit, what = self.max_array_bytes()
        if limit is not None and nbytes > limit:
            raise MemoryError(
                f"expected an array of at most {_bytes(limit)} on {self.spec} ({what}), got {dt.name} "
                f"{_shape(shape)}: {_bytes(nbytes)}"
            )

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
            host = np.ascontiguousarray(as_host_array(array, dtype=dtype))
            if isinstance(out, DeviceArray) and out.device is not self and out.device.closed:
                raise foreign_array_error(out, self, "out")
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
                raise foreign_array_error(array, self)
            if dtype is not None and np.dtype(dtype) != array.dtype:
                raise TypeError(f"expected dtype {np.dtype(dtype).name}, got {array.dtype.name}")
            return array
        host = as_host_array(array, dtype=dtype)
        self.check_dtype(host.dtype)
        if host.ndim == 0:
            raise ValueError(f"expected an array with at least one dimension, got a scalar of shape {host.shape}")
        self.check_alloc(host.shape, host.dtype)
        host = np.ascontiguousarray(host)
        self.transfers.h2d += host.nbytes
        return self._wrap(self._upload(host), host.shape, host.dtype)

    def empty(self, shape, dtype=np.float32):
        """Allocate an uninitialised array on the device (no transfer)."""
        self._check_open()
        shape = tuple(int(s) for s in (shape if isinstance(shape, (tuple, list)) else (shape,)))
        dt = self.check_dtype(dtype)
        self.check_alloc(shape, dt)
        return DeviceArray._new(self, self._empty(shape, dt), shape, dt)

    def to_numpy(self, array) -> np.ndarray:
        """Download a DeviceArray of this device (a NumPy array is returned as it is)."""
        if isinstance(array, DeviceArray):
            return array.numpy()
        return np.asarray(array)

    def synchronize(self) -> None:
        """Wait until all work queued on the device has finished."""

    def close(self) -> None:
        """Release the device; its arrays become unusable. Needed only to switch Taichi archs.

        Everything memoised for it (:func:`per_device`, :func:`per_device_cache`) and every
        buffer its caching allocator holds is released while the device still runs."""
        self.closed = True
        self._memo.clear()
        with _lock:
            caches = [r() for r in _CACHES]
        for cache in caches:
            if cache is not None:
                cache.pop(self, None)
        self.empty_pool()

    # -- caching allocator (gputrack/pool.py) --------------------------------------------------
    @property
    def pool_limit(self) -> int:
        """Bytes of freed buffers this device keeps for reuse (``$GPUTRACK_POOL_BYTES``, default
        256 MiB; 0: none). Setting it releases held buffers past the new limit."""
        return self._pool_limit

    @pool_limit.setter
    def pool_limit(self, value: int) -> None:
        self._pool_limit = check_limit(value)
        self._set_pool_limit(self._pool_limit)

    def pool_stats(self) -> PoolStats:
        """What the caching allocator holds (freed buffers kept for reuse) and how often it reused one."""
        return PoolStats(0, 0, self._pool_limit, 0, 0)

    def empty_pool(self) -> None:
        """Release every freed buffer the caching allocator holds (arrays in use are not affected)."""

    def _set_pool_limit(self, limit: int) -> None:
        pass

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



# -- things built per device -------------------------------------------------------------------
# One idiom for everything built per device (compiled programs, kernel objects, scratch buffers,
# uploaded constants): a function of the device memoised on the device itself, as PyOpenCL's
# ``first_arg_dependent_memoize`` memoises on the context. The values live in ``device._memo``,
# which ``Device.close()`` empties while the device still runs, so nothing built for a device
# outlives it (a Taichi array kept past a restart of Taichi corrupts the next program's memory).


def per_device(func=None, *, maxsize: int | None = None):
    """Memoise ``func(device, *args)`` per device (``args`` hashable, positional only).

    ``maxsize``: at most this many values per device, the oldest dropped first (for values keyed
    by sizes that change, e.g. scratch buffers of an op called with several batch sizes). The
    values of a device go when it is closed. ``func.cache_clear(device)`` drops them earlier.

    Use it for anything a backend or an op builds once per device::

        @per_device
        def _kernel(device, name, defines):
            return cl.Kernel(device.program("gt_template.cl", dict(defines)), name)
    """

    def decorate(f):
        @functools.wraps(f)
        def wrapper(device, *args):
            try:
                return device._memo[wrapper][args]
            except KeyError:
                pass
            value = f(device, *args)
            memo = device._memo.setdefault(wrapper, {})
            if maxsize is not None and len(memo) >= maxsize:
                del memo[next(iter(memo))]
            memo[args] = value
            return value

        wrapper.cache_clear = lambda device: device._memo.pop(wrapper, None)
        return wrapper

    return decorate(func) if func is not None else decorate


_lock = threading.RLock()
_CACHES: list = []  # weak references to the per-device caches (per_device_cache)


def per_device_cache() -> weakref.WeakKeyDictionary:
    """A new {device: value} table whose entry for a device goes when that device is closed.

    For state an object keeps per device (a template's copies on each device, a solver's buffer
    pool); a value computed from the device and hashable arguments is memoised with
    :func:`per_device` instead.
    """
    cache = weakref.WeakKeyDictionary()
    with _lock:
        _CACHES[:] = [r for r in _CACHES if r() is not None]
        _CACHES.append(weakref.ref(cache))
    return cache

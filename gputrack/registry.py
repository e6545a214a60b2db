"""The table of backends, and device discovery and selection that read it.

A *spec* names a device: ``numpy``, ``taichi:cpu``, ``taichi:vulkan``, ``taichi:cuda``,
``opencl`` (the best OpenCL device) or ``opencl:<substring>`` (the first OpenCL device whose
platform name, device name or listed spec contains the substring, case-insensitively).

:data:`BACKENDS` holds one :class:`Backend` row per backend: the spec forms it answers, how a
spec is parsed, the functions that probe and open it, the package that implements the ops, and
its rank for the default device. :func:`devices`, :func:`device`, :func:`gputrack.ops.backend_module`
and the tests' ``device`` fixture all read it, so a backend is added with one row (and its
package). Probe and open functions are named as ``"module:function"`` and imported only when
called: importing gputrack starts no backend.
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
import os
import threading
from collections.abc import Callable

from .device import Device, DeviceInfo, DeviceUnavailable

__all__ = [
    "BACKENDS",
    "Backend",
    "backend_for",
    "device",
    "devices",
    "implementation",
    "parse_spec",
    "register",
    "spec_forms",
    "specs",
    "unregister",
]

log = logging.getLogger("gputrack")


@dataclasses.dataclass(frozen=True)
class Backend:
    """One row of the backend table.

    name: ``Device.backend`` of its devices. forms: the spec forms, for messages.
    specs: the fixed specs it lists (each parametrises the tests' ``device`` fixture).
    parse(spec): for a stripped spec, the argument its ``open`` takes, or None if the spec is not
    this backend's. probe: ``"module:function"`` (or a callable) returning a DeviceInfo or a list of
    them (one per spec, available or not, with the reason). open: ``"module:function"`` (or a
    callable) taking parse's argument and returning a Device, or raising DeviceUnavailable (see
    :func:`gputrack.device.unavailable`).
    package: the package holding one module per primitive (``<package>.kalman`` etc.).
    preference(info): rank of an available device for the default device (lower first), or None
    for a device that is chosen only by name.
    """

    name: str
    forms: tuple[str, ...]
    specs: tuple[str, ...]
    parse: Callable[[str], str | None]
    probe: str | Callable
    open: str | Callable
    package: str
    preference: Callable[[DeviceInfo], int | None]


def _resolve(target) -> Callable:
    if callable(target):
        return target
    module, func = target.split(":")
    return getattr(importlib.import_module(module), func)


def _parse_numpy(spec: str) -> str | None:
    return "" if spec.lower() == "numpy" else None


_TAICHI_ARCHS = ("cpu", "vulkan", "cuda")


def _parse_taichi(spec: str) -> str | None:
    s = spec.lower()
    return s[7:] if s.startswith("taichi:") and s[7:] in _TAICHI_ARCHS else None


def _parse_opencl(spec: str) -> str | None:
    s = spec.lower()
    if s == "opencl":
        return ""
    return spec[7:] if s.startswith("opencl:") and len(s) > 7 else None


def _prefer_taichi(info: DeviceInfo) -> int | None:
    if info.spec == "taichi:cuda":
        return 0
    if info.spec == "taichi:vulkan" and info.kind == "gpu":
        return 1
    if info.spec == "taichi:cpu":
        return 3
    return None  # Vulkan on a software rasteriser (lavapipe) only by name


def _prefer_opencl(info: DeviceInfo) -> int | None:
    return 2 if info.kind == "gpu" else None  # a CPU OpenCL device only by name


#: the backends, in the order ``devices()`` lists them. Default device: taichi:cuda, taichi:vulkan
#: on a real GPU, an OpenCL GPU, then taichi:cpu; numpy, CPU OpenCL and software Vulkan by name.
BACKENDS: list[Backend] = [
    Backend(
        name="numpy",
        forms=("numpy",),
        specs=("numpy",),
        parse=_parse_numpy,
        probe="gputrack.backends.reference.device:probe_numpy",
        open="gputrack.backends.reference.device:open_numpy",
        package="gputrack.backends.reference",
        preference=lambda info: None,
    ),
    Backend(
        name="taichi",
        forms=tuple(f"taichi:{a}" for a in _TAICHI_ARCHS),
        specs=tuple(f"taichi:{a}" for a in _TAICHI_ARCHS),
        parse=_parse_taichi,
        probe="gputrack.backends.taichi.device:probe_taichi",
        open="gputrack.backends.taichi.device:open_taichi",
        package="gputrack.backends.taichi",
        preference=_prefer_taichi,
    ),
    Backend(
        name="opencl",
        forms=("opencl", "opencl:<platform or device substring>"),
        specs=("opencl",),
        parse=_parse_opencl,
        probe="gputrack.backends.opencl.device:probe_opencl",
        open="gputrack.backends.opencl.device:open_opencl",
        package="gputrack.backends.opencl",
        preference=_prefer_opencl,
    ),
]

_lock = threading.RLock()
_modules: dict = {}  # (backend name, primitive) -> implementing module
_devices: dict[str, Device] = {}  # spec as asked, and the device's own spec -> open device
_probed: dict[str, list[DeviceInfo]] = {}  # backend name -> what its probe found


def spec_forms() -> str:
    """Every spec form of every backend, for messages."""
    return ", ".join(f for b in BACKENDS for f in b.forms)


def specs() -> list[str]:
    """The fixed specs of every backend (the tests' ``device`` fixture runs on each)."""
    return [s for b in BACKENDS for s in b.specs]


def backend_for(name: str) -> Backend:
    """The row of the backend called ``name`` (``Device.backend``)."""
    for b in BACKENDS:
        if b.name == name:
            return b
    raise ValueError(f"unknown backend {name!r}; expected one of: {', '.join(b.name for b in BACKENDS)}")


def implementation(name: str, primitive: str):
    """The module ``<package>.<primitive>`` of backend ``name``'s row (imported once)."""
    found = _modules.get((name, primitive))
    if found is None:
        found = _modules[(name, primitive)] = importlib.import_module(f"{backend_for(name).package}.{primitive}")
    return found


def register(backend: Backend) -> None:
    """Add a backend row (replacing one of the same name); the next ``devices()`` probes it."""
    if not isinstance(backend, Backend):
        raise TypeError(f"expected a gputrack.registry.Backend, got {type(backend).__name__}")
    with _lock:
        BACKENDS[:] = [b for b in BACKENDS if b.name != backend.name] + [backend]
        _modules.clear()
        _probed.pop(backend.name, None)


def unregister(name: str) -> None:
    """Remove the row of backend ``name`` and forget its open devices (they are not closed)."""
    with _lock:
        BACKENDS[:] = [b for b in BACKENDS if b.name != name]
        _modules.clear()
        for key in [k for k, d in _devices.items() if d.backend == name]:
            del _devices[key]
        _probed.pop(name, None)


def devices(refresh: bool = False) -> list[DeviceInfo]:
    """Probe every backend; one DeviceInfo per spec, available or not (with the reason).

    The Taichi archs are probed in a subprocess (Taichi allows one arch per process), the
    OpenCL devices by building and running a trivial kernel. The result is cached per process and
    backend; ``refresh=True`` probes again.
    """
    with _lock:
        found = []
        for b in BACKENDS:
            if refresh or b.name not in _probed:
                infos = _resolve(b.probe)()
                _probed[b.name] = [infos] if isinstance(infos, DeviceInfo) else list(infos)
            found += _probed[b.name]
        return found


def _parse(spec) -> tuple[Backend, str, str]:
    """(row, argument of its open, key of the device) for a spec, else TypeError/ValueError."""
    if not isinstance(spec, str):
        raise TypeError(f"expected a device spec string ({spec_forms()}), got {type(spec).__name__}")
    s = spec.strip()
    for b in BACKENDS:
        arg = b.parse(s)
        if arg is not None:
            return b, arg, s.lower()  # OpenCL selectors match case-insensitively
    raise ValueError(f"unknown device spec {spec!r}; expected one of: {spec_forms()}")


def parse_spec(spec: str) -> str:
    """``spec`` if it is of a known form (see :func:`spec_forms`), else TypeError/ValueError;
    nothing is probed or opened."""
    _parse(spec)
    return spec


def _available() -> str:
    return ", ".join(d.spec for d in devices() if d.available) or "none"


def _default_spec() -> str:
    ranked = []
    for info in devices():
        if info.available:
            rank = next((b.preference(info) for b in BACKENDS if b.name == info.backend), None)
            if rank is not None:
                ranked.append((rank, info.spec))
    if not ranked:
        raise DeviceUnavailable(
            f"a default device is not available: no GPU backend and no taichi:cpu. Available: {_available()}"
        )
    return min(ranked)[1]


def device(spec: str | None = None) -> Device:
    """Return the Device for ``spec`` (one open device per spec and process).

    With no spec, ``GPUTRACK_DEVICE`` is used if set, else the best available device
    (taichi:cuda, taichi:vulkan on a real GPU, an OpenCL GPU, then taichi:cpu).
    Raises ValueError for an unknown spec and DeviceUnavailable for one that cannot run here.
    """
    if spec is None:
        spec = os.environ.get("GPUTRACK_DEVICE") or None
    with _lock:
        if spec is None:
            spec = _default_spec()
        backend, arg, key = _parse(spec)
        found = _devices.get(key)
        if found is not None and not found.closed:
            return found
        try:
            dev = _resolve(backend.open)(arg)
        except DeviceUnavailable as e:
            raise DeviceUnavailable(f"{e}. Available: {_available()}") from None
        _devices[key] = dev
        if _devices.get(dev.spec) is None or _devices[dev.spec].closed:
            _devices[dev.spec] = dev
        log.info("using %s (%s)", dev.spec, dev.name)
        return dev

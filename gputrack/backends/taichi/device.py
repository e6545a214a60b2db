"""Taichi devices (taichi:cpu, taichi:vulkan, taichi:cuda): probing and arrays."""

from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys

import numpy as np

from ...device import Device, DeviceInfo, TaichiArchConflict, host_memory_bytes, unavailable
from ..reference.device import cpu_name

PROBE_TIMEOUT_S = 120


def _hardware(arch: str) -> tuple[str, str]:
    """(name, kind) of what runs ``arch``."""
    if arch == "cpu":
        return cpu_name(), "cpu"
    if arch == "vulkan":
        from .vulkan_info import vulkan_devices

        found = vulkan_devices()
        return (found[0]["name"], found[0]["kind"]) if found else ("no Vulkan device", "other")
    try:
        out = subprocess.run(
            ["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True, timeout=20
        )
        return out.stdout.strip().splitlines()[0], "gpu"
    except Exception:  # noqa: BLE001 - the name is informative only
        return "NVIDIA GPU", "gpu"


def _memory(arch: str) -> tuple[int | None, str]:
    """The largest array ``arch`` can hold, in bytes (None: unknown), and what sets it."""
    if arch == "cpu":
        return host_memory_bytes(), "the machine's memory"
    if arch == "vulkan":
        from .vulkan_info import vulkan_devices

        found = vulkan_devices()
        heap = found[0]["heap"] if found else 0
        return (heap or None), "the Vulkan device's largest device-local memory heap"
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=memory.total", "--format=csv,noheader,nounits"], check=False,
                             capture_output=True, text=True, timeout=20)  # fmt: skip
        return int(out.stdout.split()[0]) << 20, "the GPU's memory"  # MiB
    except Exception:  # noqa: BLE001 - unknown: Taichi's own allocation error then
        return None, "the GPU's memory"


def _info(arch: str, found: dict) -> DeviceInfo:
    spec = f"taichi:{arch}"
    if not found.get("available"):
        return DeviceInfo(spec, "taichi", False, reason=found.get("reason", "unknown"), kind="other")
    name, kind = _hardware(arch)
    return DeviceInfo(spec, "taichi", True, name=name, fp64=bool(found.get("fp64")), kind=kind)


def probe_taichi() -> list[DeviceInfo]:
    """Probe taichi:cpu, taichi:vulkan and taichi:cuda in a subprocess (Taichi is per-process)."""
    if importlib.util.find_spec("taichi") is None:
        return [DeviceInfo(f"taichi:{a}", "taichi", False, reason="taichi is not installed") for a in ("cpu", "vulkan", "cuda")]
    cmd = [sys.executable, "-m", "gputrack.backends.taichi.probe"]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=PROBE_TIMEOUT_S)
        line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("GPUTRACK_PROBE "))
        found = json.loads(line.split(" ", 1)[1])
    except Exception as e:  # noqa: BLE001 - reported as the reason
        tail = ""
        if "proc" in locals():
            tail = (proc.stderr.strip().splitlines() or [""])[-1]
        reason = f"the Taichi probe failed: {type(e).__name__} {tail}".strip()
        return [DeviceInfo(f"taichi:{a}", "taichi", False, reason=reason) for a in ("cpu", "vulkan", "cuda")]
    return [_info(a, found.get(a, {"reason": "not probed"})) for a in ("cpu", "vulkan", "cuda")]


def open_taichi(arch: str) -> "TaichiDevice":
    """Start Taichi on ``arch`` in this process and return its device."""
    try:
        from . import runtime
    except ImportError as e:
        raise unavailable(f"taichi:{arch}", f"taichi is not installed ({e})") from None
    from .probe import _axpy32, _axpy64, _check

    try:
        runtime.start(arch)
    except TaichiArchConflict:
        raise
    except Exception as e:  # noqa: BLE001 - becomes the reason
        raise unavailable(f"taichi:{arch}", " ".join(str(e).split())[:300]) from None
    try:
        if not _check(_axpy32, np.float32):
            raise unavailable(f"taichi:{arch}", "a float32 test kernel gave wrong results")
        try:
            fp64 = _check(_axpy64, np.float64)
        except Exception:  # noqa: BLE001 - no fp64
            fp64 = False
    except BaseException:
        runtime.stop()
        raise
    name, kind = _hardware(arch)
    return TaichiDevice(arch, DeviceInfo(f"taichi:{arch}", "taichi", True, name=name, fp64=fp64, kind=kind))


def _copy(src, dst) -> bool:
    """dst[...] = src[...] in one kernel (gputrack/backends/taichi/arrays.py); False if ndim > 4."""
    from .arrays import copy

    return copy(src, dst)


class TaichiDevice(Device):
    """Arrays are ``taichi.Ndarray`` objects; kernels live in this package's modules.

    Array sizes (checked before allocating, :meth:`Device.check_alloc`): at most Taichi's
    ``max_num_indices`` (12) dimensions and 2**31 - 1 elements (Taichi sizes and indexes arrays with
    32-bit integers), and at most the memory of the arch (the machine's memory on the CPU, the
    largest device-local heap on Vulkan, the GPU's memory on CUDA).
    """

    backend = "taichi"
    max_elements = 2**31 - 1
    max_elements_reason = "Taichi sizes and indexes arrays with 32-bit integers"

    def __init__(self, arch: str, info: DeviceInfo):
        from taichi._lib import core

        from . import runtime

        super().__init__(info)
        self.arch = arch
        self.max_ndim = int(core.get_max_num_indices())
        self._memory = _memory(arch)
        runtime.set_pool_limit(self.pool_limit)

    def max_array_bytes(self) -> tuple[int | None, str]:
        return self._memory

    def _upload(self, host: np.ndarray):
        from .runtime import DTYPES, ndarray

        if host.size == 0:
            return None  # Taichi cannot allocate empty ndarrays; ops reject empty inputs anyway
        arr = ndarray(DTYPES[host.dtype.name], host.shape)
        self._upload_into(arr, host)
        return arr

    def _upload_into(self, buffer, host: np.ndarray) -> None:
        if buffer is not None and not (self.arch == "cpu" and _copy(host, buffer)):  # CPU: NumPy read in place
            buffer.from_numpy(host)

    def _empty(self, shape, dtype):
        from .runtime import ndarray, taichi_dtype

        if math.prod(shape) == 0:
            return None
        return ndarray(taichi_dtype(dtype), shape)

    def _download(self, buffer, shape, dtype) -> np.ndarray:
        if buffer is None:
            return np.empty(shape, dtype)
        if self.arch == "cpu":
            out = np.empty(shape, dtype)
            if _copy(buffer, out):  # writes the NumPy memory in place
                return out
        return np.ascontiguousarray(buffer.to_numpy(), dtype=dtype).reshape(shape)

    def synchronize(self) -> None:
        from .runtime import ti

        self._check_open()  # Taichi was reset: ti.sync() would fail inside Taichi
        ti.sync()

    def pool_stats(self):
        from . import runtime

        return runtime.pool.stats()

    def empty_pool(self) -> None:
        from . import runtime

        runtime.empty_pool()

    def _set_pool_limit(self, limit: int) -> None:
        from . import runtime

        runtime.set_pool_limit(limit)

    def close(self) -> None:
        from . import runtime

        super().close()
        runtime.stop()

"""Probe every Taichi arch; run as ``python -m gputrack.backends.taichi.probe`` (one JSON line).

Run in a subprocess so that probing never touches the calling process's Taichi state.
For each arch it starts Taichi, runs a float32 and a float64 kernel and checks the results.
"""


import json
import sys

import numpy as np

from . import runtime
from .runtime import ti


@ti.kernel
def _axpy32(a: ti.f32, x: ti.types.ndarray(dtype=ti.f32, ndim=1), y: ti.types.ndarray(dtype=ti.f32, ndim=1)):
    for i in x:
        y[i] = a * x[i] + y[i]


@ti.kernel
def _axpy64(a: ti.f64, x: ti.types.ndarray(dtype=ti.f64, ndim=1), y: ti.types.ndarray(dtype=ti.f64, ndim=1)):
    for i in x:
        y[i] = a * x[i] + y[i]


def _check(kernel, dtype) -> bool:
    x = np.arange(1, 9, dtype=dtype) / 3
    y = np.full(8, 0.25, dtype=dtype)
    tx, ty = ti.ndarray(runtime.DTYPES[np.dtype(dtype).name], 8), ti.ndarray(runtime.DTYPES[np.dtype(dtype).name], 8)
    tx.from_numpy(x)
    ty.from_numpy(y)
    kernel(2.0, tx, ty)
    return bool(np.allclose(ty.to_numpy(), 2 * x + y, rtol=1e-6 if dtype == np.float32 else 1e-14))


def probe_arch(arch: str) -> dict:
    if arch == "cuda" and not ti._lib.core.with_cuda():
        return {"available": False, "reason": "no CUDA driver found (libcuda.so not loadable or no NVIDIA GPU)"}
    if arch == "vulkan" and not ti._lib.core.with_vulkan():
        return {"available": False, "reason": "no Vulkan loader (libvulkan.so.1 not loadable) or no Vulkan in this Taichi build"}
    try:
        runtime.start(arch)
    except Exception as e:  # noqa: BLE001 - the reason is reported, not hidden
        return {"available": False, "reason": " ".join(str(e).split())[:300] or type(e).__name__}
    try:
        if not _check(_axpy32, np.float32):
            return {"available": False, "reason": "a float32 test kernel gave wrong results"}
        try:
            fp64 = _check(_axpy64, np.float64)
        except Exception:  # noqa: BLE001 - no fp64 on this device
            fp64 = False
        return {"available": True, "fp64": fp64}
    except Exception as e:  # noqa: BLE001
        return {"available": False, "reason": f"test kernel failed: {' '.join(str(e).split())[:300]}"}
    finally:
        runtime.stop()


def main(argv: list[str]) -> int:
    archs = argv or list(runtime.ARCHS)
    result = {arch: probe_arch(arch) for arch in archs}
    sys.stdout.write("GPUTRACK_PROBE " + json.dumps(result) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

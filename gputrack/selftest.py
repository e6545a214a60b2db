"""Tiny numerical self-tests, one per primitive, run on a device against the NumPy reference.

Used by ``host/doctor.py``. Each check is ``(name, "module:function")``; the function takes a
Device and raises (AssertionError with the error found, or any exception) when the device
disagrees with the reference. A primitive's check is listed here when the primitive lands.
"""

from __future__ import annotations

import importlib
import time

import numpy as np

from .device import Device

CHECKS = [
    ("arrays", "gputrack.selftest:check_arrays"),
    ("kinematics", "gputrack.ops.kinematics:_selftest"),
    ("template", "gputrack.ops.template:_selftest"),
    ("lm", "gputrack.ops.lm:_selftest"),
    ("kalman", "gputrack.ops.kalman:_selftest"),
]


def check_arrays(device: Device) -> None:
    """Upload, run y = a x + y with the backend's own kernel, download, compare with NumPy."""
    x = np.linspace(-3, 3, 1000, dtype=np.float32)
    y = np.cos(x).astype(np.float32)
    want = 2.5 * x + y
    if device.backend == "numpy":
        got = 2.5 * device.asarray(x) + device.asarray(y)
    elif device.backend == "taichi":
        from .backends.taichi.probe import _axpy32

        dy = device.asarray(y)
        _axpy32(2.5, device.asarray(x).buffer, dy.buffer)
        got = dy.numpy()
    else:
        dx, dy = device.asarray(x), device.asarray(y)
        prg = device.program("gt_selftest.cl")
        prg.gt_axpy(device.queue, (x.size,), None, np.float32(2.5), dx.buffer.data, dy.buffer.data, np.int32(x.size))
        got = dy.numpy()
    err = float(np.max(np.abs(got - want)))
    assert err <= 1e-5, f"axpy differs from NumPy by {err:g}"


def run(device: Device) -> list[dict]:
    """Run every check on ``device``: [{"check", "ok", "detail", "ms"}]."""
    rows = []
    for name, target in CHECKS:
        module, func = target.split(":")
        t0 = time.perf_counter()
        try:
            getattr(importlib.import_module(module), func)(device)
            ok, detail = True, ""
        except Exception as e:  # noqa: BLE001 - reported per check
            ok, detail = False, f"{type(e).__name__}: {' '.join(str(e).split())[:300]}"
        rows.append({"check": name, "ok": ok, "detail": detail, "ms": (time.perf_counter() - t0) * 1e3})
    return rows

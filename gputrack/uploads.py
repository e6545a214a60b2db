"""Small host constants kept on a device: uploaded once per device and value, then reused.

Ops and backends both use it (sampling sigmas, re-use tables, plans), so it sits below them: it
imports only :mod:`gputrack.device`.
"""

from __future__ import annotations

import weakref

import numpy as np

from .device import per_device_cache

__all__ = ["constant"]

#: small host constants (sampling sigmas, re-use tables) uploaded once per device and value
_CONSTANTS: weakref.WeakKeyDictionary = per_device_cache()
_MAX_CONSTANTS = 256


def constant(device, host: np.ndarray):
    """``host`` on ``device``, uploaded the first time this value is seen there, then cached (at
    most 256 values per device). The caller must not modify the returned array."""
    if device.backend == "numpy":
        return host
    per_device = _CONSTANTS.setdefault(device, {})
    key = (host.dtype.str, host.shape, host.tobytes())
    found = per_device.get(key)
    if found is None:
        if len(per_device) >= _MAX_CONSTANTS:
            per_device.clear()
        found = per_device[key] = device.asarray(host)
    return found

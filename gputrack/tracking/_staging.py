"""Per-frame host inputs uploaded into the same device arrays frame after frame.

A fresh device array costs an allocation (~0.1-0.2 ms for a small Taichi or OpenCL array on a
2-core CPU); :class:`Staging` keeps one array per name and uploads into it while the shape and
dtype stay the same (``Device.asarray(out=)``). Inputs whose number of rows changes every frame
(detections, new tracks) go through :meth:`Staging.put_rows`: a buffer of a power-of-two number
of rows, padded, with the count of rows that hold data (the ops take it as ``n_z`` /
``n_rows``). On the ``numpy`` device the host array itself is used.
"""

from __future__ import annotations

import numpy as np


class Staging:
    """Upload buffers of one device, by name."""

    def __init__(self, device):
        self.device = device
        self._arrays: dict = {}

    def put(self, name: str, host: np.ndarray):
        """``host`` on the device, in last call's array of this name when it fits."""
        host = np.ascontiguousarray(host)
        if self.device.backend == "numpy":
            return host
        prev = self._arrays.get(name)
        if prev is not None and prev.shape == host.shape and prev.dtype == host.dtype:
            return self.device.asarray(host, out=prev)
        found = self._arrays[name] = self.device.asarray(host)
        return found

    def put_rows(self, name: str, host: np.ndarray):
        """(device array of >= len(host) rows whose first rows are ``host``, len(host)); the
        buffer has a power-of-two number of rows (at least 16), made anew when it is too small
        or more than four times larger than needed (the whole buffer is uploaded every call)."""
        k = len(host)
        if self.device.backend == "numpy":
            return np.ascontiguousarray(host), k
        prev = self._arrays.get(name)
        same = prev is not None and prev.shape[1:] == host.shape[1:] and prev.dtype == host.dtype
        rows = prev.shape[0] if same else 0
        if not same or rows < k or rows > 4 * max(k, 16):  # (a first call with k = 0 too)
            rows = max(16, 1 << (max(k, 1) - 1).bit_length())
            prev = None
        padded = np.zeros((rows, *host.shape[1:]), host.dtype)
        padded[:k] = host
        if prev is None:
            found = self._arrays[name] = self.device.asarray(padded)
            return found, k
        return self.device.asarray(padded, out=prev), k

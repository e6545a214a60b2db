"""Device primitives: one public function per op, implemented once per backend.

Each op takes a ``device`` first and accepts NumPy arrays or DeviceArrays of that device; it
returns DeviceArrays on that device (NumPy arrays for the ``numpy`` device).
"""

import importlib

from ..device import Device


def backend_module(device: Device, primitive: str):
    """The module ``gputrack.backends.<backend>.<primitive>`` that implements ``primitive``."""
    backend = "reference" if device.backend == "numpy" else device.backend
    return importlib.import_module(f"gputrack.backends.{backend}.{primitive}")

"""Device primitives: one public function per op, implemented once per backend.

Each op takes a ``device`` first and accepts NumPy arrays or DeviceArrays of that device; it
returns DeviceArrays on that device (NumPy arrays for the ``numpy`` device). The modules:

- :mod:`.template`   per-hypothesis x per-point block reductions (RGB-D template cost, NCC patches)
- :mod:`.particles`  particle-filter sampling and best-k selection on the device
- :mod:`.kinematics` forward kinematics of kinematic chains
- :mod:`.lm`         batched Levenberg-Marquardt
- :mod:`.kalman`     batched Kalman filters and gating
"""

import importlib

from ..device import Device


def backend_module(device: Device, primitive: str):
    """The module ``gputrack.backends.<backend>.<primitive>`` that implements ``primitive``."""
    backend = "reference" if device.backend == "numpy" else device.backend
    return importlib.import_module(f"gputrack.backends.{backend}.{primitive}")


from .kinematics import forward_kinematics  # noqa: E402
from .lm import LeastSquaresResult, LMStatus, least_squares, lm_solve, lm_step, normal_equations  # noqa: E402
from .particles import BestK, best_k, sample_around  # noqa: E402
from .template import Camera, RgbdCost, SparseTemplate, patch_ncc, patch_ncc_per_point, rgbd_cost, rgbd_residuals  # noqa: E402

__all__ = [
    "BestK",
    "Camera",
    "LMStatus",
    "LeastSquaresResult",
    "RgbdCost",
    "SparseTemplate",
    "backend_module",
    "best_k",
    "forward_kinematics",
    "least_squares",
    "lm_solve",
    "lm_step",
    "normal_equations",
    "patch_ncc",
    "patch_ncc_per_point",
    "rgbd_cost",
    "rgbd_residuals",
    "sample_around",
]

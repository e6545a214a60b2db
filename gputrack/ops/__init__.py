"""Device primitives: one public function per op, implemented once per backend.

Each op takes a ``device`` first and accepts NumPy arrays or DeviceArrays of that device; it
returns DeviceArrays on that device (NumPy arrays for the ``numpy`` device). The modules:

- :mod:`.template`   per-hypothesis x per-point block reductions (RGB-D template cost and residuals)
- :mod:`.ncc`        zero-mean NCC of templates with image patches (paper 003)
- :mod:`.particles`  particle-filter sampling and best-k selection on the device
- :mod:`.pf`         one particle-filter stage (sample, pose, score, best k) as one op
- :mod:`.pose_residuals` RGB-D residuals of a chain's poses for the LM (block-sparse Jacobian)
- :mod:`.kinematics` forward kinematics of kinematic chains
- :mod:`.lm`         batched Levenberg-Marquardt
- :mod:`.kalman`     batched Kalman filters and gating
- :mod:`.point_groups` observation points to groups (gate, tie-break) and each group's moments
- :mod:`.background` per-pixel background median, running average and foreground mask (papers 001, 002)
- :mod:`.depth_points` foreground points of a depth frame, randomly downsampled (paper 002)
- :mod:`.clusters`   radius-graph connected components and DBSCAN (papers 001, 002)
"""

from ..device import Device
from ..registry import implementation


def backend_module(device: Device, primitive: str):
    """The module that implements ``primitive`` on ``device``: ``<package>.<primitive>``, where
    ``package`` is the implementation package of the device's backend in the registry
    (gputrack/registry.py; memoised there: ops call this on every call)."""
    return implementation(device.backend, primitive)


from .kalman import (  # noqa: E402
    KalmanState,
    KalmanStatus,
    SharedMatrix,
    constant_velocity,
    ekf_update_stereo,
    kf_predict,
    kf_update,
    mahalanobis,
    shared_matrix,
)
from .gating import GatedPairs, gate_pairs  # noqa: E402
from .kinematics import forward_kinematics  # noqa: E402
from .lm import LeastSquaresResult, LeastSquaresSolver, LMStatus, least_squares, lm_solve, lm_step, normal_equations  # noqa: E402
from .particles import BestK, best_k, sample_around  # noqa: E402
from .pf import pf_stage  # noqa: E402
from .pose_residuals import pose_residuals  # noqa: E402
from .rows import scatter_rows  # noqa: E402
from .point_groups import PointGroups, assign_points  # noqa: E402
from .ncc import patch_ncc, patch_ncc_per_point  # noqa: E402
from .template import RgbdCost, RgbdScene, SparseTemplate, rgbd_cost, rgbd_residuals  # noqa: E402
from .background import background_median, foreground_mask, update_background  # noqa: E402
from .depth_points import depth_points, floor_background  # noqa: E402
from .clusters import compact_labels, dbscan, radius_components  # noqa: E402

__all__ = [
    "BestK",
    "GatedPairs",
    "KalmanState",
    "KalmanStatus",
    "LMStatus",
    "LeastSquaresResult",
    "LeastSquaresSolver",
    "PointGroups",
    "RgbdCost",
    "RgbdScene",
    "SharedMatrix",
    "SparseTemplate",
    "assign_points",
    "backend_module",
    "best_k",
    "constant_velocity",
    "ekf_update_stereo",
    "forward_kinematics",
    "gate_pairs",
    "kf_predict",
    "kf_update",
    "least_squares",
    "lm_solve",
    "lm_step",
    "mahalanobis",
    "normal_equations",
    "patch_ncc",
    "patch_ncc_per_point",
    "pf_stage",
    "pose_residuals",
    "rgbd_cost",
    "rgbd_residuals",
    "sample_around",
    "scatter_rows",
    "shared_matrix",
    "background_median",
    "foreground_mask",
    "update_background",
    "depth_points",
    "floor_background",
    "compact_labels",
    "dbscan",
    "radius_components",
]

from .stereo import stereo_match  # noqa: E402

__all__ += ["stereo_match"]

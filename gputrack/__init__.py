"""gputrack: GPU-portable compute primitives and trackers for visual tracking.

The same ops run on NumPy (the reference), Taichi (CPU, Vulkan, CUDA) and OpenCL (PoCL or any
vendor driver). Pick a device, keep data on it, and call ops::

    import gputrack
    dev = gputrack.device("taichi:cpu")      # or None: GPUTRACK_DEVICE, else the best one
    x = dev.asarray(numpy_array)             # DeviceArray; x.numpy() downloads
    print(gputrack.devices())                # every backend, available or not and why
"""

from .device import (
    Device,
    DeviceArray,
    DeviceInfo,
    DeviceUnavailable,
    TaichiArchConflict,
    to_numpy,
)
from .registry import device, devices
from . import tuning
from .profiler import FrameStats, Profiler, StageStats
from .scheduler import Scheduler, SkipFrame, Stage
from .ops import (
    BestK,
    GatedPairs,
    KalmanState,
    KalmanStatus,
    LeastSquaresResult,
    LeastSquaresSolver,
    LMStatus,
    RgbdCost,
    RgbdScene,
    SparseTemplate,
    best_k,
    constant_velocity,
    ekf_update_stereo,
    forward_kinematics,
    gate_pairs,
    kf_predict,
    kf_update,
    least_squares,
    mahalanobis,
    patch_ncc,
    patch_ncc_per_point,
    pf_stage,
    pose_residuals,
    rgbd_cost,
    rgbd_residuals,
    sample_around,
    scatter_rows,
)
from .models import Camera, Chain, DepthCamera, Part, Shape, StereoCamera, rigid, upper_body
from .tracking import MultiTargetTracker, TrackStatus, TrackTable
from .trackers.body import BodyEstimate, BodyTracker, BodyTrackerConfig

__version__ = "0.1.0"

__all__ = [
    "BestK",
    "GatedPairs",
    "MultiTargetTracker",
    "TrackStatus",
    "TrackTable",
    "BodyEstimate",
    "BodyTracker",
    "BodyTrackerConfig",
    "Camera",
    "Chain",
    "DepthCamera",
    "KalmanState",
    "KalmanStatus",
    "LMStatus",
    "LeastSquaresResult",
    "LeastSquaresSolver",
    "Part",
    "RgbdCost",
    "RgbdScene",
    "Shape",
    "SparseTemplate",
    "StereoCamera",
    "best_k",
    "constant_velocity",
    "ekf_update_stereo",
    "forward_kinematics",
    "gate_pairs",
    "kf_predict",
    "kf_update",
    "least_squares",
    "mahalanobis",
    "patch_ncc",
    "patch_ncc_per_point",
    "pf_stage",
    "pose_residuals",
    "rgbd_cost",
    "rgbd_residuals",
    "rigid",
    "sample_around",
    "scatter_rows",
    "upper_body",
    "Device",
    "DeviceArray",
    "DeviceInfo",
    "DeviceUnavailable",
    "FrameStats",
    "Profiler",
    "Scheduler",
    "SkipFrame",
    "Stage",
    "StageStats",
    "TaichiArchConflict",
    "device",
    "devices",
    "to_numpy",
    "tuning",
    "__version__",
]

# the per-pixel front ends of papers 001 and 002
from .ops import background_median, depth_points, floor_background, foreground_mask, update_background  # noqa: E402

__all__ += ["background_median", "depth_points", "floor_background", "foreground_mask", "update_background"]

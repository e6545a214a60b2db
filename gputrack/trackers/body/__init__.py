"""Paper 000's upper-body RGB-D tracker, one module per job (the pattern the other trackers follow):

- :mod:`.tracker` — :class:`BodyTracker` and its :class:`BodyTrackerConfig`: coarse-to-fine particle
  filter + batched Levenberg-Marquardt on the device, run per frame by the scheduler;
- :mod:`.template` — its 3D sparse template (from a rendering of the model, or from a real RGB-D
  frame for rigid scenes);
- :mod:`.metrics` — the paper's accuracy measures (Tables 5-7);
- :mod:`.pictures` — the frames with silhouette, axes and template points, and the error plot
  (``gputrack demo body --save DIR``);
- :mod:`.recording` — reading a recorded RGB-D sequence, its camera, first pose and body model
  (``gputrack track body``).

Its synthetic sequences are in :mod:`gputrack.sim.body`, its demo in :mod:`gputrack.demos.body`.
"""

from .metrics import ARM_PARTS, arm_axis_errors, axis_angle, mean_arm_errors, shoulder_camera_errors, shoulder_errors
from .template import frame_template, sparse_template
from .tracker import BodyEstimate, BodyTracker, BodyTrackerConfig

__all__ = [
    "ARM_PARTS",
    "BodyEstimate",
    "BodyTracker",
    "BodyTrackerConfig",
    "arm_axis_errors",
    "axis_angle",
    "frame_template",
    "mean_arm_errors",
    "shoulder_camera_errors",
    "shoulder_errors",
    "sparse_template",
]

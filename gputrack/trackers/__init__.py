"""Trackers, one module per paper.

- :mod:`.body` — paper 000's upper-body RGB-D tracker (particle filter + batched LM on the device);
  :mod:`.body_template` builds its 3D sparse template (from a rendering of the model, or from a
  real RGB-D frame for rigid scenes).
"""

from .body import BodyEstimate, BodyTracker, BodyTrackerConfig
from .body_template import TemplatePixels, frame_template, select_pixels, sparse_template

__all__ = [
    "BodyEstimate",
    "BodyTracker",
    "TemplatePixels",
    "BodyTrackerConfig",
    "frame_template",
    "select_pixels",
    "sparse_template",
]

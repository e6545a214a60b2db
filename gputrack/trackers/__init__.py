"""Trackers, one package per paper, each with its tracker and config, template or model, and metrics.

- :mod:`.body` — paper 000's upper-body RGB-D tracker (particle filter + batched LM on the device):
  ``body/tracker.py`` (BodyTracker, BodyTrackerConfig), ``body/template.py`` (its 3D sparse
  template, from a rendering of the model or a real RGB-D frame for rigid scenes),
  ``body/metrics.py`` (Tables 5-7). A tracker's simulator is ``gputrack/sim/<name>.py`` and its
  demo ``gputrack/demos/<name>.py``; trackers never import the simulator.
"""

from .body import (
    BodyEstimate,
    BodyTracker,
    BodyTrackerConfig,
    frame_template,
    sparse_template,
)

__all__ = [
    "BodyEstimate",
    "BodyTracker",
    "BodyTrackerConfig",
    "frame_template",
    "sparse_template",
]

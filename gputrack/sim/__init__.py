"""Synthetic input with ground truth, one module per tracker, and the neutral problem generators.

- :mod:`.body` — paper 000's upper-body motion sequences (the body tracker's input), rendered with
  :func:`gputrack.models.render.render`::

      from gputrack.sim import sequence
      seq = sequence(0, frames=60, seed=0)     # arm swings; see SEQUENCES
      for frame in seq:                        # frame.gray, frame.depth (mm), frame.params (truth)
          ...

- :mod:`.scenes` — multi-target constant-velocity scenes with ground truth (births, deaths, misses,
  clutter) for :mod:`gputrack.tracking`: :func:`cv_scene`.
- :mod:`.problems` — problem and scene generators shared by the tests, benchmarks and the tuner.
"""

from .body import FPS, SEQUENCES, Frame, Sequence, sequence, sequence_params, shoulders_off
from .scenes import Scene, SceneFrame, cv_scene

__all__ = [
    "FPS",
    "Frame",
    "SEQUENCES",
    "Scene",
    "SceneFrame",
    "Sequence",
    "cv_scene",
    "sequence",
    "sequence_params",
    "shoulders_off",
]

# paper 002's pedestrian depth sequences (gputrack.sim.pedestrians)
from .pedestrians import DepthSensor, Hall, PedestrianFrame, PedestrianSequence, pedestrian_sequence  # noqa: E402

__all__ += ["DepthSensor", "Hall", "PedestrianFrame", "PedestrianSequence", "pedestrian_sequence"]

# paper 003's monocular face sequences (gputrack.sim.face)
from .face import FaceFrame, FaceSequence, face_sequence, render_face  # noqa: E402

__all__ += ["FaceFrame", "FaceSequence", "face_sequence", "render_face"]

"""Synthetic input with ground truth, one module per tracker, and the neutral problem generators.

- :mod:`.body` — paper 000's upper-body motion sequences (the body tracker's input), rendered with
  :func:`gputrack.models.render.render`::

      from gputrack.sim import sequence
      seq = sequence(0, frames=60, seed=0)     # arm swings; see SEQUENCES
      for frame in seq:                        # frame.gray, frame.depth (mm), frame.params (truth)
          ...

- :mod:`.problems` — problem and scene generators shared by the tests, benchmarks and the tuner.
"""

from .body import FPS, SEQUENCES, Frame, Sequence, sequence, sequence_params, shoulders_off

__all__ = [
    "FPS",
    "Frame",
    "SEQUENCES",
    "Sequence",
    "sequence",
    "sequence_params",
    "shoulders_off",
]

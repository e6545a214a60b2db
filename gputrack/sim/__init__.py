"""Synthetic input with ground truth: a ray-cast RGB-D renderer and paper 000's motion sequences.

    from gputrack.sim import sequence
    seq = sequence(0, frames=60, seed=0)     # arm swings; see SEQUENCES
    for frame in seq:                        # frame.gray, frame.depth (mm), frame.params (truth)
        ...
"""

from .render import DEFAULT_CAMERA, DEFAULT_SIZE, Rendering, Texture, Wall, render
from .sequences import FPS, SEQUENCES, Frame, Sequence, sequence, sequence_params

__all__ = [
    "DEFAULT_CAMERA",
    "DEFAULT_SIZE",
    "FPS",
    "Frame",
    "Rendering",
    "SEQUENCES",
    "Sequence",
    "Texture",
    "Wall",
    "render",
    "sequence",
    "sequence_params",
]

"""Camera models: the pinhole camera the template ops project with, and the default VGA camera.

Coordinates: camera x right, y down, z forward (depth); pixel (u, v) is the centre of column u,
row v.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["DEFAULT_CAMERA", "DEFAULT_SIZE", "Camera"]


def _real(owner: str, name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise TypeError(f"{owner}.{name}: expected a real number, got {type(value).__name__}")
    if not math.isfinite(float(value)):
        raise ValueError(f"{owner}.{name}: expected a finite number, got {value}")
    return float(value)


@dataclasses.dataclass(frozen=True)
class Camera:
    """Pinhole camera: u = fx X/Z + cx, v = fy Y/Z + cy (pixels; (u, v) = centre of column u, row v)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self):
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, _real("Camera", name, getattr(self, name)))
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"Camera: expected fx > 0 and fy > 0, got fx={self.fx}, fy={self.fy}")

    def as_array(self) -> np.ndarray:
        """(4,) float32 [fx, fy, cx, cy]."""
        return np.array([self.fx, self.fy, self.cx, self.cy], dtype=np.float32)


#: Kinect-like VGA camera (paper 000's input: 640x480)
DEFAULT_CAMERA = Camera(525.0, 525.0, 319.5, 239.5)
#: (width, height) of paper 000's images
DEFAULT_SIZE = (640, 480)

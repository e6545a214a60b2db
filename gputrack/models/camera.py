"""Camera models: pinhole, rectified stereo and depth cameras, and the default VGA camera.

- :class:`Camera`: the pinhole camera the template ops project with (paper 000);
- :class:`StereoCamera`: a rectified stereo pair observing (u, v, d), d the disparity (paper 001
  eq. 4-6);
- :class:`DepthCamera`: a depth sensor's intrinsics, depth units and range, back-projecting a
  depth image to 3D points (paper 002 sec. 4.1).

Coordinates: camera x right, y down, z forward (depth); pixel (u, v) is the centre of column u,
row v.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["DEFAULT_CAMERA", "DEFAULT_SIZE", "Camera", "DepthCamera", "StereoCamera"]


def _real(owner: str, name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise TypeError(f"{owner}.{name}: expected a real number, got {type(value).__name__}")
    if not math.isfinite(float(value)):
        raise ValueError(f"{owner}.{name}: expected a finite number, got {value}")
    return float(value)


def _reals(obj, *names: str) -> None:
    """Set each named field of the frozen dataclass ``obj`` to its value as a finite float (or raise)."""
    for name in names:
        object.__setattr__(obj, name, _real(type(obj).__name__, name, getattr(obj, name)))


@dataclasses.dataclass(frozen=True)
class Camera:
    """Pinhole camera: u = fx X/Z + cx, v = fy Y/Z + cy (pixels; (u, v) = centre of column u, row v)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self):
        _reals(self, "fx", "fy", "cx", "cy")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"Camera: expected fx > 0 and fy > 0, got fx={self.fx}, fy={self.fy}")

    def as_array(self) -> np.ndarray:
        """(4,) float32 [fx, fy, cx, cy]."""
        return np.array([self.fx, self.fy, self.cx, self.cy], dtype=np.float32)


def _points(points, name: str) -> np.ndarray:
    """``points`` as a float64 (..., 3) array of finite values."""
    a = np.asarray(points)
    if a.dtype.kind not in "iuf" or a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"{name}: expected a real array of shape (..., 3), got {a.dtype.name} {a.shape}")
    a = a.astype(np.float64)
    if not np.isfinite(a).all():
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
        raise ValueError(f"{name}: expected finite values, got {a[bad]} at index {bad}")
    return a


@dataclasses.dataclass(frozen=True)
class StereoCamera:
    """A rectified stereo pair (paper 001 eq. 4-6): focal length ``f`` and principal point
    (``cx``, ``cy``) in pixels (square pixels, shared by both rectified images) and baseline ``b``
    (the unit of the 3D points, e.g. metres).

    A point (x, y, z) in the left camera's frame is observed as (u, v, d) with
    u = f x / z + cx, v = f y / z + cy and the disparity d = b f / z (eq. 6). This is the
    observation of :func:`gputrack.ops.kalman.ekf_update_stereo` called with
    ``f=cam.f, b=cam.b, cx=cam.cx, cy=cam.cy``.
    """

    f: float
    cx: float
    cy: float
    b: float

    def __post_init__(self):
        _reals(self, "f", "cx", "cy", "b")
        if self.f <= 0 or self.b <= 0:
            raise ValueError(f"StereoCamera: expected f > 0 and b > 0, got f={self.f}, b={self.b}")

    def project(self, points) -> np.ndarray:
        """(..., 3) points (x, y, z), z > 0 -> (..., 3) float64 observations (u, v, d) (eq. 6)."""
        p = _points(points, "points")
        z = p[..., 2]
        if (z <= 0).any():
            bad = tuple(int(i) for i in np.argwhere(z <= 0)[0])
            raise ValueError(f"points: expected z > 0 (in front of the camera), got z = {z[bad]} at index {bad}")
        u = self.f * p[..., 0] / z + self.cx
        v = self.f * p[..., 1] / z + self.cy
        d = self.b * self.f / z  # eq. 6: disparity
        return np.stack([u, v, d], axis=-1)

    def unproject(self, uvd) -> np.ndarray:
        """(..., 3) observations (u, v, d), d > 0 -> (..., 3) float64 points (x, y, z): z = b f / d,
        x = (u - cx) z / f, y = (v - cy) z / f (eq. 6 inverted)."""
        o = _points(uvd, "uvd")
        d = o[..., 2]
        if (d <= 0).any():
            bad = tuple(int(i) for i in np.argwhere(d <= 0)[0])
            raise ValueError(f"uvd: expected a disparity d > 0, got d = {d[bad]} at index {bad}")
        z = self.b * self.f / d
        return np.stack([(o[..., 0] - self.cx) * z / self.f, (o[..., 1] - self.cy) * z / self.f, z], axis=-1)


@dataclasses.dataclass(frozen=True)
class DepthCamera:
    """A depth sensor (paper 002 sec. 4.1): pinhole intrinsics (``fx``, ``fy``, ``cx``, ``cy``, in
    pixels), the length of one depth-image unit in the unit of the 3D points (``depth_scale``;
    0.001 turns a millimetre image into metres) and the sensor's range [``min_depth``,
    ``max_depth``] in the unit of the points (paper 002's Structure Core: 0.3-5 m).

    Pixel (u, v) = (column, row) with depth z (image value times ``depth_scale``) is the point
    x = (u - cx) z / fx, y = (v - cy) z / fy, z.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float = 0.001
    min_depth: float = 0.3
    max_depth: float = 5.0

    def __post_init__(self):
        _reals(self, "fx", "fy", "cx", "cy", "depth_scale", "min_depth", "max_depth")
        if self.fx <= 0 or self.fy <= 0 or self.depth_scale <= 0:
            raise ValueError(
                f"DepthCamera: expected fx, fy and depth_scale > 0, got fx={self.fx}, fy={self.fy}, "
                f"depth_scale={self.depth_scale}"
            )
        if not 0 <= self.min_depth < self.max_depth:
            raise ValueError(
                f"DepthCamera: expected 0 <= min_depth < max_depth, got min_depth={self.min_depth}, "
                f"max_depth={self.max_depth}"
            )

    @property
    def pinhole(self) -> Camera:
        """The intrinsics as a :class:`Camera`."""
        return Camera(self.fx, self.fy, self.cx, self.cy)

    def valid(self, depth) -> np.ndarray:
        """(H, W) bool: the pixels that are measurements within the range (finite, > 0, and
        min_depth <= value * depth_scale <= max_depth)."""
        img = self._image(depth)
        z = img * self.depth_scale
        with np.errstate(invalid="ignore"):
            return np.isfinite(img) & (img > 0) & (z >= self.min_depth) & (z <= self.max_depth)

    def points(self, depth, *, return_pixels: bool = False):
        """Back-project the valid pixels of a depth image (:meth:`valid`) to 3D points.

        depth: (H, W) real array in the sensor's units (0 or non-finite: no measurement).
        Returns (N, 3) float64 points in row-major pixel order, and with ``return_pixels`` also
        (N, 2) int64 (row, column) of each point.
        """
        img = self._image(depth)
        ok = self.valid(img)
        rows, cols = np.nonzero(ok)
        z = img[rows, cols].astype(np.float64) * self.depth_scale
        pts = np.stack([(cols - self.cx) * z / self.fx, (rows - self.cy) * z / self.fy, z], axis=-1)
        if return_pixels:
            return pts, np.stack([rows, cols], axis=-1).astype(np.int64)
        return pts

    def project(self, points) -> np.ndarray:
        """(..., 3) points, z > 0 -> (..., 2) float64 pixels (u, v) (the inverse of :meth:`points`)."""
        p = _points(points, "points")
        z = p[..., 2]
        if (z <= 0).any():
            bad = tuple(int(i) for i in np.argwhere(z <= 0)[0])
            raise ValueError(f"points: expected z > 0 (in front of the camera), got z = {z[bad]} at index {bad}")
        return np.stack([self.fx * p[..., 0] / z + self.cx, self.fy * p[..., 1] / z + self.cy], axis=-1)

    @staticmethod
    def _image(depth) -> np.ndarray:
        img = np.asarray(depth)
        if img.dtype.kind not in "iuf" or img.ndim != 2:
            raise ValueError(f"depth: expected a real (H, W) image, got {img.dtype.name} {img.shape}")
        return img


#: Kinect-like VGA camera (paper 000's input: 640x480)
DEFAULT_CAMERA = Camera(525.0, 525.0, 319.5, 239.5)
#: (width, height) of paper 000's images
DEFAULT_SIZE = (640, 480)

"""Per-pixel background model and foreground mask: the front end of subtraction stereo (paper 001,
the background of each gray camera) and of pedestrians from depth (paper 002 sec. 4.1).

- :func:`background_median`: per-pixel median over F frames, ignoring NaN and a ``missing``
  value (0 for depth cameras: no reading). Paper 002: the median of 30 empty depth frames,
  which removes the sensor's dropouts.
- :func:`update_background`: the online running average bg = (1 - rate) bg + rate frame of the
  pixels that are background (not in the foreground mask) and valid in the frame (paper 001's
  subtraction stereo keeps each camera's background current).
- :func:`foreground_mask`: 1 where |frame - bg| >= threshold and both are valid (paper 002:
  100 mm); with ``nearer=True`` only pixels at least ``threshold`` nearer than the background
  (bg - frame >= threshold) count: a person stands in front of the background.

Images: frames (F, H, W) and a frame (H, W) of dtype uint8 (gray cameras), uint16 (depth in mm)
or float32; the background is (H, W) float32 with NaN where it has no value (never foreground)
and +inf where nothing is in range (e.g. above the horizon of
:func:`gputrack.ops.depth_points.floor_background`: every valid frame pixel there is foreground).
A pixel is valid when it is not NaN and, if ``missing`` is given, not equal to ``missing``. Host (NumPy) inputs are
checked (no inf; NaN is a missing sample); device inputs are trusted. A uint16 image is uploaded
as its bytes (devices hold no uint16: a uint32 array of half the width, or for an odd width a uint8
array of twice the width) and read as uint16 by the kernels; a device array must be float32 or
uint8.

Every backend computes in float32 from the same operations, so the median and the mask agree
bit for bit with the NumPy reference; the running average may differ by a rounding (a fused
multiply-add).
"""

from __future__ import annotations

import sys

import numpy as np

from ..device import DeviceArray, as_host_array
from . import backend_module
from ._args import arg, check_device, match_shape, out_array, real

__all__ = ["MAX_FRAMES", "background_median", "foreground_mask", "update_background"]

#: the most frames :func:`background_median` takes (a per-pixel sort in private memory)
MAX_FRAMES = 64
#: pixel dtypes of the images
PIXELS = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32))


def missing_value(missing) -> float | None:
    return None if missing is None else real("missing", missing)


def pixels(device, x, name: str, shape: tuple, dims: dict):
    """An image argument (pixel dtype uint8, uint16 or float32) on ``device``: returns
    ``(array, pixel)``, ``pixel`` the dtype name of the image. On devices other than ``numpy`` a
    uint16 image becomes its bytes (little-endian): a uint32 array (..., W / 2) for an even width,
    else a uint8 array (..., 2 W)."""
    if isinstance(x, DeviceArray):
        if x.dtype not in (np.dtype(np.uint8), np.dtype(np.float32)):
            raise TypeError(f"{name}: expected a device array of dtype uint8 or float32, got {x.dtype.name}")
        return arg(device, x, name, shape, dims, dtype=x.dtype), x.dtype.name
    if not isinstance(x, np.ndarray):
        if x is None:
            raise TypeError(f"{name}: expected an image, got None")
        x = as_host_array(x, name)
    if x.dtype not in PIXELS:
        raise TypeError(f"{name}: expected dtype uint8, uint16 or float32, got {x.dtype.name}")
    match_shape(name, x.shape, shape, dims)
    if x.dtype.kind == "f" and np.isinf(x).any():
        bad = tuple(int(i) for i in np.argwhere(np.isinf(x))[0])
        raise ValueError(f"{name}: expected finite values or NaN (a missing sample), got {x[bad]} at index {bad}")
    pixel = x.dtype.name
    if device.backend == "numpy":
        return np.ascontiguousarray(x), pixel
    if pixel == "uint16":  # the kernels read each pixel's two bytes (little-endian)
        x = np.ascontiguousarray(x, dtype="<u2") if sys.byteorder != "little" else np.ascontiguousarray(x)
        # (..., W / 2) uint32 words of two pixels for an even width (a Taichi upload copies element
        # by element: 2.4 ms for a 1280 x 960 frame as words, 13 ms as bytes), else (..., 2 W) bytes
        x = x.view(np.uint32) if x.shape[-1] % 2 == 0 else x.view(np.uint8)
    return device.asarray(x), pixel


def width(a, pixel: str) -> int:
    """The image width of an array from :func:`pixels`."""
    if pixel == "uint16" and a.dtype != np.uint16:
        return a.shape[-1] * 2 if a.dtype == np.uint32 else a.shape[-1] // 2
    return a.shape[-1]


def background_arg(device, bg, name: str, dims: dict):
    """A background (H, W) float32 argument (NaN = no background, +inf = nothing in range;
    -inf rejected)."""
    if not isinstance(bg, DeviceArray):
        host = as_host_array(bg, name)
        if host.dtype == np.float32 and np.isneginf(host).any():
            bad = tuple(int(i) for i in np.argwhere(np.isneginf(host))[0])
            raise ValueError(f"{name}: expected finite values, NaN or +inf, got {host[bad]} at index {bad}")
    return arg(device, bg, name, ("H", "W"), dims, finite=False)


def mask_arg(device, mask, dims: dict):
    if mask is None:
        return None
    if isinstance(mask, np.ndarray) and mask.dtype == np.bool_:
        mask = mask.view(np.uint8)
    return arg(device, mask, "mask", ("H", "W"), dims, dtype=np.uint8)


def background_median(device, frames, *, missing=None, out=None):
    """Per-pixel median of F frames: (H, W) float32.

    frames: (F, H, W) uint8, uint16 or float32, 1 <= F <= MAX_FRAMES (64); NaN samples and, if
    ``missing`` is given (0 for depth cameras: no reading), samples equal to it are ignored. A
    pixel with no valid sample is NaN. With an even number of valid samples the median is the
    mean of the two middle ones, (a + b) * 0.5 in float32 (as ``numpy.nanmedian``).
    ``out``: an (H, W) float32 array of the device to write into.
    """
    device = check_device(device)
    miss = missing_value(missing)
    if frames is not None and not isinstance(frames, (DeviceArray, np.ndarray)):
        frames = as_host_array(frames, "frames")
    shape = tuple(getattr(frames, "shape", ()))
    if len(shape) == 3:  # before any upload
        if shape[0] == 0:
            raise ValueError(f"frames: expected at least one frame (F >= 1), got shape {shape}")
        if shape[0] > MAX_FRAMES:
            raise ValueError(f"frames: expected at most {MAX_FRAMES} frames, got F = {shape[0]}")
        if shape[1] == 0 or shape[2] == 0:
            raise ValueError(f"frames: expected images of at least 1 x 1 pixels, got shape {shape}")
    f, pixel = pixels(device, frames, "frames", ("F", "H", "W"), {})
    H, W = f.shape[1], width(f, pixel)
    o = out_array(device, out, "out", (H, W), np.float32)
    return backend_module(device, "background").background_median(device, f, pixel, miss, o)


def update_background(device, background, frame, *, rate, mask=None, missing=None, out=None):
    """Running average of the background: (H, W) float32, written into ``out`` (default: a new
    array; ``out=background`` updates it in place) and returned.

    Where ``mask`` (H, W) uint8 (or bool; nonzero = foreground) is 0 and the frame is valid:
    bg = (1 - rate) bg + rate frame, ``rate`` in [0, 1]; a pixel whose background is invalid (NaN,
    ``missing``) or +inf takes the frame's value. Every other pixel keeps its background.
    background: (H, W) float32 (NaN = none); frame: (H, W) uint8, uint16 or float32.
    """
    device = check_device(device)
    r = real("rate", rate, low=0.0, high=1.0)
    miss = missing_value(missing)
    dims: dict = {}
    bg = background_arg(device, background, "background", dims)
    f, pixel = pixels(device, frame, "frame", ("H", "W"), dims)
    m = mask_arg(device, mask, dims)
    o = out_array(device, out, "out", (dims["H"], dims["W"]), np.float32)
    return backend_module(device, "background").update_background(device, bg, f, pixel, r, m, miss, o)


def foreground_mask(device, frame, background, threshold, *, missing=None, nearer=False, out=None):
    """Foreground of a frame against its background: (H, W) uint8, 1 = foreground.

    1 where frame and background are both valid (not NaN, not ``missing``) and
    |frame - background| >= threshold (paper 002 sec. 4.1: 100 mm), computed in float32; with
    ``nearer=True``, where background - frame >= threshold (only what is in front of the
    background: depth images, e.g. against :func:`gputrack.ops.depth_points.floor_background`).
    frame: (H, W) uint8, uint16 or float32; background: (H, W) float32; threshold >= 0.
    """
    device = check_device(device)
    thr = real("threshold", threshold, low=0.0)
    miss = missing_value(missing)
    dims: dict = {}
    bg = background_arg(device, background, "background", dims)
    f, pixel = pixels(device, frame, "frame", ("H", "W"), dims)
    o = out_array(device, out, "out", (dims["H"], dims["W"]), np.uint8)
    return backend_module(device, "background").foreground_mask(device, f, bg, pixel, thr, miss, bool(nearer), o)

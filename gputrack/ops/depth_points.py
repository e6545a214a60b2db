"""Foreground points of a depth image, randomly downsampled on the device (paper 002 sec. 4.1).

:func:`depth_points` turns one depth frame and its background into at most ``n_points``
foreground points in camera coordinates:

1. foreground: a reading z (0 < z <= ``max_range``; 0 or NaN = no reading, farther = beyond the
   sensor's range, paper 002: 5 m) whose depth differs from the background by >= ``threshold``
   (paper 002: 100 mm), or with ``nearer=True`` lies at least ``threshold`` in front of it;
   background NaN or 0 = none there (never foreground), +inf = nothing in range (every reading
   is foreground). This is :func:`gputrack.ops.background.foreground_mask` with ``missing=0``
   and the range cut;
2. back-projection with the pinhole intrinsics: x = (u - cx) z / fx, y = (v - cy) z / fy, z
   (camera x right, y down, z forward; pixel (u, v) = column u, row v), in the depth image's
   unit (mm for a uint16 depth image);
3. downsampling (paper 002: 1024 points): each foreground pixel i (row-major index v W + u)
   gets the key pcg(pcg(i ^ a) + b) >> 1, (a, b) = (pcg(seed), pcg(counter + a)), pcg the 32-bit
   PCG hash of :mod:`gputrack.ops.particles`; the ``n_points`` smallest keys (ties by pixel
   index) are kept. That is a uniform random subset without replacement, the same on every
   backend for the same (seed, counter); use a new ``counter`` per frame for fresh samples.

Output order: ascending key. The rows are thus a random permutation of the subset, and any
first m rows are themselves a uniform random subset of m points. When fewer than ``n_points``
pixels are foreground, all of them are returned (in key order) and the remaining rows are NaN.

On the devices the selection needs no sort of the image: one pass counts, per row (Taichi) or
per 32-pixel chunk (OpenCL), the foreground keys below four bounds 2**31, 2**28, 2**25, 2**22 and
keeps each chunk's smallest key; the tightest bound holding ``n_points`` keys gives about n to 8n
candidates, which a second pass over only the chunks holding one compacts in row order, and only
they are sorted (a stable radix sort), the first ``n_points`` back-projected. Taichi computes
keys only in the 32-pixel chunks that hold a foreground pixel; OpenCL keeps a byte per pixel
(the bounds its key is below) instead of the keys. On taichi:cpu a host (NumPy) depth image is
read in place by the kernels, with the same checks as an upload, and not copied; OpenCL copies it
into a buffer kept per image size, enqueued without a wait, and with ``host_out`` reads the points
back in the same wait as ``count`` (one wait per call).

:func:`floor_background` is a background for a scene without empty frames: the depth at which a
camera at a known height sees an empty floor, so that foreground = in front of the floor
(``nearer=True``).
"""

from __future__ import annotations

import math
import sys

import numpy as np

from ..backends.reference.depth_points import streams
from ..models.camera import Camera, DepthCamera
from . import backend_module
from ._args import check_device, match_shape, out_array, real
from .background import PIXELS, background_arg, pixels

__all__ = ["depth_points", "floor_background"]

MAX_WORD = 2**32


def _word(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name}: expected an integer in [0, 2**32), got {type(value).__name__}")
    v = int(value)
    if not 0 <= v < MAX_WORD:
        raise ValueError(f"{name}: expected an integer in [0, 2**32), got {v}")
    return v


def _intrinsics(camera) -> tuple[float, float, float, float]:
    if not isinstance(camera, (Camera, DepthCamera)):
        raise TypeError(f"camera: expected a gputrack.models.Camera or DepthCamera, got {type(camera).__name__}")
    return camera.fx, camera.fy, camera.cx, camera.cy


def depth_points(device, depth, background, camera, *, threshold=100.0, max_range=5000.0, n_points=1024, seed=0,
                 counter=0, nearer=False, out=None, host_out=None):  # fmt: skip
    """Foreground points of a depth frame, downsampled: ``(points, count)`` (see the module).

    depth: (H, W) uint16 (e.g. mm; 0 = no reading), float32 (NaN or 0 = no reading) or uint8;
    background: (H, W) float32 in the same unit (e.g. :func:`gputrack.ops.background.background_median`
    with ``missing=0``, or :func:`floor_background`); camera: a :class:`gputrack.models.Camera` or
    :class:`gputrack.models.DepthCamera` (only its intrinsics fx, fy, cx, cy are used: ``threshold``,
    ``max_range`` and the points are in the depth image's unit); threshold >= 0; max_range > 0 (inf:
    no cut); n_points >= 1; seed, counter: integers in [0, 2**32); ``out``: an (n_points, 3) float32
    array of the device to write into; ``host_out``: a C-contiguous NumPy (n_points, 3) float32
    array the points are also downloaded into, in the same wait as ``count``.

    Returns points (n_points, 3) float32 on the device, in ascending key order, NaN rows after the
    min(count, n_points) points, and ``count`` (int): the number of foreground points before
    downsampling (paper 002: a frame with fewer than 1024 has no pedestrian). Reading ``count``
    waits for the device.
    """
    device = check_device(device)
    fx, fy, cx, cy = _intrinsics(camera)
    thr = real("threshold", threshold, low=0.0)
    rng = real("max_range", max_range, positive=True, allow_inf=True)
    if isinstance(n_points, bool) or not isinstance(n_points, (int, np.integer)):
        raise TypeError(f"n_points: expected an integer, got {type(n_points).__name__}")
    if int(n_points) < 1:
        raise ValueError(f"n_points: expected n_points >= 1, got {n_points}")
    a, b = streams(_word("seed", seed), _word("counter", counter))
    dims: dict = {}
    bg = background_arg(device, background, "background", dims)
    impl = backend_module(device, "depth_points")
    if isinstance(depth, np.ndarray) and getattr(impl, "reads_host", None) is not None and impl.reads_host(device):
        d, pixel = _host_pixels(depth, dims)  # taichi:cpu reads it in place, OpenCL copies it (no wait)
    else:
        d, pixel = pixels(device, depth, "depth", ("H", "W"), dims)
    if dims["H"] * dims["W"] >= 2**31:
        raise ValueError(f"depth: expected fewer than 2**31 pixels, got {dims['H']} x {dims['W']}")
    o = out_array(device, out, "out", (int(n_points), 3), np.float32)
    if host_out is None:
        count = impl.depth_points(device, d, bg, pixel, fx, fy, cx, cy, thr, rng, bool(nearer), a, b, o)
        return o, count
    if not (isinstance(host_out, np.ndarray) and host_out.shape == (int(n_points), 3) and host_out.dtype == np.float32
            and host_out.flags.c_contiguous and host_out.flags.writeable):  # fmt: skip
        raise TypeError(f"host_out: expected a writeable C-contiguous NumPy float32 array ({int(n_points)}, 3)")
    if device.backend == "opencl":
        count = impl.depth_points(device, d, bg, pixel, fx, fy, cx, cy, thr, rng, bool(nearer), a, b, o,
                                  host_out=host_out)  # fmt: skip
    else:
        count = impl.depth_points(device, d, bg, pixel, fx, fy, cx, cy, thr, rng, bool(nearer), a, b, o)
        host_out[...] = o if device.backend == "numpy" else o.numpy()
    return o, count


def _host_pixels(x: np.ndarray, dims: dict) -> tuple:
    """A host depth image checked as :func:`gputrack.ops.background.pixels` checks it, for a
    backend that takes host memory (taichi:cpu reads it in place, OpenCL copies it into a kept
    buffer): ``(array, pixel)``, a uint16 image as
    (H, W / 2) uint32 words of two pixels (even widths) or (H, 2 W) bytes, as uploaded."""
    if x.dtype not in PIXELS:
        raise TypeError(f"depth: expected dtype uint8, uint16 or float32, got {x.dtype.name}")
    match_shape("depth", x.shape, ("H", "W"), dims)
    if x.dtype.kind == "f" and np.isinf(x).any():
        bad = tuple(int(i) for i in np.argwhere(np.isinf(x))[0])
        raise ValueError(f"depth: expected finite values or NaN (a missing sample), got {x[bad]} at index {bad}")
    pixel = x.dtype.name
    big_endian = pixel == "uint16" and sys.byteorder != "little"  # the kernels read little-endian bytes
    x = np.ascontiguousarray(x, dtype="<u2") if big_endian else np.ascontiguousarray(x)
    if pixel == "uint16":
        x = x.view(np.uint32) if x.shape[-1] % 2 == 0 else x.view(np.uint8)
    return x, pixel


def floor_background(camera, height, shape, *, pitch=0.0) -> np.ndarray:
    """The depth image of an empty, level floor: (H, W) float32, computed on the host.

    A camera ``height`` above the floor (in the depth image's unit, e.g. mm), pitched down by
    ``pitch`` radians (0: level, as paper 002's sensor), sees along the ray of pixel (u, v),
    d = ((u - cx) / fx, (v - cy) / fy, 1), the floor at depth z = height / (d . g), with
    g = (0, cos pitch, sin pitch) the downward vertical in camera coordinates (y down, z
    forward); where d . g <= 0 (at and above the horizon) no floor is in view and the value is
    +inf, so that every reading there is foreground. Use it as the background of
    :func:`depth_points` / :func:`gputrack.ops.background.foreground_mask` with ``nearer=True``:
    the foreground is whatever stands on (in front of) the floor.

    camera: Camera or DepthCamera (intrinsics); height > 0; shape: (H, W) of the depth image.
    """
    fx, fy, cx, cy = _intrinsics(camera)
    h = real("height", height)
    if h <= 0:
        raise ValueError(f"height: expected a height above the floor > 0, got {h}")
    p = real("pitch", pitch, low=-math.pi / 2, high=math.pi / 2)
    if (
        not isinstance(shape, (tuple, list))
        or len(shape) != 2
        or not all(isinstance(s, (int, np.integer)) and not isinstance(s, bool) and s >= 1 for s in shape)
    ):
        raise ValueError(f"shape: expected (H, W) with H, W >= 1, got {shape!r}")
    H, W = int(shape[0]), int(shape[1])
    v = (np.arange(H, dtype=np.float64) - cy) / fy
    down = np.broadcast_to((v * math.cos(p) + math.sin(p))[:, None], (H, W))  # d . g (no roll: u drops out)
    with np.errstate(divide="ignore"):
        z = np.where(down > 0, h / np.where(down > 0, down, 1.0), np.inf)
    return z.astype(np.float32)

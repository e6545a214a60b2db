"""OpenCL launchers of :mod:`gputrack.ops.background` (kernels/gt_background.cl), built once per
pixel type (GT_PIXEL) and, for the median, per size class of F (GT_MAX_FRAMES)."""

from __future__ import annotations

import numpy as np

from ...device import per_device
from .program import enqueue, scalar_types

_I, _F = np.int32, np.float32
#: the OpenCL C type of each pixel dtype of the ops
CL_PIXEL = {"float32": "float", "uint8": "uchar", "uint16": "ushort"}
ARG_TYPES = {
    "gt_background_median": [None, _I, _I, _I, _I, _F, None],
    "gt_update_background": [None, None, None, _I, _F, _I, _F, None],
    "gt_foreground_mask": [None, None, _F, _I, _F, _I, None],
}


@per_device
def _kernel(device, name, pixel, max_frames):
    import pyopencl as cl

    defines = {"GT_PIXEL": CL_PIXEL[pixel]}
    if max_frames:
        defines["GT_MAX_FRAMES"] = max_frames
    found = cl.Kernel(device.program("gt_background.cl", defines), name)
    scalar_types(found, ARG_TYPES[name])
    return found


def size_class(F: int) -> int:
    """The median's private array for F frames: F rounded up to a power of two, at least 8."""
    return max(8, 1 << (int(F) - 1).bit_length())


def _missing(missing):
    return (0, 0.0) if missing is None else (1, float(missing))


def background_median(device, frames, pixel, missing, out):
    F = frames.shape[0]
    H, W = out.shape
    k = _kernel(device, "gt_background_median", pixel, size_class(F))
    enqueue(device, k, (W, H), None, frames.buffer.data, F, H, W, *_missing(missing), out.buffer.data)
    return out


def update_background(device, bg, frame, pixel, rate, mask, missing, out):
    H, W = out.shape
    k = _kernel(device, "gt_update_background", pixel, 0)
    m = mask.buffer.data if mask is not None else bg.buffer.data  # not read without a mask
    enqueue(device, k, (H * W,), None, bg.buffer.data, frame.buffer.data, m, int(mask is not None), float(rate),
            *_missing(missing), out.buffer.data)  # fmt: skip
    return out


def foreground_mask(device, frame, bg, pixel, threshold, missing, nearer, out):
    H, W = out.shape
    k = _kernel(device, "gt_foreground_mask", pixel, 0)
    enqueue(device, k, (H * W,), None, frame.buffer.data, bg.buffer.data, float(threshold), *_missing(missing),
            int(nearer), out.buffer.data)  # fmt: skip
    return out

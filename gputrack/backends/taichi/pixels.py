"""Reading one pixel of an image argument of the per-pixel ops (gputrack/ops/background.py):
float32 and uint8 arrays are read as they are; a uint16 image arrives as its bytes
(little-endian): uint32 words of two pixels (even widths) or a uint8 array of twice the width.
``u16`` (a template value, :func:`mode`) says which."""

import numpy as np

from .runtime import ti

NATIVE, BYTES, WORDS = 0, 1, 2


def mode(pixel: str, array) -> int:
    """How the kernels read ``array`` (the device form of an image of dtype ``pixel``)."""
    if pixel != "uint16":
        return NATIVE
    return WORDS if array.dtype == np.uint32 else BYTES


@ti.func
def pixel2(img: ti.template(), r, c, u16: ti.template()):
    """Pixel (r, c) of an (H, W) image as float32."""
    v = ti.f32(0.0)
    if ti.static(u16 == WORDS):
        v = ti.cast((img[r, c >> 1] >> ti.cast((c & 1) * 16, ti.u32)) & ti.u32(0xFFFF), ti.f32)
    elif ti.static(u16 == BYTES):
        v = ti.cast(ti.cast(img[r, 2 * c], ti.u32) | (ti.cast(img[r, 2 * c + 1], ti.u32) << ti.u32(8)), ti.f32)
    else:
        v = ti.cast(img[r, c], ti.f32)
    return v


@ti.func
def pixel3(img: ti.template(), f, r, c, u16: ti.template()):
    """Pixel (r, c) of frame f of an (F, H, W) stack as float32."""
    v = ti.f32(0.0)
    if ti.static(u16 == WORDS):
        v = ti.cast((img[f, r, c >> 1] >> ti.cast((c & 1) * 16, ti.u32)) & ti.u32(0xFFFF), ti.f32)
    elif ti.static(u16 == BYTES):
        v = ti.cast(ti.cast(img[f, r, 2 * c], ti.u32) | (ti.cast(img[f, r, 2 * c + 1], ti.u32) << ti.u32(8)), ti.f32)
    else:
        v = ti.cast(img[f, r, c], ti.f32)
    return v


@ti.func
def is_nan(x):
    """NaN by its bits (immune to fast math; a signed compare: both sides are >= 0)."""
    return (ti.bit_cast(x, ti.i32) & 0x7FFFFFFF) > 0x7F800000


@ti.func
def is_finite(x):
    """Neither inf nor NaN, by its bits."""
    return (ti.bit_cast(x, ti.u32) & ti.u32(0x7F800000)) != ti.u32(0x7F800000)


@ti.func
def valid(x, use_missing, missing):
    """Not NaN and, when ``use_missing`` is nonzero, not the missing value."""
    return not is_nan(x) and (use_missing == 0 or x != missing)

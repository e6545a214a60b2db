"""Reading one pixel of an image argument of the per-pixel ops (gputrack/ops/background.py):
float32 and uint8 arrays are read as they are; a uint16 image arrives as its bytes (a uint8
array of twice the width, little-endian) and ``u16`` (a template value) reads it so."""

from .runtime import ti


@ti.func
def pixel2(img: ti.template(), r, c, u16: ti.template()):
    """Pixel (r, c) of an (H, W) image as float32."""
    v = ti.f32(0.0)
    if ti.static(u16):
        v = ti.cast(ti.cast(img[r, 2 * c], ti.u32) | (ti.cast(img[r, 2 * c + 1], ti.u32) << ti.u32(8)), ti.f32)
    else:
        v = ti.cast(img[r, c], ti.f32)
    return v


@ti.func
def pixel3(img: ti.template(), f, r, c, u16: ti.template()):
    """Pixel (r, c) of frame f of an (F, H, W) stack as float32."""
    v = ti.f32(0.0)
    if ti.static(u16):
        v = ti.cast(ti.cast(img[f, r, 2 * c], ti.u32) | (ti.cast(img[f, r, 2 * c + 1], ti.u32) << ti.u32(8)), ti.f32)
    else:
        v = ti.cast(img[f, r, c], ti.f32)
    return v


@ti.func
def is_nan(x):
    """NaN by its bits (immune to fast math)."""
    return (ti.bit_cast(x, ti.u32) & ti.u32(0x7FFFFFFF)) > ti.u32(0x7F800000)


@ti.func
def is_finite(x):
    """Neither inf nor NaN, by its bits."""
    return (ti.bit_cast(x, ti.u32) & ti.u32(0x7F800000)) != ti.u32(0x7F800000)


@ti.func
def valid(x, use_missing, missing):
    """Not NaN and, when ``use_missing`` is nonzero, not the missing value."""
    return not is_nan(x) and (use_missing == 0 or x != missing)

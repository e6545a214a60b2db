"""Taichi kernels of :mod:`gputrack.ops.background`: one thread per pixel; the median sorts the
pixel's valid samples in a private array (insertion sort) of F rounded up to a power of two
(one compiled kernel per size class).

On the CPU archs the loops run over rows, each row's pixels in order: for these one-pass kernels
a row loop is ~5x faster on taichi:cpu than ``ti.ndrange(H, W)`` (no division per pixel;
1280 x 960, 2026-11-25). Elsewhere (GPUs) a parallel loop over every pixel.
"""

from .launch import launch
from .pixels import is_finite, mode, pixel2, pixel3, valid
from .runtime import current_arch, scratch, ti

nd2 = ti.types.ndarray(ndim=2)
nd3 = ti.types.ndarray(ndim=3)


@ti.func
def _median_at(frames: ti.template(), out: ti.template(), r, c, use_missing, missing, u16: ti.template(),
               size: ti.template()):  # fmt: skip
    v = ti.Vector([0.0] * size, dt=ti.f32)
    n = 0
    for f in range(frames.shape[0]):
        x = pixel3(frames, f, r, c, u16)
        if valid(x, use_missing, missing):  # dropouts are ignored (paper 002 sec. 4.1)
            j = n
            while j > 0 and v[j - 1] > x:
                v[j] = v[j - 1]
                j -= 1
            v[j] = x
            n += 1
    m = ti.bit_cast(ti.u32(0x7FC00000), ti.f32)  # NaN: no valid sample
    if n > 0:
        h = n // 2
        m = v[h]
        if n % 2 == 0:
            m = (v[h - 1] + v[h]) * 0.5  # even count: the mean of the two middle samples
    out[r, c] = m


@ti.kernel
def _median(frames: nd3, out: nd2, use_missing: ti.i32, missing: ti.f32, u16: ti.template(), size: ti.template(),
            rows: ti.template()):  # fmt: skip
    if ti.static(rows):
        for r in range(out.shape[0]):
            for c in range(out.shape[1]):
                _median_at(frames, out, r, c, use_missing, missing, u16, size)
    else:
        for r, c in ti.ndrange(out.shape[0], out.shape[1]):
            _median_at(frames, out, r, c, use_missing, missing, u16, size)


@ti.func
def _update_at(bg: ti.template(), frame: ti.template(), mask: ti.template(), out: ti.template(), r, c, rate,
               use_missing, missing, u16: ti.template(), with_mask: ti.template()):  # fmt: skip
    b = bg[r, c]
    x = pixel2(frame, r, c, u16)
    upd = valid(x, use_missing, missing)
    if ti.static(with_mask):
        upd = upd and mask[r, c] == 0
    if upd:
        if valid(b, use_missing, missing) and is_finite(b):
            b = (1.0 - rate) * b + rate * x  # running average
        else:
            b = x  # no (finite) background yet
    out[r, c] = b


@ti.kernel
def _update(bg: nd2, frame: nd2, mask: nd2, out: nd2, rate: ti.f32, use_missing: ti.i32, missing: ti.f32,
            u16: ti.template(), with_mask: ti.template(), rows: ti.template()):  # fmt: skip
    if ti.static(rows):
        for r in range(out.shape[0]):
            for c in range(out.shape[1]):
                _update_at(bg, frame, mask, out, r, c, rate, use_missing, missing, u16, with_mask)
    else:
        for r, c in ti.ndrange(out.shape[0], out.shape[1]):
            _update_at(bg, frame, mask, out, r, c, rate, use_missing, missing, u16, with_mask)


@ti.func
def _mask_at(frame: ti.template(), bg: ti.template(), out: ti.template(), r, c, threshold, use_missing, missing,
             u16: ti.template(), nearer: ti.template()):  # fmt: skip
    x = pixel2(frame, r, c, u16)
    b = bg[r, c]
    d = b - x
    if ti.static(not nearer):
        d = ti.abs(d)
    fg = valid(x, use_missing, missing) and valid(b, use_missing, missing) and d >= threshold
    out[r, c] = ti.u8(1) if fg else ti.u8(0)


@ti.kernel
def _mask(frame: nd2, bg: nd2, out: nd2, threshold: ti.f32, use_missing: ti.i32, missing: ti.f32,
          u16: ti.template(), nearer: ti.template(), rows: ti.template()):  # fmt: skip
    if ti.static(rows):
        for r in range(out.shape[0]):
            for c in range(out.shape[1]):
                _mask_at(frame, bg, out, r, c, threshold, use_missing, missing, u16, nearer)
    else:
        for r, c in ti.ndrange(out.shape[0], out.shape[1]):
            _mask_at(frame, bg, out, r, c, threshold, use_missing, missing, u16, nearer)


def _missing(missing):
    return (0, 0.0) if missing is None else (1, float(missing))


def by_rows() -> bool:
    """Loop over rows (CPU archs) rather than over every pixel (GPUs)."""
    return current_arch() == "cpu"


def size_class(F: int) -> int:
    """The private array's length for F frames: F rounded up to a power of two, at least 8."""
    return max(8, 1 << (int(F) - 1).bit_length())


def background_median(device, frames, pixel, missing, out):
    size = size_class(frames.shape[0])
    launch(_median, (frames.buffer, out.buffer), (mode(pixel, frames), size, by_rows()), scalars=_missing(missing))
    return out


def update_background(device, bg, frame, pixel, rate, mask, missing, out):
    m = mask.buffer if mask is not None else scratch(device, "no mask", (1, 1), ti.u8)
    launch(_update, (bg.buffer, frame.buffer, m, out.buffer), (mode(pixel, frame), mask is not None, by_rows()),
           scalars=(float(rate), *_missing(missing)))  # fmt: skip
    return out


def foreground_mask(device, frame, bg, pixel, threshold, missing, nearer, out):
    launch(_mask, (frame.buffer, bg.buffer, out.buffer), (mode(pixel, frame), bool(nearer), by_rows()),
           scalars=(float(threshold), *_missing(missing)))  # fmt: skip
    return out

"""Taichi kernels of :mod:`gputrack.ops.background`: one thread per pixel; the median sorts the
pixel's valid samples in a private array (insertion sort) of F rounded up to a power of two
(one compiled kernel per size class).

On the CPU archs the loops run over rows, each row's pixels in order: for these one-pass kernels
a row loop is ~5x faster on taichi:cpu than ``ti.ndrange(H, W)`` (no division per pixel;
1280 x 960, 2026-11-25). Elsewhere (GPUs) a parallel loop over every pixel. The mask and the
update load CHUNK pixels of a row before they compute and store them, and are compiled for whether
a missing value is given and whether the image is of integers (never NaN): VGA on taichi:cpu,
three rounds in turn with the kernels before, mask 1.9-2.2 -> 1.1-1.6 ms, masked update 3.3-3.8 ->
1.7-2.2 ms (2-core Xeon VM, 2026-11-27).
"""

from .launch import launch
from .pixels import is_finite, is_nan, mode, pixel2, pixel3, valid
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


#: pixels of a row a CPU thread loads before it computes and stores them (Taichi reloads an
#: array's address after every store)
CHUNK = 16


@ti.func
def _valid(x, missing, use_missing: ti.template(), integer: ti.template()):
    """Not NaN (an integer image's pixel never is) and, with ``use_missing``, not the missing value."""
    ok = True
    if ti.static(not integer):
        ok = not is_nan(x)
    if ti.static(use_missing):
        ok = ok and x != missing
    return ok


@ti.func
def _updated(b, x, m, rate, missing, use_missing: ti.template(), integer: ti.template(), with_mask: ti.template()):
    """The background b after pixel x (m: the mask's value there, read only ``with_mask``)."""
    upd = _valid(x, missing, use_missing, integer)
    if ti.static(with_mask):
        upd = upd and m == 0
    if upd:
        if _valid(b, missing, use_missing, False) and is_finite(b):
            b = (1.0 - rate) * b + rate * x  # running average
        else:
            b = x  # no (finite) background yet
    return b


@ti.func
def _update_row(bg: ti.template(), frame: ti.template(), mask: ti.template(), out: ti.template(), r, c0, n: ti.template(),
                rate, missing, u16: ti.template(), use_missing: ti.template(), integer: ti.template(),
                with_mask: ti.template()):  # fmt: skip
    """Pixels c0 .. c0 + n - 1 of row r: all loaded, then computed and stored."""
    xs = ti.Vector([pixel2(frame, r, c0 + k, u16) for k in ti.static(range(n))])
    bs = ti.Vector([bg[r, c0 + k] for k in ti.static(range(n))])
    ms = ti.Vector([ti.u8(0)] * n)
    if ti.static(with_mask):
        ms = ti.Vector([mask[r, c0 + k] for k in ti.static(range(n))])
    for k in ti.static(range(n)):
        out[r, c0 + k] = _updated(bs[k], xs[k], ms[k], rate, missing, use_missing, integer, with_mask)


@ti.kernel
def _update(bg: nd2, frame: nd2, mask: nd2, out: nd2, rate: ti.f32, missing: ti.f32, u16: ti.template(),
            with_mask: ti.template(), rows: ti.template(), use_missing: ti.template(), integer: ti.template()):  # fmt: skip
    if ti.static(rows):
        for r in range(out.shape[0]):
            W = out.shape[1]
            c = 0
            while c + CHUNK <= W:
                _update_row(bg, frame, mask, out, r, c, CHUNK, rate, missing, u16, use_missing, integer, with_mask)
                c += CHUNK
            while c < W:
                _update_row(bg, frame, mask, out, r, c, 1, rate, missing, u16, use_missing, integer, with_mask)
                c += 1
    else:
        for r, c in ti.ndrange(out.shape[0], out.shape[1]):
            m = ti.u8(0)
            if ti.static(with_mask):
                m = mask[r, c]
            out[r, c] = _updated(bg[r, c], pixel2(frame, r, c, u16), m, rate, missing, use_missing, integer,
                                 with_mask)  # fmt: skip


@ti.func
def _is_fg(x, b, threshold, missing, use_missing: ti.template(), integer: ti.template(), nearer: ti.template()):
    d = b - x
    if ti.static(not nearer):
        d = ti.abs(d)
    return _valid(x, missing, use_missing, integer) and _valid(b, missing, use_missing, False) and d >= threshold


@ti.func
def _mask_row(frame: ti.template(), bg: ti.template(), out: ti.template(), r, c0, n: ti.template(), threshold,
              missing, u16: ti.template(), use_missing: ti.template(), integer: ti.template(),
              nearer: ti.template()):  # fmt: skip
    """Pixels c0 .. c0 + n - 1 of row r: all loaded, then compared and stored."""
    xs = ti.Vector([pixel2(frame, r, c0 + k, u16) for k in ti.static(range(n))])
    bs = ti.Vector([bg[r, c0 + k] for k in ti.static(range(n))])
    for k in ti.static(range(n)):
        fg = _is_fg(xs[k], bs[k], threshold, missing, use_missing, integer, nearer)
        out[r, c0 + k] = ti.u8(1) if fg else ti.u8(0)


@ti.kernel
def _mask(frame: nd2, bg: nd2, out: nd2, threshold: ti.f32, missing: ti.f32, u16: ti.template(),
          nearer: ti.template(), rows: ti.template(), use_missing: ti.template(), integer: ti.template()):  # fmt: skip
    if ti.static(rows):
        for r in range(out.shape[0]):
            W = out.shape[1]
            c = 0
            while c + CHUNK <= W:
                _mask_row(frame, bg, out, r, c, CHUNK, threshold, missing, u16, use_missing, integer, nearer)
                c += CHUNK
            while c < W:
                _mask_row(frame, bg, out, r, c, 1, threshold, missing, u16, use_missing, integer, nearer)
                c += 1
    else:
        for r, c in ti.ndrange(out.shape[0], out.shape[1]):
            fg = _is_fg(pixel2(frame, r, c, u16), bg[r, c], threshold, missing, use_missing, integer, nearer)
            out[r, c] = ti.u8(1) if fg else ti.u8(0)


def _missing(missing):
    return (0, 0.0) if missing is None else (1, float(missing))


def _static(pixel, missing) -> tuple:
    """The compile-time flags of the mask and update kernels: a missing value given; an integer image."""
    return missing is not None, pixel != "float32"


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
    launch(_update, (bg.buffer, frame.buffer, m, out.buffer),
           (mode(pixel, frame), mask is not None, by_rows(), *_static(pixel, missing)),
           scalars=(float(rate), _missing(missing)[1]))  # fmt: skip
    return out


def foreground_mask(device, frame, bg, pixel, threshold, missing, nearer, out):
    launch(_mask, (frame.buffer, bg.buffer, out.buffer), (mode(pixel, frame), bool(nearer), by_rows(),
                                                          *_static(pixel, missing)),
           scalars=(float(threshold), _missing(missing)[1]))  # fmt: skip
    return out

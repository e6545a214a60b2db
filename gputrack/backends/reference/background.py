"""NumPy reference of :mod:`gputrack.ops.background` (paper 001 subtraction stereo, paper 002
sec. 4.1): per-pixel median, running average and foreground mask, in float32."""

from __future__ import annotations

import numpy as np

F32 = np.float32


def valid(x: np.ndarray, missing) -> np.ndarray:
    """A sample is valid when it is not NaN and not the ``missing`` value (e.g. 0: no depth reading)."""
    ok = ~np.isnan(x)
    if missing is not None:
        ok &= x != F32(missing)
    return ok


def background_median(device, frames, pixel, missing, out):
    """Paper 002 sec. 4.1: the background is the per-pixel median of the (empty) frames, ignoring
    dropouts; (a + b) * 0.5 of the two middle samples for an even count, NaN for none."""
    x = frames.astype(F32)
    x[~valid(x, missing)] = np.nan
    s = np.sort(x, axis=0)  # NaN sort last
    n = (~np.isnan(x)).sum(axis=0)
    hi = np.take_along_axis(s, (n // 2)[None], axis=0)[0]
    lo = np.take_along_axis(s, np.maximum(n - 1, 0)[None] // 2, axis=0)[0]
    med = np.where(n % 2 == 1, hi, (lo + hi) * F32(0.5))
    out[...] = np.where(n > 0, med, F32(np.nan))
    return out


def update_background(device, bg, frame, pixel, rate, mask, missing, out):
    """bg = (1 - rate) bg + rate frame where the pixel is background (mask 0) and the frame valid;
    an invalid or infinite background takes the frame's value there."""
    f = frame.astype(F32)
    r = F32(rate)
    upd = valid(f, missing)
    if mask is not None:
        upd &= mask == 0
    have = valid(bg, missing) & np.isfinite(bg)
    new = np.where(have, (F32(1) - r) * bg + r * f, f).astype(F32)  # running average
    out[...] = np.where(upd, new, bg)
    return out


def foreground_mask(device, frame, bg, pixel, threshold, missing, nearer, out):
    """Paper 002 sec. 4.1: foreground = |frame - bg| >= threshold (100 mm) where both are valid;
    ``nearer``: bg - frame >= threshold (in front of the background)."""
    f = frame.astype(F32)
    d = (bg - f) if nearer else np.abs(f - bg)
    with np.errstate(invalid="ignore"):
        fg = valid(f, missing) & valid(bg, missing) & (d >= F32(threshold))
    out[...] = fg
    return out

"""NumPy reference of :mod:`gputrack.ops.depth_points` (paper 002 sec. 4.1): foreground of a depth
image, back-projection, and the seeded uniform subset of n points (the n smallest keys)."""

from __future__ import annotations

import numpy as np

from .background import F32
from .particles import pcg

U32 = np.uint32
MASK32 = 0xFFFFFFFF


def pcg_int(x: int) -> int:
    """:func:`pcg` of one Python int (the same 32-bit hash)."""
    return int(pcg(np.array([x & MASK32], U32))[0])


def streams(seed: int, counter: int) -> tuple[int, int]:
    """The two 32-bit words (a, b) of the keys of (seed, counter): a = pcg(seed),
    b = pcg(counter + a) (mod 2**32)."""
    a = pcg_int(seed)
    return a, pcg_int((counter + a) & MASK32)


def keys(index: np.ndarray, a: int, b: int) -> np.ndarray:
    """31-bit key of each pixel index (row-major r W + c): pcg(pcg(i ^ a) + b) >> 1. For fixed
    (a, b) the 32-bit hash is a bijection of i (pcg is one), so keys rarely tie; ties order by i."""
    i = np.asarray(index).astype(U32)
    return pcg(pcg(i ^ U32(a)) + U32(b)) >> U32(1)


def foreground(z: np.ndarray, bg: np.ndarray, threshold: float, max_range: float, nearer: bool) -> np.ndarray:
    """Paper 002 sec. 4.1: a reading (0 < z <= max_range: no reading or beyond the sensor's range is
    dropped) whose depth differs from a background value (not NaN, not 0) by >= threshold
    (``nearer``: is at least threshold in front of it)."""
    d = (bg - z) if nearer else np.abs(z - bg)
    with np.errstate(invalid="ignore"):
        return (z > 0) & (z <= F32(max_range)) & ~np.isnan(bg) & (bg != 0) & (d >= F32(threshold))


def depth_points(device, depth, bg, pixel, fx, fy, cx, cy, threshold, max_range, nearer, a, b, out):
    """Writes the selected points into ``out`` (n, 3) (NaN rows after them); returns the count of
    foreground points before downsampling."""
    z = depth.astype(F32)
    H, W = z.shape
    idx = np.flatnonzero(foreground(z, bg, threshold, max_range, nearer))  # row-major
    order = np.lexsort((idx, keys(idx, a, b)))  # ascending key, ties by pixel index
    sel = idx[order[: out.shape[0]]]  # random downsampling to n points (paper 002: 1024)
    r, c = np.divmod(sel, W)
    zz = z.ravel()[sel]
    out[...] = np.nan
    out[: sel.size, 0] = (c.astype(F32) - F32(cx)) * zz / F32(fx)  # pinhole back-projection
    out[: sel.size, 1] = (r.astype(F32) - F32(cy)) * zz / F32(fy)
    out[: sel.size, 2] = zz
    return int(idx.size)

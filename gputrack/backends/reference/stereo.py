"""NumPy reference of :mod:`gputrack.ops.stereo`: block matching of a rectified pair by SAD of
x-Sobel-prefiltered intensities, winner-take-all, a uniqueness check, parabola subpixel and a left-right check
(paper 001, subtraction stereo). Conventions: gputrack/ops/stereo.py.

The readable version: the whole integer cost volume C[d, y, x] (of the rows the mask touches)
with box sums from 2-D cumulative sums, then every check on whole arrays. A masked call returns
the unmasked result inside the mask (the op's guarantee), so the reference computes that and
blanks the rest.
"""

from __future__ import annotations

import numpy as np

#: a cost larger than any SAD (block <= 31, prefiltered values <= 2 * 16 * CAP): marks (x, d)
#: outside the image
BIG = np.iinfo(np.int32).max // 4


def quantise(image: np.ndarray) -> np.ndarray:
    """Integer intensities: uint8 as they are, float32 in [0, 1] as floor(4096 I) (exact: a
    product by a power of two), clamped to [0, 4096]."""
    if image.dtype == np.uint8:
        return image.astype(np.int32)
    q = np.floor(np.clip(image, np.float32(0), np.float32(1)) * np.float32(4096))
    return q.astype(np.int32)


def prefilter(q: np.ndarray, cap: int) -> np.ndarray:
    """The matched values: the x-Sobel response of the integer image clipped to [-cap, cap],
    plus cap (so in [0, 2 cap]); cap where the 3 x 3 stencil leaves the image (as OpenCV's
    StereoBM prefilter: robust to a brightness offset between the cameras)."""
    s = np.zeros_like(q)
    s[1:-1, 1:-1] = ((q[:-2, 2:] + 2 * q[1:-1, 2:] + q[2:, 2:])
                     - (q[:-2, :-2] + 2 * q[1:-1, :-2] + q[2:, :-2]))  # fmt: skip
    return np.clip(s, -cap, cap) + cap


def _box(a: np.ndarray, block: int) -> np.ndarray:
    """Sum of ``a`` (..., H, W) over every block x block window, at the window's centre; (..., H, W)
    with zeros where the window leaves the array. Integer cumulative sums: exact."""
    r = block // 2
    H, W = a.shape[-2:]
    s = np.zeros(a.shape[:-2] + (H + 1, W + 1), np.int64)
    s[..., 1:, 1:] = a.cumsum(-2, dtype=np.int64).cumsum(-1)
    out = np.zeros(a.shape, np.int64)
    if H >= block and W >= block:
        out[..., r:H - r, r:W - r] = (s[..., block:, block:] - s[..., :-block, block:]
                                      - s[..., block:, :-block] + s[..., :-block, :-block])  # fmt: skip
    return out


def cost_volume(qL: np.ndarray, qR: np.ndarray, D: int, block: int) -> np.ndarray:
    """C[d, y, x] = sum over the block x block window at (x, y) of |L(x', y') - R(x' - d, y')| (SAD),
    int64 (D, H, W); BIG where the window leaves either image."""
    H, W = qL.shape
    r = block // 2
    ad = np.zeros((D, H, W), np.int32)
    for d in range(D):
        ad[d, :, d:] = np.abs(qL[:, d:] - qR[:, : W - d])  # |L(x) - R(x - d)|
    C = _box(ad, block).astype(np.int32)  # <= 961 * 4096
    x = np.arange(W)
    d = np.arange(D)[:, None]
    inside = (x[None, :] - d - r >= 0) & (x[None, :] + r <= W - 1)  # the window at x - d is in R
    rows = np.zeros(H, bool)
    rows[r:H - r] = True
    ok = inside[:, None, :] & rows[None, :, None]
    return np.where(ok, C, BIG)


def needs_tiles(device) -> bool:
    """The reference reads neither the runs nor their tiles."""
    return False


def stereo_match(device, left, right, mask, runs, tiles, D, block, uniqueness, cap, out):
    """Writes the (H, W) float32 disparity into ``out`` (NaN where invalid) and returns it; arguments
    validated by the op (``cap``: the prefilter's clip in integer units; ``mask``: uint8 (H, W) or
    None; ``runs`` and ``tiles`` (the fast backends' work lists) are not needed here)."""
    H, W = left.shape
    r = block // 2
    out[...] = np.nan
    rows = np.arange(H)
    if mask is not None:
        touched = np.flatnonzero(mask.any(axis=1))
        if touched.size == 0:
            return out
        rows = np.arange(max(touched[0] - r, 0), min(touched[-1] + r + 1, H))  # the rows the windows read
    y0 = rows[0]
    qL = prefilter(quantise(left), cap)[rows]  # the whole image: the stencil reads rows beyond
    qR = prefilter(quantise(right), cap)[rows]
    C = cost_volume(qL, qR, D, block)  # (D, h, W)
    h = C.shape[1]
    yy = np.arange(h)[:, None] + y0
    xx = np.arange(W)[None, :]
    valid = (yy >= r) & (yy <= H - 1 - r) & (xx - r - (D - 1) >= 0) & (xx + r <= W - 1)  # every d's window inside

    # winner-take-all; np.argmin takes the smallest d of equal costs (every backend does)
    dbest = C.argmin(axis=0)
    cbest = np.take_along_axis(C, dbest[None], 0)[0]

    # uniqueness: no disparity more than 1 px away within (100 + U) % of the best cost
    far = np.abs(np.arange(D)[:, None, None] - dbest[None]) > 1
    rival = np.where(far, C, BIG).min(axis=0).astype(np.int64)
    unique = ~(100 * rival <= (100 + uniqueness) * cbest.astype(np.int64))

    # subpixel: the vertex of the parabola through (d-1, d, d+1); the ends of the range stay integer
    inner = (dbest > 0) & (dbest < D - 1)
    cm = np.take_along_axis(C, np.clip(dbest - 1, 0, D - 1)[None], 0)[0]
    cp = np.take_along_axis(C, np.clip(dbest + 1, 0, D - 1)[None], 0)[0]
    den = np.where(inner, 2 * (cm.astype(np.int64) - 2 * cbest + cp), 1)  # > 0: cm > cbest >= ... (smallest d wins ties)
    offset = np.where(inner, (cm - cp).astype(np.float32) / den.astype(np.float32), np.float32(0))
    disp = dbest.astype(np.float32) + offset.astype(np.float32)

    # left-right check: the right image's best disparity at x - d, C_R(xr, d') = C_L(xr + d', d')
    CR = np.full_like(C, BIG)
    for dd in range(D):
        CR[dd, :, : W - dd] = C[dd, :, dd:]
    dright = CR.argmin(axis=0)  # smallest d' on ties
    xr = np.clip(xx - dbest, 0, W - 1)
    consistent = np.abs(np.take_along_axis(dright, xr, 1) - dbest) <= 1

    ok = valid & unique & consistent
    if mask is not None:
        ok &= mask[rows] != 0
    out[rows] = np.where(ok, disp, np.float32(np.nan))
    return out

"""NumPy reference of the zero-mean NCC of templates with image patches (paper 003 eq. 13).

Conventions: gputrack/ops/ncc.py. The patch pixels are sampled as the template ops sample
(:func:`gputrack.backends.reference.template._bilinear`).
"""

from __future__ import annotations

import numpy as np

from ...abi import INTENSITY_MAX
from .template import _bilinear, _corners

FLAT = 1e-6


def patch_ncc(device, pts, tpl, img, *, per_point):
    s = tpl.shape[1]
    h, w = img.shape
    off = np.arange(s, dtype=np.float32) - np.float32((s - 1) / 2)
    u = pts[:, :, 0][:, :, None, None] + off[None, None, None, :]  # (B, K, S(i), S(j)): column u + j - (S-1)/2
    v = pts[:, :, 1][:, :, None, None] + off[None, None, :, None]  # row v + i - (S-1)/2
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    whole = inside.all(axis=(2, 3))
    x0, y0, a, bb = _corners(u, v, inside, (h, w))
    lim = np.float32(INTENSITY_MAX)  # pixels and template values clamped (gputrack/ops/ncc.py)
    P = _bilinear(np.clip(img, -lim, lim), x0, y0, a, bb).astype(np.float64)
    T = np.clip(tpl, -lim, lim).astype(np.float64)[None]
    n = s * s
    Pm = P.mean(axis=(2, 3), keepdims=True)
    Tm = T.mean(axis=(2, 3), keepdims=True)
    Pc, Tc = P - Pm, T - Tm
    sPP = (Pc * Pc).sum(axis=(2, 3))
    sTT = (Tc * Tc).sum(axis=(2, 3))
    sPT = (Pc * Tc).sum(axis=(2, 3))
    # flat: standard deviation <= 1e-6 (|mean| + 1)
    flatP = sPP <= n * (FLAT * (np.abs(Pm[..., 0, 0]) + 1)) ** 2
    flatT = sTT <= n * (FLAT * (np.abs(Tm[..., 0, 0]) + 1)) ** 2
    ok = whole & ~flatP & ~flatT
    with np.errstate(divide="ignore", invalid="ignore"):
        ncc = np.where(ok, sPT / np.sqrt(np.where(ok, sPP * sTT, 1.0)), 0.0)  # paper 003: N(u) per point
    ncc = np.clip(ncc, -1.0, 1.0)
    if per_point:
        return ncc.astype(np.float32)
    return ncc.sum(axis=1).astype(np.float32)  # eq. 13: N(u) = sum over the K points

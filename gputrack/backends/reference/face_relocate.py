"""NumPy: feature-point re-localisation (gputrack/ops/face_relocate.py, paper 003 eq. 14), in float64."""

import numpy as np


def patches_at(image, points, size: int, warp=None, index=None) -> np.ndarray:
    """(K, size, size) float64 bilinear patches of ``image`` (H, W) centred on ``points`` (K, 2), each
    sample coordinate clipped into the image (the convention of gputrack/ops/face_relocate.py). With
    ``warp`` (K, 2, 2), pixel (i, j) of patch k samples points[k] + warp[k] @ (j - c, i - c), c = (size-1)/2.
    With ``index`` (K,) int, ``image`` is a stack (n, H, W) and patch k is cut from image index[k]."""
    img = np.asarray(image, np.float64)
    H, W = img.shape[-2:]
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    off = np.arange(size) - (size - 1) / 2.0
    if warp is None:
        x = np.broadcast_to((pts[:, 0, None] + off)[:, None, :], (len(pts), size, size))  # (K, S, S)
        y = np.broadcast_to((pts[:, 1, None] + off)[:, :, None], (len(pts), size, size))
    else:
        w = np.asarray(warp, np.float64)[:, :, :, None, None]  # (K, 2, 2, 1, 1)
        dx, dy = off[None, :], off[:, None]  # the (x, y) offsets of pixel (i, j)
        x = pts[:, 0, None, None] + (w[:, 0, 0] * dx + w[:, 0, 1] * dy)
        y = pts[:, 1, None, None] + (w[:, 1, 0] * dx + w[:, 1, 1] * dy)
    x, y = np.clip(x, 0.0, W - 1.0), np.clip(y, 0.0, H - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), W - 2)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 2)
    fx, fy = x - x0, y - y0
    i = y0 * W + x0  # (K, S, S) flat index of the top-left pixel
    if index is not None:
        i = i + np.asarray(index, np.int64)[:, None, None] * (H * W)
    flat = img.reshape(-1)
    top = flat[i] + fx * (flat[i + 1] - flat[i])
    bot = flat[i + W] + fx * (flat[i + W + 1] - flat[i + W])
    return top + fy * (bot - top)


def _normaliser(inner, contrast, min_std, shading):
    """(mean, gain, bx, by), each (K, 1, 1), of patches ``inner`` (K, S, S): gain * (v - mean - bx x - by y)
    at offset (x, y) from the patch's centre has zero mean and standard deviation ``contrast`` (a patch
    flatter than ``min_std`` is scaled as one of ``min_std``); with ``shading`` (bx, by) is the
    least-squares ramp of the patch (0 without)."""
    S = inner.shape[-1]
    off = np.arange(S) - (S - 1) / 2.0
    mean = inner.mean(axis=(1, 2), keepdims=True)
    d = inner - mean
    var = (d * d).mean(axis=(1, 2), keepdims=True)
    bx = by = np.zeros_like(mean)
    if shading:  # x and y offsets are orthogonal to 1 and to each other on the square grid
        sxx = S * (off * off).sum()
        bx = (d * off[None, None, :]).sum(axis=(1, 2), keepdims=True) / sxx
        by = (d * off[None, :, None]).sum(axis=(1, 2), keepdims=True) / sxx
        var = np.maximum(var - (bx * bx + by * by) * sxx / (S * S), 0.0)
    return mean, contrast / np.maximum(np.sqrt(var), min_std), bx, by


def _normalised(patches, inner, contrast, min_std, shading):
    """``patches`` (K, B, B) centred like ``inner`` (K, S, S), B >= S, brought to ``inner``'s zero mean,
    standard deviation ``contrast`` and (``shading``) no ramp (:func:`_normaliser`)."""
    mean, gain, bx, by = _normaliser(inner, contrast, min_std, shading)
    off = np.arange(patches.shape[-1]) - (patches.shape[-1] - 1) / 2.0
    return (patches - mean - bx * off[None, None, :] - by * off[None, :, None]) * gain


def plane_match(patches, templates) -> np.ndarray:
    """(K,) the NCC of each patch (K, S, S) with its template, each with its least-squares intensity
    plane (mean and ramp) off; 0 where either is flat (gputrack/ops/face_relocate.py)."""
    a, b = np.asarray(patches, np.float64), np.asarray(templates, np.float64)
    off = np.arange(a.shape[-1]) - (a.shape[-1] - 1) / 2.0
    res, ok = [], True
    for p in (a, b):
        mean, _, bx, by = _normaliser(p, 1.0, 1.0, True)  # the plane: mean and ramp
        r = p - mean - bx * off[None, None, :] - by * off[None, :, None]
        ok = ok & (np.sqrt((r * r).mean(axis=(1, 2))) > 1e-6 * (np.abs(mean[:, 0, 0]) + 1.0))
        res.append(r)
    num = (res[0] * res[1]).sum(axis=(1, 2))
    den = np.sqrt((res[0] * res[0]).sum(axis=(1, 2)) * (res[1] * res[1]).sum(axis=(1, 2)))
    return np.where(ok, num / np.where(ok, den, 1.0), 0.0)


def relocate_points(device, image, predicted, previous, first, consts, iterations, points, patches, match):
    rho, eps, max_step, contrast, tol, min_std, singular, shading = (float(c) for c in consts)
    img = np.asarray(image, np.float64)
    prev, fst = np.asarray(previous, np.float64), np.asarray(first, np.float64)
    templates = fst
    K, S = prev.shape[0], prev.shape[-1]
    if contrast > 0:
        prev = _normalised(prev, prev, contrast, min_std, False)
        fst = _normalised(fst, fst, contrast, min_std, shading)
    pred = np.asarray(predicted, np.float64)
    m = pred.copy()
    active = np.ones(K, bool)
    for _ in range(iterations):
        if not active.any():
            break
        big = patches_at(img, m, S + 2)  # the patch and a one-pixel ring: gradients by central differences
        a00 = a01 = a11 = g0 = g1 = 0.0
        for w, stored, ramp in ((rho, prev, False), (1.0, fst, shading)):  # eq. 14's appearance terms
            # the patch's mean (and, against the first frame with shading, its ramp) off, its gain to the
            # contrast (the ring's samples alike)
            b = _normalised(big, big[:, 1:-1, 1:-1], contrast, min_std, ramp) if contrast > 0 else big
            gx = 0.5 * (b[:, 1:-1, 2:] - b[:, 1:-1, :-2])
            gy = 0.5 * (b[:, 2:, 1:-1] - b[:, :-2, 1:-1])
            e = b[:, 1:-1, 1:-1] - stored
            a00 = a00 + w * (gx * gx).sum(axis=(1, 2))
            a01 = a01 + w * (gx * gy).sum(axis=(1, 2))
            a11 = a11 + w * (gy * gy).sum(axis=(1, 2))
            g0 = g0 + w * (gx * e).sum(axis=(1, 2))
            g1 = g1 + w * (gy * e).sum(axis=(1, 2))
        a00, a11 = a00 + eps, a11 + eps
        g0 = g0 + eps * (m[:, 0] - pred[:, 0])
        g1 = g1 + eps * (m[:, 1] - pred[:, 1])
        det = a00 * a11 - a01 * a01
        ok = np.abs(det) > singular
        with np.errstate(all="ignore"):
            d = np.stack([a01 * g1 - a11 * g0, a01 * g0 - a00 * g1], axis=-1) / np.where(ok, det, 1.0)[:, None]
        d[~(ok[:, None] & np.isfinite(d))] = 0.0
        n = np.hypot(d[:, 0], d[:, 1])
        d *= np.minimum(1.0, max_step / np.maximum(n, 1e-12))[:, None]
        d[~active] = 0.0
        m += d
        active &= np.abs(d).max(axis=1) >= tol
    points[...] = m
    patches[...] = patches_at(img, m, S)
    match[...] = plane_match(patches, templates)

"""NumPy: feature-point re-localisation (gputrack/ops/face_relocate.py, paper 003 eq. 14), in float64."""

import numpy as np


def patches_at(image, points, size: int) -> np.ndarray:
    """(K, size, size) float64 bilinear patches of ``image`` (H, W) centred on ``points`` (K, 2), each
    sample coordinate clipped into the image (the convention of gputrack/ops/face_relocate.py)."""
    img = np.asarray(image, np.float64)
    H, W = img.shape
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    off = np.arange(size) - (size - 1) / 2.0
    x = np.clip(pts[:, 0, None] + off, 0.0, W - 1.0)[:, None, :]  # (K, 1, S)
    y = np.clip(pts[:, 1, None] + off, 0.0, H - 1.0)[:, :, None]  # (K, S, 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), W - 2)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 2)
    fx, fy = x - x0, y - y0
    i = y0 * W + x0  # (K, S, S) flat index of the top-left pixel
    flat = img.reshape(-1)
    top = flat[i] + fx * (flat[i + 1] - flat[i])
    bot = flat[i + W] + fx * (flat[i + W + 1] - flat[i + W])
    return top + fy * (bot - top)


def _mean_gain(patches, contrast, min_std):
    """(mean, gain), each (K, 1, 1): (patches - mean) * gain has zero mean and standard deviation
    ``contrast`` (a patch flatter than ``min_std`` is scaled as one of ``min_std``)."""
    mean = patches.mean(axis=(1, 2), keepdims=True)
    d = patches - mean
    return mean, contrast / np.maximum(np.sqrt((d * d).mean(axis=(1, 2), keepdims=True)), min_std)


def relocate_points(device, image, predicted, previous, first, consts, iterations, points, patches):
    rho, eps, max_step, contrast, tol, min_std, singular = (float(c) for c in consts)
    img = np.asarray(image, np.float64)
    prev, fst = np.asarray(previous, np.float64), np.asarray(first, np.float64)
    K, S = prev.shape[0], prev.shape[-1]
    if contrast > 0:
        prev, fst = ((p - mean) * gain for p in (prev, fst) for mean, gain in [_mean_gain(p, contrast, min_std)])
    target = rho * prev + fst  # e = (rho + 1) I - target
    pred = np.asarray(predicted, np.float64)
    m = pred.copy()
    active = np.ones(K, bool)
    for _ in range(iterations):
        if not active.any():
            break
        big = patches_at(img, m, S + 2)  # the patch and a one-pixel ring: gradients by central differences
        if contrast > 0:  # the patch's mean off, its gain to the contrast (the ring's samples alike)
            mean, gain = _mean_gain(big[:, 1:-1, 1:-1], contrast, min_std)
            big = (big - mean) * gain
        gx = 0.5 * (big[:, 1:-1, 2:] - big[:, 1:-1, :-2])
        gy = 0.5 * (big[:, 2:, 1:-1] - big[:, :-2, 1:-1])
        e = (rho + 1.0) * big[:, 1:-1, 1:-1] - target  # eq. 14's appearance terms
        a00 = (rho + 1.0) * (gx * gx).sum(axis=(1, 2)) + eps
        a01 = (rho + 1.0) * (gx * gy).sum(axis=(1, 2))
        a11 = (rho + 1.0) * (gy * gy).sum(axis=(1, 2)) + eps
        g0 = (gx * e).sum(axis=(1, 2)) + eps * (m[:, 0] - pred[:, 0])
        g1 = (gy * e).sum(axis=(1, 2)) + eps * (m[:, 1] - pred[:, 1])
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

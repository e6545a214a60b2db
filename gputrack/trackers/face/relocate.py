"""Feature-point re-localisation of paper 003 sec. 4.2 (eq. 14), and the image patches it compares.

The particle filter's estimate projects to points m'_t that are only as right as the identity
(Fig. 5). The true points m-hat_t minimise, per feature point k (eq. 14),

    E_k(m) = sum_ROI { rho (I_t(m + x) - I_{t-1}(m_{t-1} + x))^2 + (I_t(m + x) - I_1(m_1 + x))^2 }
             + eps ||m - m'_k||^2,

the ROI a 16 x 16 patch (x over its pixel offsets): the appearance of the previous frame and of
the first frame (against drift) around the point, held near the estimate. Gauss-Newton on the
linearised patch I_t(m + d + x) ~ I_t(m + x) + G d (G the patch's image gradient), per point:

    ((rho + 1) G^T G + eps I) d = -( G^T (rho (I_t - I_{t-1}) + (I_t - I_1)) + eps (m - m'_k) ),

a 2 x 2 solve, a few iterations, each step at most ``max_step`` pixels. The K points are
independent, so they are solved together: one matrix product per iteration gives every point's
G^T G and G^T e (the K products of the rows gx, gy with the rows gx, gy, e).

Beyond the paper, ``contrast`` c > 0 compares the patches photometrically normalised: each (I_t's at
the current point, I_{t-1}'s, I_1's) brought to zero mean and a standard deviation of c gray levels
(its gradient G scaled alike), so that a change of the light between the frames (a gain and an
offset of a patch's intensities) does not pull the points; eps keeps its meaning against patches of
contrast c. A patch of less than ``MIN_STD`` gray levels of standard deviation is scaled as one of
``MIN_STD``.

Patches sample the image bilinearly with the convention of :func:`gputrack.ops.ncc.patch_ncc`:
patch pixel (i, j) of a point (u, v) is the image at (u + j - (S-1)/2, v + i - (S-1)/2), samples
outside the image taking the nearest border pixel. Patches inside the image come from OpenCV's
``getRectSubPix``, which follows the same convention (float32 arithmetic; ~3x faster here than
the same gathers in NumPy); patches that reach the image's edge are gathered in NumPy.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["MIN_STD", "relocate", "sample_patches"]

#: the least standard deviation (gray levels) a patch is normalised by (``relocate(contrast=...)``):
#: a flat patch's noise is not blown up
MIN_STD = 1.0


def sample_patches(image, points, size: int) -> np.ndarray:
    """(K, S, S) float64 bilinear patches of ``image`` (H, W) centred on the finite ``points`` (K, 2);
    samples outside the image take the nearest border pixel."""
    img = np.asarray(image)
    if img.ndim != 2 or min(img.shape) < 2:
        raise ValueError(f"image: expected a 2-D image of at least 2 x 2 pixels, got shape {img.shape}")
    if img.dtype != np.uint8:
        img = np.ascontiguousarray(img, np.float32)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if not np.isfinite(pts).all():
        raise ValueError(f"points: expected finite pixel coordinates, got {pts[~np.isfinite(pts).all(axis=1)][:3]}")
    H, W = img.shape
    out = np.empty((len(pts), size, size), np.float64)
    # OpenCV replicates another pixel than the border one past the right and bottom edges: it takes
    # only the patches whose samples and their right and lower neighbours all lie in the image
    half = (size - 1) / 2.0
    inside = (pts >= half).all(axis=1) & (pts[:, 0] + half <= W - 2) & (pts[:, 1] + half <= H - 2)
    for k in np.flatnonzero(inside).tolist():
        out[k] = cv2.getRectSubPix(img, (size, size), (pts[k, 0], pts[k, 1]), patchType=cv2.CV_32F)
    if not inside.all():
        out[~inside] = _border_patches(img, pts[~inside], size)
    return out


def _border_patches(img, pts, size: int) -> np.ndarray:
    """sample_patches for points whose patches reach the image's edge: each sample coordinate
    clipped into the image, then bilinear."""
    H, W = img.shape
    off = np.arange(size) - (size - 1) / 2.0
    x = np.clip(pts[:, 0, None] + off, 0.0, W - 1.0)[:, None, :]  # (K, 1, S)
    y = np.clip(pts[:, 1, None] + off, 0.0, H - 1.0)[:, :, None]  # (K, S, 1)
    x0 = np.minimum(x.astype(np.int64), W - 2)  # floor: x >= 0
    y0 = np.minimum(y.astype(np.int64), H - 2)
    fx, fy = x - x0, y - y0
    i = y0 * W + x0  # (K, S, S) flat index of the top-left pixel
    flat = img.reshape(-1)
    a, b, c, d = (flat[i].astype(np.float64), flat[i + 1].astype(np.float64), flat[i + W].astype(np.float64),
                  flat[i + W + 1].astype(np.float64))  # fmt: skip
    return (1 - fy) * ((1 - fx) * a + fx * b) + fy * ((1 - fx) * c + fx * d)


def _mean_gain(patches, contrast: float) -> tuple:
    """(mean, gain), each (K, 1, 1), that bring patches (K, S, S) to zero mean and a standard
    deviation of ``contrast``: (patches - mean) * gain."""
    mean = patches.mean(axis=(1, 2), keepdims=True)
    d = patches - mean
    return mean, contrast / np.maximum(np.sqrt((d * d).mean(axis=(1, 2), keepdims=True)), MIN_STD)


def _normalised(patches, contrast: float) -> np.ndarray:
    """Patches (K, S, S) at zero mean and a standard deviation of ``contrast``."""
    mean, gain = _mean_gain(patches, contrast)
    return (patches - mean) * gain


def relocate(image, predicted, previous, first, *, start=None, rho: float = 4.0, eps: float = 4000.0,
             iterations: int = 5, max_step: float = 3.0, contrast: float = 0.0) -> np.ndarray:  # fmt: skip
    """(K, 2) feature points minimising eq. 14 in ``image`` (H, W).

    predicted: (K, 2) m'_t, the projection of the particle filter's estimate; previous, first:
    (K, S, S) the patches I_{t-1} (at the previous frame's points) and I_1 (at the first frame's);
    start: where the iteration starts (default ``predicted``); contrast: 0 compares raw intensities
    (the paper), c > 0 patches normalised to zero mean and standard deviation c (module
    docstring). Points whose 2 x 2 system is singular or whose step is not finite stay where they
    are.
    """
    prev = np.asarray(previous, np.float64)
    K, S = prev.shape[0], prev.shape[-1]
    first = np.asarray(first, np.float64)
    if contrast < 0 or not np.isfinite(contrast):
        raise ValueError(f"contrast: expected gray levels >= 0 (0: raw intensities), got {contrast!r}")
    if contrast > 0:
        prev, first = _normalised(prev, contrast), _normalised(first, contrast)
    target = (rho * prev + first).reshape(K, -1)  # e = (rho + 1) I - target
    pred = np.asarray(predicted, np.float64)
    m = pred.copy() if start is None else np.asarray(start, np.float64).copy()
    rows = np.empty((K, 3, S * S))  # gx, gy, e per point
    gx, gy, e = (rows[:, i].reshape(K, S, S) for i in range(3))
    for _ in range(iterations):
        big = sample_patches(image, m, S + 2)  # the patch and a one-pixel ring: gradients by central differences
        if contrast > 0:  # the patch's mean off, its gain to the contrast (the ring's samples alike)
            mean, gain = _mean_gain(big[:, 1:-1, 1:-1], contrast)
            big = (big - mean) * gain
        np.subtract(big[:, 1:-1, 2:], big[:, 1:-1, :-2], out=gx)
        np.subtract(big[:, 2:, 1:-1], big[:, :-2, 1:-1], out=gy)
        rows[:, :2] *= 0.5
        np.multiply(big[:, 1:-1, 1:-1], rho + 1.0, out=e)
        rows[:, 2] -= target  # eq. 14's appearance terms
        Q = rows[:, :2] @ rows.transpose(0, 2, 1)  # (K, 2, 3): G^T G | G^T e
        a00, a01, a11 = (rho + 1.0) * Q[:, 0, 0] + eps, (rho + 1.0) * Q[:, 0, 1], (rho + 1.0) * Q[:, 1, 1] + eps
        g = Q[:, :, 2] + eps * (m - pred)
        det = a00 * a11 - a01 * a01
        ok = np.abs(det) > 1e-12
        d = np.stack([a01 * g[:, 1] - a11 * g[:, 0], a01 * g[:, 0] - a00 * g[:, 1]], axis=-1) / np.where(ok, det, 1.0)[:, None]
        d[~(ok[:, None] & np.isfinite(d))] = 0.0
        n = np.hypot(d[:, 0], d[:, 1])[:, None]
        d *= np.minimum(1.0, max_step / np.maximum(n, 1e-12))
        m += d
        if np.abs(d).max(initial=0.0) < 0.01:
            break
    return m

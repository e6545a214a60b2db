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
independent, so they are solved together in NumPy (K 2 x 2 systems of 16 x 16 patches).

Patches sample the image bilinearly with the convention of :func:`gputrack.ops.ncc.patch_ncc`:
patch pixel (i, j) of a point (u, v) is the image at (u + j - (S-1)/2, v + i - (S-1)/2).
"""

from __future__ import annotations

import numpy as np

__all__ = ["relocate", "sample_patches"]


def sample_patches(image, points, size: int) -> np.ndarray:
    """(K, S, S) float64 bilinear patches of ``image`` (H, W) centred on ``points`` (K, 2); samples
    outside the image take the nearest border pixel."""
    img = np.asarray(image)
    H, W = img.shape
    pts = np.asarray(points, dtype=np.float64)
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


def relocate(image, predicted, previous, first, *, start=None, rho: float = 4.0, eps: float = 4000.0,
             iterations: int = 5, max_step: float = 3.0) -> np.ndarray:  # fmt: skip
    """(K, 2) feature points minimising eq. 14 in ``image`` (H, W).

    predicted: (K, 2) m'_t, the projection of the particle filter's estimate; previous, first:
    (K, S, S) the patches I_{t-1} (at the previous frame's points) and I_1 (at the first frame's);
    start: where the iteration starts (default ``predicted``). Points whose 2 x 2 system is
    singular or whose step is not finite stay where they are.
    """
    prev = np.asarray(previous, np.float64)
    first = np.asarray(first, np.float64)
    S = prev.shape[-1]
    pred = np.asarray(predicted, np.float64)
    m = pred.copy() if start is None else np.asarray(start, np.float64).copy()
    for _ in range(iterations):
        big = sample_patches(image, m, S + 2)  # the patch and a one-pixel ring: gradients by central differences
        I = big[:, 1:-1, 1:-1]
        gx = (big[:, 1:-1, 2:] - big[:, 1:-1, :-2]) / 2.0
        gy = (big[:, 2:, 1:-1] - big[:, :-2, 1:-1]) / 2.0
        G = np.stack([gx.reshape(len(m), -1), gy.reshape(len(m), -1)], axis=-1)  # (K, S^2, 2)
        e = (rho * (I - prev) + (I - first)).reshape(len(m), -1)  # eq. 14's appearance terms
        A = (rho + 1.0) * np.einsum("kpi,kpj->kij", G, G) + eps * np.eye(2)
        g = np.einsum("kpi,kp->ki", G, e) + eps * (m - pred)
        det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
        ok = np.abs(det) > 1e-12
        safe = np.where(ok, det, 1.0)
        d = -np.stack([A[:, 1, 1] * g[:, 0] - A[:, 0, 1] * g[:, 1], -A[:, 1, 0] * g[:, 0] + A[:, 0, 0] * g[:, 1]],
                      axis=-1) / safe[:, None]  # fmt: skip
        d = np.where(ok[:, None] & np.isfinite(d), d, 0.0)
        n = np.linalg.norm(d, axis=1, keepdims=True)
        d *= np.minimum(1.0, max_step / np.maximum(n, 1e-12))
        m += d
        if np.abs(d).max(initial=0.0) < 0.01:
            break
    return m

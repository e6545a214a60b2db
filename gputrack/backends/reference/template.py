"""NumPy reference of the sparse-template cost (paper 000 eq. 17-21).

Projection and sampling run in float32 (as on the devices); the sums run in float64 (the
oracle the devices' blocked float32 sums are compared with). Conventions: gputrack/ops/template.py.
"""

from __future__ import annotations

import numpy as np

from ...abi import INTENSITY_MAX

TINY = 1e-12


def _project(tf, pts, part, camera, shape):
    """Camera-frame Z, pixel (u, v) and the in-image mask of every (hypothesis, point): (B, N) each."""
    fx, fy, cx, cy = (np.float32(c) for c in camera)
    m = tf[:, part]  # (B, N, 3, 4): each point's part transform
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    X = m[..., 0, 0] * x + m[..., 0, 1] * y + m[..., 0, 2] * z + m[..., 0, 3]  # eq. 4: M_C = D M_O
    Y = m[..., 1, 0] * x + m[..., 1, 1] * y + m[..., 1, 2] * z + m[..., 1, 3]
    Z = m[..., 2, 0] * x + m[..., 2, 1] * y + m[..., 2, 2] * z + m[..., 2, 3]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        u = fx * (X / Z) + cx  # eq. 5: M_I = [K|0] D M_O
        v = fy * (Y / Z) + cy
        h, w = shape
        inside = (Z > 0) & (Z < np.finfo(np.float32).max) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    return Z.astype(np.float32), u.astype(np.float32), v.astype(np.float32), inside


def _corners(u, v, inside, shape):
    """Bilinear corner indices and weights (zeros where not inside)."""
    h, w = shape
    u = np.where(inside, u, 0).astype(np.float32)
    v = np.where(inside, v, 0).astype(np.float32)
    x0 = np.minimum(np.floor(u).astype(np.int64), w - 2)
    y0 = np.minimum(np.floor(v).astype(np.int64), h - 2)
    a = u - x0.astype(np.float32)
    b = v - y0.astype(np.float32)
    return x0, y0, a, b


def _bilinear(img, x0, y0, a, b):
    i00, i01 = img[y0, x0], img[y0, x0 + 1]
    i10, i11 = img[y0 + 1, x0], img[y0 + 1, x0 + 1]
    top = i00 + a * (i01 - i00)
    bot = i10 + a * (i11 - i10)
    return top + b * (bot - top)  # sec. 3.5: bilinear interpolation


def _measured(d):
    return (d > 0) & np.isfinite(d)


def _terms(tf, rgb, depth, gray, depth_image, camera, lam, c_rgb, c_depth, depth_tol):
    """Per-point d_i, d'_i (float64) and validity masks."""
    tf = np.asarray(tf, np.float32)
    shape = gray.shape
    # RGB points
    pts, part = rgb["pts"], rgb["part"]
    _, u, v, ok = _project(tf, pts, part, camera, shape)
    x0, y0, a, b = _corners(u, v, ok, shape)
    lim = np.float32(INTENSITY_MAX)
    I = _bilinear(np.clip(gray, -lim, lim), x0, y0, a, b).astype(np.float64)  # pixels clamped (gputrack/abi.py)
    T = pts[:, 3].astype(np.float64)[None, :]
    sT = np.where(ok, T, 0).sum(axis=1, keepdims=True)
    sTT = np.where(ok, T * T, 0).sum(axis=1, keepdims=True)
    sTI = np.where(ok, T * I, 0).sum(axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        alpha = np.where(sT > TINY, 1.0 / sT, 0.0)  # eq. 17: alpha = 1 / sum T_i
        beta = np.where(sTI > TINY, alpha * sTT / sTI, 0.0)  # eq. 17: beta = alpha sum T_i^2 / sum T_i I_i
    d = beta * I - alpha * T  # eq. 17: d_i = beta I_i - alpha T_i
    # depth points
    pts, part = depth["pts"], depth["part"]
    Z, u, v, okd = _project(tf, pts, part, camera, shape)
    x0, y0, a, b = _corners(u, v, okd, shape)
    D = depth_image
    okd &= _measured(D[y0, x0]) & _measured(D[y0, x0 + 1]) & _measured(D[y0 + 1, x0]) & _measured(D[y0 + 1, x0 + 1])
    with np.errstate(invalid="ignore"):
        Zhat = _bilinear(D, x0, y0, a, b).astype(np.float64)
        dd = Zhat - Z.astype(np.float64)  # eq. 18: d'_i = Zhat(M'_i; D_k) - Z_i
        if depth_tol > 0:  # a difference within the tolerance counts as none (a quantised sensor)
            dd = np.sign(dd) * np.maximum(np.abs(dd) - depth_tol, 0.0)
    return d, ok, dd, okd


def _rho(x, c):
    return x * x / (c * c + x * x)  # eq. 17: rho_c(x) = x^2 / (c^2 + x^2)


def rgbd_cost(device, tf, rgb, depth, gray, depth_image, camera, out_total, out_rgb, out_depth, *, lam, c_rgb, c_depth,
              depth_tol):  # fmt: skip
    d, ok, dd, okd = _terms(tf, rgb, depth, gray, depth_image, camera, lam, c_rgb, c_depth, depth_tol)
    eps_c = np.where(ok, _rho(d, c_rgb), 1.0).sum(axis=1)  # eq. 17 (invalid point: rho's limit 1)
    with np.errstate(invalid="ignore"):
        eps_d = np.where(okd, _rho(dd, c_depth), 1.0).sum(axis=1)  # eq. 18
    out_total[...] = (1.0 - lam) * eps_c + lam * eps_d  # eq. 19
    out_rgb[...] = eps_c
    out_depth[...] = eps_d


def rgbd_residuals(device, tf, rgb, depth, gray, depth_image, camera, out, *, lam, c_rgb, c_depth, depth_tol):
    d, ok, dd, okd = _terms(tf, rgb, depth, gray, depth_image, camera, lam, c_rgb, c_depth, depth_tol)
    w_c, w_d = np.sqrt(1.0 - lam), np.sqrt(lam)
    r = np.empty(d.shape, np.float64)
    rd = np.empty(dd.shape, np.float64)
    # the template's points are grouped by part; perm puts them back in the caller's order
    r[:, rgb["index"][rgb["parts"] + 1 :]] = np.where(
        ok, w_c * d / np.sqrt(c_rgb * c_rgb + d * d), w_c
    )  # eq. 20-21: r_i
    with np.errstate(invalid="ignore"):
        rd[:, depth["index"][depth["parts"] + 1 :]] = np.where(
            okd, w_d * dd / np.sqrt(c_depth * c_depth + dd * dd), w_d
        )  # eq. 20-21: r'_i
    out[:, : r.shape[1]] = r
    out[:, r.shape[1] :] = rd

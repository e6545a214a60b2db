"""NumPy: the landmark residuals of paper 003's bundle adjustment and their Jacobian
(gputrack/ops/face_bundle.py): the oracle of the device kernels, and the face tracker's host model."""

from __future__ import annotations

import numpy as np

from ...models.pose import rodrigues, rotation_coefficients, skew


def _rotations(r: np.ndarray):
    """(..., 3) Rodrigues vectors -> R (..., 3, 3) and the left Jacobian of SO(3) J_l (..., 3, 3):
    R(r + dr) = exp([J_l dr]x) R(r) + O(dr^2); both from the same coefficients and [r]x."""
    a, b, c = rotation_coefficients(r)
    K = skew(r)
    K2 = K @ K
    a, b, c = (v[..., None, None] for v in (a, b, c))
    eye = np.eye(3)
    return eye + a * K + b * K2, eye + b * K + c * K2


def geometry(model, x, R=None):
    """For parameter vectors x (B, P) of ``model`` (a :class:`gputrack.ops.face_bundle.LandmarkModel`)
    with n frames: R (B, n, 3, 3) (given or from the rvecs), the expression basis Bs (B, K, 3, A) of
    each identity, RX (B, n, K, 3) and Y = RX + t (B, n, K, 3) camera-frame points (eq. 4-5)."""
    K, A, S = model.K, model.A, model.S
    B, n = x.shape[0], (x.shape[1] - S) // (6 + A)
    fr = x[:, : n * (6 + A)].reshape(B, n, 6 + A)
    rv, tv, ex, s = fr[..., :3], fr[..., 3:6], fr[..., 6:], x[:, n * (6 + A) :]
    if R is None:
        R = rodrigues(rv)
    Bs = model.L0 + (s @ model.G.transpose(2, 0, 1, 3).reshape(S, K * 3 * A)).reshape(B, K, 3, A)  # eq. 4
    X = model.mean + (ex @ Bs.reshape(B, K * 3, A).transpose(0, 2, 1)).reshape(B, n, K, 3)  # eq. 4: M_i(a_i, s)
    RX = X @ R.transpose(0, 1, 3, 2)
    return R, Bs, RX, RX + tv[:, :, None, :]


def evaluate(model, frames, x: np.ndarray, jacobian: bool = True):
    """(B, P) float64 parameters (unscaled) -> (residuals (B, rows), Jacobian (B, rows, P) or None):
    matrix products on small stacks (``einsum`` and ``np.cross`` cost 2.6x as much a call here)."""
    K, A, S = model.K, model.A, model.S
    F = 6 + A
    B = x.shape[0]
    n = frames.n
    cam = model.camera
    fr = x[:, : n * F].reshape(B, n, F)
    R, Jl = _rotations(fr[..., :3]) if jacobian else (None, None)  # R from the same coefficients as J_l
    R, Bs, RX, Y = geometry(model, x, R)
    iz = 1.0 / np.maximum(Y[..., 2], model.min_depth)  # eq. 5: the projection
    uv = np.empty((*Y.shape[:-1], 2))
    uv[..., 0] = cam.fx * Y[..., 0] * iz + cam.cx
    uv[..., 1] = cam.fy * Y[..., 1] * iz + cam.cy
    sw = frames.sqrt_weights
    M = 2 * K * n
    r = ((uv - frames.target) * sw[..., None]).reshape(B, M)  # eq. 6 (weighted)
    if frames.prior is not None:
        r = np.concatenate([r, (x[:, n * F :] - frames.prior_mean) * frames.prior], axis=1)
    if not jacobian:
        return r, None
    a = sw * iz
    Dp = np.zeros((*Y.shape[:-1], 2, 3))  # (B, n, K, 2, 3) dm/dY, weighted
    Dp[..., 0, 0] = cam.fx * a
    Dp[..., 0, 2] = -cam.fx * Y[..., 0] * iz * a
    Dp[..., 1, 1] = cam.fy * a
    Dp[..., 1, 2] = -cam.fy * Y[..., 1] * iz * a
    DpR = Dp @ R[:, :, None]  # dm/dX
    frame = np.empty((B, n, K, 2, F))  # frame i's rows depend on frame i's parameters only
    frame[..., :3] = Dp @ (skew(-RX) @ Jl[:, :, None])  # d(RX)/dr = -[RX]x J_l(r)
    frame[..., 3:6] = Dp  # dY/dt = I
    frame[..., 6:] = DpR @ Bs[:, None]  # dY/da = R Bs
    P = n * F + S
    J = np.zeros((B, frames.rows, P))
    idx = np.arange(n)
    J[:, :M, : n * F].reshape(B, n, 2 * K, n, F)[:, idx, :, idx, :] = frame.reshape(B, n, 2 * K, F).transpose(1, 0, 2, 3)
    if S:  # dY/ds = R G a: (G a) (B, n, K, 3, S')
        ex = fr[..., 6:]
        Ga = (model.G.reshape(K * 3 * S, A) @ ex.transpose(0, 2, 1)).reshape(B, K, 3, S, n)
        J[:, :M, n * F :] = (DpR @ Ga.transpose(0, 4, 1, 2, 3)).reshape(B, M, S)
    if frames.prior is not None:
        J[:, M + np.arange(S), n * F + np.arange(S)] = frames.prior
    return r, J


def landmark_residuals(device, points, model, frames, consts, values, jacobian, out):
    """The op on the NumPy device (``consts`` and ``values``, the device kernels' packed constants, are
    not used): points (B, P) scaled by ``frames.scale`` into ``out`` (R, J)."""
    x = np.asarray(points, np.float64) * frames.scale
    r, J = evaluate(model, frames, x, jacobian)
    R_out, J_out = out
    R_out[...] = r
    if jacobian:
        np.multiply(J, frames.scale, out=J_out)

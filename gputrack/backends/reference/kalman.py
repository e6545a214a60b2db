"""NumPy reference of the batched Kalman filter ops (papers 001 and 002), vectorised over tracks.

Every function takes validated arrays (see :mod:`gputrack.ops.kalman`): x (T,n), P (T,n,n),
shared matrices as (n,n) or per-track ones as (T,n,n) (NumPy broadcasting covers both), and
computes in the dtype of x. Equation numbers refer to paper 001 (Hoshikawa et al.) unless noted.

Numerics shared with the Taichi and OpenCL kernels (keep them in step):
- P and R are symmetrised, (A + A^T)/2, before use; results are symmetrised on output.
- The innovation covariance S = H P H^T + R is factorised by Cholesky, S = L L^T. A pivot
  d_j <= PD_EPS_FACTOR * eps * S_jj (eps of the dtype), or a non-finite one, marks S as not
  positive definite: that track is left unchanged and flagged (status NOT_PD).
- The gain is never formed from an inverse: K^T = S^-1 (H P) by two triangular solves.
- Covariance update in Joseph form, P+ = (I - K H) P (I - K H)^T + K R K^T, which stays
  symmetric positive semi-definite and is the exact covariance for *any* gain, hence also for
  the scaled gain s K of paper 002 (eq. 4-6). It is evaluated as B = P - K (H P), then
  P+ = B - (B H^T) K^T + K R K^T (the same product, without forming I - K H).
"""

from __future__ import annotations

import numpy as np

from ...abi import KalmanStatus

# status codes of an update (gputrack/abi.py)
UPDATED, SKIPPED, NOT_PD, BAD_DEPTH = (int(s) for s in (KalmanStatus.UPDATED, KalmanStatus.SKIPPED,
                                                         KalmanStatus.NOT_PD, KalmanStatus.BAD_DEPTH))
PD_EPS_FACTOR = 4.0


def _t(A):
    return np.swapaxes(A, -1, -2)


def _sym(A):
    return 0.5 * (A + _t(A))


def _mv(A, v):
    """A (n,k) or (T,n,k) times v (T,k) -> (T,n)."""
    return np.einsum("...ij,...j->...i", A, v)


def cholesky(S):
    """Batched Cholesky of S (T,m,m): (L (T,m,m), ok (T,) bool); L is usable (finite) where not ok."""
    T, m, _ = S.shape
    L = np.zeros_like(S)
    ok = np.ones(T, dtype=bool)
    eps = np.finfo(S.dtype).eps
    for j in range(m):
        d = S[:, j, j] - np.sum(L[:, j, :j] * L[:, j, :j], axis=1)
        good = np.isfinite(d) & (d > PD_EPS_FACTOR * eps * S[:, j, j])
        ok &= good
        d = np.sqrt(np.where(good, d, 1.0)).astype(S.dtype)
        L[:, j, j] = d
        for i in range(j + 1, m):
            L[:, i, j] = (S[:, i, j] - np.sum(L[:, i, :j] * L[:, j, :j], axis=1)) / d
    return L, ok


def forward(L, B):
    """Solve L W = B for lower-triangular L (T,m,m), B (T,m,k)."""
    W = np.empty_like(B)
    m = L.shape[1]
    for i in range(m):
        W[:, i] = (B[:, i] - np.einsum("tk,tkc->tc", L[:, i, :i], W[:, :i])) / L[:, i, i, None]
    return W


def backward(L, W):
    """Solve L^T X = W for lower-triangular L (T,m,m), W (T,m,k)."""
    X = np.empty_like(W)
    m = L.shape[1]
    for i in reversed(range(m)):
        X[:, i] = (W[:, i] - np.einsum("tk,tkc->tc", L[:, i + 1 :, i], X[:, i + 1 :])) / L[:, i, i, None]
    return X


def _into(out, results):
    """Copy results into caller-provided arrays (which may alias the inputs)."""
    if out is None:
        return results
    for dst, src in zip(out, results):
        np.copyto(dst, src)
    return tuple(out[: len(results)])


def kf_predict(device, x, P, F, Q, out=None, pats=None):
    """x' = F x, P' = F P F^T + Q (eq. 2-3: x_{k+1} = Phi x_k + Gamma w_k)."""
    x1 = _mv(F, x)  # eq. 2
    P1 = _sym(F @ _sym(P) @ _t(F) + _sym(Q))  # eq. 2, covariance of Phi x + w
    return _into(out, (x1.astype(x.dtype, copy=False), P1.astype(x.dtype, copy=False)))


def _update(x, P, y, H, R, valid, gain_scale):
    """Shared linear/linearised update given the innovation y (T,m) and observation matrix H.

    valid (T,) bool: tracks to update (others are returned unchanged). Returns (x, P, pd_ok).
    """
    T = x.shape[0]
    Ps = _sym(P)
    Rs = _sym(R)
    Hb = np.broadcast_to(H, (T,) + H.shape[-2:])
    Rb = np.broadcast_to(Rs, (T,) + Rs.shape[-2:])
    HP = Hb @ Ps  # (T,m,n)
    S = HP @ _t(Hb) + Rb  # innovation covariance H P H^T + R
    L, pd_ok = cholesky(S)
    with np.errstate(all="ignore"):  # tracks not updated may hold garbage; they are masked below
        x1, P1 = _gain_and_joseph(x, Ps, y, Hb, Rb, HP, L, gain_scale)
    do = valid & pd_ok
    x_out = np.where(do[:, None], x1, x).astype(x.dtype, copy=False)
    P_out = np.where(do[:, None, None], P1, P).astype(x.dtype, copy=False)
    return x_out, P_out, pd_ok


def _gain_and_joseph(x, Ps, y, Hb, Rb, HP, L, gain_scale):
    Kt = backward(L, forward(L, HP))  # K^T = S^-1 H P: K = P H^T S^-1 (Kalman gain)
    K = _t(Kt)
    if gain_scale is not None:
        K = K * gain_scale[:, None, None]  # paper 002 eq. 4-6: scaled gain s K
    x1 = x + _mv(K, y)  # x+ = x + K y
    B = Ps - K @ HP  # (I - K H) P
    P1 = B - (B @ _t(Hb)) @ _t(K) + K @ Rb @ _t(K)  # Joseph form (I-KH) P (I-KH)^T + K R K^T
    return x1, _sym(P1)


def _prologue(x, P, z, mask, F, Q):
    """Predict first if F, Q are given; the per-track 'valid' mask (mask and no NaN in z)."""
    if F is not None:
        x, P = kf_predict(None, x, P, F, Q)
    valid = np.isfinite(z).all(axis=1)  # NaN (non-finite) observation = missing
    if mask is not None:
        valid &= mask.astype(bool)
    return x, P, valid


def _status(valid, extra_fail, extra_code, pd_ok):
    st = np.full(valid.shape, UPDATED, dtype=np.uint8)
    st[~pd_ok] = NOT_PD
    if extra_fail is not None:
        st[extra_fail] = extra_code
    st[~valid] = SKIPPED
    return st


def kf_update(device, x, P, z, H, R, mask=None, gain_scale=None, F=None, Q=None, out=None, pats=None):
    """Linear update: y = z - H x, K = P H^T S^-1, Joseph-form covariance. Returns (x, P, status)."""
    x, P, valid = _prologue(x, P, z, mask, F, Q)
    zf = np.where(np.isfinite(z), z, 0).astype(x.dtype)
    y = zf - _mv(H, x)  # innovation
    xo, Po, pd_ok = _update(x, P, y, H, R, valid, gain_scale)
    return _into(out, (xo, Po, _status(valid, None, 0, pd_ok)))


def stereo_observation(x, f, b, cx, cy):
    """h(x) (T,3) and its Jacobian (T,3,6) at x (T,6) = [x xdot y ydot z zdot] (eq. 1, 4-6)."""
    T = x.shape[0]
    X, Y, Z = x[:, 0], x[:, 2], x[:, 4]
    Zs = np.where(Z > 0, Z, 1).astype(x.dtype)  # failures are masked by the caller
    h = np.stack([f * X / Zs + cx, f * Y / Zs + cy, f * b / Zs], axis=1)  # eq. 6 (+ principal point)
    J = np.zeros((T, 3, 6), dtype=x.dtype)
    J[:, 0, 0] = f / Zs  # du/dx
    J[:, 0, 4] = -f * X / Zs**2  # du/dz
    J[:, 1, 2] = f / Zs  # dv/dy
    J[:, 1, 4] = -f * Y / Zs**2  # dv/dz
    J[:, 2, 4] = -f * b / Zs**2  # dd/dz
    return h.astype(x.dtype), J


def ekf_update_stereo(
    device, x, P, z, R, f, b, cx=0.0, cy=0.0, mask=None, gain_scale=None, F=None, Q=None, out=None, pats=None
):
    """Stereo EKF update (eq. 4-6): z = [u v d], Jacobian at the (predicted) state."""
    x, P, valid = _prologue(x, P, z, mask, F, Q)
    dt = x.dtype.type
    f, b, cx, cy = dt(f), dt(b), dt(cx), dt(cy)
    bad_depth = ~(x[:, 4] > 0)
    h, J = stereo_observation(x, f, b, cx, cy)
    zf = np.where(np.isfinite(z), z, 0).astype(x.dtype)
    y = zf - h  # eq. 5: z = f(x) + v
    xo, Po, pd_ok = _update(x, P, y, J, R, valid & ~bad_depth, gain_scale)
    return _into(out, (xo, Po, _status(valid, bad_depth & valid, BAD_DEPTH, pd_ok | bad_depth)))


def mahalanobis(device, x, P, H, R, z, out=None, pats=None):
    """(T,D) squared Mahalanobis distances (z_d - H x)^T S^-1 (z_d - H x), S = H P H^T + R (eq. 8).

    inf for a track whose S is not positive definite.
    """
    T = x.shape[0]
    Hb = np.broadcast_to(H, (T,) + H.shape[-2:])
    S = Hb @ _sym(P) @ _t(Hb) + _sym(np.broadcast_to(R, (T,) + R.shape[-2:]))
    L, ok = cholesky(S)
    r = z[None, :, :] - _mv(Hb, x)[:, None, :]  # (T,D,m) residuals y_i - xi_j
    W = forward(L, np.swapaxes(r, 1, 2))  # (T,m,D): L^-1 r
    d2 = np.sum(W * W, axis=1)
    d2[~ok] = np.inf
    return _into(None if out is None else (out,), (d2.astype(x.dtype, copy=False),))[0]

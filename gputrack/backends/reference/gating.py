"""NumPy reference of :mod:`gputrack.ops.gating`: the dense distances of
:func:`gputrack.backends.reference.kalman.mahalanobis` (paper 001 eq. 8), then the pairs below the
threshold, per track in ascending detection order. ``sorted_z`` changes nothing here (every
detection is scanned; the device kernels use it to skip detections that cannot be gated)."""

from __future__ import annotations

import numpy as np

from . import kalman as _kalman


def gate_pairs(device, x, P, H, R, z, D, threshold, active, sorted_z, out):
    T = x.shape[0]
    K = out[1].shape[1] if out is not None else 16
    Ps = 0.5 * (P + np.swapaxes(P, 1, 2))
    trace = np.einsum("ak,tkl,al->t", H, Ps, H).astype(x.dtype)  # trace(H P H^T)
    count = np.zeros(T, np.int32)
    det = np.full((T, K), -1, np.int32)
    d2 = np.full((T, K), np.inf, x.dtype)
    if D > 0:
        full = _kalman.mahalanobis(None, x, P, H, R, z[:D])  # (T, D), inf where S is not positive definite
        inside = full < x.dtype.type(threshold)  # gated: d2 < threshold
        if active is not None:
            inside &= active.astype(bool)[:, None]
        count[:] = inside.sum(axis=1)
        rank = np.cumsum(inside, axis=1) - 1  # position of each gated pair in its track's list
        keep = inside & (rank < K)
        t, d = np.nonzero(keep)
        det[t, rank[t, d]] = d
        d2[t, rank[t, d]] = full[t, d]
    result = (count, det, d2, trace)
    if out is None:
        return result
    for dst, src in zip(out, result):
        np.copyto(dst, src)
    return tuple(out)

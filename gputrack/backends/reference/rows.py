"""NumPy reference of :mod:`gputrack.ops.rows`: fancy-index assignment."""

from __future__ import annotations


def scatter_rows(device, dst, index, src, K):
    """dst[index[k]] = src[k] for k < K (index distinct, validated by the op); src (1, ...)
    broadcasts."""
    dst[index[:K]] = src[:K] if src.shape[0] > 1 else src
    return dst

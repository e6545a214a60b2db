"""NumPy reference of :mod:`gputrack.ops.rows`: fancy-index assignment."""

from __future__ import annotations


def scatter_rows(device, dst, index, src):
    """dst[index[k]] = src[k] (index distinct, validated by the op); src (1, ...) broadcasts."""
    dst[index] = src
    return dst

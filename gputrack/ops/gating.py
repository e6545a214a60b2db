"""Mahalanobis gating that returns only the gated pairs: ``gate_pairs``.

Multi-target tracking (papers 001 and 002) gates every track against every detection and then
associates only the pairs inside the gate. :func:`gputrack.ops.mahalanobis` returns the dense
(T, D) distance matrix, which for 1000 tracks x 1000 detections is 4 MB to download and scan on
the host every frame; ``gate_pairs`` keeps that scan on the device and returns, per track, the
detections inside its gate (at most ``max_pairs`` of them, and how many there were)::

    g = gate_pairs(device, x, P, H, R, z, threshold, active=active, max_pairs=16)
    g.count (T,) int32      detections with d2 < threshold, per track (may exceed max_pairs)
    g.det   (T, K) int32    the first min(count, K) of them, ascending detection index
    g.d2    (T, K) float    their squared Mahalanobis distances (dtype of x)
    g.trace (T,) float      trace(H P H^T) per track: its position variance in measurement space

Shapes: x (T,n), P (T,n,n), H (m,n) and R (m,m) shared by all tracks, z (D,m) detections,
``active`` (T,) uint8 or bool (0: a free slot, never gated; None: every track). Distances are
those of :func:`gputrack.ops.mahalanobis` (paper 001 eq. 8): d2 = r^T S^-1 r, r = z - H x,
S = H Ps H^T + Rs with Ps, Rs symmetrised, S factorised by Cholesky (a pivot d_j <= 4 eps S_jj
marks S not positive definite: that track gates nothing), d2 = |L^-1 r|^2. A pair is gated when
d2 < threshold (``threshold`` is cast to the dtype of x first, on every backend). Columns at or
beyond ``count[t]`` are unspecified.

``sorted_z=True`` promises that z is sorted by its first coordinate (non-decreasing): the device
kernels then visit, per track, only the detections with |z_0 - (H x)_0| <= sqrt(threshold S_00)
(a binary search and a sweep), which is exact — a detection outside that strip cannot have
d2 < threshold, since r_0^2 / S_00 <= r^T S^-1 r — and turns the T x D scan into about T x (the
detections in a strip) for a sparse crowd. The returned indices are indices into the sorted z.
A NumPy z is checked to be sorted (ValueError otherwise); a device z is trusted. The NumPy
reference always scans every detection (the same pairs).

``out=(count, det, d2, trace)``: arrays of the device to write into (their K is the det array's
second dimension; ``max_pairs`` is then ignored). Every backend returns the same pairs as the
NumPy reference (up to distances within rounding of the threshold).

Validation: shapes and dtypes, 1 <= n <= 12, 1 <= m <= 6, a positive finite threshold,
max_pairs >= 1, finite NumPy z (a device z is not inspected; a NaN detection gates nothing).
T = 0 or D = 0 returns counts of 0 (and the traces).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..device import DeviceArray, as_host_array
from . import backend_module
from ..uploads import constant
from ._args import FLOAT, arg, check_device, out_arrays, real

__all__ = ["GatedPairs", "gate_pairs"]

MAX_N = 12
MAX_M = 6


class GatedPairs(NamedTuple):
    """Result of :func:`gate_pairs`: count (T,) int32, det (T,K) int32, d2 (T,K), trace (T,)."""

    count: object
    det: object
    d2: object
    trace: object


def _shared(device, A, name, shape, dims, dt):
    A = getattr(A, "array", A)  # a SharedMatrix (gputrack.ops.kalman.shared_matrix): its device array
    if getattr(A, "ndim", np.ndim(A)) != 2:
        shp = tuple(getattr(A, "shape", np.shape(A)))
        raise ValueError(f"{name}: expected a shared matrix of shape ({shape[0]}, {shape[1]}), got {shp}")
    return arg(device, A, name, shape, dims, dtype=dt, cast=True)


def gate_pairs(device, x, P, H, R, z, threshold, *, active=None, max_pairs=16, sorted_z=False, n_z=None,
               out=None) -> GatedPairs:  # fmt: skip
    """The detections inside each track's Mahalanobis gate (see the module for shapes and rules).

    ``n_z``: only the first n_z rows of z are detections (default: all), so that a caller can
    upload every frame's detections into one buffer of a fixed number of rows."""
    device = check_device(device)
    dims: dict = {}
    x = arg(device, x, "x", ("T", "n"), dims, dtype=FLOAT)
    dt = x.dtype
    if not 1 <= dims["n"] <= MAX_N:
        raise ValueError(f"x: expected a state size n between 1 and {MAX_N}, got n={dims['n']}")
    P = arg(device, P, "P", ("T", "n", "n"), dims, dtype=dt, cast=True)
    z_host = None if isinstance(z, DeviceArray) else as_host_array(z, "z")
    z = arg(device, z, "z", ("D", "m"), dims, dtype=dt, cast=True)
    if not 1 <= dims["m"] <= MAX_M:
        raise ValueError(f"z: expected an observation size m between 1 and {MAX_M}, got m={dims['m']}")
    H = _shared(device, H, "H", ("m", "n"), dims, dt)
    R = _shared(device, R, "R", ("m", "m"), dims, dt)
    thr = real("threshold", threshold, positive=True)
    if active is not None:
        if not isinstance(active, DeviceArray) and as_host_array(active, "active").dtype == np.bool_:
            active = as_host_array(active, "active").astype(np.uint8)
        active = arg(device, active, "active", ("T",), dims, dtype=np.uint8)
    D = dims["D"]
    if n_z is not None:
        if isinstance(n_z, bool) or not isinstance(n_z, (int, np.integer)) or not 0 <= n_z <= D:
            raise ValueError(f"n_z: expected an integer in [0, {D}] (rows of z), got {n_z!r}")
        D = int(n_z)
    if sorted_z and z_host is not None and D > 1:
        col = z_host[:D, 0]
        if (np.diff(col) < 0).any():
            i = int(np.argmax(np.diff(col) < 0))
            raise ValueError(f"z: expected rows sorted by z[:, 0] (sorted_z=True), got z[{i + 1}, 0] < z[{i}, 0]")
    T = dims["T"]
    if out is None:
        if isinstance(max_pairs, bool) or not isinstance(max_pairs, (int, np.integer)) or max_pairs < 1:
            raise ValueError(f"max_pairs: expected a positive integer, got {max_pairs!r}")
        K = int(max_pairs)
    else:
        if not isinstance(out, (tuple, list)) or len(out) != 4:
            raise TypeError("out: expected a tuple of 4 arrays (count, det, d2, trace) or None, got "
                            f"{type(out).__name__}")
        K = int(out[1].shape[1]) if getattr(out[1], "ndim", 0) == 2 and out[1].shape[1] >= 1 else -1
        if K < 1:
            raise ValueError(f"out det: expected shape (T={T}, K >= 1), got {tuple(getattr(out[1], 'shape', ()))}")
    specs = (("count", (T,), np.dtype(np.int32)), ("det", (T, K), np.dtype(np.int32)), ("d2", (T, K), dt),
             ("trace", (T,), dt))  # fmt: skip
    out = out_arrays(device, out, specs)
    if T == 0:
        return GatedPairs(*out)
    if D == 0 and device.backend != "numpy":  # the kernels still compute the traces; z is never read
        z = constant(device, np.zeros((1, dims["m"]), dt))
    be = backend_module(device, "gating")
    return GatedPairs(*be.gate_pairs(device, x, P, H, R, z, D, dt.type(thr), active, bool(sorted_z), out))

"""Observation points to groups, and each group's moments, in one call: ``assign_points``.

Paper 001 follows groups of people by the 3D points of their KLT tracks. Every frame each point
y_i (position, with velocity lambda_i) is tested against every group j (mean xi_j, velocity v_j
from the group's state x = [x xdot y ydot z zdot], eq. 1, and the group's spread Sigma_j, eq. 7):

- gating, eq. 8: the point may join group j if (y_i - xi_j)^T Sigma_p,j^-1 (y_i - xi_j) < gamma,
  Sigma_p the position block of Sigma;
- tie-break, eq. 9-11: among the groups that qualify the point joins the one with the largest
  m_total = m_p m_v = k_p N(y_i; xi_j, Sigma_p,j) k_v N(lambda_i; v_j, Sigma_v,j) (Sigma_v the
  velocity block). k_p, k_v and the 2 pi factors are the same for every group and drop out; a
  group whose velocity block is not positive definite contributes m_p only. Exact ties go to the
  lowest slot.

Then the moments of each group's points, the observation of the group's update: ``counts`` (T,)
int32, ``mean`` (T, 6) the mean position and velocity of its points in state order, ``cov``
(T, 6, 6) their population covariance in state order (cov(C_y) of eq. 7). A group with no point
gets the group's own mean and a zero covariance (never NaN).

Shapes: points, velocities (N, 3) float32 (mm, mm per frame); means (T, 6); spreads (T, 6, 6);
active (T,) uint8 (0 = an empty slot of the track table: never gated), optional. A point is used
only if its six values are finite (a NaN row is "no point", label -1); host arrays with +-inf
are rejected. ``n_points``: only the first n rows are points (a caller uploads each frame into
one buffer of fixed size); the labels after them are -1. ``out`` = an earlier result
(labels, counts, mean, cov) to write into.

Work: each point tests only the groups that can gate it (the groups sorted by x once; a point
visits the strip of groups within the largest gate radius in x, and skips a group farther than
sqrt(gamma trace Sigma_p), where d2 >= |d|^2 / trace >= gamma), then each group's points are
listed in point order (O(N)) and summed twice (mean, then covariance about it). One launch on
Taichi, five on OpenCL; no atomics: every backend sums a group's points in point order, so the
results are the same from run to run.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..device import DeviceArray
from . import backend_module
from ._args import arg, check_device, out_arrays

__all__ = ["PointGroups", "assign_points"]


class PointGroups(NamedTuple):
    """labels (N,) int32 (-1: no group), counts (T,) int32, mean (T, 6), cov (T, 6, 6)."""

    labels: object
    counts: object
    mean: object
    cov: object


def _gamma(gamma) -> float:
    if isinstance(gamma, bool) or not isinstance(gamma, (int, float, np.integer, np.floating)):
        raise TypeError(f"gamma: expected a positive number (squared Mahalanobis gate), got {type(gamma).__name__}")
    g = float(gamma)
    if not (np.isfinite(g) and g > 0):
        raise ValueError(f"gamma: expected a positive finite gate, got {gamma}")
    return g


def _finite_or_nan(device, a, name):
    """Host points may hold NaN rows ("no point"), never +-inf."""
    if isinstance(a, DeviceArray):
        return a
    h = np.asarray(a)
    if h.dtype.kind == "f" and np.isinf(h).any():
        bad = tuple(int(i) for i in np.argwhere(np.isinf(h))[0])
        raise ValueError(f"{name}: expected finite values or NaN rows (no point), got {h[bad]} at index {bad}")
    return a


def assign_points(device, points, velocities, means, spreads, gamma, *, active=None, n_points=None,
                  out=None) -> PointGroups:  # fmt: skip
    """Assign every point to at most one group and return the groups' moments (see the module)."""
    device = check_device(device)
    g = _gamma(gamma)
    dims: dict = {}
    points = arg(device, _finite_or_nan(device, points, "points"), "points", ("N", 3), dims, finite=False, cast=True)
    velocities = arg(device, _finite_or_nan(device, velocities, "velocities"), "velocities", ("N", 3), dims,
                     finite=False, cast=True)  # fmt: skip
    means = arg(device, means, "means", ("T", 6), dims, cast=True)
    spreads = arg(device, spreads, "spreads", ("T", 6, 6), dims, cast=True)
    if active is not None:
        active = arg(device, active, "active", ("T",), dims, dtype=np.uint8, cast=True)
    N, T = dims["N"], dims["T"]
    if n_points is None:
        n = N
    elif isinstance(n_points, bool) or not isinstance(n_points, (int, np.integer)) or not 0 <= n_points <= N:
        raise ValueError(f"n_points: expected an integer in [0, {N}] (rows of points), got {n_points!r}")
    else:
        n = int(n_points)
    out = PointGroups(*out_arrays(device, out, (("labels", (N,), np.int32), ("counts", (T,), np.int32),
                                                ("mean", (T, 6), np.float32), ("cov", (T, 6, 6), np.float32))))  # fmt: skip
    if T == 0:  # no group: every point unassigned
        if device.backend == "numpy":
            out.labels[:] = -1
        elif N:
            device.asarray(np.full(N, -1, np.int32), out=out.labels)
        return out
    backend_module(device, "point_groups").assign_points(device, points, velocities, means, spreads, active, g, n,
                                                         out)  # fmt: skip
    return out

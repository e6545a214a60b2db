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

from ..device import DeviceArray, as_host_array
from . import backend_module
from ._args import arg, check_device, out_arrays

__all__ = ["PointGroups", "assign_points", "group_constants", "group_frame"]


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
    h = as_host_array(a, name)
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
    n = _rows_used(n_points, N)
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


# -- a whole frame of the group table: group_frame ------------------------------------------------

#: columns of the group table of :func:`group_frame` (float32 rows, one per slot)
X, P, SIGMA, ACTIVE = 0, 6, 42, 78  # state (6), Kalman covariance (36), spread (36, eq. 7), 1 = live
COUNT, MEAN, SEEN, NCAND, CAND = 79, 80, 86, 87, 88  # written by each frame (see group_frame)
MAX_CAND = 4  #: merge candidates listed per group (NCAND may be larger: then the list is cut)
COLUMNS = 96
#: the constants vector of :func:`group_constants`
CONSTANTS = 88


def group_constants(F, Q, R, *, f, b, cx, cy, gamma, alpha_s, min_points, min_spread, surface_offset,
                    merge_gamma) -> np.ndarray:  # fmt: skip
    """The constants of :func:`group_frame` as one (88,) float32 vector (uploaded once): the
    motion model F, Q (6, 6), the observation variances R (3,) of (u, v, d), the camera (f px,
    b mm, cx, cy), the gate ``gamma`` (eq. 8), the spread weight ``alpha_s`` (eq. 7), the points a
    group needs to be updated (``min_points``), ``min_spread`` (2,) standard deviations (mm,
    mm/frame) added to the spreads' position and velocity blocks for gating and the merge test, the
    ``surface_offset`` (mm, along each viewing ray) and the merge regions' ``merge_gamma``."""
    c = np.zeros(CONSTANTS, np.float64)
    F, Q, R, ms = (np.asarray(a, np.float64) for a in (F, Q, R, min_spread))
    if F.shape != (6, 6) or Q.shape != (6, 6) or R.shape != (3,) or ms.shape != (2,):
        raise ValueError(f"group_constants: expected F, Q (6, 6), R (3,), min_spread (2,), got {F.shape}, {Q.shape}, "
                         f"{R.shape}, {ms.shape}")  # fmt: skip
    c[0:36], c[36:72], c[72:75] = F.ravel(), Q.ravel(), R
    c[75:86] = (f, b, cx, cy, gamma, alpha_s, min_points, ms[0] ** 2, ms[1] ** 2, surface_offset, merge_gamma)
    if not np.isfinite(c).all():
        raise ValueError("group_constants: expected finite constants")
    return c.astype(np.float32)


def group_frame(device, table, points, velocities, constants, *, n_points=None, labels=None):
    """One frame of paper 001's group table on the device, in place (the tracking core of
    :class:`gputrack.trackers.groups.GroupTracker`; one launch on Taichi).

    ``table`` (T, 96) float32, one row per slot: x (6) = [x xdot y ydot z zdot] at column 0, the
    Kalman covariance P (6 x 6, row-major) at 6, the spread Sigma (6 x 6, eq. 7) at 42, active (1 =
    a live group, 0 = a free slot) at 78; ``points`` (N, 3) and ``velocities`` (N, 3) float32
    (mm, mm per frame; a row with a NaN in either is no point; only the first ``n_points`` rows are
    points); ``constants`` (88,) float32 from :func:`group_constants`; ``labels`` an (N,) int32
    array to write into. Per frame:

    1. every slot predicted: x = F x, P = F P F^T + Q (eq. 2-3, as :func:`kf_predict`);
    2. each point moved ``surface_offset`` mm further along its viewing ray, then gated and
       assigned as :func:`assign_points` does against the live groups, with the spreads Sigma +
       diag(min_spread^2) (eq. 8-11): ``labels``, and each group's count, mean and covariance;
    3. a live group with at least ``min_points`` points whose mean lies in front of the camera is
       *seen*: its spread follows eq. 7, Sigma = alpha_s Sigma + (1 - alpha_s) cov (then
       symmetrised), and the stereo EKF updates it from its points' mean as z = [u v d] (eq. 4-6,
       as :func:`ekf_update_stereo`: Joseph form; an innovation covariance that is not positive
       definite, or a state behind the camera, leaves the prediction);
    4. the merge pre-test (eq. 13): pairs of live groups whose bounding spheres of the merge
       regions meet in position *and* in velocity (radius sqrt(merge_gamma lambda), lambda an
       upper bound of the largest eigenvalue of the block of Sigma + diag(min_spread^2): the
       smaller of its trace and its largest absolute row sum), centred on the updated position
       and on the points' mean velocity (the state's where the group has fewer than min_points
       points). The exact test of those few pairs is the caller's.

    Written into the table: x, P, Sigma; the count at column 79, the points' mean (6, state order)
    at 80, seen (0/1) at 86, the number of merge candidates j > i at 87 and the first 4 of them
    (slots, ascending) at 88. Returns (table, labels)."""
    device = check_device(device)
    dims: dict = {}
    table = arg(device, table, "table", ("T", COLUMNS), dims)
    points = arg(device, _finite_or_nan(device, points, "points"), "points", ("N", 3), dims, finite=False, cast=True)
    velocities = arg(device, _finite_or_nan(device, velocities, "velocities"), "velocities", ("N", 3), dims,
                     finite=False, cast=True)  # fmt: skip
    constants = arg(device, constants, "constants", (CONSTANTS,), dims)
    N, T = dims["N"], dims["T"]
    n = _rows_used(n_points, N)
    labels = out_arrays(device, None if labels is None else (labels,), (("labels", (N,), np.int32),))[0]
    if T == 0:
        raise ValueError("table: expected at least one slot (T >= 1), got 0")
    backend_module(device, "point_groups").group_frame(device, table, points, velocities, constants, n, labels)
    return table, labels


def _rows_used(n_points, N: int) -> int:
    """The rows of ``points`` in use: ``n_points`` (an integer in [0, N]), all N when None."""
    if n_points is None:
        return N
    if isinstance(n_points, bool) or not isinstance(n_points, (int, np.integer)) or not 0 <= n_points <= N:
        raise ValueError(f"n_points: expected an integer in [0, {N}] (rows of points), got {n_points!r}")
    return int(n_points)

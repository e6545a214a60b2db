"""Clusters of points: ``radius_components`` and ``dbscan``, one primitive for two trackers.

- Paper 001 eq. 12 (initial grouping): observation points whose search regions overlap are
  linked, and a linked set with enough points starts a group: the connected components of the
  radius graph of the 3D points (two 1 m regions overlap when the points are within 2 m: pass
  ``radius=2.0``; the size threshold is the caller's, e.g. ``np.bincount`` of the labels).
- Paper 002 sec. 4.2 (segments): DBSCAN of the 2D points (the vertical axis dropped)::

    labels = radius_components(device, points, radius)            # (N,) int32
    labels = dbscan(device, points, eps, min_samples)              # (N,) int32, -1 = noise

Shapes: ``points`` (N, 2) or (N, 3) float32; a row with a NaN in it is not a point (label -1;
it is nobody's neighbour). ``n_points``: only the first n rows are points (default: all), so a
caller can upload every frame into one buffer of a fixed size; the rows after them are not read
and get label -1. ``out``: an (N,) int32 array of the device to write into.

Neighbours: points i and j are neighbours when d2 <= r2, with d = p_i - p_j, d2 = (d_0 d_0 +
d_1 d_1) + d_2 d_2 in float32 and r2 = float32(r)**2, on every backend, with no fused multiply-add
(OpenCL builds with FP_CONTRACT OFF; tests/test_clusters.py pins every backend on pairs exactly
on the radius, where a fused multiply-add would round d2 to the other side of r2). The exception is
taichi:cuda: Taichi's CUDA code generator lets LLVM contract every multiply-add, so there a pair
exactly on the radius is linked by the fused rounding of d2 (the test pins that too).

Labels are canonical, the same on every backend, so results compare exactly:

- ``radius_components``: each component is labelled by its smallest point index.
- ``dbscan``: a core point has at least ``min_samples`` neighbours within ``eps``, itself included
  (as scikit-learn counts). Clusters are the connected components of the core points, each
  labelled by its smallest core point index. A border point (not core, with a core neighbour)
  joins, of the clusters of its core neighbours, the one with the smallest label. That is the
  cluster scikit-learn gives it: ``sklearn.cluster.DBSCAN`` expands clusters in the order of their
  smallest core point and never relabels a point, so the first cluster to reach a border point is
  the one with the smallest core index. Other points are noise (-1). :func:`compact_labels` maps
  the labels to 0..C-1 in increasing order, which is exactly scikit-learn's ``labels_``
  (radius_components is dbscan with ``min_samples=1``).

Device algorithm (Taichi and OpenCL): the points are binned into a hashed uniform grid by a
counting sort (per-bucket counts by atomic add, a scan, a scatter). The cell side is
r (1 - 1e-3) / sqrt(dim), so any two points of a cell are neighbours; a point's neighbour search
visits the cells of the box p +- r (1 + 1e-3), found from floor((p +- w) / side), so no neighbour is
missed whatever the rounding, and takes each candidate only in its own cell. Neighbour counts
(own cell first, stopping at min_samples) give the core points. The components come from a
concurrent union-find with min-label hooking: parent pointers only ever decrease (hooks and path
halving by atomic min, retried where another edge hooked a root first), so every root is its
component's smallest index. The core points of a cell join the cell's first core point; then each
cell is linked to each cell that can hold a neighbour: skipped when the two are connected already
or their bounding boxes are farther apart than r, else the first pair within r is united. It needs
no rounds to convergence: the whole op is one Taichi kernel launch (its stages are the kernel's
top-level loops) or one fixed sequence of OpenCL launches, with no host read-back, even for a path
graph of N points. Where float32 rounding of huge coordinates puts points farther apart than r in
one cell, that cell's bucket is linked pair by pair instead. taichi:vulkan, whose atomics are not
trusted (gputrack/backends/taichi/clusters.py), runs rounds of min-label hooking and pointer
jumping (8 per launch, a changed flag read back after each launch; about log2 of the longest path
in rounds).

Validation: points (N, 2) or (N, 3) float32 (TypeError for another dtype), no infinities in a
NumPy input (a device input is not inspected); radius / eps a positive finite real whose float32
square is a positive finite float32; min_samples an integer >= 1; n_points an integer in [0, N].
N = 0 (or n_points = 0) returns labels of -1.
"""

from __future__ import annotations

import numpy as np

from ..device import DeviceArray, as_host_array
from . import backend_module
from ._args import arg, check_device, compact, out_array, real, shape_of

__all__ = ["compact_labels", "dbscan", "radius_components"]


def _points(device, points):
    shape = tuple(shape_of(points, "points"))
    if len(shape) != 2 or shape[1] not in (2, 3):
        raise ValueError(f"points: expected shape (N, 2) or (N, 3), got {shape}")
    if shape[0] >= 2**31:
        raise ValueError(f"points: expected fewer than 2**31 rows (int32 labels), got {shape[0]}")
    if not isinstance(points, DeviceArray):
        device.check_alloc(shape, np.float32)  # before any value check reads the whole input
        host = compact(as_host_array(points, "points"))  # a broadcast view: each element once
        if host.dtype.kind == "f" and np.isinf(host).any():
            bad = tuple(int(i) for i in np.argwhere(np.isinf(host))[0])
            raise ValueError(f"points: expected finite coordinates or NaN rows (not a point), got {host[bad]} at {bad}")
    return arg(device, points, "points", (shape[0], shape[1]), {}, dtype=np.float32, finite=False)


def _radius(value, name):
    r = real(name, value, positive=True)
    r32 = np.float32(r)
    with np.errstate(over="ignore", under="ignore"):
        r2 = np.float32(r32 * r32)
    if not (np.isfinite(r) and r > 0 and np.isfinite(r2) and r2 > 0):
        raise ValueError(f"{name}: expected a positive finite distance (float32 square in (0, inf)), got {value!r}")
    return r2


def _n_points(n_points, N):
    if n_points is None:
        return N
    if isinstance(n_points, bool) or not isinstance(n_points, (int, np.integer)) or not 0 <= n_points <= N:
        raise ValueError(f"n_points: expected an integer in [0, {N}] (rows of points), got {n_points!r}")
    return int(n_points)


def _labels(device, out, N):
    return out_array(device, out, "out", (N,), np.int32)


def _fill(device, out, value):
    if device.backend == "numpy":
        out[:] = value
    else:
        device.asarray(np.full(out.shape, value, np.int32), out=out)
    return out


def radius_components(device, points, radius, *, n_points=None, out=None):
    """Connected components of the graph with an edge where ||p_i - p_j|| <= radius (see the
    module): labels (N,) int32, each component labelled by its smallest point index, -1 for NaN
    rows and rows at or beyond ``n_points``."""
    device = check_device(device)
    points = _points(device, points)
    r2 = _radius(radius, "radius")
    N = points.shape[0]
    n = _n_points(n_points, N)
    out = _labels(device, out, N)
    if n == 0:
        return _fill(device, out, -1)
    return backend_module(device, "clusters").radius_components(device, points, n, r2, out)


def dbscan(device, points, eps, min_samples, *, n_points=None, out=None):
    """DBSCAN (paper 002 sec. 4.2; see the module): labels (N,) int32, each cluster labelled by
    its smallest core point index, a border point in the cluster with the smallest label among its
    core neighbours' clusters, -1 for noise, NaN rows and rows at or beyond ``n_points``."""
    device = check_device(device)
    points = _points(device, points)
    r2 = _radius(eps, "eps")
    if isinstance(min_samples, bool) or not isinstance(min_samples, (int, np.integer)) or min_samples < 1:
        raise ValueError(f"min_samples: expected an integer >= 1, got {min_samples!r}")
    N = points.shape[0]
    n = _n_points(n_points, N)
    out = _labels(device, out, N)
    if n == 0:
        return _fill(device, out, -1)
    ms = int(min(int(min_samples), np.iinfo(np.int32).max))
    return backend_module(device, "clusters").dbscan(device, points, n, r2, ms, out)


def compact_labels(labels) -> np.ndarray:
    """Host helper: labels (N,) of :func:`radius_components` / :func:`dbscan` (NumPy or device
    array) renumbered 0..C-1 in increasing order of the canonical label, -1 kept. For dbscan this
    is exactly scikit-learn's ``DBSCAN(eps, min_samples).fit(points).labels_``."""
    from ..device import to_numpy

    lab = np.asarray(to_numpy(labels))
    if lab.ndim != 1 or lab.dtype.kind not in "iu":
        raise ValueError(f"labels: expected a 1-D integer array, got {lab.dtype.name} {lab.shape}")
    out = np.full(lab.shape, -1, np.int32)
    keep = lab >= 0
    if keep.any():
        _, inverse = np.unique(lab[keep], return_inverse=True)
        out[keep] = inverse
    return out

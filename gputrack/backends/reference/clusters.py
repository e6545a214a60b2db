"""NumPy/SciPy reference of :mod:`gputrack.ops.clusters`: the radius graph from a k-d tree,
filtered by the kernels' float32 distance test, then SciPy's connected components.

Conventions (gputrack/ops/clusters.py): a row with a NaN is not a point (label -1); two points
are neighbours when d2 = (dx*dx + dy*dy) + dz*dz, computed in float32 in that order, is <= r2
(r2 = float32(r)**2, given); a component (a cluster) is labelled by its smallest point index
(its smallest core point index).
"""

from __future__ import annotations

import numpy as np

#: the k-d tree is asked for the pairs within r * (1 + TREE_SLACK); the float32 test decides
TREE_SLACK = 1e-3


def _pairs(p, valid, r2):
    """(i, j) with i < j, both valid, d2(i, j) <= r2 (the kernels' float32 test, in their order)."""
    from scipy.spatial import cKDTree

    idx = np.flatnonzero(valid)
    if idx.size < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    r = float(np.sqrt(np.float64(r2))) * (1 + TREE_SLACK) + 1e-30
    pairs = cKDTree(p[idx].astype(np.float64)).query_pairs(r, output_type="ndarray")
    i, j = idx[pairs[:, 0]], idx[pairs[:, 1]]
    d = p[i] - p[j]  # float32
    d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]
    if p.shape[1] == 3:
        d2 = d2 + d[:, 2] * d[:, 2]
    keep = d2 <= r2  # paper 001 eq. 12: linked when the search regions overlap
    return i[keep], j[keep]


def _min_index_components(n, i, j, members):
    """Label of each member = the smallest member index of its component (edges i-j among
    members); -1 for the rest."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    labels = np.full(n, -1, np.int32)
    if n == 0:
        return labels
    graph = coo_matrix((np.ones(i.size, np.int8), (i, j)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    first = np.full(comp.max() + 1, n, np.int64)
    where = np.flatnonzero(members)
    np.minimum.at(first, comp[where], where)  # smallest member index per component
    labels[where] = first[comp[where]]
    return labels


def radius_components(device, points, n, r2, out):
    p = points[:n]
    valid = ~np.isnan(p).any(axis=1)  # a row with a NaN is not a point
    i, j = _pairs(p, valid, r2)
    out[:] = -1
    out[:n] = _min_index_components(n, i, j, valid)
    return out


def dbscan(device, points, n, r2, min_samples, out):
    p = points[:n]
    valid = ~np.isnan(p).any(axis=1)
    i, j = _pairs(p, valid, r2)
    # core points: at least min_samples neighbours, the point itself included (paper 002 sec. 4.2)
    count = valid.astype(np.int64) + np.bincount(i, minlength=n) + np.bincount(j, minlength=n)
    core = valid & (count >= min_samples)
    both = core[i] & core[j]
    labels = _min_index_components(n, i[both], j[both], core)  # clusters: components of core points
    # border points: the smallest label among the clusters of their core neighbours
    border = np.full(n, np.iinfo(np.int32).max, np.int64)
    a = core[i] & ~core[j]  # i core, j not
    np.minimum.at(border, j[a], labels[i[a]])
    b = core[j] & ~core[i]
    np.minimum.at(border, i[b], labels[j[b]])
    reached = ~core & (border < np.iinfo(np.int32).max)
    labels[reached] = border[reached]
    out[:] = -1
    out[:n] = labels
    return out

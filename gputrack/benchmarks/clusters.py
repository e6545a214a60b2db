"""Clusters: DBSCAN of paper 002's 1024 2D points and the radius-graph components of paper 001's
~10 000 3D points (gputrack/ops/clusters.py).

Cases, each timed on the device with the NumPy reference (the same op on the ``numpy`` device)
and the peers in the same run:

- ``dbscan N=1024 2D``: pedestrians seen from above (paper 002: 1024 foreground points, the
  vertical axis dropped): 5 people as 2D blobs (std 0.12 m) in a 5 m x 5 m view plus 5 % clutter,
  eps = 0.1 m, min_samples = 8. Peer: ``sklearn.cluster.DBSCAN(eps, min_samples).fit``.
- ``radius_components N=10000 3D``: KLT points on a crowd (paper 001): 100 people, 100 points each
  on a 0.5 x 0.3 x 1.7 m box, scattered over 30 m x 30 m; radius = 2 m (1 m search regions that
  overlap). Peer: ``scipy.spatial.cKDTree(p).query_pairs(r, output_type='ndarray')`` +
  ``scipy.sparse.csgraph.connected_components`` (``scipy kd-tree+cc``).

The device figure has the points already on the device and the labels left there (``out=``);
``e2e`` uploads the points and downloads the labels. The labels are checked against the reference
once before timing.
"""

import sys

import numpy as np

from .harness import Case, bench_main

NAME = "clusters"


def add_arguments(parser):
    parser.add_argument("--dbscan-points", type=int, default=1024, help="points of the 2D DBSCAN case")
    parser.add_argument("--components-points", type=int, default=10_000, help="points of the 3D components case")


def pedestrians_2d(n, rng):
    """n 2D points: 5 people (std 0.12 m) in a 5 m x 5 m view, 5 % uniform clutter."""
    centres = rng.uniform(0.5, 4.5, (5, 2))
    k = n - n // 20
    p = centres[rng.integers(0, 5, k)] + 0.12 * rng.standard_normal((k, 2))
    clutter = rng.uniform(0.0, 5.0, (n - k, 2))
    return np.concatenate([p, clutter]).astype(np.float32)[rng.permutation(n)]


def crowd_3d(n, rng, per_person=100):
    """n 3D points on people (0.5 x 0.3 x 1.7 m boxes) scattered over 30 m x 30 m."""
    people = max(1, n // per_person)
    feet = np.column_stack([rng.uniform(0, 30, (people, 2)), np.zeros(people)])
    owner = np.arange(n) % people
    p = feet[owner] + rng.uniform(0, 1, (n, 3)) * np.array([0.5, 0.3, 1.7])
    return p.astype(np.float32)[rng.permutation(n)]


def _scipy_components(p, r):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = cKDTree(p).query_pairs(r, output_type="ndarray")
    n = p.shape[0]
    g = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(g, directed=False)[1]


def cases(device, args):
    from ..registry import device as get_device
    from ..ops.clusters import dbscan, radius_components

    ref = get_device("numpy")
    rng = np.random.default_rng(0)
    out = []

    n = args.dbscan_points
    p2 = pedestrians_2d(n, rng)
    eps, ms = 0.1, 8
    d2 = device.asarray(p2)
    lab2 = device.empty((n,), np.int32)
    want = dbscan(ref, p2, eps, ms)
    np.testing.assert_array_equal(device.to_numpy(dbscan(device, d2, eps, ms, out=lab2)), want)
    peers = {}
    try:
        from sklearn.cluster import DBSCAN

        peers["sklearn DBSCAN"] = lambda: DBSCAN(eps=eps, min_samples=ms).fit(p2).labels_
    except ImportError:  # the bench extra is not installed
        print("clusters: scikit-learn not installed, no DBSCAN peer", file=sys.stderr)
    out.append(
        Case(
            f"dbscan N={n} 2D",
            run=lambda: dbscan(device, d2, eps, ms, out=lab2),
            reference=lambda: dbscan(ref, p2, eps, ms),
            end_to_end=lambda: device.to_numpy(dbscan(device, p2, eps, ms)),
            peers=peers,
            params={"N": n, "dim": 2, "eps": eps, "min_samples": ms, "clusters": int(np.unique(want[want >= 0]).size)},
        )
    )

    n = args.components_points
    p3 = crowd_3d(n, rng)
    r = 2.0
    d3 = device.asarray(p3)
    lab3 = device.empty((n,), np.int32)
    want = radius_components(ref, p3, r)
    np.testing.assert_array_equal(device.to_numpy(radius_components(device, d3, r, out=lab3)), want)
    out.append(
        Case(
            f"radius_components N={n} 3D",
            run=lambda: radius_components(device, d3, r, out=lab3),
            reference=lambda: radius_components(ref, p3, r),
            end_to_end=lambda: device.to_numpy(radius_components(device, p3, r)),
            peers={"scipy kd-tree+cc": lambda: _scipy_components(p3, r)},
            params={"N": n, "dim": 3, "radius": r, "components": int(np.unique(want).size)},
        )
    )
    return out


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

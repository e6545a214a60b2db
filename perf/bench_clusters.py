#!/usr/bin/env python3
"""DBSCAN of 1024 2D points and radius-graph components of 10 000 3D points on every device
(see gputrack/benchmarks/clusters.py); scikit-learn and SciPy as peers."""

import sys

from gputrack.benchmarks.harness import bench_main
from gputrack.benchmarks import clusters

if __name__ == "__main__":
    sys.exit(bench_main(clusters))

#!/usr/bin/env python3
"""Paper 002's pedestrian tracker on every device: a 1280 x 960 depth frame -> tracks, 5 and 50
people, with a NumPy + scikit-learn front end and scikit-learn's DBSCAN as peers (see
gputrack/benchmarks/pedestrians.py)."""

import sys

from gputrack.benchmarks import pedestrians
from gputrack.benchmarks.harness import bench_main

if __name__ == "__main__":
    sys.exit(bench_main(pedestrians))

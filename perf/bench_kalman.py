#!/usr/bin/env python3
"""Batched Kalman predict + update + gating on every device (see gputrack/benchmarks/kalman.py)."""

import sys

from gputrack.benchmarks.harness import bench_main
from gputrack.benchmarks import kalman

if __name__ == "__main__":
    sys.exit(bench_main(kalman))

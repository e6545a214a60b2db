#!/usr/bin/env python3
"""Background median, foreground mask and depth points at 1280 x 960 on every device (see
gputrack/benchmarks/background.py)."""

import sys

from gputrack.benchmarks import background
from gputrack.benchmarks.harness import bench_main

if __name__ == "__main__":
    sys.exit(bench_main(background))

#!/usr/bin/env python3
"""Paper 001's group tracker on every device: the whole VGA frame and the tracking core (see gputrack/benchmarks/groups.py)."""

import sys

from gputrack.benchmarks import groups
from gputrack.benchmarks.harness import bench_main

if __name__ == "__main__":
    sys.exit(bench_main(groups))

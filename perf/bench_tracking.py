#!/usr/bin/env python3
"""The multi-target tracking cycle on every device, with Stone Soup as a peer (see gputrack/benchmarks/tracking.py)."""

import sys

from gputrack.benchmarks.harness import bench_main
from gputrack.benchmarks import tracking

if __name__ == "__main__":
    sys.exit(bench_main(tracking))

#!/usr/bin/env python3
"""Batched Levenberg-Marquardt on every device (see gputrack/benchmarks/lm.py)."""

import sys

from gputrack.benchmarks.harness import bench_main
from gputrack.benchmarks import lm

if __name__ == "__main__":
    sys.exit(bench_main(lm))

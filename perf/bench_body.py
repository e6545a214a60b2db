#!/usr/bin/env python3
"""Paper 000's body tracker per frame on every device (see gputrack/benchmarks/body.py)."""

import sys

from gputrack.benchmarks.harness import bench_main
from gputrack.benchmarks import body

if __name__ == "__main__":
    sys.exit(bench_main(body))

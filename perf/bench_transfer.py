#!/usr/bin/env python3
"""Upload/download of a 640x480 float32 frame on every device (see gputrack/benchmarks/transfer.py)."""

import sys

from gputrack.benchmarks.harness import bench_main
from gputrack.benchmarks import transfer

if __name__ == "__main__":
    sys.exit(bench_main(transfer))

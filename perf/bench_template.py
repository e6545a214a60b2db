#!/usr/bin/env python3
"""rgbd_cost, rgbd_residuals, patch_ncc and the particle helpers on every device (see gputrack/benchmarks/template.py)."""

import sys

from gputrack.benchmarks.harness import bench_main
from gputrack.benchmarks import template

if __name__ == "__main__":
    sys.exit(bench_main(template))

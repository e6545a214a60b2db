#!/usr/bin/env python3
"""Paper 003's face tracker on every device: one tracked 640 x 480 frame (PF N = 1000, NCC, re-localisation,
incremental bundle adjustment), the NCC scoring alone and one bundle-adjustment step with scipy as peer
(see gputrack/benchmarks/face.py)."""

import sys

from gputrack.benchmarks import face
from gputrack.benchmarks.harness import bench_main

if __name__ == "__main__":
    sys.exit(bench_main(face))

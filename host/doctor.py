#!/usr/bin/env python3
"""gputrack doctor: check that a deployment host can run gputrack.

A thin wrapper of ``gputrack doctor`` (the logic lives in :mod:`gputrack.doctor`, shipped in the
wheel): probes every backend, builds every OpenCL kernel on every OpenCL device, runs the
numerical self-tests per available device, prints a table and exits 1 on a problem.

    python host/doctor.py                       # check everything found
    python host/doctor.py --require taichi:cpu,opencl --json report.json
"""

import sys

from gputrack.doctor import main

if __name__ == "__main__":
    sys.exit(main())

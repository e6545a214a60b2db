#!/usr/bin/env python3
"""Time from process start to the body tracker's first estimate, with empty and with warm kernel caches.

Each run is a new Python process that imports gputrack, opens the device, makes the tracker and
tracks one simulated frame (the frame is rendered before the clock of the frame starts and its
time is left out: a recording's frame is read from a file). The first run uses empty caches (a
fresh temporary HOME and XDG_CACHE_HOME, so Taichi's offline cache, PoCL's kernel cache and
PyOpenCL's cache all start empty, as on a fresh install); the next ``--warm`` runs reuse them.
Per run: seconds from the process's start to gputrack imported, to the device open, to the
tracker made, and to the first estimate.

Pre-warming a deployment: ``python host/doctor.py`` builds every kernel of every backend into the
same caches (``~/.cache/taichi``, ``~/.cache/pocl``, ``~/.cache/pytools``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

CHILD = r"""
import time
t0 = time.perf_counter()
import sys, json
spec = sys.argv[1]
import numpy as np
import gputrack
t_import = time.perf_counter()
dev = gputrack.device(spec)
t_device = time.perf_counter()
from gputrack.sim import sequence
from gputrack.trackers.body import BodyTracker
seq = sequence(0, frames=2, seed=0)
frame = seq[1]
t_sim = time.perf_counter()
tracker = BodyTracker(dev, seq.params[0])
t_tracker = time.perf_counter()
est = tracker.track(frame.gray, frame.depth)
t_frame = time.perf_counter()
sim = t_sim - t_device
print(json.dumps({"import_s": t_import - t0, "device_s": t_device - t0, "tracker_s": t_tracker - t0 - sim,
                  "first_frame_s": t_frame - t0 - sim, "sim_left_out_s": sim,
                  "confidence": est.confidence}))
"""


def run(spec: str, env: dict) -> dict:
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", CHILD, spec], env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if out.returncode != 0:
        raise SystemExit(f"the run failed ({out.returncode}):\n{out.stderr[-4000:]}")
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res["process_wall_s"] = wall - res["sim_left_out_s"]
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", action="append", help="device spec (repeatable; default taichi:cpu and opencl)")
    ap.add_argument("--warm", type=int, default=2, help="runs with warm caches after the empty-cache run (2)")
    ap.add_argument("--json", default=None, help="write the figures as JSON")
    args = ap.parse_args(argv)
    specs = args.device or ["taichi:cpu", "opencl"]
    results = []
    for spec in specs:
        with tempfile.TemporaryDirectory(prefix="gputrack-first-frame-") as home:
            env = dict(os.environ, HOME=home, XDG_CACHE_HOME=os.path.join(home, ".cache"))
            for k in range(1 + args.warm):
                res = run(spec, env)
                res.update(device=spec, caches="empty" if k == 0 else "warm")
                results.append(res)
                print(f"{spec:14s} {res['caches']:5s}  import {res['import_s']:5.2f} s  device {res['device_s']:5.2f} s"
                      f"  tracker {res['tracker_s']:5.2f} s  first estimate {res['first_frame_s']:6.2f} s"
                      f"  (process {res['process_wall_s']:6.2f} s)", flush=True)  # fmt: skip
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""stereo_match on every device, VGA with a ~15 % foreground mask and on the whole image, with
cv2.StereoBM as a peer; then the accuracy table on the Middlebury motorcycle pair against
cv2.StereoBM and cv2.StereoSGBM (see gputrack/benchmarks/stereo.py). With ``--json FILE`` the
accuracy goes into the file's document as ``"accuracy"``; ``--cpu-time`` also prints the CPU time
per call of every case and of the peer (closer to the work done than the wall time on a shared
machine)."""

import argparse
import json
import sys
from pathlib import Path

from gputrack.benchmarks import stereo
from gputrack.benchmarks.harness import bench_main, environment


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--json")
    parser.add_argument("--no-accuracy", action="store_true")
    parser.add_argument("--accuracy-only", action="store_true")
    parser.add_argument("--cpu-time", action="store_true")
    parser.add_argument("--cpu-time-child")
    opts, _ = parser.parse_known_args(argv)
    if opts.cpu_time_child:  # one device in its own process (Taichi: one arch a process)
        from gputrack.registry import device

        sub = argparse.ArgumentParser()
        stereo.add_arguments(sub)
        args, _ = sub.parse_known_args(argv)
        for name, ms in stereo.cpu_times(device(opts.cpu_time_child), args).items():
            print(f"{opts.cpu_time_child:<16}{name:<60}{ms:9.1f} ms CPU a call")
        return 0
    rc = 0
    if not opts.accuracy_only:
        rc = bench_main(stereo, argv)
    if opts.cpu_time and not opts.accuracy_only:
        import subprocess

        devs = [a for i, a in enumerate(argv[1:]) if argv[i] == "--device"] or ["taichi:cpu", "opencl"]
        rest = [a for i, a in enumerate(argv) if a not in ("--cpu-time",) and (i == 0 or argv[i - 1] != "--json")
                and not (a == "--json")]  # fmt: skip
        print("\nCPU time per call (time.process_time, 10 calls after 3 warm-up):")
        for spec in devs:
            subprocess.run([sys.executable, __file__, *rest, "--cpu-time-child", spec], check=False)
    if opts.no_accuracy:
        return rc
    rows = stereo.accuracy()
    print("\nAccuracy: Middlebury motorcycle (scikit-image), 741 x 500, max_disparity 64")
    print(stereo.format_accuracy(rows))
    if opts.json and opts.json != "-":
        path = Path(opts.json)
        doc = json.loads(path.read_text()) if path.exists() and not opts.accuracy_only else environment()
        doc["accuracy"] = rows
        path.write_text(json.dumps(doc, indent=2) + "\n")
    return rc


if __name__ == "__main__":
    sys.exit(main())

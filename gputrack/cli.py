"""The ``gputrack`` command line: ``gputrack devices [--json]`` and ``gputrack bench``."""

from __future__ import annotations

import argparse
import json
import logging
import sys


def format_devices(infos) -> str:
    """The device table: spec, available or not, fp64, kind, name or reason."""
    w = max([16, *(len(d.spec) + 2 for d in infos)])
    head = f"{'spec':<{w}}{'available':<11}{'fp64':<6}{'kind':<6}name / reason"
    lines = [head, "-" * (w + 80)]
    for d in infos:
        what = d.name if d.available else d.reason
        lines.append(f"{d.spec:<{w}}{('yes' if d.available else 'no'):<11}{('yes' if d.fp64 else '-'):<6}{d.kind:<6}{what}")
    return "\n".join(lines)


def cmd_devices(args) -> int:
    import gputrack

    infos = gputrack.devices()
    if args.json:
        print(json.dumps([d.as_dict() for d in infos], indent=2))
    else:
        print(format_devices(infos))
    return 0


def cmd_bench(args) -> int:
    import importlib
    import pkgutil

    from . import benchmarks
    from .benchmark import bench_main

    names = sorted(m.name for m in pkgutil.iter_modules(benchmarks.__path__))
    ops = args.op or names
    unknown = sorted(set(ops) - set(names))
    if unknown:
        print(f"gputrack bench: unknown --op {', '.join(unknown)}; expected one of: {', '.join(names)}", file=sys.stderr)
        return 2
    status = 0
    for name in ops:
        argv = ["--min-time", str(args.min_time)]
        for spec in args.device or ["all"]:
            argv += ["--device", spec]
        if args.json:
            argv += ["--json", args.json if len(ops) == 1 else args.json.replace(".json", f".{name}.json")]
        status |= bench_main(importlib.import_module(f"gputrack.benchmarks.{name}"), argv)
    return status


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="gputrack", description="GPU-portable compute primitives for visual tracking")
    parser.add_argument("-v", "--verbose", action="store_true", help="log what gputrack does")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("devices", help="list every backend, available or not and why")
    p.add_argument("--json", action="store_true", help="print the table as JSON")
    p.set_defaults(func=cmd_devices)

    p = sub.add_parser("bench", help="time the ops on every device, with ratios against NumPy")
    p.add_argument("--device", action="append", help="spec, or 'all' (default; repeatable)")
    p.add_argument("--op", action="append", help="benchmark name (default: all; repeatable)")
    p.add_argument("--json", metavar="FILE", help="write results as JSON (FILE.<op>.json with several ops)")
    p.add_argument("--min-time", type=float, default=0.2, help="seconds of timed calls per figure")
    p.set_defaults(func=cmd_bench)

    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(name)s: %(message)s")
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())

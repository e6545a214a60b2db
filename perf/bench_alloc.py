#!/usr/bin/env python3
"""Fresh outputs vs out= on every device, and memory over many calls (see gputrack/benchmarks/alloc.py).

Prints the benchmark table, then per device the ratio fresh / out= of each pair (the caching
allocator's target: <= 1.3) and the memory check: process RSS and the device pool's held bytes
and allocation count before and after the calls. ``GPUTRACK_POOL_BYTES=0`` turns reuse off.
"""

import json
import sys
import tempfile
from pathlib import Path

from gputrack.benchmarks.harness import bench_main
from gputrack.benchmarks import alloc


def summary(doc: dict) -> str:
    lines = ["", f"{'device':<16}{'case':<34}{'fresh ms':>10}{'out= ms':>10}{'fresh/out=':>12}"]
    memory = []
    for run in doc["runs"]:
        rows = {r["case"]: r for r in run["results"]}
        spec = run["device"]["spec"]
        for name, row in rows.items():
            if name.endswith(" fresh") and name[: -len(" fresh")] + " out=" in rows:
                base = name[: -len(" fresh")]
                f, o = row["device"]["median_ms"], rows[base + " out="]["device"]["median_ms"]
                lines.append(f"{spec:<16}{base:<34}{f:>10.3f}{o:>10.3f}{f / o:>12.2f}")
            mem = row["params"].get("memory")
            if mem:
                b, a = mem["before"], mem["after"]
                mib = 2**20
                memory.append(
                    f"{spec:<16}{mem['calls']:>6} calls  RSS {b['rss_bytes'] / mib:8.1f} -> "
                    f"{a['rss_bytes'] / mib:8.1f} MiB"
                    f"  pool held {b['pool']['held_bytes'] / 2**20:7.2f} -> {a['pool']['held_bytes'] / 2**20:7.2f} MiB"
                    f"  allocations {b['pool']['allocated']} -> {a['pool']['allocated']}"
                    f"  reused {b['pool']['reused']} -> {a['pool']['reused']}"
                )
                trace = mem.get("rss_trace") or [a["rss_bytes"]]
                lo, hi = min(trace) / mib, max(trace) / mib
                memory.append(f"{'':<16}RSS at {len(trace)} points in between: {lo:.1f}-{hi:.1f} MiB")
    if memory:
        lines += ["", "memory check (kf_predict+kf_update and rgbd_cost, fresh outputs each call):", *memory]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    given = [a[7:] for a in argv if a.startswith("--json=")] + [b for a, b in zip(argv, argv[1:]) if a == "--json"]
    if given:
        path = Path(given[0])
        status = bench_main(alloc, argv)
    else:
        path = Path(tempfile.mkdtemp(prefix="gputrack-bench-alloc-")) / "alloc.json"
        status = bench_main(alloc, [*argv, "--json", str(path)])
    if path.is_file():
        print(summary(json.loads(path.read_text())))
    return status


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

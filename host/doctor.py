#!/usr/bin/env python3
"""gputrack doctor: check that a deployment host can run gputrack.

Probes every backend, builds every OpenCL source under gputrack's ``kernels/`` on every OpenCL
device, runs the numerical self-tests (``gputrack.selftest``) on every available device (each in
its own process: Taichi runs one arch per process) and prints a table.

Exit status: 0 when every requested device (``--require``, default: none) is available and
passes, and no available device fails a kernel build or a self-test; 1 otherwise.

    python host/doctor.py                       # check everything found
    python host/doctor.py --require taichi:cpu,opencl --json report.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import gputrack
from gputrack.cli import format_devices


def build_kernels(info) -> list[dict]:
    """Build every .cl file for one OpenCL device listed by the probe (available or not)."""
    import pyopencl as cl

    from gputrack.backends.opencl.device import _enumerate
    from gputrack.backends.opencl.program import build_options, kernel_files

    cl_dev = next(d for s, _, d in _enumerate() if s == info.spec)
    rows = []
    for path in kernel_files():
        try:
            ctx = cl.Context([cl_dev])
            cl.Program(ctx, path.read_text()).build(options=build_options())
            rows.append({"device": info.spec, "kernel": path.name, "ok": True, "detail": ""})
        except Exception as e:  # noqa: BLE001 - reported
            rows.append({"device": info.spec, "kernel": path.name, "ok": False, "detail": " ".join(str(e).split())[:300]})
    return rows


def selftest_in_subprocess(spec: str) -> list[dict]:
    proc = subprocess.run([sys.executable, __file__, "--selftest-child", spec], capture_output=True, text=True)
    line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("GPUTRACK_SELFTEST ")), None)
    if line is None:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return [{"check": "start", "ok": False, "detail": f"self-test process failed: {tail}", "ms": 0.0}]
    return json.loads(line.split(" ", 1)[1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--require", default="", help="comma-separated specs that must be available and pass")
    parser.add_argument("--json", metavar="FILE", help="also write the report as JSON")
    parser.add_argument("--selftest-child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.selftest_child:
        from gputrack import selftest

        rows = selftest.run(gputrack.device(args.selftest_child))
        print("GPUTRACK_SELFTEST " + json.dumps(rows))
        return 0

    required = [s.strip() for s in args.require.split(",") if s.strip()]
    infos = gputrack.devices()
    known = {d.spec: d for d in infos}
    print(format_devices(infos))
    problems = [f"{s}: unknown spec" for s in required if s not in known]
    problems += [f"{s}: not available ({known[s].reason})" for s in required if s in known and not known[s].available]

    builds = []
    for info in infos:
        if info.backend == "opencl" and info.spec != "opencl":
            builds += build_kernels(info)
    if builds:
        print("\nOpenCL kernel builds")
        for r in builds:
            print(f"  {r['device']:<40} {r['kernel']:<22} {'ok' if r['ok'] else 'FAILED ' + r['detail']}")
    working = {d.spec for d in infos if d.available}
    for r in builds:
        if not r["ok"] and r["device"] in working:
            problems.append(f"{r['device']}: {r['kernel']} does not build")

    tests = {}
    print("\nself-tests")
    for info in infos:
        if not info.available or info.spec.startswith("opencl:") and known.get("opencl") and known["opencl"].name == info.name:
            continue
        tests[info.spec] = selftest_in_subprocess(info.spec)
        for r in tests[info.spec]:
            status = "ok" if r["ok"] else "FAILED " + r["detail"]
            print(f"  {info.spec:<22} {r['check']:<16} {r['ms']:>9.1f} ms  {status}")
            if not r["ok"]:
                problems.append(f"{info.spec}: self-test {r['check']} failed")

    print("\n" + ("all checks passed" if not problems else "problems:\n  " + "\n  ".join(problems)))
    if args.json:
        doc = {"devices": [d.as_dict() for d in infos], "builds": builds, "selftests": tests, "problems": problems}
        with open(args.json, "w") as f:
            json.dump(doc, f, indent=2)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())

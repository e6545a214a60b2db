"""gputrack doctor: check that a deployment host can run gputrack (``gputrack doctor``).

Probes every backend, builds every OpenCL source of gputrack's ``kernels/`` on every OpenCL device,
runs the numerical self-tests (:mod:`gputrack.selftest`) on every available device (each in its own
process: Taichi runs one arch per process) and prints a table, with hints where a GPU is there but
a backend cannot reach it (:func:`hints`).

Exit status: 0 when every requested device (``--require``, default: none) is available and passes,
and no available device fails a kernel build or a self-test; 1 otherwise.

    gputrack doctor                                   # check everything found
    gputrack doctor --require taichi:cpu,opencl --json report.json
    gputrack doctor --device numpy                    # self-test only the devices named
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import sys
from pathlib import Path

#: seconds one device's self-tests may take (its process is then stopped and the device fails)
SELFTEST_TIMEOUT = 900

#: where a driver's OpenCL library may lie (NVIDIA's containers mount theirs under /usr/local/nvidia)
LIBRARY_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib",
                "/usr/local/nvidia/lib64", "/usr/local/nvidia/lib")  # fmt: skip
#: where the OpenCL ICD loader looks for vendor files (``OCL_ICD_VENDORS`` overrides it)
ICD_DIR = "/etc/OpenCL/vendors"


def hints(infos, library_dirs=LIBRARY_DIRS, icd_dir=None) -> list[str]:
    """What to install or register where a GPU is there but a backend cannot use it: NVIDIA's OpenCL
    library found in ``library_dirs`` but no OpenCL GPU, and no ICD file in ``icd_dir`` naming it
    (containers built from CUDA images often lack that file); Taichi's Vulkan without its loader."""
    known = {d.spec: d for d in infos}
    out = []
    gpu_opencl = any(d.backend == "opencl" and d.available and d.kind == "gpu" for d in infos)
    libs = sorted({p for d in library_dirs for p in glob.glob(os.path.join(d, "libnvidia-opencl.so*"))})
    if not gpu_opencl and libs:
        icd_dir = icd_dir or os.environ.get("OCL_ICD_VENDORS") or ICD_DIR
        icds = glob.glob(os.path.join(icd_dir, "*.icd")) if os.path.isdir(icd_dir) else []
        named = any("nvidia-opencl" in Path(f).read_text(errors="replace") for f in icds)
        if not named:
            out.append(f"NVIDIA's OpenCL library is installed ({libs[0]}) but no ICD file in {icd_dir} names it: "
                       f"echo {os.path.basename(libs[0])} > {icd_dir}/nvidia.icd")  # fmt: skip
    vk = known.get("taichi:vulkan")
    if vk is not None and not vk.available and "loader" in vk.reason:
        out.append("taichi:vulkan needs the Vulkan loader (Debian/Ubuntu: libvulkan1) and a driver: the GPU "
                   "vendor's, or mesa-vulkan-drivers (lavapipe) on a CPU")  # fmt: skip
    return out


def format_devices(infos) -> str:
    """The device table: spec, available or not, fp64, kind, name or reason."""
    w = max([16, *(len(d.spec) + 2 for d in infos)])
    head = f"{'spec':<{w}}{'available':<11}{'fp64':<6}{'kind':<6}name / reason"
    lines = [head, "-" * (w + 80)]
    for d in infos:
        what = d.name if d.available else d.reason
        lines.append(f"{d.spec:<{w}}{('yes' if d.available else 'no'):<11}{('yes' if d.fp64 else '-'):<6}{d.kind:<6}{what}")
    return "\n".join(lines)


def build_kernels(info) -> list[dict]:
    """Build every .cl file for one OpenCL device listed by the probe (available or not)."""
    import pyopencl as cl

    from .backends.opencl.device import _enumerate
    from .backends.opencl.program import build_options, kernel_files

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


def selftest_in_subprocess(spec: str, timeout: float = SELFTEST_TIMEOUT) -> list[dict]:
    """The self-test rows of ``spec``, run in a fresh process (``python -m gputrack.doctor
    --selftest-child SPEC``); a process that dies, hangs or prints no report gives one failed row."""
    cmd = [sys.executable, "-m", "gputrack.doctor", "--selftest-child", spec]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return [{"check": "start", "ok": False, "detail": f"self-test process ran past {timeout:g} s", "ms": 0.0}]
    line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("GPUTRACK_SELFTEST ")), None)
    if line is None:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return [{"check": "start", "ok": False,
                 "detail": f"self-test process failed (return code {proc.returncode}): {tail}", "ms": 0.0}]  # fmt: skip
    return json.loads(line.split(" ", 1)[1])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--require", default="", help="comma-separated specs that must be available and pass")
    parser.add_argument("--device", action="append", metavar="SPEC",
                        help="self-test only this device (repeatable; default: every available one)")  # fmt: skip
    parser.add_argument("--json", metavar="FILE", help="also write the report as JSON")
    parser.add_argument("--selftest-child", help=argparse.SUPPRESS)


def run(args, out=print) -> int:
    """The doctor on parsed ``args`` (see :func:`add_arguments`); returns the exit status."""
    from . import registry

    if args.selftest_child:
        from . import selftest

        rows = selftest.run(registry.device(args.selftest_child))
        out("GPUTRACK_SELFTEST " + json.dumps(rows))
        return 0

    required = [s.strip() for s in args.require.split(",") if s.strip()]
    infos = registry.devices()
    known = {d.spec: d for d in infos}
    out(format_devices(infos))
    problems = [f"{s}: unknown spec" for s in required if s not in known]
    problems += [f"{s}: not available ({known[s].reason})" for s in required if s in known and not known[s].available]
    chosen = set(args.device or known) | {s for s in required if s in known}
    problems += [f"{s}: unknown spec (--device)" for s in sorted(chosen - set(known))]

    builds = []
    for info in infos:
        if info.backend == "opencl" and info.spec != "opencl" and (info.spec in chosen or "opencl" in chosen):
            builds += build_kernels(info)
    if builds:
        out("\nOpenCL kernel builds")
        for r in builds:
            out(f"  {r['device']:<40} {r['kernel']:<22} {'ok' if r['ok'] else 'FAILED ' + r['detail']}")
    working = {d.spec for d in infos if d.available}
    for r in builds:
        if not r["ok"] and r["device"] in working:
            problems.append(f"{r['device']}: {r['kernel']} does not build")

    tests = {}
    out("\nself-tests")
    default = known.get("opencl")
    for info in infos:
        if not info.available or info.spec not in chosen:
            continue
        if info.spec.startswith("opencl:") and default and default.name == info.name and "opencl" in chosen:
            continue  # the same device as "opencl"
        tests[info.spec] = selftest_in_subprocess(info.spec)
        for r in tests[info.spec]:
            status = "ok" if r["ok"] else "FAILED " + r["detail"]
            out(f"  {info.spec:<22} {r['check']:<16} {r['ms']:>9.1f} ms  {status}")
            if not r["ok"]:
                problems.append(f"{info.spec}: self-test {r['check']} failed")

    advice = hints(infos)
    if advice:
        out("\nhints\n  " + "\n  ".join(advice))
    out("\n" + ("all checks passed" if not problems else "problems:\n  " + "\n  ".join(problems)))
    if args.json:
        doc = {"devices": [d.as_dict() for d in infos], "builds": builds, "selftests": tests, "problems": problems,
               "hints": advice}  # fmt: skip
        with open(args.json, "w") as f:
            json.dump(doc, f, indent=2)
    return 1 if problems else 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="gputrack doctor", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())

"""The benchmark harness shared by ``perf/bench_*.py`` and ``gputrack bench``.

A benchmark is a module in :mod:`gputrack.benchmarks` with ``NAME``, a function
``cases(device, args) -> list[Case]`` and optionally ``add_arguments(parser)``; each :class:`Case` names one
problem and gives callables that run it on ``device`` (``run``: inputs already on the device;
``end_to_end``: with uploads and downloads), its NumPy reference (``reference``), and any named
peers (``peers``, e.g. ``scipy.optimize.least_squares`` in a loop). :func:`bench_main` runs the
cases on every requested device, each device in its own subprocess (Taichi allows one arch per
process), and times everything in the same run so every figure comes with a ratio:

- warm-up calls are excluded (they include compilation);
- the device is synchronised before the clock stops;
- the repeat count grows until the total time reaches ``min_time`` (and at least ``min_reps``);
- a case's callables (device, end to end, reference, peers) are timed in turns, ``ROUNDS`` rounds
  of ``min_time / ROUNDS`` each (:func:`time_interleaved`): a machine whose speed drifts over the
  seconds of a case (a shared VM's can change by 2x within minutes) then slows each of them alike,
  and the ratios compare calls timed under the same conditions;
- the median and the 10th/90th percentiles are reported.

Output: a table, and with ``--json FILE`` a JSON document naming device, backend, versions and
git commit (schema ``gputrack-bench/1``, see :func:`environment` and :func:`bench_main`).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

SCHEMA = "gputrack-bench/1"


@dataclasses.dataclass
class Timing:
    """Seconds per call: median, 10th and 90th percentile, over ``reps`` timed calls."""

    median_s: float
    p10_s: float
    p90_s: float
    reps: int

    def as_dict(self) -> dict:
        return {"median_ms": self.median_s * 1e3, "p10_ms": self.p10_s * 1e3, "p90_ms": self.p90_s * 1e3, "reps": self.reps}


@dataclasses.dataclass
class Case:
    """One benchmark problem. ``params`` (sizes etc.) go into the JSON as they are."""

    name: str
    run: Callable[[], object]
    reference: Callable[[], object] | None = None
    end_to_end: Callable[[], object] | None = None
    peers: dict = dataclasses.field(default_factory=dict)
    params: dict = dataclasses.field(default_factory=dict)
    #: called after the timing: ``(text, data)`` to print under the table and store in the JSON
    #: (e.g. a tracker's per-stage table: the stages of the timed device calls)
    details: Callable[[], tuple] | None = None


def repeat_count(elapsed_s: float, done: int, min_time: float, min_reps: int, max_reps: int) -> int:
    """How many more calls to time, given ``done`` calls took ``elapsed_s`` in all (0 = stop)."""
    if done >= max_reps:
        return 0
    if done >= min_reps and elapsed_s >= min_time:
        return 0
    per_call = elapsed_s / done if done else 0.0
    want = max(min_reps - done, 1)
    if per_call > 0:
        want = max(want, int(np.ceil((min_time - elapsed_s) / per_call)))
    return int(min(max(want, 1), max_reps - done))


def time_call(
    fn: Callable[[], object],
    sync: Callable[[], None] | None = None,
    *,
    warmup: int = 2,
    min_time: float = 0.2,
    min_reps: int = 5,
    max_reps: int = 10_000,
) -> Timing:
    """Time ``fn`` (synchronising with ``sync`` after every call) after ``warmup`` untimed calls:
    :func:`time_interleaved` of ``fn`` alone, in one round."""
    return time_interleaved({"fn": (fn, sync)}, rounds=1, warmup=warmup, min_time=min_time, min_reps=min_reps,
                            max_reps=max_reps)["fn"]  # fmt: skip


#: rounds of :func:`time_interleaved` (each callable timed for min_time / ROUNDS per round)
ROUNDS = 5


def time_interleaved(fns: dict, *, rounds: int = ROUNDS, warmup: int = 2, min_time: float = 0.2, min_reps: int = 5,
                     max_reps: int = 10_000) -> dict:  # fmt: skip
    """Time the callables ``fns`` {name: (fn, sync or None)} in turns: after ``warmup`` untimed
    calls of each, ``rounds`` rounds in which each callable is timed for ``min_time / rounds``
    seconds (and at least ``ceil(min_reps / rounds)`` calls), one after the other. {name: Timing}
    over all of its rounds' calls."""
    if rounds < 1:
        raise ValueError(f"rounds: expected an integer >= 1, got {rounds!r}")
    for fn, sync in fns.values():
        for _ in range(warmup):
            fn()
            if sync:
                sync()
    share, reps = min_time / rounds, -(-min_reps // rounds)
    times: dict = {name: [] for name in fns}
    for _ in range(rounds):
        for name, (fn, sync) in fns.items():
            mine = times[name]
            spent, done, cap = 0.0, 0, max(1, max_reps // rounds)
            while True:
                more = repeat_count(spent, done, share, reps, cap)
                if not more:
                    break
                for _ in range(more):
                    t0 = time.perf_counter()
                    fn()
                    if sync:
                        sync()
                    dt = time.perf_counter() - t0
                    mine.append(dt)
                    spent += dt
                    done += 1
    out = {}
    for name, ts in times.items():
        arr = np.asarray(ts)
        out[name] = Timing(float(np.median(arr)), float(np.percentile(arr, 10)), float(np.percentile(arr, 90)), len(ts))
    return out


def git_commit() -> str:
    """The git commit of the source tree gputrack runs from, or 'unknown'."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=10,
        )
        return out.stdout.strip() or "unknown"
    except Exception:  # noqa: BLE001 - not a git checkout
        return "unknown"


def _version(module: str) -> str:
    try:
        from importlib.metadata import version

        return version(module)
    except Exception:  # noqa: BLE001
        return "not installed"


def environment(device=None) -> dict:
    """What a figure was measured on: device, versions, commit, date, host."""
    env = {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "commit": git_commit(),
        "host": {"cpu": _cpu(), "machine": platform.machine(), "python": platform.python_version()},
        "versions": {m: _version(m) for m in ("gputrack", "numpy", "scipy", "taichi", "pyopencl")},
    }
    if device is not None:
        env["device"] = {"spec": device.spec, "backend": device.backend, "name": device.name, "fp64": device.fp64}
    return env


def _cpu() -> str:
    from ..backends.reference.device import cpu_name

    return cpu_name()


def run_cases(device, cases: list[Case], *, min_time: float = 0.2, progress=None) -> list[dict]:
    """Time every case on ``device`` (and its reference and peers); one dict per case."""
    rows = []
    for case in cases:
        if progress:
            progress(f"{device.spec}: {case.name}")
        row = {"case": case.name, "params": case.params, "spec": device.spec}
        fns = {"device": (case.run, device.synchronize)}
        if case.end_to_end is not None:
            fns["end_to_end"] = (case.end_to_end, device.synchronize)
        if case.reference is not None:
            fns["reference"] = (case.reference, None)
        for peer, fn in case.peers.items():
            fns[("peer", peer)] = (fn, None)
        got = time_interleaved(fns, min_time=min_time)
        t = got["device"]
        row["device"] = t.as_dict()
        if case.details is not None:
            row["details_text"], row["details"] = case.details()
        if case.end_to_end is not None:
            row["end_to_end"] = got["end_to_end"].as_dict()
        if case.reference is not None:
            row["reference"] = got["reference"].as_dict()
            row["speedup_vs_reference"] = got["reference"].median_s / t.median_s
        row["peers"] = {}
        for peer in case.peers:
            pt = got[("peer", peer)]
            row["peers"][peer] = {**pt.as_dict(), "speedup": pt.median_s / t.median_s}
        rows.append(row)
    return rows


def format_table(rows: list[dict]) -> str:
    """Rows from :func:`run_cases` as a text table (ms per call, and ratios)."""
    cw = max([40] + [len(r["case"]) + 2 for r in rows])  # the case column fits the longest name
    dw = max([16] + [len(r["spec"]) + 2 for r in rows])
    head = f"{'case':<{cw}}{'device':<{dw}}{'median ms':>11}{'p10-p90 ms':>17}{'e2e ms':>9}{'numpy ms':>10}{'x numpy':>9}  peers"
    lines = [head, "-" * len(head)]
    for r in rows:
        d = r["device"]
        e2e = f"{r['end_to_end']['median_ms']:.3f}" if "end_to_end" in r else "-"
        ref = f"{r['reference']['median_ms']:.3f}" if "reference" in r else "-"
        ratio = f"{r['speedup_vs_reference']:.2f}" if "speedup_vs_reference" in r else "-"
        peers = ", ".join(f"{k} {v['median_ms']:.3f} ms (x{v['speedup']:.1f})" for k, v in r.get("peers", {}).items())
        spread = f"{d['p10_ms']:.3f}-{d['p90_ms']:.3f}"
        lines.append(f"{r['case']:<{cw}}{r['spec']:<{dw}}{d['median_ms']:>11.3f}{spread:>17}{e2e:>9}{ref:>10}{ratio:>9}  {peers}")
    return "\n".join(lines)


def _child(name: str, cases_fn, spec: str, args) -> dict:
    from ..registry import device

    dev = device(spec)
    cases = cases_fn(dev, args)
    rows = run_cases(dev, cases, min_time=args.min_time, progress=lambda m: print(m, file=sys.stderr, flush=True))
    return {"schema": SCHEMA, "bench": name, **environment(dev), "results": rows}


def bench_main(module, argv=None) -> int:
    """Command line of a benchmark module: ``--device SPEC|all`` (repeatable), ``--json FILE``.

    Each device runs in a subprocess (``python -m <module> --child SPEC``), which times the
    device and the NumPy reference in the same process, so ratios compare like with like.
    """
    from ..registry import devices

    name, cases_fn = module.NAME, module.cases
    add_arguments = getattr(module, "add_arguments", None)
    module_name = module.__spec__.name

    parser = argparse.ArgumentParser(description=f"gputrack benchmark: {name}")
    parser.add_argument("--device", action="append", help="spec to run (repeatable); default: all available but numpy")
    parser.add_argument("--json", metavar="FILE", help="write the results as JSON ('-' for stdout)")
    parser.add_argument("--min-time", type=float, default=0.2, help="seconds of timed calls per figure (default 0.2)")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    if add_arguments:
        add_arguments(parser)
    args = parser.parse_args(argv)
    if args.child:
        doc = _child(name, cases_fn, args.child, args)
        sys.stdout.write("GPUTRACK_BENCH " + json.dumps(doc) + "\n")
        return 0
    specs = args.device or ["all"]
    if "all" in specs:
        specs = [d.spec for d in devices() if d.available and d.spec != "numpy" and not d.spec.startswith("opencl:")]
    forwarded = [a for a in (argv if argv is not None else sys.argv[1:])]
    forwarded = _strip_options(forwarded, {"--device", "--json"})
    docs, failures = [], []
    for spec in specs:
        print(f"[{name}] {spec} ...", file=sys.stderr, flush=True)
        cmd = [sys.executable, "-m", module_name, "--child", spec, *forwarded]
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
        line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("GPUTRACK_BENCH ")), None)
        if proc.returncode != 0 or line is None:
            failures.append(spec)
            print(f"[{name}] {spec} failed (exit {proc.returncode})", file=sys.stderr)
            continue
        docs.append(json.loads(line.split(" ", 1)[1]))
    rows = [r for d in docs for r in d["results"]]
    if rows:
        print(format_table(rows))
        for r in rows:
            if r.get("details_text"):
                print(f"\n{r['case']} on {r['spec']}:\n{r['details_text']}")
    if args.json:
        out = {"schema": SCHEMA, "bench": name, **environment(), "runs": docs}
        text = json.dumps(out, indent=2)
        if args.json == "-":
            print(text)
        else:
            Path(args.json).write_text(text + "\n")
    return 1 if failures else 0


def _strip_options(argv: list[str], names: set[str]) -> list[str]:
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
            continue
        if a in names:
            skip = True
            continue
        if any(a.startswith(n + "=") for n in names):
            continue
        out.append(a)
    return out

"""The standing fuzz suite: every public op and tracker entry point, every backend, bad and awkward
arguments (tests/fuzzing.py has the table, the mutations and the oracle).

Default profile "fast" (within the suite's time budget); ``GPUTRACK_FUZZ=deep`` for every mutation
of every argument with several seeds. Cases that could crash the process or run away with memory
run in a subprocess under resource limits (tests/fuzz_child.py)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import gputrack
from conftest import full_protocol
from fuzzing import Outcome, assert_refused, OP_NAMES, TRACKER_NAMES, LAYOUT, known_defect, tracker_cases, REF, SCALARS, VALUE, assert_clear, huge_count, judge, op_cases, profile, results, run

HERE = Path(__file__).resolve().parent
DEEP = profile() == "deep"
SEEDS = (0, 1, 2) if DEEP else (0,)
CASE_NAMES = OP_NAMES + TRACKER_NAMES  # the table itself is built by the case_tables fixture, when first used


@pytest.fixture(scope="session")
def case_tables():
    trackers = {c.name: c for c in tracker_cases(face=DEEP)}  # one frame each: the same for every seed
    return {seed: {**{c.name: c for c in op_cases(seed)}, **trackers} for seed in SEEDS}


# public names that are not device ops (host helpers), with the reason they have no fuzz case
NOT_DEVICE_OPS = {
    "backend_module": "the registry's look-up, not an op",
    "constant_velocity": "builds the model's F and Q on the host",
    "shared_matrix": "wraps a matrix for the Kalman ops (fuzzed through them)",
    "compact_labels": "relabels host labels",
    "floor_background": "host geometry",
}


def test_every_public_op_and_tracker_entry_point_has_a_case(case_tables):
    """The table grows with the ops: a public function of gputrack.ops without a case fails here."""
    import inspect

    from gputrack import ops

    table = case_tables[SEEDS[0]]
    assert set(table) <= set(CASE_NAMES) and set(CASE_NAMES) - set(table) <= {"FaceTracker.start"}
    assert set(DEEP_ONLY) <= set(CASE_NAMES)
    public = {n for n in ops.__all__ if inspect.isfunction(getattr(ops, n))} - set(NOT_DEVICE_OPS)
    missing = sorted(n for n in public if not any(c == n or c.startswith(n + " ") for c in table))
    assert not missing, f"public ops without a fuzz case (tests/fuzzing.py op_cases): {missing}"
    assert {"BodyTracker.track", "GroupTracker.update_points", "GroupTracker.track",
            "PedestrianTracker.track"} <= set(table)  # fmt: skip


#: cases the fast profile leaves to the deep one (the suite's time budget), with the reason
DEEP_ONLY = {"FaceTracker.start": "loading the ICT model and rendering its 7 start frames takes ~3 s, each start "
                                  "~0.2 s per device"}

#: the mutations a tracker's frame gets in the fast profile (those every tracker must refuse)
TRACKER_FAST = {"ndim+1", "ndim-1", "shape+1", "empty", "complex", "object", "nan", "inf", "None", "string", "ragged"}


def _foreign(device):
    """A device other than ``device`` whose arrays can coexist with it in this process (an OpenCL
    device: a second Device object for the same OpenCL device when ``device`` is OpenCL)."""
    infos = {d.spec: d for d in gputrack.devices()}
    if not infos["opencl"].available:
        return None
    if device.backend != "opencl":
        return gputrack.device("opencl")
    other = [s for s, d in infos.items() if s.startswith("opencl:") and d.available and s != device.spec]
    return gputrack.device(other[0]) if other else None


def _check_case(device, case, seed_index: int) -> list[tuple[str, str]]:
    """Every mutation of ``case`` on ``device``; returns the failures as (what, message).

    The reference runs every mutation. The device runs every mutation the reference refuses (its
    validation is cheap and must refuse it too). Of those the reference accepts (each a kernel run;
    a new dtype or option also a fresh compile), the fast profile runs the layout mutations only,
    one in two per argument (rotating with the argument and the seed), and the device-resident
    mutations of one argument in two; on the slow devices (outside conftest.FULL_PROTOCOL) those of
    the first argument only. The deep profile runs all."""
    failures = []

    def check(what, fn):
        try:
            fn()
        except AssertionError as e:
            failures.append((what, " ".join(str(e).split())[:600]))

    wide = DEEP or device.backend == "numpy" or full_protocol(device)
    # slow devices (fast profile): besides the clean call, one run of the first argument per case, a
    # layout mutation, the array on the device or NaN written there, rotating over the cases
    extra = ("layout", "resident", "nan")[(CASE_NAMES.index(case.name) + seed_index) % 3]

    def dev_run(args, ref: Outcome | None = None) -> Outcome:
        # on numpy the device is the reference: its outcome is the reference's (one run)
        return ref if ref is not None and device is REF else run(case, device, args)

    def sampled(i, j, kind="layout") -> bool:
        if DEEP:
            return True
        if case.tracker:
            return False  # each accepted frame is a whole tracker frame
        return kind == "layout" and ((i + j + seed_index) % 2 == 0 if wide else extra == "layout" and i == 0
                                     and j == len(VALUE) + seed_index % len(LAYOUT))

    want = run(case, REF, case.args)
    assert want.error is None, f"{case.name}: the clean call fails on the reference: {want.describe()}"
    clean = results(case, want.value)
    check("clean", lambda: judge(device, case, "clean", dev_run(case.args, want), want))

    for i, name in enumerate(case.arrays):
        x = case.args[name]
        for j, (mname, kind, mutate) in enumerate(VALUE + LAYOUT):
            if case.tracker and not DEEP and mname not in TRACKER_FAST:
                continue  # an accepted frame costs a whole tracker frame on both devices
            try:
                y = mutate(x)
            except Exception:  # noqa: BLE001 - the mutation does not apply to this argument
                continue
            if y is None and mname != "None":
                continue
            args = {**case.args, name: y}
            what = f"{name} {mname}"
            ref = run(case, REF, args)
            if ref.error is None and not sampled(i, j, kind):
                check(what, lambda: assert_refused(case, what, ref))
                continue
            check(what, lambda: judge(device, case, what, dev_run(args, ref), ref,
                                      clean=clean if kind == "layout" else None))  # fmt: skip
        if device.backend == "numpy" or not isinstance(x, np.ndarray) or case.tracker and not DEEP or not (
                DEEP or ((i + seed_index) % 2 == 0 if wide else i == 0)):
            continue
        try:
            on_device = device.asarray(x)
        except TypeError:
            continue  # a dtype no device array has (uint16 frames, bool masks): host input only
        # an array already on the device: the clean result, or a clear refusal (an argument the op
        # documents as host-only)
        got = run(case, device, {**case.args, name: on_device}) if wide or extra == "resident" else None

        def resident(got=got, name=name):
            if got is None:
                return
            if got.error is not None:
                assert_clear(case, f"{name} on the device", got.error)
            else:
                judge(device, case, f"{name} on the device", got, want, clean=clean)

        check(f"{name} on the device", resident)
        # NaN written on the device (not checked there: that would cost a download): a clear error
        # or results of the clean call's shapes, never a crash
        if x.dtype.kind == "f" and x.size and (wide or extra == "nan"):
            bad = x.copy()
            bad.flat[bad.size // 2] = np.nan
            got = run(case, device, {**case.args, name: device.asarray(bad)})

            def nan_on_device(got=got, name=name):
                if got.error is not None:
                    assert_clear(case, f"{name} NaN on the device", got.error)
                else:
                    shapes = [a.shape for a in results(case, got.value)]
                    assert shapes == [a.shape for a in clean], f"{case.name} {name} NaN on the device: shapes {shapes}"

            check(f"{name} NaN on the device", nan_on_device)
        other = _foreign(device)
        if other is not None and x.dtype.kind in "biuf" and x.size:
            got = run(case, device, {**case.args, name: other.asarray(x)})

            def foreign(got=got, name=name, other=other):
                assert got.error is not None, f"{case.name} {name}: an array of {other.spec} accepted by {device.spec}"
                assert_clear(case, f"{name} on {other.spec}", got.error)

            check(f"{name} foreign", foreign)

    for i, name in enumerate(_scalar_names(case)):
        for j, v in enumerate(SCALARS + list(case.scalars.get(name, []))):
            if huge_count(case.args[name], v):
                continue  # tests/fuzz_child.py, under limits
            args = {**case.args, name: v}
            what = f"{name}={v!r}"
            ref = run(case, REF, args)
            if ref.error is None and not sampled(i, j, "value"):
                continue
            check(what, lambda: judge(device, case, what, dev_run(args, ref), ref))
    for name, values in case.scalars.items():
        if name in case.args and not _is_scalar(case.args[name]):  # object arguments (templates)
            for v in values:
                args = {**case.args, name: v}
                what = f"{name}={type(v).__name__}"
                check(what, lambda: judge(device, case, what, run(case, device, args), run(case, REF, args)))
    if case.tracker and wide:  # the refused frames left the tracker usable (a frame: not on the slow devices)
        check("clean again", lambda: judge(device, case, "clean again", run(case, device, case.args), want))
    return failures


def _is_scalar(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)


def _scalar_names(case):
    return [n for n, v in case.args.items() if _is_scalar(v)]


@pytest.mark.parametrize("name", CASE_NAMES)
def test_op_under_mutation(device, case_tables, name):
    """Every mutation of every argument of the op: the reference's clear exception or its results."""
    if name in DEEP_ONLY and not DEEP:
        pytest.skip(f"{name}: deep profile only (GPUTRACK_FUZZ=deep): {DEEP_ONLY[name]}")
    if name not in case_tables[SEEDS[0]]:
        pytest.skip(f"{name}: the ICT face data is absent (shared/data/ict_face beside the repository, or $GPUTRACK_DATA/ict_face)")
    failures = []
    for k, seed in enumerate(SEEDS):
        failures += _check_case(device, case_tables[seed][name], k)
    unknown = [msg for what, msg in failures if known_defect(name, what) is None]
    assert not unknown, f"{len(unknown)} failures on {device.spec}:\n" + "\n".join(unknown[:40])
    if failures:
        pytest.xfail("known defects in ops owned elsewhere: "
                     + "; ".join(sorted({f"{what}: {known_defect(name, what)}" for what, _ in failures})))


# -- risky cases, in a subprocess under limits --------------------------------------------------------------
#: the devices whose risky cases one child process runs together (one Taichi arch per process, last)
HOST_GROUP = ("numpy", "opencl", "taichi:cpu")
_CHILD_RUNS: dict = {}


def _child_run(spec: str):
    """(return code, stdout, stderr) of the child that runs ``spec``'s group (run once per group)."""
    available = {d.spec for d in gputrack.devices() if d.available}
    group = tuple(s for s in HOST_GROUP if s in available)
    group = group if spec in group else (spec,)
    if group not in _CHILD_RUNS:
        env = {**os.environ, "PYTHONPATH": str(HERE) + os.pathsep + os.environ.get("PYTHONPATH", "")}
        proc = subprocess.run([sys.executable, str(HERE / "fuzz_child.py"), ",".join(group), profile()],
                              capture_output=True, text=True, timeout=300, env=env, cwd=HERE)  # fmt: skip
        _CHILD_RUNS[group] = (proc.returncode, proc.stdout, proc.stderr)
    return _CHILD_RUNS[group]


def test_risky_cases_in_a_limited_subprocess(device):
    """Outputs too large for the device, huge sizes and counts, broadcast views of 2**32 rows: each
    must end in a clear exception, with no crash and no runaway memory (the child runs under an
    address-space limit and a CPU-time limit; tests/fuzz_child.py)."""
    code, out, err = _child_run(device.spec)
    rows = [json.loads(ln.split(" ", 1)[1]) for ln in out.splitlines() if ln.startswith("FUZZ ")]
    started = [ln.split(" ", 1)[1] for ln in out.splitlines() if ln.startswith("START ")]
    assert code == 0, f"the child died (return code {code}) in case {started[-1] if started else '?'}:\n{err[-3000:]}"
    rows = [r for r in rows if r["spec"] == device.spec]
    assert rows and len(rows) == len([s for s in started if s.startswith(device.spec + " ")]), out[-3000:]
    bad = [r for r in rows if not r["ok"] and not r["known"]]
    assert not bad, "\n".join(f"{r['case']}: {r['outcome']}" for r in bad)
    fixed = [r["case"] for r in rows if r["ok"] and r["known"]]
    assert not fixed, f"known failures that pass now (drop them from fuzz_child.KNOWN): {fixed}"
    known = [f"{r['case']}: {r['known']}" for r in rows if not r["ok"]]
    if known:
        pytest.xfail("known defects in ops owned elsewhere: " + "; ".join(known))

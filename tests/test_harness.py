"""The benchmark harness's logic (no timing assertions)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from gputrack.benchmarks import harness

ROOT = Path(__file__).resolve().parents[1]


def test_repeat_count_grows_until_stable():
    # nothing timed yet: at least min_reps
    assert harness.repeat_count(0.0, 0, min_time=0.2, min_reps=5, max_reps=1000) == 5
    # 5 calls of 1 ms: about 195 more to reach 0.2 s
    assert harness.repeat_count(0.005, 5, min_time=0.2, min_reps=5, max_reps=1000) == 195
    # enough time and reps: stop
    assert harness.repeat_count(0.3, 5, min_time=0.2, min_reps=5, max_reps=1000) == 0
    # capped by max_reps
    assert harness.repeat_count(0.001, 999, min_time=10.0, min_reps=5, max_reps=1000) == 1
    assert harness.repeat_count(0.001, 1000, min_time=10.0, min_reps=5, max_reps=1000) == 0
    # slow calls: min_reps still honoured
    assert harness.repeat_count(2.0, 2, min_time=0.2, min_reps=5, max_reps=1000) == 3


def test_time_call_excludes_warmup_and_syncs_each_call():
    calls, syncs = [], []
    t = harness.time_call(lambda: calls.append(1), lambda: syncs.append(1), warmup=3, min_time=0.0, min_reps=7)
    assert t.reps == 7
    assert len(calls) == 10 and len(syncs) == 10
    assert 0 <= t.p10_s <= t.median_s <= t.p90_s


def test_time_interleaved_takes_turns():
    """Each callable is timed in every round, one after the other (a drifting machine slows each
    alike); warm-up calls first, the device's sync after each of its calls, the reps counted."""
    log = []
    fns = {
        "a": (lambda: log.append("a"), lambda: log.append("sync")),
        "b": (lambda: log.append("b"), None),
    }
    got = harness.time_interleaved(fns, rounds=3, warmup=1, min_time=0.0, min_reps=6)
    calls = [x for x in log if x != "sync"]
    assert calls[:2] == ["a", "b"]  # the warm-up calls
    # then 3 rounds of ceil(6 / 3) = 2 calls each, a's before b's in every round
    assert calls[2:] == ["a", "a", "b", "b"] * 3
    assert log.count("sync") == 1 + 6
    assert got["a"].reps == got["b"].reps == 6
    for t in got.values():
        assert 0 <= t.p10_s <= t.median_s <= t.p90_s
    with pytest.raises(ValueError, match="rounds: expected an integer >= 1, got 0"):
        harness.time_interleaved(fns, rounds=0)


def test_run_cases_reports_every_callable_of_a_case():
    from gputrack.registry import device

    case = harness.Case("c", run=lambda: None, reference=lambda: None, end_to_end=lambda: None,
                        peers={"p": lambda: None}, details=lambda: ("text", {"k": 1}))  # fmt: skip
    (row,) = harness.run_cases(device("numpy"), [case], min_time=0.0)
    assert {"device", "end_to_end", "reference", "peers", "speedup_vs_reference"} <= set(row)
    assert row["device"]["reps"] >= 5 and row["reference"]["reps"] >= 5 and row["end_to_end"]["reps"] >= 5
    assert set(row["peers"]) == {"p"} and row["peers"]["p"]["speedup"] > 0
    assert row["details_text"] == "text" and row["details"] == {"k": 1}


def test_bench_json_schema(tmp_path):
    out = tmp_path / "b.json"
    r = subprocess.run(
        [sys.executable, "-m", "gputrack.benchmarks.transfer", "--device", "numpy", "--min-time", "0.01", "--json", str(out)],
        capture_output=True, text=True, cwd=ROOT, timeout=300,
    )
    assert r.returncode == 0, r.stderr
    doc = json.loads(out.read_text())
    assert doc["schema"] == harness.SCHEMA and doc["bench"] == "transfer"
    assert {"date", "commit", "host", "versions"} <= set(doc)
    (run,) = doc["runs"]
    assert run["device"]["spec"] == "numpy" and run["device"]["name"]
    assert [row["case"] for row in run["results"]] == ["upload 640x480 f32", "download 640x480 f32"]
    for row in run["results"]:
        assert row["device"]["reps"] >= 5 and row["device"]["median_ms"] > 0
    assert "upload 640x480 f32" in r.stdout  # the table


def test_cli_bench_rejects_unknown_op():
    r = subprocess.run([sys.executable, "-m", "gputrack.cli", "bench", "--op", "nope"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2 and "unknown --op nope" in r.stderr


@pytest.mark.parametrize("given, files", [
    ("out", ["out.transfer.json", "out.kalman.json"]),
    ("out.json", ["out.transfer.json", "out.kalman.json"]),
    ("out.txt", ["out.txt.transfer.json", "out.txt.kalman.json"]),
])  # fmt: skip
def test_cli_bench_json_gives_each_op_its_own_file(tmp_path, monkeypatch, given, files):
    """--json FILE with several ops: one file per op, also when FILE does not end in .json (all
    ops wrote the same FILE before)."""
    from gputrack import cli

    written = []

    def bench_main(module, argv):
        written.append(argv[argv.index("--json") + 1])
        return 0

    monkeypatch.setattr(harness, "bench_main", bench_main)
    argv = ["bench", "--device", "numpy", "--op", "transfer", "--op", "kalman", "--json", str(tmp_path / given)]
    assert cli.main(argv) == 0
    assert written == [str(tmp_path / f) for f in files]


def test_cli_bench_lists_the_definitions_not_the_harness(capsys):
    from gputrack import cli

    assert cli.main(["bench", "--op", "harness", "--device", "numpy"]) == 2
    err = capsys.readouterr().err
    assert "unknown --op harness" in err
    names = err.split("expected one of: ")[1].strip().split(", ")
    from pathlib import Path

    from gputrack import benchmarks

    files = sorted(p.stem for p in Path(benchmarks.__file__).parent.glob("*.py") if p.stem not in ("__init__", "harness"))
    assert names == files and "harness" not in names
    assert {"alloc", "body", "kalman", "lm", "template", "tracking", "transfer"} <= set(names)


def test_table_columns_fit_the_longest_case_name():
    """A case name longer than the default column does not run into the device column: every
    row's figures end where the header's do."""
    t = {"median_ms": 1.5, "p10_ms": 1.0, "p90_ms": 2.0}
    rows = [
        {"case": "short", "spec": "opencl", "device": t},
        {"case": "body frame, PF 3 stages + LM 10, template kept", "spec": "taichi:cuda", "device": t},
    ]
    head, _, *lines = harness.format_table(rows).splitlines()
    end = head.index("median ms") + len("median ms")
    for line, r in zip(lines, rows, strict=True):
        assert line.startswith(r["case"] + " ") and line[len(r["case"]) :].split()[0] == r["spec"], line
        assert line[:end].endswith(" 1.500"), line

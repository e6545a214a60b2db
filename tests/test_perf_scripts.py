"""perf/sweep.py: the sweep cases on every backend, the JSON it writes, the plot and the Tables 1/2
layout (no timing assertions: figures are whatever the machine gives)."""

import argparse
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tolerances import assert_matches

import gputrack

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "perf" / "sweep.py"


def load_sweep():
    spec = importlib.util.spec_from_file_location("perf_sweep_under_test", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


sweep = load_sweep()


def args_for(**kw):
    parser = argparse.ArgumentParser()
    sweep.add_arguments(parser)
    argv = []
    for k, v in kw.items():
        for item in v if isinstance(v, list) else [v]:
            argv += [f"--{k.replace('_', '-')}", str(item)]
    return parser.parse_args(argv)


def test_sweep_cases_run_on_every_backend(device):
    """Every sweep point builds and runs on the device; its result matches the reference's."""
    args = args_for(k=[7, 33], n=[16], t=[13], reference_max_k=7, reference_max_tracks=13)
    cases = sweep.cases(device, args)
    assert [c.params["sweep"] for c in cases] == ["K", "K", "N", "T"]
    assert [c.params["x"] for c in cases] == [7, 33, 16, 13]
    # the reference is timed up to the --reference-max-* sizes only
    assert [c.reference is not None for c in cases] == [True, False, True, True]
    for c in cases:
        got = c.run()
        device.synchronize()
        if c.params["sweep"] in "KN" and c.reference is not None:
            want = c.reference()
            assert_matches(device, got.total, want.total)
    k7 = cases[0]
    assert gputrack.to_numpy(k7.end_to_end()).shape == (7,)


def test_k_cases_do_not_depend_on_the_other_sweeps():
    """A K point computes the same costs whether or not the N sweep is built after it (the
    closures keep their own templates)."""
    dev = gputrack.device("numpy")
    alone = sweep.cases(dev, args_for(sweep="K", k=9))
    both = sweep.cases(dev, args_for(sweep="K,N", k=9, n=[16, 64]))
    np.testing.assert_array_equal(alone[0].run().total, both[0].run().total)
    np.testing.assert_array_equal(alone[0].reference().total, both[0].reference().total)


def test_unknown_sweep_is_an_error():
    with pytest.raises(SystemExit, match="expected some of K,N,T, got X"):
        sweep.cases(gputrack.device("numpy"), args_for(sweep="K,X"))


def test_scaled_batch_keeps_the_poses_and_adds_noise():
    rng = np.random.default_rng(0)
    tf = rng.normal(size=(5, 2, 3, 4)).astype(np.float32)
    out = sweep._scaled(tf, 12, rng)
    assert out.shape == (12, 2, 3, 4) and out.dtype == np.float32
    np.testing.assert_array_equal(out[7, :, :, :3], tf[2, :, :, :3])  # rotations repeat
    assert not np.array_equal(out[7, :, :, 3], tf[2, :, :, 3])  # translations get fresh noise


def fake_doc():
    def row(spec, s, x, ms, ref=None):
        r = {"case": f"{s} {x}", "spec": spec, "params": {"sweep": s, "x": x},
             "device": {"median_ms": ms, "p10_ms": ms * 0.9, "p90_ms": ms * 1.2, "reps": 5}}  # fmt: skip
        if ref is not None:
            r["reference"] = {"median_ms": ref, "p10_ms": ref, "p90_ms": ref, "reps": 5}
        return r

    runs = [
        {"results": [row(spec, "K", x, f * x / 100, ref=x / 10) for x in (100, 1000)] + [row(spec, "T", 1000, f)]}
        for spec, f in (("opencl", 1.0), ("taichi:cpu", 2.0))
    ]
    return {"commit": "abc1234", "date": "2026-01-01T00:00:00+00:00", "runs": runs}


def test_plot_writes_a_png(tmp_path):
    pytest.importorskip("matplotlib")
    path = tmp_path / "sweep.png"
    assert sweep.plot(fake_doc(), str(path)) is True
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plot_without_matplotlib_is_skipped_with_a_message(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    path = tmp_path / "sweep.png"
    assert sweep.plot(fake_doc(), str(path)) is False
    assert not path.exists()
    assert "matplotlib is not installed: skipping the plot" in capsys.readouterr().err


def test_tables_layout_has_one_column_per_device_and_ms_per_frame():
    def doc(spec, scale):
        stages = [{"name": "upload frame", "total_ms": 2.0 * scale}, {"name": "PF stage 1", "total_ms": 10.0 * scale}]
        if spec != "numpy":
            stages.append({"name": "LM", "total_ms": 4.0 * scale})
        return {"device": {"spec": spec}, "config": {"frames": 2}, "stages": stages, "frame_ms": [7.0, 9.0, 100.0]}

    text = sweep.format_tables([doc("numpy", 10), doc("opencl", 1)])
    lines = text.splitlines()
    assert lines[0].split()[-2:] == ["numpy", "opencl"]
    assert lines[2].split()[-2:] == ["10.000", "1.000"]  # upload frame: total / frames
    assert lines[3].split()[-2:] == ["50.000", "5.000"]
    assert lines[4].split()[-2:] == ["-", "2.000"]  # a stage a device did not run
    assert lines[5].split()[-2:] == ["9.000", "9.000"]  # median frame


def test_sweep_script_end_to_end_json(tmp_path):
    """The script as users run it: one subprocess per device, JSON with the harness's schema."""
    out = tmp_path / "sweep.json"
    cmd = [sys.executable, str(SCRIPT), "--device", "numpy", "--sweep", "K,T", "--k", "5", "--t", "7",
           "--min-time", "0.001", "--json", str(out)]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path, check=False)
    assert proc.returncode == 0, proc.stderr
    assert "K: rgbd_cost K=5" in proc.stdout and "x numpy" in proc.stdout
    doc = json.loads(out.read_text())
    assert doc["schema"] == "gputrack-bench/1" and doc["bench"] == "sweep"
    assert {"commit", "date", "versions", "host"} <= set(doc)
    (run,) = doc["runs"]
    assert run["device"]["spec"] == "numpy"
    assert [(r["params"]["sweep"], r["params"]["x"]) for r in run["results"]] == [("K", 5), ("T", 7)]
    for r in run["results"]:
        assert {"median_ms", "p10_ms", "p90_ms", "reps"} <= set(r["device"])
        assert r["device"]["p10_ms"] <= r["device"]["median_ms"] <= r["device"]["p90_ms"]


# -- every benchmark script, on numpy at a tiny size --------------------------------------------------
#: each perf/bench_*.py with the options that make its cases tiny (None: not run here, with the reason)
TINY = {
    "bench_alloc.py": ["--tracks", "100", "--batch", "8", "--memory-calls", "0"],
    "bench_background.py": ["--frames", "3", "--size", "32x24"],
    "bench_body.py": ["--samples", "20", "--lm", "1", "--points", "16"],
    "bench_clusters.py": ["--dbscan-points", "64", "--components-points", "64"],
    "bench_face.py": ["--frames", "9", "--particles", "16", "--no-scipy"],
    # VGA frames only (the simulator's rig): ~30 s on numpy, most of it the reference stereo matching
    "bench_groups.py": ["--frames", "2", "--core-groups", "4", "--core-points", "10"],
    "bench_kalman.py": ["--tracks", "100", "--loop-max-tracks", "100", "--reference-max-tracks", "100"],
    "bench_lm.py": ["--params", "14", "--residuals", "16", "--iterations", "2", "--no-scipy"],
    "bench_pedestrians.py": ["--people", "2", "--frames", "2", "--scale", "0.25", "--no-sklearn"],
    "bench_stereo.py": ["--size", "64x48", "--no-accuracy"],
    "bench_template.py": ["--batch", "8", "--points", "16", "--lm-batch", "4", "--ncc-batch", "4"],
    "bench_tracking.py": ["--tracks", "10", "--frames", "40", "--no-stonesoup", "--no-kdtree"],
    "bench_transfer.py": [],
}


def test_every_benchmark_script_has_a_smoke_entry():
    scripts = sorted(p.name for p in (ROOT / "perf").glob("bench_*.py"))
    assert scripts == sorted(TINY), f"perf scripts without a TINY entry: {sorted(set(scripts) - set(TINY))}"


@pytest.mark.parametrize("script", sorted(TINY))
def test_benchmark_script_runs_on_numpy_at_a_tiny_size(script, monkeypatch, capsys):
    """The script as users run it, in its per-device child mode on numpy (the harness's one process
    per device), with tiny sizes: every case is timed and reported with its medians."""
    import runpy

    if script == "bench_face.py":
        try:
            from gputrack.models.face import load_ict

            load_ict()
        except FileNotFoundError as e:
            pytest.skip(f"the ICT face data is absent: {e}")
    path = ROOT / "perf" / script
    monkeypatch.setattr(sys, "argv", [str(path), "--child", "numpy", "--min-time", "0.001", *TINY[script]])
    with pytest.raises(SystemExit) as e:
        runpy.run_path(str(path), run_name="__main__")
    out = capsys.readouterr().out
    assert e.value.code in (0, None), out
    line = next((ln for ln in out.splitlines() if ln.startswith("GPUTRACK_BENCH ")), None)
    assert line is not None, out[-2000:]
    doc = json.loads(line.split(" ", 1)[1])
    assert doc["device"]["spec"] == "numpy" and doc["results"], doc
    for r in doc["results"]:
        t = r["device"]
        assert t["reps"] >= 1 and 0 < t["p10_ms"] <= t["median_ms"] <= t["p90_ms"], r


# -- the body tracker's long-run and first-frame scripts ----------------------------------------------
def test_soak_body_reports_its_figures(tmp_path):
    """perf/soak_body.py on numpy, 4 frames of a 3-frame loop: the figures it promises, in JSON."""
    out = tmp_path / "soak.json"
    cmd = [sys.executable, str(ROOT / "perf" / "soak_body.py"), "--device", "numpy", "--frames", "4", "--loop", "3",
           "--json", str(out), "--per-frame"]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    doc = json.loads(out.read_text())
    assert doc["device"] == "numpy" and doc["frames"] == 4 and len(doc["errors_deg"]) == 4
    assert 0.0 <= doc["lost_fraction"] <= 1.0 and doc["nan_or_kept_frames"] == 0
    assert doc["median_frame_ms"] > 0 and doc["rss_growth_mb_per_1000_frames"] is not None
    assert 0 <= doc["recovery_kept"] <= doc["recovery_passes"] and doc["predict"] is True
    assert "lost frames (an arm part > 10 deg)" in proc.stdout and "recovery passes" in proc.stdout


def test_soak_episodes():
    spec = importlib.util.spec_from_file_location("soak_body_under_test", ROOT / "perf" / "soak_body.py")
    soak = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(soak)
    lost = np.array([0, 1, 1, 0, 0, 1, 0, 1, 1, 1], bool)
    assert soak.episodes(lost) == [(1, 2), (5, 1), (7, 3)]
    assert soak.episodes(np.zeros(4, bool)) == []


def test_first_frame_times_a_fresh_and_a_warm_process(tmp_path):
    """perf/first_frame.py on numpy (nothing to compile): one run with empty caches, one warm."""
    out = tmp_path / "first.json"
    cmd = [sys.executable, str(ROOT / "perf" / "first_frame.py"), "--device", "numpy", "--warm", "1", "--json",
           str(out)]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    runs = json.loads(out.read_text())
    assert [r["caches"] for r in runs] == ["empty", "warm"]
    for r in runs:
        assert 0 < r["import_s"] <= r["device_s"] <= r["tracker_s"] <= r["first_frame_s"] <= r["process_wall_s"]
        assert r["confidence"] == 1.0


# -- the face tracker over many simulated people -------------------------------------------------------
def _face_seeds():
    spec = importlib.util.spec_from_file_location("face_seeds_under_test", ROOT / "perf" / "face_seeds.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_face_seeds_runs_and_compares(tmp_path):
    """perf/face_seeds.py on numpy, one short sequence with and without a FaceConfig change: every run in
    the JSON, the table and the paired counts printed."""
    from gputrack.models.face import load_ict

    try:
        load_ict()
    except FileNotFoundError as e:
        pytest.skip(f"the ICT face data is absent (shared/data/ict_face beside the repository, or $GPUTRACK_DATA): {e}")
    out = tmp_path / "seeds.json"
    cmd = [sys.executable, str(ROOT / "perf" / "face_seeds.py"), "--device", "numpy", "--sequence", "depth",
           "--seeds", "0", "--frames", "9", "--compare", "anchor_templates=false", "--floor", "--generic",
           "--true-points", "--json", str(out)]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    runs = json.loads(out.read_text())["runs"]
    assert sorted(json.dumps(r["overrides"]) for r in runs) == [
        '{"anchor_templates": false}', '{"generic_model": true}', '{"true_identity": true}', '{"true_points": true}',
        "{}"]  # fmt: skip
    for r in runs:
        assert r["sequence"] == "depth" and r["seed"] == 0 and r["lost"] == 0
        assert all(np.isfinite(r[c]) and r[c] >= 0 for c in ("x", "y", "z", "roll", "pitch", "yaw", "feature_px"))
    assert "with anchor_templates=False" in proc.stdout and "runs in which the default was better" in proc.stdout
    assert "  generic PCA " in proc.stdout and "  true identity " in proc.stdout and "  true points " in proc.stdout
    # the default run says where its rotation error comes from; the variants do not
    split = next(r["split"] for r in runs if not r["overrides"])
    assert sorted(split) == ["jitter", "offset", "points", "shape", "slow"]
    assert all(len(v) == 3 and all(np.isfinite(x) and x >= 0 for x in v) for v in split.values())
    assert all("split" not in r for r in runs if r["overrides"])
    assert "where the rotation error comes from" in proc.stdout
    # the true landmarks are the tracked frames' feature points (the start's are the detector's, as in every run)
    px = {json.dumps(r["overrides"]): r["feature_px"] for r in runs}
    assert px['{"true_points": true}'] < px["{}"]


def test_face_seeds_report_and_arguments():
    fs = _face_seeds()
    assert fs._seeds("0-2,5") == [0, 1, 2, 5]
    for bad in ("2-1", "x", "-1"):
        with pytest.raises(argparse.ArgumentTypeError):
            fs._seeds(bad)
    assert fs._override("anchor_templates=false") == {"anchor_templates": False}
    assert fs._override("rho=3.5") == {"rho": 3.5}
    for bad in ("nonsense=1", "rho", "particles=0", "seed=3"):
        with pytest.raises(argparse.ArgumentTypeError):
            fs._override(bad)

    def row(seq, seed, ov, v):
        return {"sequence": seq, "seed": seed, "overrides": ov, "feature_px": v,
                **{c: v for c in ("x", "y", "z", "roll", "pitch", "yaw")}}  # fmt: skip

    ov = {"rho": 3.0}
    rows = [row("turns", 0, {}, 1.0), row("turns", 0, ov, 2.0), row("turns", 1, {}, 3.0), row("turns", 1, ov, 2.0)]
    text = fs.report(rows, ("turns",), ov)
    means = [line.split() for line in text.splitlines() if line.startswith(("turns", "  with rho=3.0"))]
    assert means[0] == ["turns", "2"] + ["2.00"] * 7  # the default's mean over two seeds
    assert means[1] == ["with", "rho=3.0", "2"] + ["2.00"] * 7
    assert text.splitlines()[-1].split()[1:] == ["2"] + ["1"] * 7  # the default better in one of the two runs
    # the floor's and the generic model's runs get their own rows and stay out of the paired counts; the
    # floor's perfect-point depth (landmark_z) is set beside the tracker's z, run by run
    rows += [row("turns", 0, fs.FLOOR, 0.5) | {"landmark_z": 0.5}, row("turns", 1, fs.FLOOR, 1.5) | {"landmark_z": 3.0},
             row("turns", 0, fs.GENERIC, 9.0), row("turns", 1, fs.POINTS, 4.0)]  # fmt: skip
    text = fs.report(rows, ("turns",), ov, floor=True, generic=True, points=True)
    lines = text.splitlines()
    assert [ln.split() for ln in lines if ln.startswith("  true points")] == [["true", "points", "1"] + ["4.00"] * 7]
    assert [ln.split() for ln in lines if ln.startswith("  true identity")] == [["true", "identity", "2"] + ["1.00"] * 7]
    assert [ln.split() for ln in lines if ln.startswith("  generic PCA")] == [["generic", "PCA", "1"] + ["9.00"] * 7]
    assert lines[-1].split()[1:] == ["2"] + ["1"] * 7
    # z 1.0 against 1.15 x 0.5 (not within), 3.0 against 1.15 x 3.0 (within)
    assert [ln.split()[1:] for ln in lines if ln.startswith("turns") and "perfect points" in ln] == [
        ["2", "tracker", "2.00", "true", "identity", "1.00", "perfect", "points", "1.75", "within", "15", "%:", "1", "of",
         "2"]]  # fmt: skip
    # the rotation error's sources: the mean of each part over the default runs that have them
    rows[0]["split"] = {"offset": [1.0, 2.0, 3.0], "slow": [0.0] * 3, "jitter": [4.0] * 3, "points": [1.0] * 3,
                        "shape": [2.0] * 3}  # fmt: skip
    rows[2]["split"] = {"offset": [3.0, 2.0, 1.0], "slow": [1.0] * 3, "jitter": [2.0] * 3, "points": [1.0] * 3,
                        "shape": [0.0] * 3}  # fmt: skip
    lines = fs.report(rows, ("turns",), ov).splitlines()
    at = lines.index(next(ln for ln in lines if ln.startswith("where the rotation error comes from")))
    assert lines[at + 1].split() == ["sequence", "runs", "offset", "slow", "jitter", "points", "shape"]
    assert lines[at + 2].split() == ["turns", "2"] + ["2.00"] * 3 + ["0.50"] * 3 + ["3.00"] * 3 + ["1.00"] * 6

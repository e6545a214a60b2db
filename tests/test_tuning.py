"""The tuning cache: read, write, corruption, staleness, and the choice the launchers get."""

import inspect
import json

import numpy as np
import pytest
from conftest import deep
from tolerances import assert_matches

import gputrack
from gputrack import tuning, tuning_cache
from gputrack.ops import backend_module
from gputrack.ops.template import RgbdScene, rgbd_cost, rgbd_residuals
from gputrack.sim.problems import template_scene


def fake_clock(monkeypatch, ms):
    """Time every candidate's run as ``ms(run)`` milliseconds instead of by a clock (each run is
    still called once, so what it records is recorded): the tuner's choice then follows from the
    figures alone, the same on every run and machine."""
    from gputrack.benchmarks import harness

    def time_call(fn, sync=None, **kw):
        fn()
        s = ms(fn) * 1e-3
        return harness.Timing(s, s, s, 1)

    monkeypatch.setattr(harness, "time_call", time_call)


def make_problem(runs=None):
    """Candidates whose runs record their wg; with :func:`fake_wg_clock` wg=64 is the fastest."""
    runs = runs if runs is not None else []

    def problem(device, size, params):
        def run():
            runs.append(params["wg"])

        run.wg = params["wg"]
        return run

    return problem


def fake_wg_clock(monkeypatch):
    """wg=64 runs in 0.2 ms, every other candidate in 2 ms."""
    fake_clock(monkeypatch, lambda run: 0.2 if run.wg == 64 else 2.0)


def make_tunable(op="demo", candidates=None):
    return tuning.Tunable(
        op=op,
        backend="numpy",
        candidates=candidates or {"wg": [32, 64, 128]},
        default={"wg": 128},
        sizes=({"B": 1500, "N": 128},),
    )


@pytest.fixture
def numpy_device():
    return gputrack.device("numpy")


def test_size_bucket_rounds_up_to_powers_of_two():
    assert tuning.size_bucket({"N": 128, "B": 1500}) == "B=2048,N=128"
    assert tuning.size_bucket({"B": 1}) == "B=1"
    assert tuning.size_bucket({"B": 129}) == "B=256"


def test_tune_stores_fastest_and_choose_uses_it(tmp_path, monkeypatch, numpy_device):
    monkeypatch.setenv("GPUTRACK_TUNING_CACHE", str(tmp_path / "t.json"))
    fake_wg_clock(monkeypatch)
    t = make_tunable()
    assert tuning.choose(numpy_device, t, {"B": 1500, "N": 128}) == {"wg": 128}  # default
    chosen = tuning.tune(numpy_device, t, problem=make_problem(), min_time=0.005)
    assert chosen == {"B=2048,N=128": {"wg": 64}}
    assert tuning.choose(numpy_device, t, {"B": 1500, "N": 128}) == {"wg": 64}
    assert tuning.choose(numpy_device, t, {"B": 1025, "N": 100}) == {"wg": 64}  # same bucket
    assert tuning.choose(numpy_device, t, {"B": 10, "N": 128}) == {"wg": 128}  # other bucket: default
    doc = json.loads((tmp_path / "t.json").read_text())
    (key,) = doc["devices"]
    assert key.startswith("numpy|NumPy")
    assert set(doc["devices"][key]["demo"]["B=2048,N=128"]["timings_ms"]) == {
        json.dumps({"wg": w}) for w in (32, 64, 128)
    }


def test_corrupt_cache_is_ignored_with_warning(tmp_path, monkeypatch, numpy_device):
    path = tmp_path / "t.json"
    path.write_text("{not json")
    monkeypatch.setenv("GPUTRACK_TUNING_CACHE", str(path))
    with pytest.warns(RuntimeWarning, match="ignoring the tuning cache"):
        assert tuning.choose(numpy_device, make_tunable(), {"B": 1500, "N": 128}) == {"wg": 128}


def test_stale_or_invalid_entries_are_ignored_with_warning(tmp_path, numpy_device):
    cache = tuning.TuningCache(tmp_path / "t.json")
    t = make_tunable()
    cache.put(numpy_device, t, {"B": 1500, "N": 128}, {"wg": 64})
    cache.save()
    assert tuning.TuningCache(tmp_path / "t.json").get(numpy_device, t, {"B": 1500, "N": 128}) == {"wg": 64}
    # the candidate grid (or kernel source) changed: the entry is stale
    t2 = make_tunable(candidates={"wg": [32, 64, 128, 256]})
    with pytest.warns(RuntimeWarning, match="stale"):
        assert tuning.TuningCache(tmp_path / "t.json").get(numpy_device, t2, {"B": 1500, "N": 128}) is None
    # a value outside the candidates
    doc = json.loads((tmp_path / "t.json").read_text())
    entry = next(iter(doc["devices"].values()))["demo"]["B=2048,N=128"]
    entry["params"] = {"wg": 48}
    (tmp_path / "t.json").write_text(json.dumps(doc))
    with pytest.warns(RuntimeWarning, match="wg=48 is not one of"):
        assert tuning.TuningCache(tmp_path / "t.json").get(numpy_device, t, {"B": 1500, "N": 128}) is None


def test_wrong_version_is_ignored(tmp_path, numpy_device):
    (tmp_path / "t.json").write_text(json.dumps({"version": 99, "devices": {}}))
    with pytest.warns(RuntimeWarning, match="expected a version 1 tuning cache"):
        assert tuning.TuningCache(tmp_path / "t.json").get(numpy_device, make_tunable(), {"B": 1}) is None


def test_a_tunable_without_a_problem_cannot_be_swept(numpy_device):
    with pytest.raises(ValueError, match="expected an op with a problem in gputrack.tuning.PROBLEMS"):
        tuning.tune(numpy_device, make_tunable(op="no_such_op"), min_time=0.001)


# -- the template ops' tunables ----------------------------------------------------------------


REF = gputrack.device("numpy")

#: the function of each backend's template module that launches gt_rgbd with the chosen ``params``
LAUNCHER = {"opencl": "_run", "taichi": "_common"}


def spy_launches(monkeypatch, backend_mod, backend):
    """Record the ``params`` each rgbd launch of ``backend_mod`` runs with."""
    launched = []
    real = getattr(backend_mod, LAUNCHER[backend])
    sig = inspect.signature(real)

    def run(*a, **kw):
        launched.append(sig.bind(*a, **kw).arguments["params"])
        return real(*a, **kw)

    monkeypatch.setattr(backend_mod, LAUNCHER[backend], run)
    return launched


def force_choice(monkeypatch, params, asked=None):
    """The tuning cache answers ``params`` for every tunable (and records the ops asked for)."""

    def choose(dev, t, size):
        if asked is not None:
            asked.append(t.op)
        return dict(params)

    monkeypatch.setattr(tuning_cache, "choose", choose)


def _scene(b=37, n=29, m=31):
    rng = np.random.default_rng(b * 1000 + n)
    return template_scene(rng, b=b, j=3, n=n, m=m, h=48, w=64)


def test_every_backend_has_tunables_with_the_default_among_the_candidates(device):
    found = tuning.tunables(device.backend)
    if device.backend == "numpy":
        assert found == []
        return
    want = {"rgbd_cost", "rgbd_residuals"} | ({"kalman"} if device.backend == "opencl" else set())
    assert {t.op for t in found} == want
    for t in found:
        default = t.default_for(device)
        assert default in t.grid(), f"{t.op}: default {default} is not a candidate"
        assert len(t.grid()) > 1
        assert t.fingerprint() == t.fingerprint() and len(t.fingerprint()) == 16


def _candidates(tunable) -> list[dict]:
    """Every combination in the deep profile; by default each candidate value at least once
    (Tunable.cover: each value changes the build or the launch on its own)."""
    return tunable.grid() if deep() else tunable.cover()


def test_cover_tries_every_value():
    t = tuning_cache.Tunable("op", "opencl", {"lanes": [1, 4, 8, 16], "work_group": [None, 16]}, {}, ())
    assert t.cover() == [{"lanes": 1, "work_group": None}, {"lanes": 4, "work_group": 16},
                         {"lanes": 8, "work_group": None}, {"lanes": 16, "work_group": 16}]  # fmt: skip
    assert len(t.grid()) == 8


def test_every_candidate_matches_the_reference(device, monkeypatch):
    """Results do not depend on the launch parameters: every candidate, through the public ops."""
    if device.backend == "numpy":
        pytest.skip("the reference has no launch parameters")
    tf, rgb, dep, gray, depth, cam = _scene()
    scene = RgbdScene(rgb, dep, cam, c_depth=0.05)
    want = rgbd_cost(REF, tf, scene, gray, depth)
    want_res = rgbd_residuals(REF, tf, scene, gray, depth)
    backend = backend_module(device, "template")
    launched = spy_launches(monkeypatch, backend, device.backend)
    asked = []
    for op in ("rgbd_cost", "rgbd_residuals"):
        for params in _candidates(backend.TUNABLES[op]):
            force_choice(monkeypatch, params, asked)
            launched.clear()
            asked.clear()
            if op == "rgbd_cost":
                got = rgbd_cost(device, tf, scene, gray, depth)
                for f in ("total", "rgb", "depth"):
                    assert_matches(device, getattr(got, f), getattr(want, f), err_msg=f"{op} {f} {params}")
            else:
                got = rgbd_residuals(device, tf, scene, gray, depth)
                assert_matches(device, got, want_res, scale=5.0, err_msg=f"{op} {params}")
            assert launched == [params] and asked == [op]


def _fake_fast(monkeypatch, tunable, winner):
    """(the real tunable on a tiny size, a problem where ``winner`` is clearly the fastest: 0.2 ms
    against 2 ms on the fake clock)."""
    import dataclasses

    def problem(device, size, params):
        def run():
            pass

        run.params = params
        return run

    fake_clock(monkeypatch, lambda run: 0.2 if run.params == winner else 2.0)
    return dataclasses.replace(tunable, sizes=({"B": 37, "N": 29},)), problem


def test_cli_tune_stores_a_choice_and_the_op_uses_it(device, tmp_path, monkeypatch, capsys):
    from gputrack import cli

    if device.backend == "numpy":
        assert cli.main(["tune", "--device", "numpy"]) == 0
        assert "nothing to tune" in capsys.readouterr().out
        return
    monkeypatch.setenv("GPUTRACK_TUNING_CACHE", str(tmp_path / "tuning.json"))
    backend = backend_module(device, "template")
    real = backend.TUNABLES["rgbd_cost"]
    default = real.default_for(device)
    winner = next(p for p in reversed(real.grid()) if p != default)
    fake, problem = _fake_fast(monkeypatch, real, winner)
    monkeypatch.setitem(backend.TUNABLES, "rgbd_cost", fake)
    monkeypatch.setitem(tuning.PROBLEMS, "rgbd_cost", problem)

    tf, rgb, dep, gray, depth, cam = _scene()
    scene = RgbdScene(rgb, dep, cam)
    launched = spy_launches(monkeypatch, backend, device.backend)
    rgbd_cost(device, tf, scene, gray, depth)
    assert launched == [default]  # no cache entry yet

    assert cli.main(["tune", "--device", device.spec, "--op", "rgbd_cost", "--min-time", "0.001"]) == 0
    captured = capsys.readouterr()
    assert "<- chosen" in captured.out and "[tune]" in captured.err  # table, and progress while it ran
    doc = json.loads((tmp_path / "tuning.json").read_text())
    (entry,) = doc["devices"].values()
    assert entry["rgbd_cost"]["B=64,N=32"]["params"] == winner

    launched.clear()
    got = rgbd_cost(device, tf, scene, gray, depth)
    assert launched == [winner]
    want = rgbd_cost(REF, tf, scene, gray, depth)
    assert_matches(device, got.total, want.total)
    # another size bucket keeps the default
    launched.clear()
    rgbd_cost(device, tf[:3], scene, gray, depth)
    assert launched == [default]


def test_cli_tune_unknown_op_is_an_error(device, capsys):
    from gputrack import cli

    assert cli.main(["tune", "--device", device.spec, "--op", "no_such_op"]) == 2
    err = capsys.readouterr().err
    assert "unknown --op no_such_op" in err
    if device.backend != "numpy":
        assert "rgbd_cost" in err


def test_cli_tune_rejects_a_bad_min_time(capsys):
    from gputrack import cli

    assert cli.main(["tune", "--device", "numpy", "--min-time", "0"]) == 2
    assert "--min-time" in capsys.readouterr().err


def test_a_failing_candidate_is_skipped(tmp_path, numpy_device, monkeypatch):
    fake_wg_clock(monkeypatch)
    runs = []
    t = make_tunable()
    ok_problem = make_problem(runs)

    def problem(device, size, params):
        if params["wg"] == 64:
            raise RuntimeError("work-group size not supported")
        return ok_problem(device, size, params)

    reports = []
    cache = tuning.TuningCache(tmp_path / "t.json")
    chosen = tuning.tune(numpy_device, t, problem=problem, cache=cache, min_time=0.002,
                         report=lambda *a: reports.append(a))  # fmt: skip
    assert chosen["B=2048,N=128"] == {"wg": 128}  # 32 and 128 tie (2 ms): the default is kept
    ((_size, trials, _best),) = reports
    failed = [tr for tr in trials if tr.timing is None]
    assert [tr.params for tr in failed] == [{"wg": 64}] and "not supported" in failed[0].error
    assert 64 not in runs


@pytest.mark.parametrize("fast, expected", [(0.99, 128), (0.5, 32)])
def test_the_default_is_kept_unless_clearly_faster(tmp_path, numpy_device, monkeypatch, fast, expected):
    """A candidate 1% faster than the default (noise) does not replace it; one 2x faster does."""
    from gputrack.benchmarks import harness

    ms = {32: fast, 64: 1.2, 128: 1.0}  # the default is wg=128

    def problem(device, size, params):
        def run():
            pass

        run.wg = params["wg"]
        return run

    def fake_time_call(fn, sync=None, **kw):
        s = ms[fn.wg] * 1e-3
        return harness.Timing(s, s, s, 5)

    monkeypatch.setattr(harness, "time_call", fake_time_call)
    chosen = tuning.tune(numpy_device, make_tunable(), problem=problem, cache=tuning.TuningCache(tmp_path / "t.json"),
                         min_time=0.002)  # fmt: skip
    assert chosen == {"B=2048,N=128": {"wg": expected}}


def test_op_with_a_corrupt_cache_warns_and_uses_the_default(device, tmp_path, monkeypatch):
    if device.backend == "numpy":
        pytest.skip("the reference has no launch parameters")
    path = tmp_path / "tuning.json"
    path.write_text('{"version": 1, "devices": ')
    monkeypatch.setenv("GPUTRACK_TUNING_CACHE", str(path))
    tf, rgb, dep, gray, depth, cam = _scene()
    scene = RgbdScene(rgb, dep, cam)
    with pytest.warns(RuntimeWarning, match="ignoring the tuning cache"):
        got = rgbd_cost(device, tf, scene, gray, depth)
    assert_matches(device, got.total, rgbd_cost(REF, tf, scene, gray, depth).total)


def test_every_kalman_candidate_matches_the_reference(device, monkeypatch):
    """The OpenCL filter kernels' tracks per work-item and work-group sizes: identical results."""
    from gputrack.ops import kalman

    found = tuning.tunables(device.backend, "kalman")
    if not found:
        pytest.skip(f"no Kalman launch parameters on {device.backend}")
    rng = np.random.default_rng(11)
    T = 37  # not a multiple of any lane count or work-group size
    F, Q = kalman.constant_velocity(3, 1.0 / 30, 1.0)
    H = np.zeros((3, 6), np.float32)
    H[0, 0] = H[1, 2] = H[2, 4] = 1
    R = (0.05 * np.eye(3)).astype(np.float32)
    x = rng.normal(0, 1, (T, 6)).astype(np.float32)
    x[:, 4] += 5.0  # positive depth for the stereo EKF
    P = np.tile(np.diag([0.1, 1.0] * 3).astype(np.float32), (T, 1, 1))
    z = rng.normal(0, 1, (T, 3)).astype(np.float32)
    zs = np.stack([400 * x[:, 0] / x[:, 4], 400 * x[:, 2] / x[:, 4], 40 / x[:, 4]], 1).astype(np.float32)
    mask = np.arange(T) % 5 != 2
    want = kalman.kf_update(REF, x, P, z, H, R, mask=mask, predict=(F, Q))
    want_p = kalman.kf_predict(REF, x, P, F, Q)
    want_s = kalman.ekf_update_stereo(REF, x, P, zs + 0.3, R, f=400.0, b=0.1)
    (tunable,) = found
    asked = []
    for params in _candidates(tunable):
        force_choice(monkeypatch, params, asked)
        asked.clear()
        got = kalman.kf_update(device, x, P, z, H, R, mask=mask, predict=(F, Q))
        for g, w, name in zip(got, want, ("x", "P", "status")):
            if name == "status":
                np.testing.assert_array_equal(gputrack.to_numpy(g), w, err_msg=f"{params}")
            else:
                assert_matches(device, g, w, err_msg=f"kf_update {name} {params}")
        for g, w in zip(kalman.kf_predict(device, x, P, F, Q), want_p):
            assert_matches(device, g, w, err_msg=f"kf_predict {params}")
        for g, w in zip(kalman.ekf_update_stereo(device, x, P, zs + 0.3, R, f=400.0, b=0.1)[:2], want_s[:2]):
            assert_matches(device, g, w, err_msg=f"ekf_update_stereo {params}")
        assert asked == ["kalman"] * 3  # each op launched with the forced choice


def test_a_bad_entry_warns_once_and_lookups_are_memoised(tmp_path, numpy_device):
    import warnings

    cache = tuning.TuningCache(tmp_path / "t.json")
    t = make_tunable()
    cache.put(numpy_device, t, {"B": 1500, "N": 128}, {"wg": 64})
    cache.save()
    doc = json.loads((tmp_path / "t.json").read_text())
    next(iter(doc["devices"].values()))["demo"]["B=2048,N=128"]["fingerprint"] = "0" * 16
    (tmp_path / "t.json").write_text(json.dumps(doc))
    fresh = tuning.TuningCache(tmp_path / "t.json")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for b in (1500, 1500, 1100, 2048):  # one bucket, several sizes
            assert fresh.get(numpy_device, t, {"B": b, "N": 128}) is None
    # one warning per distinct size asked for, none for repeats
    assert len([w for w in caught if "stale" in str(w.message)]) == 3
    # put() forgets the memo: the new choice is seen at once
    fresh.put(numpy_device, t, {"B": 1500, "N": 128}, {"wg": 32})
    assert fresh.get(numpy_device, t, {"B": 1500, "N": 128}) == {"wg": 32}

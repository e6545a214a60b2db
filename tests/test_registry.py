"""Device discovery and selection, the CLI, the doctor and the wheel."""

import json
import os
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest

import gputrack

ROOT = Path(__file__).resolve().parents[1]
SPECS = {"numpy", "taichi:cpu", "taichi:vulkan", "taichi:cuda", "opencl"}


def run_py(code: str, env=None, timeout=300):
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=timeout, cwd=ROOT,
        env={**os.environ, **(env or {})},
    )


def test_devices_lists_every_backend_with_reason():
    infos = gputrack.devices()
    specs = [d.spec for d in infos]
    assert SPECS <= set(specs)
    assert len(specs) == len(set(specs))
    for d in infos:
        if d.available:
            assert d.name, d
        else:
            assert d.reason and "\n" not in d.reason, d
    opencl_named = [d for d in infos if d.spec.startswith("opencl:")]
    assert all(d.backend == "opencl" for d in opencl_named)


def test_unknown_spec_lists_valid_forms():
    with pytest.raises(ValueError, match=r"unknown device spec 'cuda'.*taichi:cpu.*opencl:<"):
        gputrack.device("cuda")
    with pytest.raises(ValueError, match="unknown device spec"):
        gputrack.device("taichi:metal")
    with pytest.raises(TypeError, match="expected a device spec string"):
        gputrack.device(3)


def test_unavailable_spec_names_reason_and_available_specs():
    with pytest.raises(gputrack.DeviceUnavailable, match=r"no OpenCL device matches 'no-such-device'.*Available: numpy"):
        gputrack.device("opencl:no-such-device")


def test_unavailable_cuda_reason_when_there_is_no_gpu():
    cuda = next(d for d in gputrack.devices() if d.spec == "taichi:cuda")
    if cuda.available:
        pytest.skip("this machine has CUDA")
    r = run_py("""
        import gputrack
        try:
            gputrack.device("taichi:cuda")
        except gputrack.DeviceUnavailable as e:
            print("UNAVAILABLE", e)
    """)
    assert "UNAVAILABLE taichi:cuda is not available" in r.stdout, r.stderr
    assert "Available: numpy" in r.stdout


def test_default_device_honours_env_and_prefers_gpu():
    r = run_py("import gputrack; print('SPEC', gputrack.device().spec)", env={"GPUTRACK_DEVICE": "numpy"})
    assert "SPEC numpy" in r.stdout, r.stderr
    r = run_py("import gputrack; print('SPEC', gputrack.device().spec)", env={"GPUTRACK_DEVICE": ""})
    infos = {d.spec: d for d in gputrack.devices()}
    if infos["taichi:cuda"].available:
        expected = "taichi:cuda"
    elif infos["taichi:vulkan"].available and infos["taichi:vulkan"].kind == "gpu":
        expected = "taichi:vulkan"
    elif infos["opencl"].available and infos["opencl"].kind == "gpu":
        expected = "opencl"
    else:
        expected = "taichi:cpu"
    assert f"SPEC {expected}" in r.stdout, r.stderr


def test_second_taichi_arch_is_refused_not_reset():
    r = run_py("""
        import numpy as np, gputrack
        cpu = gputrack.device("taichi:cpu")
        a = cpu.asarray(np.arange(5, dtype=np.float32))
        try:
            gputrack.device("taichi:vulkan")
        except gputrack.TaichiArchConflict as e:
            print("CONFLICT", e)
        print("INTACT", a.numpy().tolist())
        cpu.close()
        try:
            a.numpy()
        except gputrack.DeviceUnavailable as e:
            print("CLOSED", e)
    """)
    assert "CONFLICT Taichi already runs on taichi:cpu" in r.stdout, r.stderr
    assert "INTACT [0.0, 1.0, 2.0, 3.0, 4.0]" in r.stdout
    assert "CLOSED taichi:cpu was closed" in r.stdout


def test_cli_devices_text_and_json():
    text = subprocess.run([sys.executable, "-m", "gputrack.cli", "devices"], capture_output=True, text=True, cwd=ROOT)
    assert text.returncode == 0, text.stderr
    for spec in SPECS:
        assert spec in text.stdout
    js = subprocess.run([sys.executable, "-m", "gputrack.cli", "devices", "--json"], capture_output=True, text=True, cwd=ROOT)
    rows = json.loads(js.stdout)
    assert SPECS <= {r["spec"] for r in rows}
    for r in rows:
        assert {"spec", "available", "reason", "fp64", "name"} <= set(r)
        assert r["available"] or r["reason"]


def test_doctor_passes_on_available_devices_and_fails_on_missing_requirement(tmp_path):
    # one run of `gputrack doctor` (it builds every OpenCL kernel on every OpenCL device and self-tests
    # the devices asked for: numpy and opencl here, for the suite's time; every device's self-tests run
    # in the op tests and tests/test_doctor.py): a required spec that does not exist is its only
    # problem, and it makes the exit status 1. Its other failure paths (a failing self-test, a
    # self-test process that dies): tests/test_doctor.py
    run = subprocess.run([sys.executable, "-m", "gputrack.cli", "doctor", "--require", "numpy,opencl:no-such-device",
                          "--device", "numpy", "--device", "opencl", "--json", str(tmp_path / "r.json")],
                         capture_output=True, text=True, cwd=ROOT, timeout=600)  # fmt: skip
    assert run.returncode == 1, run.stdout + run.stderr
    assert "opencl:no-such-device: unknown spec" in run.stdout
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["problems"] == ["opencl:no-such-device: unknown spec"], report["problems"]
    assert report["builds"] and all(r["ok"] for r in report["builds"])
    assert all(r["ok"] for rows in report["selftests"].values() for r in rows)
    opencl = [d for d in report["devices"] if d["spec"] == "opencl"]
    assert set(report["selftests"]) == ({"numpy", "opencl"} if opencl[0]["available"] else {"numpy"})
    checks = [name for name, _ in __import__("gputrack.selftest", fromlist=["CHECKS"]).CHECKS]
    for spec, rows in report["selftests"].items():
        assert [r["check"] for r in rows] == checks, (spec, rows)


def test_wheel_ships_kernels_and_nothing_stray(tmp_path):
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path), str(ROOT)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    (wheel,) = tmp_path.glob("gputrack-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    kernels = sorted(p.name for p in (ROOT / "kernels").iterdir() if p.suffix in (".cl", ".clh"))
    assert kernels and sorted(n.split("/")[-1] for n in names if n.startswith("gputrack/kernels/")) == kernels
    for n in names:
        assert n.startswith(("gputrack/", "gputrack-0.1.0.dist-info/")), n
        assert "__pycache__" not in n and not n.endswith(".pyc"), n
    assert "gputrack/__init__.py" in names and "gputrack/cli.py" in names
    # the doctor of the installed wheel (its files alone on the path, run from elsewhere): it finds
    # the wheel's kernels, builds them on every OpenCL device and passes its self-tests
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    env = {**os.environ, "PYTHONPATH": str(site)}
    run = subprocess.run([sys.executable, "-c", "import gputrack, sys; print(gputrack.__file__); "
                          "from gputrack.cli import main; sys.exit(main(['doctor', '--device', 'numpy']))"],
                         capture_output=True, text=True, cwd=tmp_path, env=env, timeout=600)  # fmt: skip
    assert run.returncode == 0, run.stdout + run.stderr
    assert run.stdout.splitlines()[0] == str(site / "gputrack" / "__init__.py")
    entry = zipfile.ZipFile(wheel).read("gputrack-0.1.0.dist-info/entry_points.txt").decode()
    assert "gputrack = gputrack.cli:main" in entry


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    blocks = [b.split("```", 1)[0].strip() for b in readme.split("```sh")[1:]]
    test_cmd = next(b for b in blocks if "pytest" in b)
    assert test_cmd in ci
    assert "GPUTRACK_REQUIRE=taichi:cpu,taichi:vulkan,opencl" in ci


def test_closing_a_taichi_device_drops_the_arrays_cached_for_it():
    """Scratch buffers, constants, template copies, solver pools, memoised values and the caching
    allocator's buffers of a closed Taichi device go with it (a Taichi array kept past a restart corrupts the next program's memory), and a
    restarted device computes what the first one did."""
    r = run_py("""
        import numpy as np, gputrack
        from gputrack.sim.problems import pf_scene
        from gputrack.device import _CACHES
        from gputrack.backends.taichi import launch

        def work(dev):
            tf, rgb, dep, gray, depth, cam = pf_scene(np.random.default_rng(0), b=64)
            total = gputrack.rgbd_cost(dev, tf.astype(np.float32), gputrack.RgbdScene(rgb, dep, cam), gray, depth).total
            best = gputrack.best_k(dev, total, 5)
            res = gputrack.least_squares(lambda x: gputrack.to_numpy(x) - 1.0, np.zeros((3, 2)), device=dev)
            return np.concatenate([gputrack.to_numpy(total), gputrack.to_numpy(best.indices), res.x.ravel()])

        dev = gputrack.device("taichi:cpu")
        first = work(dev)
        memo, pooled = len(dev._memo), dev.pool_stats().held_buffers
        launched = len(launch._cache)
        dev.close()
        held = sum(1 for ref in _CACHES if ref() is not None and dev in ref())
        print("HELD", held, "MEMO", len(dev._memo), "POOL", dev.pool_stats().held_buffers, "BEFORE", memo > 0)
        # the compiled kernels of direct launches hold the program: kept past the reset, it was
        # destroyed inside the next program's life and that one's kernels segfaulted now and then
        print("LAUNCH CACHE", len(launch._cache), "BEFORE", launched > 0)
        again = gputrack.device("taichi:cpu")
        same = all(np.array_equal(work(again), first) for _ in range(3))
        print("SAME", same)
    """)
    assert "HELD 0 MEMO 0 POOL 0 BEFORE True" in r.stdout, r.stdout + r.stderr
    assert "LAUNCH CACHE 0 BEFORE True" in r.stdout, r.stdout + r.stderr
    assert "SAME True" in r.stdout, r.stdout + r.stderr


def test_arrays_kept_past_a_taichi_restart_leave_the_next_program_intact():
    """Arrays of a closed Taichi device that the caller still holds neither free nor overwrite the
    next program's arrays (direct launches are turned off then; see backends/taichi/launch.py)."""
    r = run_py("""
        import numpy as np, gputrack
        cpu = gputrack.device("taichi:cpu")
        old = [cpu.asarray(np.full(1000, i, np.float32)) for i in range(50)]
        cpu.close()
        again = gputrack.device("taichi:cpu")
        new = [again.asarray(np.full(1000, 100 + i, np.float32)) for i in range(50)]
        del old[::2]
        more = [again.asarray(np.full(1000, 200 + i, np.float32)) for i in range(50)]
        bad = [i for i, a in enumerate(new) if not (a.numpy() == 100 + i).all()]
        bad += [i for i, a in enumerate(more) if not (a.numpy() == 200 + i).all()]
        print("BAD", bad)
    """)
    assert "BAD []" in r.stdout, r.stdout + r.stderr


def test_a_closed_taichi_device_and_its_arrays_are_unavailable():
    """Tracking after close() (a Taichi-internal AttributeError before) and an array of the closed
    device given to the reopened one (a message naming taichi:cpu twice): DeviceUnavailable."""
    code = """
        import numpy as np, gputrack
        from gputrack.models import upper_body
        from gputrack.trackers.body import BodyTracker
        dev = gputrack.device("taichi:cpu")
        old = dev.asarray(np.zeros(5, np.float32))
        tracker = BodyTracker(dev, upper_body().rest_params())
        dev.close()
        again = gputrack.device("taichi:cpu")
        frame = np.zeros((480, 640), np.float32)
        for name, call in (("track", lambda: tracker.track(frame, frame)), ("sync", dev.synchronize),
                           ("op", lambda: gputrack.best_k(again, old, 1)), ("upload", lambda: again.asarray(old))):
            try:
                call()
                print(name, "no error")
            except Exception as e:
                print(name, type(e).__name__, e)
    """
    r = run_py(code)
    closed = "DeviceUnavailable taichi:cpu was closed; get a new device with gputrack.device('taichi:cpu')"
    assert f"track {closed}" in r.stdout and f"sync {closed}" in r.stdout, (r.stdout, r.stderr)
    other = "expected an array on taichi:cpu, got an array of a closed taichi:cpu device"
    assert f"op DeviceUnavailable scores: {other}" in r.stdout and f"upload DeviceUnavailable {other}" in r.stdout


def test_taichi_cpu_thread_count_follows_the_environment():
    code = """
        import gputrack, taichi as ti
        from gputrack.backends.taichi.runtime import cpu_threads
        try:
            print("DEFAULT", cpu_threads())
            gputrack.device("taichi:cpu")
            print("THREADS", ti.lang.impl.current_cfg().cpu_max_num_threads)
            print("CACHE", ti.lang.impl.current_cfg().offline_cache_max_size_of_files)
        except Exception as e:
            print("ERROR", type(e).__name__, e)
    """
    r = run_py(code, env={"GPUTRACK_CPU_THREADS": "3"})
    assert "THREADS 3" in r.stdout, (r.stdout, r.stderr)
    assert "DEFAULT 3" in r.stdout
    assert f"CACHE {1 << 30}" in r.stdout  # not Taichi's default 100 MB
    # a value that is not a positive integer: a warning naming it, and the default
    default = 2 * len(os.sched_getaffinity(0))
    r = run_py(code, env={"GPUTRACK_CPU_THREADS": "two"})
    assert f"THREADS {default}" in r.stdout, (r.stdout, r.stderr)
    assert "RuntimeWarning: GPUTRACK_CPU_THREADS: expected a positive integer, got 'two'" in r.stderr, r.stderr
    env = {k: v for k, v in os.environ.items() if k != "GPUTRACK_CPU_THREADS"}
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=300,
                       cwd=ROOT, env=env)  # fmt: skip
    assert f"DEFAULT {2 * len(os.sched_getaffinity(0))}" in r.stdout, (r.stdout, r.stderr)


# -- a backend is one row of the registry table ----------------------------------------------------
def types_module(name):
    import types

    mod = types.ModuleType(name)
    mod.__path__ = []  # a package
    return mod


class _HostDevice(gputrack.Device):
    """A device whose arrays are DeviceArrays over host NumPy buffers (for the fake backend)."""

    backend = "fakehost"

    def _upload(self, host):
        return host.copy()

    def _upload_into(self, buffer, host):
        np.copyto(buffer, host)

    def _download(self, buffer, shape, dtype):
        return buffer.copy()

    def _empty(self, shape, dtype):
        return np.empty(shape, dtype)


def _fake_kalman_module():
    """``<package>.kalman`` of the fake backend: the NumPy reference over the DeviceArrays' buffers."""
    import types

    from gputrack.backends.reference import kalman as ref

    mod = types.ModuleType("fakehost_impl.kalman")

    def kf_predict(device, x, P, F, Q, out=None, pats=None):
        mod.calls += 1
        xo, Po = ref.kf_predict(None, x.buffer, P.buffer, F.buffer, Q.buffer)
        return tuple(device.asarray(a) for a in (xo, Po))

    mod.kf_predict = kf_predict
    mod.calls = 0
    return mod


@pytest.fixture
def fake_backend(monkeypatch):
    from gputrack import registry
    from gputrack.device import DeviceInfo

    info = DeviceInfo("fakehost", "fakehost", True, name="host memory", fp64=True, kind="cpu")
    package = types_module("fakehost_impl")
    kalman = _fake_kalman_module()
    monkeypatch.setitem(sys.modules, "fakehost_impl", package)
    monkeypatch.setitem(sys.modules, "fakehost_impl.kalman", kalman)
    row = registry.Backend(
        name="fakehost",
        forms=("fakehost",),
        specs=("fakehost",),
        parse=lambda s: "" if s.lower() == "fakehost" else None,
        probe=lambda: info,
        open=lambda arg: _HostDevice(info),
        package="fakehost_impl",
        preference=lambda i: None,
    )
    registry.register(row)
    yield kalman
    registry.unregister("fakehost")


def test_a_backend_registered_as_one_row_is_listed_opened_and_runs_the_ops(fake_backend):
    from gputrack import registry
    from gputrack.ops import backend_module
    from gputrack.ops.kalman import constant_velocity, kf_predict

    infos = {d.spec: d for d in gputrack.devices()}
    assert infos["fakehost"].available and infos["fakehost"].backend == "fakehost"
    assert SPECS <= set(infos)  # the other rows are still there
    assert "fakehost" in registry.specs() and "fakehost" in registry.spec_forms()
    dev = gputrack.device("fakehost")
    assert isinstance(dev, _HostDevice) and gputrack.device(" FakeHost ") is dev
    assert backend_module(dev, "kalman") is fake_backend

    rng = np.random.default_rng(0)
    F, Q = constant_velocity(3, 0.5, 0.2)
    x = rng.normal(size=(13, 6)).astype(np.float32)
    P = np.tile(np.eye(6, dtype=np.float32), (13, 1, 1))
    xp, Pp = kf_predict(dev, x, P, F, Q)
    assert fake_backend.calls == 1
    assert isinstance(xp, gputrack.DeviceArray) and xp.device is dev
    want = kf_predict(gputrack.device("numpy"), x, P, F, Q)
    np.testing.assert_array_equal(xp.numpy(), want[0])
    np.testing.assert_array_equal(Pp.numpy(), want[1])

    # the default device never picks a backend whose preference is None
    assert registry._default_spec() != "fakehost"


def test_an_unregistered_backend_is_gone():
    from gputrack import registry

    assert "fakehost" not in {d.spec for d in gputrack.devices()}
    with pytest.raises(ValueError, match="unknown device spec 'fakehost'"):
        gputrack.device("fakehost")
    with pytest.raises(ValueError, match="unknown backend 'fakehost'"):
        registry.backend_for("fakehost")
    with pytest.raises(TypeError, match="expected a gputrack.registry.Backend"):
        registry.register("fakehost")


def test_the_test_fixture_and_the_registry_list_the_same_specs():
    from conftest import ALL_SPECS

    from gputrack import registry

    assert ALL_SPECS == registry.specs()
    assert {"numpy", "taichi:cpu", "taichi:vulkan", "taichi:cuda", "opencl"} == set(ALL_SPECS)
    for row in registry.BACKENDS:
        assert row.package.startswith("gputrack.backends.")
        for spec in row.specs:
            assert row.parse(spec) is not None

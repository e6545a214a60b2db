"""The profiler (per-stage time and bytes) and the host scheduler (declared stages over device buffers)."""

import numpy as np
import pytest

import gputrack
from gputrack import Profiler, Scheduler, SkipFrame, Stage


def test_profiler_counts_bytes_and_time(device):
    prof = Profiler(device)
    x = np.random.default_rng(1).random((127, 3), dtype=np.float32)
    frames = []
    for _ in range(3):
        with prof.frame() as f:
            with prof.stage("upload"):
                d = device.asarray(x)
            with prof.stage("work"):
                out = device.empty((127, 3), np.float32)
            with prof.stage("download"):
                back = gputrack.to_numpy(d)
        frames.append(f)
        np.testing.assert_array_equal(back, x)
        assert out.shape == (127, 3)
    moved = 0 if device.backend == "numpy" else x.nbytes
    for f in frames:
        assert f.h2d == moved and f.d2h == moved
        assert f.stages["work"][1:] == (0, 0)
        assert f.wall_s >= sum(s[0] for s in f.stages.values()) * 0.5
    stats = {r["name"]: r for r in prof.report()}
    assert stats["upload"]["calls"] == 3 and stats["upload"]["h2d_bytes"] == 3 * moved
    assert stats["download"]["d2h_bytes"] == 3 * moved and stats["download"]["h2d_bytes"] == 0
    assert all(r["median_ms"] >= 0 for r in stats.values())
    table = prof.table()
    assert "upload" in table and "download" in table and device.spec in table


def test_profiler_rejects_bad_use(device):
    with pytest.raises(TypeError, match="expected a gputrack.Device"):
        Profiler("numpy")
    prof = Profiler(device)
    with pytest.raises(ValueError, match="non-empty stage name"):
        with prof.stage(""):
            pass
    with pytest.raises(RuntimeError, match="frame inside a frame"):
        with prof.frame():
            with prof.frame():
                pass


def _kalman_like(device, calls):
    """A three-stage frame: scale the state by the input on the device, a host stage that reads the
    product, and a device stage that adds the host's sum. ``calls`` records what each stage saw."""
    def scale(b):
        x = gputrack.to_numpy(b["x"]) if device.backend != "numpy" else b["x"]
        calls.append(("scale", type(b["z"]).__name__))
        b["y"] = device.asarray((x * gputrack.to_numpy(b["z"])).astype(np.float32), out=b.get("y"))

    def total(b):
        calls.append(("total", type(b["y"]).__name__))
        b["s"] = np.float32(b["y"].sum())

    def add(b):
        x = gputrack.to_numpy(b["y"]) + b["s"]
        b["x"] = device.asarray(x.astype(np.float32), out=b["x"])

    return [
        Stage("scale", scale, reads=("x", "z"), writes=("y",)),
        Stage("total", total, host_reads=("y",), writes=("s",)),
        Stage("add", add, reads=("y", "s", "x"), writes=("x",)),
    ]


def test_scheduler_runs_stages_in_order_with_state_and_reused_buffers(device):
    calls = []
    sched = Scheduler(device, _kalman_like(device, calls), inputs=("z",), state=("x",), outputs=("x", "s"))
    x0 = np.arange(5, dtype=np.float32)
    sched.set("x", x0)
    x_first = sched.buffers["x"]
    want = x0.astype(np.float64)
    z_arrays = []
    for k in range(4):
        z = np.full(5, 0.5 + k, np.float32)
        out = sched.run(z=z)
        y = want * z
        want = y + y.astype(np.float32).sum()
        np.testing.assert_allclose(out["x"], want, rtol=1e-5)
        assert isinstance(out["x"], np.ndarray) and float(out["s"]) == pytest.approx(y.sum(), rel=1e-5)
        z_arrays.append(sched.buffers["z"])
    # the input went into the same device array every frame; the state array is the one first set
    assert all(a is z_arrays[0] for a in z_arrays)
    assert sched.buffers["x"] is x_first
    x0[:] = -1  # the caller's array was copied, never kept
    assert sched.buffers["x"] is not x0
    assert ("total", "ndarray") in calls  # the host stage saw NumPy data
    assert len(sched.frames) == 4 and [r["name"] for r in sched.report()] == [
        "upload inputs", "scale", "total", "add", "download outputs"]  # fmt: skip


def test_scheduler_counts_steady_state_bytes(device):
    sched = Scheduler(device, _kalman_like(device, []), inputs=("z",), state=("x",), outputs=("x",))
    sched.set("x", np.ones(7, np.float32))
    for _ in range(3):
        sched.run(z=np.full(7, 2.0, np.float32))
    frame = sched.last_frame
    if device.backend == "numpy":
        assert frame.h2d == frame.d2h == 0
        return
    # upload z (28 bytes); the test's own stages move x and y through the host: scale downloads x
    # and z and uploads y, total downloads y (the declared host read), add downloads y and uploads
    # x; the output download is x
    assert frame.stages["upload inputs"][1:] == (28, 0)
    assert frame.stages["total"][1:] == (0, 28)
    assert frame.stages["download outputs"][1:] == (0, 28)
    assert (frame.h2d, frame.d2h) == (28 + 28 + 28, 28 + 28 + 28 + 28 + 28)


def test_scheduler_without_profile_does_not_synchronise(device, monkeypatch):
    syncs = []
    monkeypatch.setattr(device, "synchronize", lambda: syncs.append(1))

    def noop(b):
        b["y"] = b["x"]

    sched = Scheduler(device, [Stage("a", noop, reads="x", writes="y"), Stage("b", noop, reads="x", writes="y")],
                      state=("x",))  # fmt: skip
    sched.set("x", np.ones(3, np.float32))
    sched.run()
    assert syncs == []
    sched_p = Scheduler(device, [Stage("a", noop, reads="x", writes="y")], state=("x",), profile=True)
    sched_p.set("x", np.ones(3, np.float32))
    sched_p.run()
    assert len(syncs) >= 2  # around the stage


def test_scheduler_checks_declarations(device):
    def noop(b):
        pass

    with pytest.raises(ValueError, match="stage 'gate' reads 'z', which no earlier stage writes"):
        Scheduler(device, [Stage("gate", noop, reads=("x", "z"))], state=("x",))
    with pytest.raises(ValueError, match="stage 'b' reads 'y', which no earlier stage writes"):
        Scheduler(device, [Stage("b", noop, reads="y"), Stage("a", noop, writes="y")])
    with pytest.raises(ValueError, match="unique stage names"):
        Scheduler(device, [Stage("a", noop), Stage("a", noop)])
    with pytest.raises(ValueError, match="output 'q' is written by no stage"):
        Scheduler(device, [Stage("a", noop, writes="y")], outputs=("q",))
    with pytest.raises(ValueError, match="both as an input and as state"):
        Scheduler(device, [], inputs=("x",), state=("x",))
    with pytest.raises(TypeError, match="expected gputrack.Stage"):
        Scheduler(device, [noop])
    with pytest.raises(TypeError, match="expected a gputrack.Device"):
        Scheduler("numpy", [])
    with pytest.raises(TypeError, match="callable"):
        Stage("a", 3)
    with pytest.raises(TypeError, match="non-empty strings"):
        Stage("a", noop, reads=("x", 2))


def test_scheduler_rejects_bad_use_at_run_time(device):
    def reads_undeclared(b):
        return b["x"]

    def writes_undeclared(b):
        b["w"] = 1

    def reads_unwritten(b):
        return b["y"]

    sched = Scheduler(device, [Stage("a", reads_undeclared, reads="z")], inputs=("z",))
    with pytest.raises(KeyError, match="stage 'a' reads 'x', which it does not declare"):
        sched.run(z=np.ones(2, np.float32))
    sched = Scheduler(device, [Stage("a", writes_undeclared)])
    with pytest.raises(KeyError, match="stage 'a' writes 'w', which it does not declare"):
        sched.run()
    # state that was never set: a clear error, not a stale or missing buffer
    sched = Scheduler(device, [Stage("a", reads_unwritten, reads="y")], state=("y",))
    with pytest.raises(KeyError, match="reads 'y', which has no value yet"):
        sched.run()
    with pytest.raises(TypeError, match=r"run: expected the inputs \(\)"):
        sched.run(q=np.ones(2))
    with pytest.raises(KeyError, match="not a state buffer"):
        sched.set("q", np.ones(2))


def test_skip_frame_ends_the_frame_and_is_recorded(device):
    ran = []

    def first(b):
        ran.append("first")
        raise SkipFrame("no usable depth")

    def second(b):
        ran.append("second")

    sched = Scheduler(device, [Stage("first", first), Stage("second", second)])
    with pytest.raises(SkipFrame, match="no usable depth"):
        sched.run()
    assert ran == ["first"] and sched.last_frame is sched.frames[-1]
    assert "first" in sched.last_frame.stages and "second" not in sched.last_frame.stages


def test_profiler_keeps_a_bounded_history(device):
    prof = Profiler(device, history=5)
    for _ in range(12):
        with prof.frame(sync=False):
            with prof.stage("a", sync=False):
                pass
    assert len(prof.frames) == 5 and prof.stats["a"].calls == 5
    with pytest.raises(ValueError, match="history: expected a positive int, got 0"):
        Profiler(device, history=0)

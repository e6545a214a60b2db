"""The caching allocator: freed device buffers are reused for the next array of the same dtype and
size, never while an array still references them; the pool stays within its byte limit; ops with
fresh outputs give exactly what they give with ``out=``."""

import gc
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from tolerances import assert_matches

import gputrack
from gputrack.ops.kalman import constant_velocity, kf_predict, kf_update, shared_matrix
from gputrack.pool import BufferPool, PoolStats, limit_from_env

ROOT = Path(__file__).resolve().parents[1]


def _address(a):
    """Where a DeviceArray's memory is (the backend's handle of it)."""
    if a.device.backend == "taichi":
        return id(a.buffer.arr)  # Taichi's array object, which the pool hands on
    return a.buffer.data.int_ptr


def _pooled(device):
    """Skip the numpy device; start from an empty pool (earlier tests in the process may have
    filled it up to its limit, and a full pool evicts its oldest buffer for each one it takes)."""
    if device.backend == "numpy":
        pytest.skip("the numpy device's arrays are NumPy arrays (NumPy's own allocator)")
    gc.collect()
    device.empty_pool()


# -- the bookkeeping ---------------------------------------------------------------------------------
def test_buffer_pool_reuses_by_key_and_releases_past_its_limit():
    pool = BufferPool(limit_bytes=100)
    assert pool.take("a", 40) is None
    assert pool.give("a", "A1", 40) == []
    assert pool.give("b", "B1", 40) == []
    assert pool.stats() == PoolStats(80, 2, 100, 0, 1)
    assert pool.take("c", 40) is None  # another key: not reused
    assert pool.take("a", 40) == "A1" and pool.take("a", 40) is None  # taken out once
    assert pool.give("a", "A1", 40) == []
    released = pool.give("c", "C1", 40)  # 120 > 100: the least recently freed goes
    assert released == ["B1"] and pool.held_bytes == 80
    assert pool.give("d", "D1", 101) == ["D1"]  # larger than the limit: never kept
    assert sorted(pool.set_limit(40)) == ["A1"] and pool.held_bytes == 40
    assert pool.clear() == ["C1"] and pool.stats().held_bytes == 0 and pool.held_buffers == 0
    st = pool.stats()
    assert (st.reused, st.allocated) == (1, 3)


def test_pool_limit_from_the_environment_and_bad_limits(monkeypatch):
    monkeypatch.setenv("GPUTRACK_POOL_BYTES", "1234")
    assert limit_from_env() == 1234
    monkeypatch.setenv("GPUTRACK_POOL_BYTES", "lots")
    with pytest.raises(ValueError, match="GPUTRACK_POOL_BYTES: expected a non-negative number of bytes, got 'lots'"):
        limit_from_env()
    monkeypatch.delenv("GPUTRACK_POOL_BYTES")
    assert limit_from_env() == 256 << 20
    with pytest.raises(ValueError, match="expected a non-negative int"):
        BufferPool(-1)
    dev = gputrack.device("numpy")
    with pytest.raises(TypeError, match="pool_limit: expected a non-negative int"):
        dev.pool_limit = 1.5


# -- on every device ----------------------------------------------------------------------------------
def test_a_freed_buffer_comes_back_for_the_same_shape_and_dtype_never_while_referenced(device):
    _pooled(device)
    gc.collect()  # arrays of earlier tests go back now, not in the middle of this test
    shape = (129, 7)
    a = device.empty(shape, np.float32)
    where = _address(a)
    b = device.empty(shape, np.float32)  # a is alive: b gets other memory
    assert _address(b) != where
    before = device.pool_stats()
    del a
    gc.collect()
    assert device.pool_stats().held_buffers == before.held_buffers + 1
    c = device.asarray(np.arange(129 * 7, dtype=np.float32).reshape(shape))  # an upload allocates too
    assert _address(c) == where
    assert device.pool_stats().reused == before.reused + 1
    assert _address(b) != where  # b untouched
    np.testing.assert_array_equal(c.numpy(), np.arange(129 * 7, dtype=np.float32).reshape(shape))
    if device.backend == "taichi":  # Taichi arrays are kept by dtype and shape
        del c
        gc.collect()
        assert _address(device.empty(shape, np.int32)) != where
        assert _address(device.empty((7, 129), np.float32)) != where


def _kalman_inputs(device, T, rng):
    F, Q = constant_velocity(3, 1.0 / 30, 1.0)
    H = np.zeros((3, 6), np.float32)
    H[0, 0] = H[1, 2] = H[2, 4] = 1
    R = (0.05 * np.eye(3)).astype(np.float32)
    x = rng.normal(size=(T, 6)).astype(np.float32)
    x[:, 4] += 5
    P = np.tile(np.diag([0.1, 1.0] * 3).astype(np.float32), (T, 1, 1))
    z = (x[:, 0::2] + rng.normal(0, 0.2, (T, 3))).astype(np.float32)
    z[3] = np.nan  # a SKIPPED track: its outputs are the inputs, also in a reused buffer
    model = tuple(shared_matrix(device, a) for a in (F, Q, H, R))
    return model, device.asarray(x), device.asarray(P), device.asarray(z)


def test_fresh_outputs_equal_out_outputs_and_allocate_nothing_in_steady_state(device):
    """kf_predict then kf_update with fresh outputs: once warm, every output buffer comes from the
    pool (no allocation), the pool's bytes stay flat, and the results equal those of the out= path
    and of the NumPy reference."""
    _pooled(device)
    rng = np.random.default_rng(0)
    T = 1001
    (Fs, Qs, Hs, Rs), x, P, z = _kalman_inputs(device, T, rng)
    xp, Pp = device.empty((T, 6)), device.empty((T, 6, 6))
    xu, Pu, st = device.empty((T, 6)), device.empty((T, 6, 6)), device.empty((T,), np.uint8)
    kf_predict(device, x, P, Fs, Qs, out=(xp, Pp))
    want = kf_update(device, xp, Pp, z, Hs, Rs, out=(xu, Pu, st))
    want = [a.numpy() for a in want]

    def fresh():
        a, b = kf_predict(device, x, P, Fs, Qs)
        return kf_update(device, a, b, z, Hs, Rs)

    for _ in range(3):  # warm up as the loop below runs: the last result alive during the next call
        got = fresh()
    gc.collect()
    warm = device.pool_stats()
    for _ in range(50):
        got = fresh()
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g.numpy(), w)
    gc.collect()
    after = device.pool_stats()  # in the state of ``warm``: one result alive
    assert after.allocated == warm.allocated  # nothing allocated in steady state
    assert after.reused >= warm.reused + 50 * 5
    assert after.held_bytes == warm.held_bytes and after.held_buffers == warm.held_buffers
    ref = gputrack.device("numpy")
    F, Q, H, R = (a.array.numpy() for a in (Fs, Qs, Hs, Rs))
    r = kf_update(ref, *kf_predict(ref, x.numpy(), P.numpy(), F, Q), z.numpy(), H, R)
    assert_matches(device, want[0], r[0])
    assert_matches(device, want[1], r[1])
    np.testing.assert_array_equal(want[2], r[2])


def test_rgbd_cost_with_fresh_outputs_equals_out(device):
    from gputrack.sim.problems import pf_scene

    tf, rgb, dep, gray, depth, cam = pf_scene(np.random.default_rng(2), 129)
    scene = gputrack.RgbdScene(rgb, dep, cam)
    d_tf, d_gray, d_depth = device.asarray(tf), device.asarray(gray), device.asarray(depth)
    fields = ("total", "rgb", "depth")
    keep = gputrack.rgbd_cost(device, d_tf, scene, d_gray, d_depth)
    want = [gputrack.to_numpy(getattr(keep, f)) for f in fields]
    for _ in range(3):  # fresh outputs, reusing the buffers the previous call freed
        got = gputrack.rgbd_cost(device, d_tf, scene, d_gray, d_depth)
        for f, w in zip(fields, want):
            np.testing.assert_array_equal(gputrack.to_numpy(getattr(got, f)), w)
    again = gputrack.rgbd_cost(device, d_tf, scene, d_gray, d_depth, out=keep)
    for f, w in zip(fields, want):
        np.testing.assert_array_equal(gputrack.to_numpy(getattr(again, f)), w)


def test_the_pool_stays_within_its_limit_and_a_zero_limit_turns_reuse_off(device):
    _pooled(device)
    limit = device.pool_limit
    try:
        device.pool_limit = 64 << 10
        arrays = [device.empty((1000 + i, 16), np.float32) for i in range(8)]  # 8 x ~64 KiB
        del arrays
        gc.collect()
        if device.backend == "opencl":  # PyOpenCL's pool releases everything it holds past the limit, at
            small = device.empty((3,), np.float32)  # the next allocation (kept: not freed)
            assert device.pool_stats().held_buffers == 0 and small.shape == (3,)
        else:
            assert 0 < device.pool_stats().held_bytes <= 64 << 10
        device.pool_limit = 0
        assert device.pool_stats().held_buffers == 0
        a = device.empty((257,), np.float32)
        del a
        gc.collect()
        assert device.pool_stats().held_buffers == 0
        b = device.empty((257,), np.float32)
        assert device.pool_stats().held_buffers == 0 and b.numpy().shape == (257,)
    finally:
        device.pool_limit = limit


def test_closing_a_device_releases_its_pool():
    code = """
        import gc, numpy as np, gputrack
        for spec in ("taichi:cpu", "opencl"):
            dev = gputrack.device(spec)
            arrays = [dev.asarray(np.ones((100, 10), np.float32)) for _ in range(4)]
            del arrays
            gc.collect()
            held = dev.pool_stats().held_buffers
            dev.close()
            print(spec, "HELD", held, "AFTER", dev.pool_stats().held_buffers)
    """
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=300,
                       cwd=ROOT, env={**os.environ, "GPUTRACK_POOL_BYTES": str(1 << 20)})  # fmt: skip
    infos = {d.spec: d for d in gputrack.devices()}
    for spec in ("taichi:cpu", "opencl"):
        if infos[spec].available:
            assert f"{spec} HELD 4 AFTER 0" in r.stdout, r.stdout + r.stderr


def test_the_alloc_benchmark_cases_run_and_report_flat_memory(device):
    """perf/bench_alloc.py's cases at small sizes: each runs, and the memory check's pool figures
    show no allocation during its calls (no timing asserted)."""
    import argparse

    from gputrack.benchmarks import alloc

    parser = argparse.ArgumentParser()
    alloc.add_arguments(parser)
    args = parser.parse_args(["--tracks", "13", "--batch", "7", "--memory-calls", "20", "--memory-tracks", "5"])
    cases = alloc.cases(device, args)
    assert [c.name for c in cases] == [
        "kf_predict+kf_update T=1e+01 fresh", "kf_predict+kf_update T=1e+01 out=", "rgbd_cost B=7 fresh",
        "rgbd_cost B=7 out=", "memory: 20 calls fresh",
    ]  # fmt: skip
    for c in cases:
        c.run()
        if c.reference is not None:
            c.reference()
    device.synchronize()
    mem = cases[-1].params["memory"]
    assert mem["calls"] == 20 and mem["before"]["rss_bytes"] > 0
    assert mem["after"]["pool"]["allocated"] == mem["before"]["pool"]["allocated"]
    if device.backend != "numpy":
        assert mem["after"]["pool"]["reused"] >= mem["before"]["pool"]["reused"] + 20 * 8


def test_a_vector_typed_scratch_array_leaves_the_pool_on(device):
    """An ndarray of a vector element type (the stereo kernels' scratch) takes Taichi's own path;
    the arrays after it still come from the pool (it once turned pooling off for the process)."""
    if device.backend != "taichi":
        pytest.skip("Taichi's allocator")
    dev = device
    from gputrack.backends.taichi import runtime

    vec = runtime.ndarray(runtime.ti.types.vector(4, runtime.ti.i32), (3,))
    assert vec.shape == (3,)
    gc.collect()
    dev.empty_pool()
    a = dev.empty((17, 5), np.float32)
    del a
    gc.collect()
    assert dev.pool_stats().held_buffers == 1

"""The caching allocator: ops with fresh outputs against the same ops writing into existing arrays.

Cases, each timed on the device with the NumPy reference in the same run:

- ``kf_predict+kf_update T=1e5 fresh``: ``kf_predict`` then ``kf_update`` of the constant-velocity
  model (n = 6, m = 3; F, Q, H, R uploaded once as SharedMatrix), each returning new arrays (the
  plain API: five arrays per call pair, 17 MB at T = 1e5);
- ``kf_predict+kf_update T=1e5 out=``: the same two calls writing into arrays allocated once
  (``out=``), i.e. the same kernels without any allocation;
- ``rgbd_cost B=1500 fresh`` and ``rgbd_cost B=1500 out=``: the sparse-template cost of paper 000
  (N = N' = 128 points, 640x480) with new result arrays, or into an earlier result;
- ``memory: <calls> calls fresh``: times one call of each fresh case, and records in its params
  the process's resident memory (VmRSS) and the device's pool (``Device.pool_stats()``) before
  and after ``--memory-calls`` calls of both fresh cases (T = ``--memory-tracks``): flat memory
  means the allocator reuses what the previous calls freed.

The ratio fresh / out= of each pair is what the allocator is for (perf/bench_alloc.py prints it;
the target is <= 1.3 on every device). ``GPUTRACK_POOL_BYTES=0`` turns reuse off for a comparison.
"""

import gc
import sys

import numpy as np

from ..registry import device as get_device
from ..sim.problems import kalman_tracks, pf_scene
from .harness import Case, bench_main

NAME = "alloc"


def add_arguments(parser):
    parser.add_argument("--tracks", type=float, default=1e5, help="T of the Kalman cases (default 1e5)")
    parser.add_argument("--batch", type=int, default=1500, help="B of the rgbd_cost cases (default 1500)")
    parser.add_argument("--memory-calls", type=int, default=10_000, help="calls of the memory check (0: none)")
    parser.add_argument("--memory-tracks", type=float, default=1e4, help="T of the memory check (default 1e4)")


def rss_bytes() -> int:
    """Resident memory of this process (VmRSS), 0 where /proc is not there."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def _kalman(device, T, rng):
    """(fresh, out) callables: kf_predict then kf_update of T tracks."""
    from ..ops.kalman import kf_predict, kf_update, shared_matrix

    F, Q, H, R, x0, P0, z, _det = kalman_tracks(T, rng)
    Fs, Qs, Hs, Rs = (shared_matrix(device, a) for a in (F, Q, H, R))
    x, P, zd = device.asarray(x0), device.asarray(P0), device.asarray(z)
    xp, Pp = device.asarray(x0), device.asarray(P0)
    xu, Pu, st = device.asarray(x0), device.asarray(P0), device.empty((T,), np.uint8)

    def fresh():
        a, b = kf_predict(device, x, P, Fs, Qs)
        return kf_update(device, a, b, zd, Hs, Rs)

    def into():
        kf_predict(device, x, P, Fs, Qs, out=(xp, Pp))
        return kf_update(device, xp, Pp, zd, Hs, Rs, out=(xu, Pu, st))

    return fresh, into


def _rgbd(device, B, rng):
    """(fresh, out) callables: rgbd_cost of B hypotheses."""
    from ..ops.template import RgbdScene, rgbd_cost

    tf, rgb, dep, gray, depth, cam = pf_scene(rng, B)
    d_tf, d_gray, d_depth = device.asarray(tf), device.asarray(gray), device.asarray(depth)
    scene = RgbdScene(rgb, dep, cam).to(device)  # once per template, as a tracker does
    keep = rgbd_cost(device, d_tf, scene, d_gray, d_depth)

    def fresh():
        return rgbd_cost(device, d_tf, scene, d_gray, d_depth)

    def into():
        return rgbd_cost(device, d_tf, scene, d_gray, d_depth, out=keep)

    return fresh, into


def memory_check(device, calls: int, fns, checkpoints: int = 10) -> dict:
    """RSS and pool figures before and after ``calls`` rounds of ``fns`` (fresh outputs each), and
    the RSS at ``checkpoints`` evenly spaced points in between (``rss_trace``: a leak shows as a
    trend; on a machine that reclaims idle pages, RSS also moves by some MiB without one)."""
    for fn in fns:  # warm up: compile, and fill the pool with what one round frees
        fn()
        fn()
    device.synchronize()
    gc.collect()
    before = {"rss_bytes": rss_bytes(), "pool": device.pool_stats()._asdict()}
    trace = []
    step = max(1, calls // max(1, checkpoints))
    for i in range(calls):
        for fn in fns:
            fn()
        if (i + 1) % step == 0:
            device.synchronize()
            trace.append(rss_bytes())
    device.synchronize()
    gc.collect()
    after = {"rss_bytes": rss_bytes(), "pool": device.pool_stats()._asdict()}
    return {"calls": calls, "before": before, "after": after, "rss_trace": trace}


def cases(device, args):
    ref = get_device("numpy")
    T, B = int(args.tracks), int(args.batch)
    rng = np.random.default_rng(0)
    kf_fresh, kf_out = _kalman(device, T, rng)
    kf_fresh_ref, kf_out_ref = _kalman(ref, T, np.random.default_rng(0))
    cost_fresh, cost_out = _rgbd(device, B, np.random.default_rng(1))
    cost_fresh_ref, cost_out_ref = _rgbd(ref, B, np.random.default_rng(1))
    kf = {"T": T, "n": 6, "m": 3, "pool_limit": device.pool_limit}
    cost = {"B": B, "N": 128, "N'": 128, "H": 480, "W": 640, "pool_limit": device.pool_limit}
    out = [
        Case(f"kf_predict+kf_update T={T:.0e} fresh", run=kf_fresh, reference=kf_fresh_ref, params=kf),
        Case(f"kf_predict+kf_update T={T:.0e} out=", run=kf_out, reference=kf_out_ref, params=kf),
        Case(f"rgbd_cost B={B} fresh", run=cost_fresh, reference=cost_fresh_ref, params=cost),
        Case(f"rgbd_cost B={B} out=", run=cost_out, reference=cost_out_ref, params=cost),
    ]
    if args.memory_calls > 0:
        Tm = int(args.memory_tracks)
        small_kf, _ = _kalman(device, Tm, np.random.default_rng(2))
        memory = memory_check(device, args.memory_calls, (small_kf, cost_fresh))
        out.append(
            Case(
                f"memory: {args.memory_calls} calls fresh",
                run=lambda: (small_kf(), cost_fresh()),
                params={"T": Tm, "B": B, "memory": memory, "pool_limit": device.pool_limit},
            )
        )
    return out


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

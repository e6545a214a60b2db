"""The fuzz suite's risky cases, run by tests/test_fuzz.py in a child process under limits:
``python tests/fuzz_child.py SPEC[,SPEC...] [fast|deep]`` (deep: also every op's count, size and seed
arguments at huge values).

Outputs too large for the device, huge sizes and counts and broadcast views of billions of rows:
each must end in a clear exception (tests/fuzzing.py: CLEAR, with an "expected ..., got ..."
message) before any large allocation. The process runs with its address space limited (so a
runaway allocation fails here instead of swapping the machine) and its CPU time limited (a hang
ends); a crash shows as the parent's non-zero return code, after the START line of its case.
Prints ``START <spec> <case>`` before and ``FUZZ <json>`` after each case.
"""

from __future__ import annotations

import json
import os
import resource
import sys
import time

import numpy as np

#: the child's limits: address space (generous: the Taichi and OpenCL runtimes reserve virtual
#: memory at start) and CPU seconds
ADDRESS_SPACE = 24 << 30
CPU_SECONDS = 240


#: devices whose driver reserves more address space than ADDRESS_SPACE at start (the CUDA driver maps
#: the GPU's memory and the host's into one unified address space): the child runs them without the
#: address-space limit; their huge outputs are still refused by the device-memory check first
UNIFIED_ADDRESSING = ("taichi:cuda",)


def limit(specs) -> None:
    limits = [(resource.RLIMIT_CPU, CPU_SECONDS)]
    if not set(specs) & set(UNIFIED_ADDRESSING):
        limits.append((resource.RLIMIT_AS, ADDRESS_SPACE))
    for what, value in limits:
        soft, hard = resource.getrlimit(what)
        want = value if hard == resource.RLIM_INFINITY else min(value, hard)
        resource.setrlimit(what, (want, hard))


#: cases that fail for a known reason in an op this suite does not own: reported, not hidden (the
#: parent marks the test xfail naming them, and fails when one of them passes: drop it here then)
KNOWN: dict = {}

#: returned by a case that ran the fuzz oracle itself (tests/fuzzing.py judge) and passed
JUDGED = object()


def risky_cases(device):
    """(name, thunk) of every risky call on ``device``."""
    import gputrack
    from gputrack import ops
    from gputrack.models import upper_body
    from gputrack.ops.template import SparseTemplate
    from gputrack.sim import problems

    f32 = np.float32
    chain = upper_body()
    P = chain.n_params
    rng = np.random.default_rng(0)
    k = problems.kalman_mixed(rng, T=5, detections=3)
    big = lambda shape, dtype=f32: np.broadcast_to(np.zeros((1,) * len(shape), dtype), shape)  # noqa: E731
    tf, rgb, dep, gray, depth, cam = problems.template_scene(rng, b=3, j=2, n=5, m=4, h=12, w=14)
    scene = ops.RgbdScene(rgb, dep, cam)
    cand = np.tile(chain.rest_params().astype(f32), (2, 1))
    sigma = np.full(P, 0.01, f32)
    cases = [
        ("empty 2**17 x 2**20", lambda: device.empty((2**17, 2**20), f32)),
        ("empty 2**40", lambda: device.empty((2**40,), f32)),
        ("empty of 20 dimensions", lambda: device.empty((1,) * 20, f32).shape == (1,) * 20 and JUDGED),
        ("asarray of a broadcast 2**36", lambda: device.asarray(big((2**36,)))),
        ("mahalanobis 2**17 tracks x 2**20 detections",
         lambda: ops.mahalanobis(device, big((2**17, 6)), big((2**17, 6, 6)), k["H"], k["R"], big((2**20, 3)))),
        ("kf_predict F of (2**32, 6)", lambda: ops.kf_predict(device, k["x"], k["P"], big((2**32, 6)), k["Q"])),
        ("kf_update x of 2**32 rows", lambda: ops.kf_update(device, big((2**32, 6)), k["P"], k["z"], k["H"], k["R"])),
        ("best_k broadcast 2**40 scores, k = 2**39", lambda: ops.best_k(device, big((2**40,)), 2**39)),
        ("best_k rows of 2**32", lambda: ops.best_k(device, np.zeros(8, f32), 2, rows=big((2**32, 4)))),
        ("sample_around n = 10**12", lambda: ops.sample_around(device, cand, sigma, 10**12, 1)),
        ("sample_around n = 2**30", lambda: ops.sample_around(device, cand, sigma, 2**30, 1)),
        ("forward_kinematics of 2**31 broadcast poses", lambda: ops.forward_kinematics(device, chain, big((2**31, P)))),
        ("SparseTemplate part 2e9", lambda: SparseTemplate(np.zeros((1, 3)), np.array([2_000_000_000]))),
        ("rgbd_cost of 2**31 broadcast hypotheses",
         lambda: ops.rgbd_cost(device, big((2**31, 2, 3, 4)), scene, gray, depth)),
        ("patch_ncc of 2**40 broadcast points",
         lambda: ops.patch_ncc(device, big((2**20, 2**20, 2)), big((2**20, 3, 3)), gray)),
        ("gate_pairs max_pairs 2**40",
         lambda: ops.gate_pairs(device, k["x"], k["P"], k["H"], k["R"], k["det"], 9.0, max_pairs=2**40)),
        ("depth_points n_points 2**40",
         lambda: ops.depth_points(device, np.zeros((4, 5), np.uint16), np.zeros((4, 5), f32), cam, n_points=2**40)),
        ("dbscan of 2**34 broadcast points", lambda: ops.dbscan(device, big((2**34, 2)), 0.1, 3)),
        ("stereo_match max_disparity 2**40",
         lambda: ops.stereo_match(device, np.zeros((9, 9), np.uint8), np.zeros((9, 9), np.uint8), max_disparity=2**40)),
        ("background_median of 2**20 broadcast frames",
         lambda: ops.background_median(device, big((2**20, 2**10, 2**10), np.uint16))),
        ("lm_solve of 2**31 broadcast problems",
         lambda: ops.lm_solve(device, big((2**31, 4, 2)), big((2**31, 4)), big((2**31,)))),
        ("normal_equations of a (2**12, 2**12, 2**12) J",
         lambda: ops.normal_equations(device, big((2**12, 2**12, 2**12)), big((2**12, 2**12)))),
    ]
    # every op's scalar arguments at huge values (counts, sizes, seeds): the reference's outcome
    # (deep profile: the ops that accept one run their kernels, compiled afresh in this process)
    from fuzzing import REF, SCALARS, huge_count, judge, op_cases, profile, run

    for case in op_cases(0) if profile() == "deep" else []:
        for name, v in case.args.items():
            for value in [s for s in SCALARS + case.scalars.get(name, []) if huge_count(v, s)]:
                def thunk(case=case, name=name, value=value):
                    args = {**case.args, name: value}
                    judge(device, case, f"{name}={value}", run(case, device, args), run(case, REF, args))
                    return JUDGED

                cases.append((f"{case.name} {name}={value}", thunk))
    return gputrack, cases


def main(argv) -> int:
    specs = argv[1].split(",")
    if len(argv) > 2:
        os.environ["GPUTRACK_FUZZ"] = argv[2]
    limit(specs)
    import gputrack
    from fuzzing import CLEAR

    for spec in specs:  # at most one Taichi arch, last (one arch per process)
        device = gputrack.device(spec)
        _, cases = risky_cases(device)
        for name, thunk in cases:
            print(f"START {spec} {name}", flush=True)
            t0 = time.perf_counter()
            try:
                got = thunk()
                row = {"case": name, "ok": got is JUDGED,
                       "outcome": "as the reference" if got is JUDGED else "returned (expected a clear exception)"}
            except AssertionError as e:  # the oracle's verdict
                row = {"case": name, "ok": False, "outcome": " ".join(str(e).split())[:600]}
            except Exception as e:  # noqa: BLE001 - judged here
                msg = " ".join(str(e).split())
                low = msg.lower()
                clear = isinstance(e, CLEAR) and "expected" in low and "got" in low
                row = {"case": name, "ok": clear, "outcome": f"{type(e).__name__}: {msg[:400]}"}
            row.update(spec=spec, s=round(time.perf_counter() - t0, 3), known=KNOWN.get(name))
            print("FUZZ " + json.dumps(row), flush=True)
        if device.backend == "taichi":
            device.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))

"""``gputrack demo body``: simulate a sequence, track it, print the paper's tables.

Paper 000's evaluation on its own simulator: a seeded motion sequence is rendered (640x480
gray + depth quantised to 5 mm, 30 fps), the tracker starts from the true first pose and
tracks the rest; the report has the mean arm-axis angle error per part (Tables 5-6), the
shoulder-position error per axis when the shoulders are estimated (Table 7; they start 30 mm
off, :func:`shoulders_off`), and the per-stage timing table (Tables 1-2 layout, ms per frame).
"""

from __future__ import annotations

import json
import logging
import sys
import time

import numpy as np

from .metrics import ARM_PARTS, arm_axis_errors, shoulder_camera_errors, shoulder_errors

log = logging.getLogger("gputrack")


def body(
    device,
    *,
    frames: int = 30,
    sequence_index: int = 0,
    lm: int = 10,
    stages: int = 3,
    shoulders: bool = False,
    seed: int = 0,
    template_every: int = 1,
    depth_tol: float = 0.0,
    n_depth: int = 128,
    out=None,
) -> dict:
    """Run the body-tracking demo on ``device``; print progress and tables to ``out`` (default: stdout); return the report."""
    from .sim import SEQUENCES, sequence
    from .trackers.body import BodyTracker, TrackerConfig

    out = sys.stdout if out is None else out
    if frames < 2:
        raise ValueError(f"frames: expected at least 2 (the first is the start pose), got {frames}")
    seq = sequence(sequence_index, frames=frames, seed=seed, shoulders=shoulders)
    start = seq.params[0].copy()
    if shoulders:
        start = shoulders_off(start, seed)
    config = TrackerConfig(stages=stages, lm_iterations=lm, shoulders=shoulders, seed=seed,
                           template_every=template_every, depth_tol=depth_tol, n_depth=n_depth)  # fmt: skip
    tracker = BodyTracker(device, start, config=config)
    print(f"gputrack demo body: sequence {seq.index} ({SEQUENCES[seq.index]}), {frames} frames, device "
          f"{device.spec} ({device.name}), PF {stages} stages x K={config.samples}, LM {lm} iterations, "
          f"N'={n_depth} depth points, depth tolerance {depth_tol:g} mm"
          + (", shoulders estimated (started 30 mm off)" if shoulders else ""), file=out)  # fmt: skip
    estimates, per_frame = [], []
    for f in list(seq)[1:]:
        t0 = time.perf_counter()
        est = tracker.track(f.gray, f.depth)
        dt = time.perf_counter() - t0
        err = arm_axis_errors(seq.chain, est.params, f.params)[0]
        if not per_frame:
            tracker.scheduler.reset()  # the first frame compiles the kernels: leave it out of the tables
        estimates.append(est.params)
        per_frame.append({"frame": f.index, "ms": dt * 1e3, "cost": est.cost, "confidence": est.confidence,
                          "arm_errors_deg": err.tolist()})  # fmt: skip
        print(f"  frame {f.index:4d}  {dt * 1e3:8.1f} ms  cost {est.cost:8.3f}  arm-axis error (deg) "
              + " ".join(f"{e:5.2f}" for e in err), file=out, flush=True)  # fmt: skip
    estimates = np.asarray(estimates)
    errors = arm_axis_errors(seq.chain, estimates, seq.params[1:])
    mean = dict(zip(ARM_PARTS, errors.mean(axis=0).tolist()))
    print("\nmean arm-axis angle error (deg), Table 5/6 layout", file=out)
    print("  " + "".join(f"{name:>18}" for name in ARM_PARTS), file=out)
    print("  " + "".join(f"{v:>18.3f}" for v in mean.values()), file=out)
    report = {
        "device": {"spec": device.spec, "name": device.name},
        "sequence": {"index": seq.index, "name": SEQUENCES[seq.index], "frames": frames, "seed": seed},
        "config": {
            "stages": stages,
            "lm_iterations": lm,
            "shoulders": shoulders,
            "samples": config.samples,
            "candidates": config.candidates,
            "template_every": template_every,
            "depth_tol": depth_tol,
            "n_depth": n_depth,
        },
        "mean_arm_axis_error_deg": mean,
        "frames": per_frame,
    }
    if shoulders:
        sh = shoulder_errors(estimates[-1], seq.params[-1]).reshape(2, 3)
        start_err = shoulder_errors(start, seq.params[0]).reshape(2, 3)
        print("\nshoulder position error (mm), Table 7 layout       x        y        z", file=out)
        for side, row, row0 in zip(("right", "left"), sh, start_err):
            print(f"  {side:<6} start {' '.join(f'{v:8.2f}' for v in row0)}  ->  final {' '.join(f'{v:8.2f}' for v in row)}",
                  file=out)  # fmt: skip
        report["shoulder_error_mm"] = {"right": sh[0].tolist(), "left": sh[1].tolist()}
        cam = shoulder_camera_errors(seq.chain, estimates[-1], seq.params[-1]).reshape(2, 3)
        turn = np.degrees(estimates[-1][1] - seq.params[-1][1])
        print("  shoulder joints in camera coordinates (mm)         x        y        z", file=out)
        for side, row in zip(("right", "left"), cam):
            print(f"  {side:<6} {'':>41} {' '.join(f'{v:8.2f}' for v in row)}", file=out)
        lever = abs(np.radians(turn)) * abs(seq.params[-1][17])  # the turn times the shoulder's x
        print(f"  torso turn error {turn:+.2f} deg (moves t_RS, t_LS along torso z by -+{lever:.1f} mm)", file=out)
        report["shoulder_camera_error_mm"] = {"right": cam[0].tolist(), "left": cam[1].tolist()}
        report["torso_turn_error_deg"] = float(turn)
    ms = np.array([p["ms"] for p in per_frame])
    print("\nper-stage time, Table 1/2 layout (ms; frames after the first, which compiles kernels)", file=out)
    print(tracker.scheduler.table(), file=out)
    print(f"median frame time {np.median(ms[1:] if len(ms) > 1 else ms):.1f} ms", file=out)
    report["stages"] = tracker.scheduler.report()
    report["median_frame_ms"] = float(np.median(ms[1:] if len(ms) > 1 else ms))
    return report


def shoulders_off(params, seed: int, mm: float = 30.0) -> np.ndarray:
    """A copy of the 20-parameter pose ``params`` with t_RS and t_LS each moved ``mm`` in a seeded direction.

    Table 7's start: the shoulder positions are not known, the tracker starts them off by 30 mm.
    """
    out = np.array(params, dtype=np.float64)
    if out.shape != (20,):
        raise ValueError(f"params: expected a 20-parameter pose (shoulders estimated), got shape {out.shape}")
    direction = np.random.default_rng([7, seed]).normal(size=(2, 3))
    out[14:] += (mm * direction / np.linalg.norm(direction, axis=1, keepdims=True)).ravel()
    return out


def write_json(report: dict, path: str) -> None:
    with open(path, "w") as f:
        json.dump(report, f, indent=2)

"""``gputrack demo body``: simulate a sequence, track it, print the paper's tables.

Paper 000's evaluation on its own simulator: a seeded motion sequence is rendered (640x480
gray + depth quantised to 5 mm, 30 fps), the tracker starts from the true first pose and
tracks the rest; the report has the mean arm-axis angle error per part (Tables 5-6), the
shoulder-position error per axis when the shoulders are estimated (Table 7; they start 30 mm
off, :func:`gputrack.sim.body.shoulders_off`), and the per-stage timing table (Tables 1-2
layout, ms per frame). ``save``: a directory for pictures: the first tracked frame, every 10th and the
last, with the model's silhouette and axes at the estimate, the true arm axes and the template points
the frame was matched with (``frame_NNNN.png``, :func:`gputrack.trackers.body.pictures.draw_estimate`),
and the per-part arm-axis errors over the frames (``errors.png``, with matplotlib, the ``plot`` extra).
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time

import numpy as np

from ..sim import SEQUENCES, sequence, shoulders_off
from ..trackers.body import BodyTracker, BodyTrackerConfig
from ..trackers.body.metrics import ARM_PARTS, arm_axis_errors, shoulder_camera_errors, shoulder_errors

log = logging.getLogger("gputrack")


def run(
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
    samples: int = 1500,
    predict: bool = True,
    save: str | None = None,
    out=None,
) -> dict:
    """Run the body-tracking demo on ``device``; print progress and tables to ``out`` (default: stdout); return the report."""
    out = sys.stdout if out is None else out
    if frames < 2:
        raise ValueError(f"frames: expected at least 2 (the first is the start pose), got {frames}")
    seq = sequence(sequence_index, frames=frames, seed=seed, shoulders=shoulders)
    start = seq.params[0].copy()
    if shoulders:
        start = shoulders_off(start, seed)
    config = BodyTrackerConfig(stages=stages, lm_iterations=lm, shoulders=shoulders, seed=seed,
                           template_every=template_every, depth_tol=depth_tol, n_depth=n_depth,
                               samples=samples, predict=predict)  # fmt: skip
    tracker = BodyTracker(device, start, config=config, profile=True)  # the stage table below
    print(f"gputrack demo body: sequence {seq.index} ({SEQUENCES[seq.index]}), {frames} frames, device "
          f"{device.spec} ({device.name}), PF {stages} stages x K={config.samples}, LM {lm} iterations, "
          f"N'={n_depth} depth points, depth tolerance {depth_tol:g} mm"
          + ("" if predict else ", no motion prediction")
          + (", shoulders estimated (started 30 mm off)" if shoulders else ""), file=out)  # fmt: skip
    if save:
        os.makedirs(save, exist_ok=True)
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
        if save and (f.index == 1 or f.index % 10 == 0 or f.index == frames - 1):
            _picture(save, seq, f, est, tracker.templates)
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
            "predict": predict,
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
    if save:
        _error_plot(save, seq, errors, out)
        print(f"pictures written to {save}", file=out)
    return report


def _picture(save, seq, f, est, templates) -> None:
    """Frame ``f`` with the model at the estimate, the true arm axes and the template points (the
    templates this frame was matched with, at the estimate)."""
    import cv2

    from ..trackers.body.pictures import draw_estimate

    label = f"frame {f.index}  cost {est.cost:.3f}  confidence {est.confidence:.0f}"
    img = draw_estimate(f.gray, seq.chain, est.params, seq.camera, templates=templates, truth=f.params, label=label)
    cv2.imwrite(os.path.join(save, f"frame_{f.index:04d}.png"), img)


def _error_plot(save, seq, errors, out) -> None:
    from ..trackers.body.pictures import error_plot

    try:
        fig = error_plot(np.arange(1, len(errors) + 1), errors, list(ARM_PARTS),
                         title=f"sequence {seq.index} ({SEQUENCES[seq.index]}): arm-axis error per part")  # fmt: skip
    except ImportError as e:
        print(f"  (no error plot: {e})", file=out)
        return
    import matplotlib.pyplot as plt

    fig.savefig(os.path.join(save, "errors.png"), dpi=90)
    plt.close(fig)


def write_json(report: dict, path: str) -> None:
    with open(path, "w") as f:
        json.dump(report, f, indent=2)

"""``gputrack demo pedestrians``: simulate paper 002's entrance hall, track it, print the metrics.

The simulator (:mod:`gputrack.sim.pedestrians`: a level Structure-Core-like depth camera 1 m up,
1280 x 960 at ``scale`` 1, 5 fps, people walking across, often side by side and occluding each
other, at most ``people`` in view) gives the depth frames and the ground truth. The background is
the median of 30 empty frames; every frame goes through :meth:`PedestrianTracker.track`. The
report: per-frame progress, Tables 2-4 of the paper (:mod:`gputrack.trackers.pedestrians.metrics`:
detection precision / recall / F, trajectory-identification precision and recall by the largest
number of people in view), CLEAR MOT / IDF1 (motmetrics, when installed), the same for the
ablations (``ablations=True``: without the occlusion gain; without the split/merge reasoning;
plain Kalman + Hungarian) and the per-stage timing. ``save``: a directory for pictures (a top view
of the tracks with ids and the segments, as Fig. 10; the depth image with the segments' boxes).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time

import numpy as np

from ..sim.pedestrians import pedestrian_sequence
from ..trackers.pedestrians import PedestrianConfig, PedestrianTracker
from ..trackers.pedestrians.recording import image_boxes
from ..trackers.pedestrians.metrics import clear_mot, detection_metrics, format_tables, identification_metrics

__all__ = ["ABLATIONS", "evaluate", "run", "track_sequence", "write_json"]

#: config switches of the ablation table: name -> changes to the config
ABLATIONS = {
    "full": {},
    "no occlusion gain": {"occlusion_gain": False},
    "no split/merge": {"split_merge": False},
    "Kalman + Hungarian": {"occlusion_gain": False, "split_merge": False},
}


def _mot_available() -> bool:
    try:
        import motmetrics  # noqa: F401
    except ImportError:
        return False
    return True


def _boxes(segments) -> np.ndarray:
    return np.array([[s.lo[0], s.hi[0], s.lo[2], s.hi[2]] for s in segments]).reshape(-1, 4)


def track_sequence(device, seq, config: PedestrianConfig, *, frames=None, progress=None, save=None) -> dict:
    """Track the frames of a simulated sequence; return the per-frame records for the metrics and
    the tracker (``"tracker"``)."""
    trk = PedestrianTracker(device, camera=seq.camera, config=config)
    trk.learn_background(seq.background(config.background_frames))
    n = len(seq) if frames is None else min(int(frames), len(seq))
    rec = {"truth_ids": [], "truth_pos": [], "hyp_ids": [], "hyp_pos": [], "segments": [], "ms": []}
    history: dict = {}
    for k in range(n):
        f = seq[k]
        t0 = time.perf_counter()
        fr = trk.track(f.depth)
        dt = time.perf_counter() - t0
        if k == 0:
            trk.scheduler.reset()  # the first frame compiles the kernels
        rec["truth_ids"].append(f.ids)
        rec["truth_pos"].append(f.position)
        rec["hyp_ids"].append(np.array([p.id for p in fr.pedestrians], np.int64))
        rec["hyp_pos"].append(np.array([p.position for p in fr.pedestrians]).reshape(-1, 3))
        rec["segments"].append(_boxes(fr.segments))
        rec["ms"].append(dt * 1e3)
        for p in fr.pedestrians:
            history.setdefault(p.id, []).append(p.position)
        if progress is not None:
            progress(k, f, fr, dt)
        if save and (k % 50 == 0 or k == n - 1):
            _pictures(save, k, seq, f, fr, history)
    rec["tracker"] = trk
    return rec


def _pictures(save, k, seq, f, fr, history) -> None:
    import cv2

    from ..trackers.pedestrians.pictures import depth_picture, top_view

    img = depth_picture(f.depth, image_boxes(seq.camera, fr.segments), list(range(len(fr.segments))))
    cv2.imwrite(os.path.join(save, f"depth_{k:04d}.png"), img)
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        ids = [p.id for p in fr.pedestrians]
        ax = top_view(ids, np.array([p.position for p in fr.pedestrians]).reshape(-1, 3), _boxes(fr.segments),
                      history={i: np.array(history[i][-25:]) for i in ids}, truth_positions=f.position,
                      title=f"frame {k}: tracks (ids), segments (grey), truth (x)")  # fmt: skip
        ax.figure.savefig(os.path.join(save, f"top_{k:04d}.png"), dpi=90)
        plt.close(ax.figure)
    except ImportError:
        pass


def evaluate(rec, *, mot: bool = True) -> dict:
    """The paper's measures of a tracked sequence's records."""
    det = detection_metrics(rec["truth_pos"], rec["segments"])
    ident = identification_metrics(rec["truth_ids"], rec["truth_pos"], rec["hyp_ids"], rec["hyp_pos"],
                                   segments=rec["segments"])  # fmt: skip
    m = clear_mot(rec["truth_ids"], rec["truth_pos"], rec["hyp_ids"], rec["hyp_pos"], plane=True) if mot else None
    return {"detection": det, "identification": ident, "mot": m}


def _summary(m) -> dict:
    d, i = m["detection"], m["identification"]
    out = {"detection": {"precision": d.precision, "recall": d.recall, "f": d.f},
           "identification": {"precision": i.precision, "recall": i.recall, "recall_detected": i.recall_detected,
                              "precision_rows": {int(k): v[1] for k, v in i.precision_rows.items()},
                              "recall_rows": {int(k): v[1] for k, v in i.recall_rows.items()}}}  # fmt: skip
    if m["mot"] is not None:
        out["mot"] = m["mot"]
    return out


def run(device, *, people: int = 5, frames: int = 851, seed: int = 0, scale: float = 1.0, ablations: bool = True,
        save: str | None = None, out=None, config: PedestrianConfig | None = None) -> dict:  # fmt: skip
    """Run the pedestrian demo on ``device``: a sequence of ``frames`` frames with at most ``people``
    in view (32 people at 851 frames, scaled with the length). Prints to ``out`` (default stdout);
    returns the report."""
    out = sys.stdout if out is None else out
    if isinstance(people, bool) or not isinstance(people, int) or people < 1:
        raise ValueError(f"people: expected an integer >= 1, got {people!r}")
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 2:
        raise ValueError(f"frames: expected an integer >= 2, got {frames!r}")
    config = PedestrianConfig() if config is None else config
    total = max(1, round(32 * frames / 851 * people / 5))
    seq = pedestrian_sequence(np.random.default_rng(seed), frames=frames, people=total, max_in_view=people,
                              scale=scale)  # fmt: skip
    H, W = seq.sensor.shape if hasattr(seq.sensor, "shape") else (seq.sensor.height, seq.sensor.width)
    print(f"gputrack demo pedestrians: {frames} frames at 5 fps, {total} people, at most {seq.max_in_view} in view, "
          f"{W} x {H} depth (scale {scale}), device {device.spec} ({device.name})", file=out)  # fmt: skip
    if save:
        os.makedirs(save, exist_ok=True)

    def progress(k, f, fr, dt):
        ped = " ".join(f"{p.id}{'' if p.status == 'tracked' else ':' + p.status}" for p in fr.pedestrians)
        print(f"  frame {k:4d}  {dt * 1e3:7.1f} ms  {f.in_view} in view  {len(fr.segments)} segments  "
              f"pedestrians {ped}", file=out, flush=True)  # fmt: skip

    mot = _mot_available()
    rec = track_sequence(device, seq, config, progress=progress, save=save)
    trk = rec.pop("tracker")
    m = evaluate(rec, mot=mot)
    print(f"\npaper 002 Tables 2-4 ({frames} frames, scale {scale}, device {device.spec})", file=out)
    print(format_tables(m["detection"], m["identification"], m["mot"]), file=out)
    report = {"device": {"spec": device.spec, "name": device.name},
              "sequence": {"frames": frames, "people": total, "max_in_view": int(seq.max_in_view), "seed": seed,
                           "scale": scale},
              "metrics": {"full": _summary(m)}}  # fmt: skip
    if ablations:
        rows = [("full", m)]
        for name, change in ABLATIONS.items():
            if name == "full":
                continue
            r = track_sequence(device, seq, dataclasses.replace(config, **change))
            r.pop("tracker")
            mm = evaluate(r, mot=mot)
            rows.append((name, mm))
            report["metrics"][name] = _summary(mm)
        print("\nwhat each part adds (same sequence; id Rd: identification recall over the detected frames)",
              file=out)  # fmt: skip
        print(f"  {'tracker':<20}{'det P':>7}{'det R':>7}{'det F':>7}{'id P':>7}{'id R':>7}{'id Rd':>7}{'MOTA':>7}"
              f"{'IDF1':>7}{'IDsw':>6}", file=out)  # fmt: skip
        for name, mm in rows:
            d, i, mo = mm["detection"], mm["identification"], mm["mot"]
            tail = (f"{100 * mo['mota']:7.1f}{100 * mo['idf1']:7.1f}{mo['num_switches']:6d}" if mo else "")
            print(f"  {name:<20}{100 * d.precision:7.1f}{100 * d.recall:7.1f}{100 * d.f:7.1f}"
                  f"{100 * i.precision:7.1f}{100 * i.recall:7.1f}{100 * i.recall_detected:7.1f}" + tail,
                  file=out)  # fmt: skip
    ms = np.array(rec["ms"])
    print("\nper-stage time (ms; frames after the first, which compiles kernels)", file=out)
    print(trk.scheduler.table("pedestrians"), file=out)
    med = float(np.median(ms[1:]))
    print(f"median frame time {med:.1f} ms", file=out)
    if save:
        print(f"pictures written to {save}", file=out)
    report["stages"] = trk.scheduler.report()
    report["median_frame_ms"] = med
    return report


def write_json(report: dict, path: str) -> None:
    with open(path, "w") as f:
        json.dump(report, f, indent=2, default=float)

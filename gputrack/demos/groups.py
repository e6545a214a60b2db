"""``gputrack demo groups``: simulate a stereo scene of groups of people, track it, print the metrics.

Paper 001's experiments on its own simulator (:mod:`gputrack.sim.groups`: a Bumblebee2-like
rectified pair, 640 x 480, 48 fps): "crossing" (two groups of 2 and 3 people pass each other with
partial occlusion, Fig. 4-5), "merging" (two groups become one, Fig. 6-7) and "stairs" (a group
climbs a staircase, Fig. 8-9). The background is learnt from the scene's empty first frames;
every later pair goes through the whole pipeline (:meth:`GroupTracker.track`: background
subtraction, masked stereo, KLT, groups), or, with ``points=True``, the simulator's observation
points go straight to :meth:`GroupTracker.update_points`. The report: per-frame progress, the
paper's results as numbers (:mod:`gputrack.trackers.groups.metrics`: purity, id switches, merge
latency, the error of the group means, CLEAR MOT / IDF1 when motmetrics is installed) and the
per-stage timing of both schedulers (Tables 1-2 layout). ``save``: a directory for pictures
(the left image with points and ellipses, as Fig. 4; a top view of the trajectories, as Fig. 5).
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from ..sim.groups import SCENES, scene
from ..trackers.groups import GroupTracker
from ..trackers.groups.metrics import FrameRecord, evaluate
from ..trackers.groups.pictures import draw_groups, plot_trajectories

__all__ = ["image_ellipses", "run"]


def image_ellipses(camera, groups) -> dict:
    """{id: (uv (2,), covariance (2, 2))}: each group's position spread projected into the left
    image (the Jacobian of eq. 6's u, v at the group's mean)."""
    out = {}
    for g in groups:
        x, y, z = g.position
        if z <= 0:
            continue
        J = np.array([[camera.f / z, 0, -camera.f * x / z**2], [0, camera.f / z, -camera.f * y / z**2]])
        S = g.spread[np.ix_([0, 2, 4], [0, 2, 4])]
        out[g.id] = (np.array([camera.f * x / z + camera.cx, camera.f * y / z + camera.cy]), J @ S @ J.T)
    return out


def _mot_available() -> bool:
    try:
        import motmetrics  # noqa: F401
    except ImportError:
        return False
    return True


def run(device, *, scene_name: str = "crossing", seconds: float | None = None, seed: int = 0, points: bool = False,
        save: str | None = None, out=None) -> dict:  # fmt: skip
    """Run the group-tracking demo on ``device``; print progress and tables to ``out`` (default:
    stdout); return the report."""
    out = sys.stdout if out is None else out
    if scene_name not in SCENES:
        raise ValueError(f"scene: expected one of {', '.join(SCENES)}, got {scene_name!r}")
    kw = {} if seconds is None else {"frames": 24 + int(round(seconds * 48))}
    if seconds is not None and seconds <= 0:
        raise ValueError(f"seconds: expected a positive duration, got {seconds}")
    sc = scene(scene_name, np.random.default_rng(seed), **kw)
    trk = GroupTracker(device, camera=sc.camera)
    n = len(sc.present)
    empty = [k for k in range(n) if not sc.present[k].any()]
    busy = [k for k in range(n) if sc.present[k].any()]
    print(f"gputrack demo groups: scene {scene_name}, {len(busy)} frames at 48 fps after {len(empty)} empty "
          f"frames, device {device.spec} ({device.name}), "
          + ("observation points from the simulator" if points else "the whole pipeline on the image pairs"),
          file=out)  # fmt: skip
    if not points:
        trk.learn_background(np.stack([sc[k].left for k in empty]))
    if save:
        os.makedirs(save, exist_ok=True)
    rng = np.random.default_rng(seed + 1)
    records, per_frame, tracks, truth = [], [], {}, {}
    for i, k in enumerate(busy):
        t = sc.truth(k)
        t0 = time.perf_counter()
        if points:
            y, v, pid = sc.observations(k, rng)
            fr = trk.update_points(y, v)
            uv = sc.camera.project(np.where(np.isfinite(y), y, 1.0))[:, :2] if len(y) else np.zeros((0, 2))
        else:
            f = sc[k]
            fr = trk.track(f.left, f.right)
            uv = fr.uv
            iu = np.clip(np.round(uv).astype(int), 0, [f.left.shape[1] - 1, f.left.shape[0] - 1])
            pid = f.person_id[iu[:, 1], iu[:, 0]] if len(uv) else np.zeros(0, np.int64)
        dt = time.perf_counter() - t0
        if i == 0:  # the first frame compiles the kernels: leave it out of the tables
            trk.scheduler.reset()
            trk.front.scheduler.reset()
        ids = np.array([g.id for g in fr.groups], np.int64)
        means = np.array([g.position for g in fr.groups]).reshape(-1, 3)
        records.append(FrameRecord(fr.labels, pid, t.person_group, ids, means, t.group_ids, t.group_mean))
        for g in fr.groups:
            tracks.setdefault(g.id, np.full((len(busy), 3), np.nan))[i] = g.position
        for g, m in zip(t.group_ids, t.group_mean):
            truth.setdefault(int(g), np.full((len(busy), 3), np.nan))[i] = m
        events = [f"started {fr.started}" if fr.started else "", f"merged {fr.merged}" if fr.merged else "",
                  f"split {fr.split}" if fr.split else "", f"ended {fr.ended}" if fr.ended else ""]  # fmt: skip
        per_frame.append({"frame": k, "ms": dt * 1e3, "points": int(len(fr.labels)),
                          "groups": {int(g.id): int(g.n_points) for g in fr.groups}})  # fmt: skip
        print(f"  frame {k:4d}  {dt * 1e3:7.1f} ms  {len(fr.labels):4d} points  groups "
              + " ".join(f"{g.id}:{g.n_points}" for g in fr.groups) + "  " + " ".join(e for e in events if e),
              file=out, flush=True)  # fmt: skip
        if save and not points and (i % 48 == 0 or fr.merged or fr.split or fr.started):
            img = draw_groups(f.left, uv, fr.labels, ellipses=image_ellipses(sc.camera, fr.groups))
            import cv2

            cv2.imwrite(os.path.join(save, f"groups_{k:04d}.png"), img)
    merge = None if sc.merge_frame is None or not busy[0] <= sc.merge_frame <= busy[-1] else sc.merge_frame - busy[0]
    mot = _mot_available()
    m = evaluate(records, merge_frame=merge, merged_group=sc.merged_group, mot=mot)
    print(f"\npaper 001 results as numbers ({scene_name})", file=out)
    print(f"  purity (share of points in their true group's group)   {m.mean_purity:8.4f}", file=out)
    print(f"  group id switches                                      {m.total_switches:8d}", file=out)
    if merge is not None:
        lat = "never" if m.merge_latency is None else f"{m.merge_latency:d} frames"
        print(f"  frames from the true merge to one group                {lat:>8}", file=out)
    elif scene_name == "merging":
        print("  (the groups merge after the last frame tracked: run longer to see it)", file=out)
    print(f"  error of the group means (mm)                          {m.mean_error:8.1f}", file=out)
    if mot:
        print(f"  CLEAR MOT: MOTA {m.mot['mota']:.3f}  MOTP {m.mot['motp']:.1f} mm  IDF1 {m.mot['idf1']:.3f}", file=out)
    else:
        print("  CLEAR MOT / IDF1: install motmetrics (pip install 'gputrack[test]')", file=out)
    ms = np.array([p["ms"] for p in per_frame])
    print("\nper-stage time, Table 1/2 layout (ms; frames after the first, which compiles kernels)", file=out)
    if not points:
        print(trk.front.scheduler.table("front end"), file=out)
    print(trk.scheduler.table("groups"), file=out)
    med = float(np.median(ms[1:] if len(ms) > 1 else ms))
    print(f"median frame time {med:.1f} ms", file=out)
    if save:
        try:
            fig = plot_trajectories(tracks, truth=truth, title=f"{scene_name}: group means (truth dashed)")
            fig.savefig(os.path.join(save, "trajectories.png"), dpi=100)
        except ImportError as e:
            print(f"  (no trajectory plot: {e})", file=out)
        print(f"pictures written to {save}", file=out)
    return {
        "device": {"spec": device.spec, "name": device.name},
        "scene": {"name": scene_name, "frames": len(busy), "seed": seed, "points": points},
        "metrics": {"purity": m.mean_purity, "id_switches": m.total_switches, "merge_latency": m.merge_latency,
                    "mean_error_mm": m.mean_error, "mot": m.mot},  # fmt: skip
        "stages": trk.scheduler.report() + ([] if points else trk.front.scheduler.report()),
        "median_frame_ms": med,
        "frames": per_frame,
    }


def write_json(report: dict, path: str) -> None:
    with open(path, "w") as f:
        json.dump(report, f, indent=2, default=float)

#!/usr/bin/env python3
"""Long runs of paper 000's body tracker: losses, their length, memory, on one simulated sequence.

The sequence's first ``--loop`` frames are rendered once and played forth and back (0, 1, ..., L-1,
L-2, ..., 1, 0, 1, ...): a seamless loop of any sequence (the pose is continuous; the motion turns at
the ends). The tracker runs ``--frames`` frames with the default settings (the paper's PF 3 stages, K = 1500, LM
10, the template every frame; ``--no-predict``: the paper's start, see BodyTrackerConfig.predict) and reports:

- lost frames: an arm part's axis more than ``--lost`` degrees (10) off the truth (Tables 5-6 measure);
- episodes: runs of consecutive lost frames (count, longest, the worst error in any);
- frames with a NaN pose or confidence 0;
- the recovery passes run (BodyTrackerConfig.recover_ratio) and how many of them were kept;
- the median frame time (ms) and the resident memory's growth per 1000 frames, from frame
  max(20 % of the run, min(1100, half of it)) (after warm-up and the profiler's 1000-frame history) to the end.

``--json FILE`` writes the figures (and the per-frame errors with ``--per-frame``).
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time

import numpy as np


def _rss_mb() -> float:
    """The process's resident memory now (MB), from /proc (the peak from getrusage elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * resource.getpagesize() / 2**20
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def episodes(lost: np.ndarray) -> list[tuple[int, int]]:
    """(start, length) of each run of consecutive True in ``lost``."""
    edges = np.diff(np.concatenate([[0], lost.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(int(s), int(e - s)) for s, e in zip(starts, ends)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None, help="device spec (default: the best available)")
    ap.add_argument("--sequence", type=int, default=0, help="simulated sequence 0-8 (default 0)")
    ap.add_argument("--frames", type=int, default=5000, help="frames to track (default 5000)")
    ap.add_argument("--loop", type=int, default=96, help="frames of the sequence played forth and back (96)")
    ap.add_argument("--lost", type=float, default=10.0, help="an arm part this many degrees off is lost (10)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-predict", action="store_true", help="the paper's start (no constant-velocity candidates)")
    ap.add_argument("--json", default=None, help="write the figures as JSON ('-': stdout)")
    ap.add_argument("--per-frame", action="store_true", help="with --json: the per-frame errors too")
    args = ap.parse_args(argv)
    if args.frames < 1 or args.loop < 2:
        ap.error("--frames: expected >= 1, --loop: expected >= 2")

    import gputrack
    from gputrack.sim import SEQUENCES, sequence
    from gputrack.trackers.body import BodyTracker, BodyTrackerConfig, arm_axis_errors

    dev = gputrack.device(args.device)
    seq = sequence(args.sequence, frames=args.loop, seed=args.seed)
    print(f"soak: sequence {args.sequence} ({SEQUENCES[args.sequence]}), {args.frames} frames looping "
          f"{args.loop} forth and back, {dev.spec} ({dev.name}); rendering the loop ...", flush=True)  # fmt: skip
    frames = list(seq)
    order = np.concatenate([np.arange(args.loop), np.arange(args.loop - 2, 0, -1)])
    config = BodyTrackerConfig(predict=not args.no_predict)
    tracker = BodyTracker(dev, seq.params[0], profile=False, config=config)
    errors = np.zeros((args.frames, 4))
    bad = 0
    ms = np.zeros(args.frames)
    rss = {}
    mark = max(1, args.frames // 5, min(1100, args.frames // 2))  # after the profiler's 1000-frame history fills
    t_start = time.perf_counter()
    for k in range(args.frames):
        f = frames[order[(k + 1) % len(order)]]
        t0 = time.perf_counter()
        est = tracker.track(f.gray, f.depth)
        ms[k] = (time.perf_counter() - t0) * 1e3
        if not np.isfinite(est.params).all() or est.confidence == 0.0:
            bad += 1
        errors[k] = arm_axis_errors(seq.chain, est.params, f.params)[0]
        if k == mark or k == args.frames - 1:
            rss[k] = _rss_mb()
        if (k + 1) % 500 == 0:
            lost_so_far = (errors[: k + 1].max(axis=1) > args.lost).mean()
            print(f"  {k + 1:6d} frames  {time.perf_counter() - t_start:7.1f} s  lost {lost_so_far:6.2%}  "
                  f"rss {_rss_mb():7.1f} MB", flush=True)  # fmt: skip
    worst = errors.max(axis=1)
    lost = worst > args.lost
    eps = episodes(lost)
    growth = None
    if len(rss) == 2 and args.frames - 1 > mark:
        (k0, m0), (k1, m1) = sorted(rss.items())
        growth = (m1 - m0) / (k1 - k0) * 1000
    report = {
        "device": dev.spec, "sequence": args.sequence, "name": SEQUENCES[args.sequence], "frames": args.frames,
        "loop": args.loop, "predict": config.predict, "lost_deg": args.lost, "lost_fraction": float(lost.mean()), "episodes": len(eps),
        "longest_episode": max((n for _, n in eps), default=0), "worst_deg": float(worst.max()),
        "median_error_deg": float(np.median(errors)), "nan_or_kept_frames": bad,
        "median_frame_ms": float(np.median(ms)), "rss_growth_mb_per_1000_frames": growth,
        "recovery_passes": tracker.recoveries, "recovery_kept": tracker.recovered,
    }  # fmt: skip
    print(f"lost frames (an arm part > {args.lost:g} deg): {lost.mean():.2%}; episodes {len(eps)}, longest "
          f"{report['longest_episode']} frames; worst {worst.max():.1f} deg; median error "
          f"{report['median_error_deg']:.3f} deg; NaN or kept frames {bad}; median frame "
          f"{report['median_frame_ms']:.1f} ms; memory growth "
          + ("n/a" if growth is None else f"{growth:+.2f} MB per 1000 frames")
          + f"; recovery passes {tracker.recoveries} ({tracker.recovered} kept)")  # fmt: skip
    if args.json:
        if args.per_frame:
            report["errors_deg"] = errors.round(4).tolist()
        text = json.dumps(report, indent=1)
        if args.json == "-":
            print(text)
        else:
            with open(args.json, "w") as fh:
                fh.write(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

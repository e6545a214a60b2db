"""Paper 001's group tracker: the whole frame (two VGA images -> groups) and the tracking core.

Cases:

- ``groups frame VGA fg 15%``: :meth:`GroupTracker.track` on 48 rendered pairs of the simulator's
  crossing scene (:mod:`gputrack.sim.groups`, 640 x 480, Bumblebee2-like rig), cycled. The scene's
  people cover 1-3 % of the image; the issue's budget is for a foreground of about 15 %, so the
  left background given to the tracker differs from the scene's in a band of rows as well (every
  pixel of the band is foreground: stereo, KLT and the groups then work on 15 % of the image, on
  the floor's real texture). Its peer is OpenCV's ``StereoBM`` on the same full pair (the
  disparity only, every pixel, no foreground restriction), the figure the masked matcher
  competes with; the reference is the same tracker on the ``numpy`` device.
- ``groups frame VGA crossing``: the same on the scene as it is (foreground 1-3 %).
- ``groups core 10000 points x 100 groups``: :meth:`GroupTracker.update_points` with 100 groups
  of 100 points each (a 10 x 10 grid 4 m apart, each group circling at its own speed, 8-16
  mm/frame, once per 40 frames; points spread 300 mm about their group, velocities 2 mm/frame),
  the 40 frames of a circle cycled after the groups formed (no jump where the cycle restarts):
  gate, tie-break, moments, update, spreads, merge test, split test, starts, ends. (Until
  2026-12-06 the groups moved in straight lines and jumped back where the cycle restarted,
  every 40th frame, where about 37 groups started from the points they lost and merged back:
  ~12 ms frames that added ~0.4 ms to the mean.)

Each case prints its per-stage table (the trackers' Schedulers, time the host spent issuing
each stage; ``--profile`` synchronises around every stage so the times are the device's). KLT
runs in a worker thread from the ``stereo`` stage on, beside the matching: the ``klt`` stage is
the wait for it after the matching was issued (on taichi:cpu, after it ran).
"""

from __future__ import annotations

import sys

import numpy as np

from ..registry import device as get_device
from .harness import Case, bench_main

NAME = "groups"
BAND = 0.15  # share of the image rows forced to foreground in the "fg 15%" case


def add_arguments(parser):
    parser.add_argument("--profile", action="store_true", help="synchronise around every stage (device times)")
    parser.add_argument("--frames", type=int, default=48, help="rendered pairs cycled per frame case (default 48)")
    parser.add_argument("--core-groups", type=int, default=100, help="groups of the tracking-core case (default 100)")
    parser.add_argument("--core-points", type=int, default=100, help="points per group of that case (default 100)")


def _scene(frames: int):
    from ..sim.groups import scene

    sc = scene("crossing", np.random.default_rng(0))
    empty = [k for k in range(len(sc.present)) if not sc.present[k].any()]
    busy = [k for k in range(len(sc.present)) if sc.present[k].any()][40 : 40 + frames]
    pairs = [(sc[k].left, sc[k].right) for k in busy]
    background = np.stack([sc[k].left for k in empty])
    return sc.camera, pairs, background


def _frame_case(device, camera, pairs, background, *, band: bool, profile: bool):
    from ..trackers.groups import GroupTracker

    def make(dev):
        trk = GroupTracker(dev, camera=camera, profile=profile)
        bg = background.copy()
        if band:
            H = bg.shape[1]
            r0 = int(H * 0.55)
            bg[:, r0 : r0 + int(H * BAND)] ^= 128  # every pixel of the band differs: foreground
        trk.learn_background(bg)
        k = [0]

        def step():
            L, R = pairs[k[0] % len(pairs)]
            k[0] += 1
            return trk.track(L, R)

        for _ in range(len(pairs)):  # KLT tracks and groups formed before the timing
            step()
        trk.scheduler.reset()
        trk.front.scheduler.reset()
        step.tracker = trk
        return step

    return make


def _stereo_bm(pairs):
    import cv2

    bm = cv2.StereoBM_create(numDisparities=64, blockSize=9)
    k = [0]

    def run():
        L, R = pairs[k[0] % len(pairs)]
        k[0] += 1
        return bm.compute(L, R)

    return run


def _core_frames(G: int = 100, per: int = 100, frames: int = 60, cycle: int = 40):
    """The core case's points: G groups on a 10-wide grid 4 m apart, each circling at its own
    speed (radius 50-100 mm: 8-16 mm/frame) and phase, once per ``cycle`` frames, so that the
    frames after the first ``frames - cycle`` repeat with no jump; per group ``per`` points 300 mm
    about it, velocities 2 mm/frame about its own."""
    rng = np.random.default_rng(0)
    centres = np.stack([np.arange(G) % 10 * 4000.0 - 18000, np.full(G, 1000.0), np.arange(G) // 10 * 4000.0 + 6000], 1)
    radius, phase = rng.uniform(50.0, 100.0, G), rng.uniform(0.0, 2 * np.pi, G)
    turn = np.where(rng.random(G) < 0.5, -1.0, 1.0) * 2 * np.pi / cycle
    out = []
    for k in range(frames):
        a = phase + turn * k
        at = centres + radius[:, None] * np.stack([np.cos(a), np.zeros(G), np.sin(a)], 1)
        vel = (radius * turn)[:, None] * np.stack([-np.sin(a), np.zeros(G), np.cos(a)], 1)
        y = np.repeat(at, per, 0) + rng.normal(0, 300, (G * per, 3))
        v = np.repeat(vel, per, 0) + rng.normal(0, 2, (G * per, 3))
        out.append((y.astype(np.float32), v.astype(np.float32)))
    return out


def _core_case(device, camera, frames, *, profile: bool):
    from ..trackers.groups import GroupConfig, GroupTracker

    def make(dev):
        trk = GroupTracker(dev, camera=camera, config=GroupConfig(capacity=128), profile=profile)
        for y, v in frames[:20]:
            trk.update_points(y, v)
        trk.scheduler.reset()
        k = [20]

        def step():
            y, v = frames[20 + k[0] % (len(frames) - 20)]
            k[0] += 1
            return trk.update_points(y, v)

        step.tracker = trk
        return step

    return make


def _details(step, front: bool):
    def details():
        trk = step.tracker
        text = (trk.front.scheduler.table("front end") + "\n" if front else "") + trk.scheduler.table("groups")
        data = (trk.front.scheduler.report() if front else []) + trk.scheduler.report()
        return text, data

    return details


def cases(device, args):
    ref = get_device("numpy")
    camera, pairs, background = _scene(args.frames)
    out = []
    for band, name in ((True, f"groups frame VGA fg {BAND:.0%}"), (False, "groups frame VGA crossing")):
        make = _frame_case(device, camera, pairs, background, band=band, profile=args.profile)
        run = make(device)
        out.append(Case(name, run=run, reference=make(ref), peers={"cv2.StereoBM full image": _stereo_bm(pairs)},
                        params={"size": [640, 480], "band": BAND if band else 0.0}, details=_details(run, True)))  # fmt: skip
    G, per = args.core_groups, args.core_points
    if G < 1 or per < 1:
        raise SystemExit(f"--core-groups and --core-points: expected positive counts, got {G} and {per}")
    frames = _core_frames(G, per)
    make = _core_case(device, camera, frames, profile=args.profile)
    run = make(device)
    out.append(Case(f"groups core {G * per} points x {G} groups", run=run, reference=make(ref),
                    params={"points": G * per, "groups": G}, details=_details(run, False)))  # fmt: skip
    return out


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

"""Benchmark: paper 002's pedestrian tracker, a 1280 x 960 depth frame -> tracks, 5 and 50 people.

The frames come from :func:`crowd_depth`, a cheap synthetic level depth camera 1 m up (people as
upright 0.45 x 1.7 m boards facing the camera, nearer ones hiding farther ones, a back wall at
6 m, beyond the 5 m cut) so that 50 people fit in the view; they walk 100 mm a frame to the right
and back (a ping-pong of ``--frames`` frames), so the tracker keeps its tracks.

Cases per crowd size N (``--people``, default 5 and 50):

- ``pedestrian frame N=..``: :meth:`PedestrianTracker.track` of one frame (front end, segments,
  predict, associate, update) on the device; reference: the same on ``numpy``; peer "numpy front
  end": the front end written in plain NumPy (foreground, back-projection, ``rng.choice`` of 1024,
  the points above the sensor) with scikit-learn's DBSCAN and the same segments, i.e. what a
  host-only implementation costs before any tracking;
- ``dbscan N=..``: the device DBSCAN of the frame's 2D points; peer: ``sklearn.cluster.DBSCAN``.

``--stages F`` also prints the tracker's per-stage table (device-synchronised, F frames) to stderr.
"""

from __future__ import annotations

import sys

import numpy as np

from ..models.camera import Camera
from ..registry import device as get_device
from .harness import Case, bench_main

NAME = "pedestrians"
SHAPE = (960, 1280)
CAMERA = Camera(1280 / (2 * np.tan(np.radians(59.0) / 2)), 960 / (2 * np.tan(np.radians(46.0) / 2)), 639.5, 479.5)


def add_arguments(parser):
    parser.add_argument("--people", type=int, action="append", help="people in view (repeatable; default 5 and 50)")
    parser.add_argument("--frames", type=int, default=8, help="frames of the walk (ping-pong; default 8)")
    parser.add_argument("--scale", type=float, default=1.0, help="image size (1: 1280 x 960)")
    parser.add_argument("--stages", type=int, default=0, metavar="F", help="print the per-stage table over F frames")
    parser.add_argument("--no-sklearn", action="store_true", help="skip the scikit-learn peers")


def crowd_positions(n: int, seed: int = 0) -> np.ndarray:
    """(n, 2) ground positions (x, z) mm of n people spread over the view, 1.2-4.8 m away."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(1200.0, 4800.0, n)
    x = rng.uniform(-0.45, 0.45, n) * z  # within the 59 deg view (tan 29.5 deg = 0.57)
    return np.stack([x, z], axis=1)


def crowd_depth(camera: Camera, shape, people_xz, *, camera_height: float = 1000.0, height: float = 1700.0,
                width: float = 450.0, wall: float = 6000.0) -> np.ndarray:  # fmt: skip
    """A level depth camera's (H, W) uint16 mm frame of people as boards (``width`` x ``height`` mm,
    facing the camera, feet on the floor ``camera_height`` below it) at ``people_xz`` (K, 2) in
    front of a wall at ``wall`` mm and the floor; nearer boards hide farther ones."""
    H, W = (int(s) for s in shape)
    v = (np.arange(H, dtype=np.float64) - camera.cy) / camera.fy
    with np.errstate(divide="ignore"):
        floor = np.where(v > 0, camera_height / np.where(v > 0, v, 1.0), np.inf)
    depth = np.minimum(np.full((H, W), wall), floor[:, None])
    for x, z in sorted(np.asarray(people_xz, np.float64).reshape(-1, 2).tolist(), key=lambda p: -p[1]):
        c0 = int(np.clip(np.floor(camera.fx * (x - width / 2) / z + camera.cx), 0, W))
        c1 = int(np.clip(np.ceil(camera.fx * (x + width / 2) / z + camera.cx), 0, W))
        r0 = int(np.clip(np.floor(camera.fy * (camera_height - height) / z + camera.cy), 0, H))
        r1 = int(np.clip(np.ceil(camera.fy * camera_height / z + camera.cy), 0, H))
        depth[r0:r1, c0:c1] = np.minimum(depth[r0:r1, c0:c1], z)
    return np.round(depth).astype(np.uint16)


def walk(n: int, frames: int, shape=SHAPE, camera: Camera = CAMERA, seed: int = 0) -> tuple:
    """(background (1, H, W) uint16, frames list of (H, W) uint16): n people walking 100 mm a frame."""
    xz = crowd_positions(n, seed)
    bg = crowd_depth(camera, shape, np.zeros((0, 2)))[None]
    out = []
    for k in range(frames):
        step = xz.copy()
        step[:, 0] += 100.0 * k
        out.append(crowd_depth(camera, shape, step))
    return bg, out + out[-2:0:-1]


def numpy_front_end(depth, background, camera, config, rng):
    """The front end in plain NumPy with scikit-learn's DBSCAN (the benchmark's host peer)."""
    from sklearn.cluster import DBSCAN

    from ..trackers.pedestrians.front import segments_of

    d = depth.astype(np.float32)
    fg = (d > 0) & (d <= config.max_range) & np.isfinite(background)
    fg &= np.abs(d - background) >= config.foreground_threshold
    rows, cols = np.nonzero(fg)
    if len(rows) < config.n_points:
        return []
    pick = rng.choice(len(rows), config.n_points, replace=False)
    r, c = rows[pick], cols[pick]
    z = d[r, c]
    p = np.stack([(c - camera.cx) * z / camera.fx, (r - camera.cy) * z / camera.fy, z], axis=1)
    p = p[p[:, 1] < 0]  # above the sensor (level camera)
    if not len(p):
        return []
    lab = DBSCAN(eps=config.eps, min_samples=config.min_samples).fit(p[:, [0, 2]]).labels_
    return segments_of(p, lab, config.min_segment_points, config.min_extent)[0]


def _cycle(device, bg, frames, config, profile=False):
    from ..trackers.pedestrians import PedestrianTracker

    trk = PedestrianTracker(device, camera=CAMERA_FOR[bg.shape[1:]], config=config, profile=profile)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trk.learn_background(bg)
    state = {"k": 0}

    def step():
        fr = trk.track(frames[state["k"] % len(frames)])
        state["k"] += 1
        return fr

    step.tracker = trk
    return step


CAMERA_FOR: dict = {}


def _camera(scale: float) -> tuple:
    shape = (int(round(SHAPE[0] * scale)), int(round(SHAPE[1] * scale)))
    cam = Camera(CAMERA.fx * scale, CAMERA.fy * scale, (shape[1] - 1) / 2, (shape[0] - 1) / 2)
    CAMERA_FOR[shape] = cam
    return shape, cam


def cases(device, args):
    from ..trackers.pedestrians import PedestrianConfig

    config = PedestrianConfig()
    shape, cam = _camera(args.scale)
    ref = get_device("numpy")
    out = []
    for n in args.people or [5, 50]:
        bg, frames = walk(n, args.frames, shape, cam)
        run = _cycle(device, bg, frames, config)
        reference = _cycle(ref, bg, frames, config)
        peers = {}
        bgf = bg[0].astype(np.float32)
        rng = np.random.default_rng(0)
        if not args.no_sklearn:
            ks = {"k": 0}

            def host_front(ks=ks, frames=frames, bgf=bgf):
                ks["k"] += 1
                return numpy_front_end(frames[ks["k"] % len(frames)], bgf, cam, config, rng)

            peers["numpy front end + sklearn"] = host_front
        params = {"people": n, "width": shape[1], "height": shape[0], "frames": len(frames)}
        out.append(Case(f"pedestrian frame N={n} {shape[1]}x{shape[0]}", run=run, reference=reference, peers=peers,
                        params=params))
        # the DBSCAN of one frame's points, alone
        fr = run()
        pts = np.ascontiguousarray((fr.points.astype(np.float64) @ run.tracker.front.axes.T).astype(np.float32))
        from ..ops import dbscan

        dpts = pts if device.backend == "numpy" else device.asarray(pts)
        dl = device.empty((len(pts),), np.int32) if device.backend != "numpy" else None
        dpeers = {}
        if not args.no_sklearn:
            from sklearn.cluster import DBSCAN

            dpeers["sklearn DBSCAN"] = lambda pts=pts: DBSCAN(eps=config.eps, min_samples=config.min_samples).fit(pts)
        out.append(Case(f"dbscan N={n} ({len(pts)} points)",
                        run=lambda dpts=dpts, dl=dl: dbscan(device, dpts, config.eps, config.min_samples, out=dl),
                        reference=lambda pts=pts: dbscan(ref, pts, config.eps, config.min_samples),
                        peers=dpeers, params={"people": n, "points": len(pts)}))  # fmt: skip
        if args.stages:
            prof = _cycle(device, bg, frames, config, profile=True)
            for _ in range(2):
                prof()
            prof.tracker.scheduler.reset()
            for _ in range(args.stages):
                prof()
            print(prof.tracker.scheduler.table(f"{device.spec}: pedestrian frame N={n} {shape[1]}x{shape[0]}"),
                  file=sys.stderr, flush=True)  # fmt: skip
    return out


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

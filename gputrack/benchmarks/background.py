"""The per-pixel front ends of papers 001 and 002 at the depth sensor's size, 1280 x 960:

- ``background_median F=30``: the per-pixel median of 30 empty frames (paper 002 sec. 4.1), float32
  frames with 2 % NaN dropouts on the device; end to end: uint16 frames with 0 dropouts
  (``missing=0``) uploaded as their bytes and the background downloaded. Peer: ``numpy.nanmedian``
  over the frames.
- ``foreground_mask``: |frame - background| >= 100 mm of one frame. Peer: OpenCV
  (``cv2.absdiff`` + ``cv2.compare``, no validity test: a lower bound on what it would cost).
- ``depth_points n=1024``: foreground, range cut at 5 m, back-projection and a seeded uniform
  subset of 1024 points (paper 002 sec. 4.1), a new counter every call; end to end: a uint16 frame
  uploaded, the points and the count downloaded. Peer: the same steps in plain NumPy
  (mask, ``numpy.flatnonzero``, ``Generator.choice`` without replacement, back-projection).

The scene: a level camera 1 m above an empty floor in front of a wall 4.5 m away (uint16 mm,
2 % dropouts), with three people 3-4 m away (about 250 000 foreground pixels).
"""

import sys

import numpy as np

from .harness import Case, bench_main

NAME = "background"
H, W = 960, 1280


def add_arguments(parser):
    parser.add_argument("--frames", type=int, default=30, help="frames of the median (default 30)")
    parser.add_argument("--no-median", action="store_true", help="skip the median case (its reference takes seconds)")
    parser.add_argument("--size", default=f"{W}x{H}", help=f"image width x height (default {W}x{H})")


def depth_scene(rng, h=H, w=W):
    """(background uint16 (h, w), frame uint16 (h, w)) of the benchmark's scene, in mm."""
    from ..models.camera import Camera
    from ..ops.depth_points import floor_background

    cam = Camera(1050.0 * w / 1280, 1050.0 * w / 1280, w / 2, h / 2)
    floor = floor_background(cam, 1000.0, (h, w))
    bg = np.minimum(floor, 4500.0)
    frame = bg + rng.normal(0, 8, (h, w))
    for left, dist in ((0.2, 3000.0), (0.45, 3500.0), (0.7, 4000.0)):  # three people, 1.8 m tall
        top = int(h / 2 - 800.0 * cam.fy / dist)
        bottom = int(h / 2 + 1000.0 * cam.fy / dist)
        c0, c1 = int(left * w), int(left * w + 500.0 * cam.fx / dist)
        frame[max(top, 0) : min(bottom, h), c0:c1] = dist + rng.normal(0, 8, (min(bottom, h) - max(top, 0), c1 - c0))
    frame[rng.random((h, w)) < 0.02] = 0
    return np.rint(bg).astype(np.uint16), np.rint(frame).astype(np.uint16), cam


def _numpy_points(depth, bg, cam, rng, n=1024, threshold=100.0, max_range=5000.0):
    """Paper 002 sec. 4.1 in plain NumPy: the peer of depth_points."""
    z = depth.astype(np.float32)
    with np.errstate(invalid="ignore"):
        fg = (z > 0) & (z <= max_range) & (bg > 0) & (np.abs(z - bg) >= threshold)
    idx = np.flatnonzero(fg)
    sel = rng.choice(idx, n, replace=False) if idx.size > n else idx
    r, c = np.divmod(sel, depth.shape[1])
    zz = z.ravel()[sel]
    return np.stack([(c - cam.cx) * zz / cam.fx, (r - cam.cy) * zz / cam.fy, zz], axis=1), idx.size


def cases(device, args):
    from ..registry import device as get_device
    from ..ops.background import background_median, foreground_mask
    from ..ops.depth_points import depth_points

    ref = get_device("numpy")
    rng = np.random.default_rng(0)
    try:
        W, H = (int(v) for v in str(args.size).lower().split("x"))
    except ValueError:
        raise SystemExit(f"--size: expected WIDTHxHEIGHT, got {args.size!r}") from None
    bg16, frame16, cam = depth_scene(rng, H, W)
    bg = bg16.astype(np.float32)
    frame = frame16.astype(np.float32)
    frame[frame16 == 0] = np.nan
    out = []
    F = int(args.frames)
    if not args.no_median:
        frames16 = np.stack([np.where(rng.random((H, W)) < 0.02, 0, bg16) for _ in range(F)])
        frames = frames16.astype(np.float32)
        frames[frames16 == 0] = np.nan
        on_dev = device.asarray(frames)
        med = device.empty((H, W), np.float32)

        def nanmedian(frames=frames):
            return np.nanmedian(frames, axis=0)

        out.append(
            Case(
                f"background_median F={F} {W}x{H}",
                run=lambda: background_median(device, on_dev, out=med),
                reference=lambda: background_median(ref, frames),
                end_to_end=lambda: device.to_numpy(background_median(device, frames16, missing=0)),
                peers={"numpy.nanmedian": nanmedian},
                params={"F": F, "H": H, "W": W, "dtype": "float32", "e2e dtype": "uint16"},
            )
        )
    f_dev, bg_dev = device.asarray(frame), device.asarray(bg)
    mask = device.empty((H, W), np.uint8)
    peers = {}
    try:
        import cv2

        def opencv(frame=frame, bg=bg):
            return cv2.compare(cv2.absdiff(frame, bg), 100.0, cv2.CMP_GE)

        peers["opencv absdiff+compare"] = opencv
    except ImportError:
        pass
    out.append(
        Case(
            f"foreground_mask {W}x{H}",
            run=lambda: foreground_mask(device, f_dev, bg_dev, 100.0, out=mask),
            reference=lambda: foreground_mask(ref, frame, bg, 100.0),
            end_to_end=lambda: device.to_numpy(foreground_mask(device, frame16, bg, 100.0, missing=0)),
            peers=peers,
            params={"H": H, "W": W, "threshold_mm": 100.0},
        )
    )
    pts = device.empty((1024, 3), np.float32)
    counter = iter(range(1 << 31))
    prng = np.random.default_rng(1)
    count = depth_points(ref, frame16, bg, cam)[1]
    out.append(
        Case(
            f"depth_points n=1024 {W}x{H}",
            run=lambda: depth_points(device, f_dev, bg_dev, cam, out=pts, counter=next(counter)),
            reference=lambda: depth_points(ref, frame16, bg, cam, counter=next(counter)),
            end_to_end=lambda: device.to_numpy(depth_points(device, frame16, bg, cam, counter=next(counter))[0]),
            peers={"numpy mask+choice": lambda: _numpy_points(frame16, bg, cam, prng)},
            params={"H": H, "W": W, "n_points": 1024, "foreground": int(count), "threshold_mm": 100.0,
                    "max_range_mm": 5000.0},  # fmt: skip
        )
    )
    return out


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

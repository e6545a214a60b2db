"""Subtraction stereo (paper 001): ``stereo_match`` speed with a foreground mask and on the whole
image, and its accuracy against OpenCV's block matchers on a real pair.

Timing cases (each on the device with the NumPy reference, the same op on the ``numpy`` device,
in the same run), on a VGA crop (rows 10-489, columns 50-689) of the Middlebury motorcycle
pair from scikit-image, max_disparity 64, block 9, inputs already on the device:

- ``stereo_match VGA mask <f> %``: a foreground mask of three upright ellipses (people seen by
  a static camera; f ~ 15 % of the pixels, ``--foreground``);
- ``stereo_match VGA full``: every pixel.

Peer: ``cv2.StereoBM`` (numDisparities 64, blockSize 9) on the whole image, in both rows (it has
no mask), the reference being ``--no-reference`` skippable on the full image (~3 s a call).

Accuracy (:func:`accuracy`, device-independent: every backend gives the reference's result):
the whole 741 x 500 motorcycle pair (ground-truth disparities 7-60 px, so max_disparity 64 at
full resolution, no downsampling), bad-pixel rates at 1 and 2 px over the pixels where the
ground truth is finite and the method gives a value, and the density (the share of those
ground-truth pixels with a value), for stereo_match, ``cv2.StereoBM`` and ``cv2.StereoSGBM``.
"""

import sys

import numpy as np

from .harness import Case, bench_main

NAME = "stereo"
MAX_DISPARITY = 64
BLOCK = 9


def add_arguments(parser):
    parser.add_argument("--foreground", type=float, default=0.15, help="mask share of the pixels (default 0.15)")
    parser.add_argument("--size", default="640x480", help="WxH of the timed pair, a crop of the motorcycle (default 640x480)")
    parser.add_argument("--no-reference", action="store_true", help="skip the NumPy reference on the full image")
    parser.add_argument("--no-accuracy", action="store_true", help="perf/bench_stereo.py: skip the accuracy table")
    parser.add_argument("--accuracy-only", action="store_true", help="perf/bench_stereo.py: only the accuracy table")
    parser.add_argument("--cpu-time", action="store_true",
                        help="perf/bench_stereo.py: also CPU time per call of every case and the peer (time.process_time)")


def motorcycle_gray():
    """The Middlebury motorcycle pair as uint8 gray images and its ground-truth disparity
    (float32, inf where unknown), from scikit-image (shipped in its wheel)."""
    import cv2
    from skimage.data import stereo_motorcycle

    left, right, truth = stereo_motorcycle()
    return cv2.cvtColor(left, cv2.COLOR_RGB2GRAY), cv2.cvtColor(right, cv2.COLOR_RGB2GRAY), truth


def foreground_mask(H: int, W: int, share: float) -> np.ndarray:
    """Three upright ellipses across the image, scaled to cover ``share`` of the pixels."""
    yy, xx = np.mgrid[:H, :W]
    centres = [(0.23, 0.54), (0.52, 0.52), (0.78, 0.56)]
    lo, hi = 0.0, 1.0
    for _ in range(30):  # bisect the size
        k = (lo + hi) / 2
        mask = np.zeros((H, W), bool)
        for cx, cy in centres:
            mask |= ((xx - cx * W) / (0.27 * k * W / 2)) ** 2 + ((yy - cy * H) / (0.8 * k * H / 2)) ** 2 < 1
        lo, hi = (k, hi) if mask.mean() < share else (lo, k)
    return mask


def _pair(size: str):
    W, H = (int(v) for v in size.lower().split("x"))
    left, right, _ = motorcycle_gray()
    if H > left.shape[0] - 10 or W > left.shape[1] - 50:
        raise SystemExit(f"--size: expected at most {left.shape[1] - 50}x{left.shape[0] - 10}, got {size}")
    return np.ascontiguousarray(left[10:10 + H, 50:50 + W]), np.ascontiguousarray(right[10:10 + H, 50:50 + W])


def stereo_bm(max_disparity: int = MAX_DISPARITY, block: int = BLOCK):
    """``cv2.StereoBM``; its output (int16, 1/16 px, negative = none) -> float32 with NaN."""
    import cv2

    bm = cv2.StereoBM_create(numDisparities=max_disparity, blockSize=block)
    return lambda left, right: _cv_disparity(bm.compute(left, right))


def stereo_sgbm(max_disparity: int = MAX_DISPARITY, block: int = 5):
    """``cv2.StereoSGBM`` with the parameters OpenCV's samples use (P1 = 8 block^2, P2 = 32 block^2,
    uniqueness 10, left-right 1 px, speckle window 100 / range 2)."""
    import cv2

    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=max_disparity, blockSize=block, P1=8 * block * block,
                                 P2=32 * block * block, disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100,
                                 speckleRange=2)  # fmt: skip
    return lambda left, right: _cv_disparity(sgbm.compute(left, right))


def _cv_disparity(raw):
    d = raw.astype(np.float32) / 16
    d[raw < 0] = np.nan
    return d


def scores(disparity: np.ndarray, truth: np.ndarray) -> dict:
    """Bad-pixel rates at 1 and 2 px over the pixels with a finite ground truth and a value, and
    the density (share of the finite-ground-truth pixels with a value)."""
    known = np.isfinite(truth)
    both = known & np.isfinite(disparity)
    err = np.abs(disparity[both] - truth[both])
    return {"bad1": float(np.mean(err > 1)) if err.size else float("nan"),
            "bad2": float(np.mean(err > 2)) if err.size else float("nan"),
            "density": float(both.sum() / known.sum())}  # fmt: skip


def accuracy(device=None) -> dict:
    """stereo_match (on ``device``, default numpy), cv2.StereoBM and cv2.StereoSGBM on the whole
    motorcycle pair at max_disparity 64: {method: scores}."""
    from ..device import to_numpy
    from ..ops import stereo_match
    from ..registry import device as get_device

    device = device or get_device("numpy")
    left, right, truth = motorcycle_gray()
    ours = to_numpy(stereo_match(device, left, right, max_disparity=MAX_DISPARITY, block=BLOCK))
    return {
        f"stereo_match (block {BLOCK})": scores(ours, truth),
        f"cv2.StereoBM (block {BLOCK})": scores(stereo_bm()(left, right), truth),
        "cv2.StereoSGBM (block 5)": scores(stereo_sgbm()(left, right), truth),
    }


def format_accuracy(rows: dict) -> str:
    head = f"{'method':<28}{'bad 1 px':>10}{'bad 2 px':>10}{'density':>10}"
    lines = [head, "-" * len(head)]
    for name, s in rows.items():
        lines.append(f"{name:<28}{100 * s['bad1']:>9.1f}%{100 * s['bad2']:>9.1f}%{100 * s['density']:>9.1f}%")
    return "\n".join(lines)


def cpu_times(device, args, reps: int = 10) -> dict:
    """CPU time per call (``time.process_time``, every thread of the process) of each case of
    :func:`cases` and of its peers, in ms, after 3 warm-up calls: on a shared machine, closer to
    the work done than the wall time."""
    import time

    rows = {}
    for case in cases(device, args):
        for name, fn in [(case.name, case.run), *((f"{p} ({case.name})", f) for p, f in case.peers.items())]:
            for _ in range(3):
                fn()
                device.synchronize()
            t0 = time.process_time()
            for _ in range(reps):
                fn()
                device.synchronize()
            rows[name] = (time.process_time() - t0) / reps * 1e3
    return rows


def cases(device, args):
    from ..ops import stereo_match
    from ..registry import device as get_device

    ref = get_device("numpy")
    left, right = _pair(args.size)
    H, W = left.shape
    mask = foreground_mask(H, W, args.foreground)
    L, R = device.asarray(left), device.asarray(right)
    out = device.empty((H, W), np.float32) if device.backend != "numpy" else np.empty((H, W), np.float32)
    kw = {"max_disparity": MAX_DISPARITY, "block": BLOCK}
    bm = stereo_bm()
    peers = {"cv2.StereoBM full": lambda: bm(left, right)}
    params = {"H": H, "W": W, **kw}
    share = round(100 * float(mask.mean()), 1)
    return [
        Case(f"stereo_match {W}x{H} mask {share} %", run=lambda: stereo_match(device, L, R, mask=mask, out=out, **kw),
             reference=lambda: stereo_match(ref, left, right, mask=mask, **kw), peers=peers,
             params={**params, "foreground": share}),
        Case(f"stereo_match {W}x{H} full", run=lambda: stereo_match(device, L, R, out=out, **kw),
             reference=None if args.no_reference else (lambda: stereo_match(ref, left, right, **kw)), peers=peers,
             params={**params, "foreground": 100.0}),
    ]  # fmt: skip


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

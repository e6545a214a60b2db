"""Upload and download bandwidth of a 640x480 float32 frame (the per-frame input of the trackers)."""

import sys

import numpy as np

from .harness import Case, bench_main

NAME = "transfer"


def cases(device, args):
    frame = np.random.default_rng(0).random((480, 640), dtype=np.float32)
    on_device = device.asarray(frame)
    return [
        Case("upload 640x480 f32", run=lambda: device.asarray(frame), params={"bytes": frame.nbytes}),
        Case("download 640x480 f32", run=lambda: device.to_numpy(on_device), params={"bytes": frame.nbytes}),
    ]


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

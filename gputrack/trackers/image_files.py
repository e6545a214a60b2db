"""Image sequences of the ``gputrack track`` commands: a video file, a directory of images or a glob pattern."""

from __future__ import annotations

import glob
import os

__all__ = ["frames"]


def frames(path: str):
    """The grey frames (uint8 (H, W)) of a video file, a glob pattern or a directory of images, one
    at a time. Raises FileNotFoundError / ValueError naming the path when nothing can be read."""
    import cv2

    if os.path.isfile(path) and not path.lower().endswith((".png", ".jpg", ".jpeg", ".pgm", ".ppm", ".bmp", ".tif",
                                                            ".tiff")):  # fmt: skip
        cap = cv2.VideoCapture(path)
        if not cap.isOpened():
            raise ValueError(f"{path}: expected a video OpenCV can read, got an unreadable file")
        try:
            while True:
                ok, img = cap.read()
                if not ok:
                    return
                yield cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
        finally:
            cap.release()
    names = sorted(glob.glob(os.path.join(path, "*"))) if os.path.isdir(path) else sorted(glob.glob(path))
    if not names:
        raise FileNotFoundError(f"{path}: expected a video, a directory of images or a glob pattern, found nothing")
    for name in names:
        img = cv2.imread(name, cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise ValueError(f"{name}: expected an image OpenCV can read, got an unreadable file")
        yield img

"""``gputrack track pedestrians``: a depth recording in, the pedestrians' tracks out (CSV).

A recording is 16-bit depth images in millimetres (0 = no reading), PNG or anything OpenCV reads
unchanged, given by a glob pattern or a directory (sorted by name). The camera is a JSON file
``{"fx": ..., "fy": ..., "cx": ..., "cy": ...}`` (pixels) with, optionally, ``"camera_height"``
(mm, a level camera; default 1000 as paper 002) or ``"ground_plane": [a, b, c, d]`` (mm, camera
coordinates, for another mounting). The background is the median of empty frames given by
``background`` (a glob or directory, at most 64 frames; fewer than 30 warns), or else the floor
plane (documented alternative for a scene without empty frames: every static thing above the
floor is then foreground).

Output: one CSV line per pedestrian and frame, MOTChallenge-like ``frame,id,bb_left,bb_top,
bb_width,bb_height,conf,x,y,z`` with frames counted from 1, no image box (-1) and confidence 1,
and (x, y, z) the pedestrian's position in mm (camera coordinates: x right, y down, z forward).
``save``: a directory for pictures every ``every`` frames (the depth image with the segments'
boxes; the top view of the tracks with ids and the segments, as paper 002's Fig. 10).
"""

from __future__ import annotations

import glob
import os

import numpy as np

from ...models.camera import Camera
from ..camera_file import read_camera_json

__all__ = ["depth_frames", "image_boxes", "read_camera", "track_recording"]


def _names(path: str) -> list:
    names = sorted(glob.glob(os.path.join(path, "*"))) if os.path.isdir(path) else sorted(glob.glob(path))
    if not names:
        raise FileNotFoundError(f"{path}: expected a directory of depth images or a glob pattern, found nothing")
    return names


def depth_frames(path: str):
    """The depth frames (uint16 (H, W) mm) of a glob pattern or directory, one at a time. Raises
    ValueError naming the file when one is not a 16-bit single-channel image."""
    import cv2

    for name in _names(path):
        img = cv2.imread(name, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"{name}: expected a depth image OpenCV can read, got an unreadable file")
        if img.dtype != np.uint16 or img.ndim != 2:
            raise ValueError(f"{name}: expected a 16-bit single-channel depth image (mm), got {img.dtype.name} "
                             f"{img.shape}")  # fmt: skip
        yield img


def read_camera(path: str) -> tuple[Camera, dict]:
    """(Camera, mounting) from a JSON file with fx, fy, cx, cy and optionally camera_height or
    ground_plane (``mounting``: the PedestrianConfig fields they set)."""
    data = read_camera_json(path, ("fx", "fy", "cx", "cy"))
    mounting = {}
    if "camera_height" in data:
        mounting["camera_height"] = float(data["camera_height"])
    if "ground_plane" in data:
        mounting["ground_plane"] = tuple(float(v) for v in data["ground_plane"])
    return Camera(data["fx"], data["fy"], data["cx"], data["cy"]), mounting


def track_recording(device, depth: str, camera: Camera, out, *, config=None, background: str | None = None,
                    save: str | None = None, every: int = 10, progress=None) -> int:  # fmt: skip
    """Track a depth recording; write the CSV lines to ``out``; return the number of frames."""
    from .tracker import PedestrianConfig, PedestrianTracker

    config = PedestrianConfig() if config is None else config
    trk = PedestrianTracker(device, camera=camera, config=config)
    if background:
        trk.learn_background(np.stack(list(depth_frames(background))))
    if save:
        os.makedirs(save, exist_ok=True)
    history: dict = {}
    n = 0
    for k, d in enumerate(depth_frames(depth)):
        if k == 0 and not background:
            trk.floor_background(d.shape)
        fr = trk.track(d)
        for p in fr.pedestrians:
            x, y, z = (float(v) for v in p.position)
            out.write(f"{k + 1},{p.id},-1,-1,-1,-1,1,{x:.1f},{y:.1f},{z:.1f}\n")
            history.setdefault(p.id, []).append(p.position)
        if progress is not None:
            progress(k, fr)
        if save and k % max(1, every) == 0:
            _pictures(save, k, camera, d, fr, history)
        n = k + 1
    return n


def _pictures(save, k, camera, depth, fr, history) -> None:
    import cv2

    from .pictures import depth_picture, top_view

    boxes = image_boxes(camera, fr.segments)
    cv2.imwrite(os.path.join(save, f"depth_{k:05d}.png"), depth_picture(depth, boxes, list(range(len(boxes)))))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    ids = [p.id for p in fr.pedestrians]
    seg = np.array([[s.lo[0], s.hi[0], s.lo[2], s.hi[2]] for s in fr.segments]).reshape(-1, 4)
    ax = top_view(ids, np.array([p.position for p in fr.pedestrians]).reshape(-1, 3), seg,
                  history={i: np.array(history[i][-25:]) for i in ids}, title=f"frame {k + 1}")  # fmt: skip
    ax.figure.savefig(os.path.join(save, f"top_{k:05d}.png"), dpi=90)
    plt.close(ax.figure)


def image_boxes(camera, segments) -> np.ndarray:
    """(S, 4) image boxes [row0, row1, col0, col1) of the segments' 3D boxes (projected corners)."""
    out = []
    for s in segments:
        c = np.array([[x, y, z] for x in (s.lo[0], s.hi[0]) for y in (s.lo[1], s.hi[1]) for z in (s.lo[2], s.hi[2])])
        c[:, 2] = np.maximum(c[:, 2], 1.0)
        u = camera.fx * c[:, 0] / c[:, 2] + camera.cx
        v = camera.fy * c[:, 1] / c[:, 2] + camera.cy
        out.append([np.floor(v.min()), np.ceil(v.max()) + 1, np.floor(u.min()), np.ceil(u.max()) + 1])
    return np.array(out, dtype=np.float64).reshape(-1, 4)

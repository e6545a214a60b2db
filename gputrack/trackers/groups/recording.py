"""``gputrack track groups``: a rectified stereo recording in, the groups per frame out (JSON lines).

A recording is two image sequences of equal length and size: each a video file (anything OpenCV
reads) or image files given by a glob pattern or a directory (sorted by name). Colour frames are
converted to grey. The camera is the rectified pair's f (px), baseline b (mm) and principal point
(cx, cy), from the command line or a JSON file ``{"f": ..., "b": ..., "cx": ..., "cy": ...}``. The
first ``background`` frames teach the background (people may walk through them: the per-pixel
median ignores them while they move), or ``--background-left`` names empty frames.

Each output line: ``{"frame": k, "groups": [{"id", "position", "velocity", "n_points"}...],
"points": N, "events": {...}}`` with positions in mm (left camera: x right, y down, z forward)
and velocities in mm per frame.
"""

from __future__ import annotations

import json

import numpy as np

from ...models.camera import StereoCamera
from ..camera_file import read_camera_json
from ..image_files import frames

__all__ = ["frames", "read_camera", "track_recording"]


def read_camera(path: str) -> StereoCamera:
    """A StereoCamera from a JSON file with f (px), b (mm), cx, cy."""
    data = read_camera_json(path, ("f", "b", "cx", "cy"))
    return StereoCamera(f=data["f"], b=data["b"], cx=data["cx"], cy=data["cy"])


def track_recording(device, left: str, right: str, camera: StereoCamera, out, *, config=None, background: int = 24,
                    background_left: str | None = None, progress=None) -> int:  # fmt: skip
    """Track a recording; write one JSON line per frame to ``out``; return the number of frames."""
    from .tracker import GroupConfig, GroupTracker
    from .front import FrontEndConfig

    if config is None:
        config = GroupConfig(front=FrontEndConfig(background_frames=background))
    trk = GroupTracker(device, camera=camera, config=config)
    if background_left:
        trk.learn_background(np.stack(list(frames(background_left))))
    k = 0
    for k, (L, R) in enumerate(zip(frames(left), frames(right), strict=False)):
        if L.shape != R.shape:
            raise ValueError(f"frame {k}: expected left and right of one size, got {L.shape} and {R.shape}")
        fr = trk.track(L, R)
        line = {
            "frame": k,
            "points": int(len(fr.labels)),
            "groups": [{"id": g.id, "position": [round(float(v), 1) for v in g.position],
                        "velocity": [round(float(v), 2) for v in g.velocity], "n_points": g.n_points}
                       for g in fr.groups],  # fmt: skip
            "events": {"started": fr.started, "merged": fr.merged, "split": fr.split, "ended": fr.ended},
        }
        out.write(json.dumps(line) + "\n")
        if progress is not None:
            progress(k, fr)
    return k + 1 if trk.front.shape is not None else 0

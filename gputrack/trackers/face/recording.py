"""``gputrack track face``: a video of one face in, its pose, deformation and feature points per frame out.

The video is a file OpenCV reads, a directory of images or a glob pattern (colour is converted to
grey). The camera is a JSON file ``{"fx": ..., "fy": ..., "cx": ..., "cy": ...}`` (px); without one,
fx = fy = the image width and the principal point at the centre are assumed (a ~53 deg field of
view; depths then scale with the true focal length). The start: the K feature points of the first
frame from ``--landmarks first.json`` (``{"landmarks": [[u, v], ...]}`` in the order of
:data:`gputrack.models.face.LANDMARK_NAMES`, or a list of n such lists for the first n frames), or
else a Haar face box in the first frame. The model: :func:`gputrack.models.face.load_face_model`
file, or the multilinear model built from the ICT data.

Each output line: ``{"frame": k, "rvec": [3], "rotation": [[3] x 3], "translation": [3] mm,
"euler_deg": [roll, pitch, yaw], "expression": [A'], "landmarks": [[u, v] x K], "confidence": c,
"lost": bool}``; a last line ``{"frames": N, "identity": [S'], "keyframes": [n]}`` (the identity learnt
and the frame numbers of the bundle adjustment's key frames).
"""

from __future__ import annotations

import json
import os

import numpy as np

from ...models.camera import Camera
from ...models.pose import euler_from_rotation
from ..camera_file import read_camera_json
from ..image_files import frames as read_frames
from .config import FaceConfig
from .tracker import FaceTracker

__all__ = ["read_landmarks", "track_recording"]


def read_camera(path: str) -> Camera:
    """A pinhole Camera from a JSON file with fx, fy, cx, cy (px)."""
    d = read_camera_json(path, ("fx", "fy", "cx", "cy"))
    return Camera(d["fx"], d["fy"], d["cx"], d["cy"])


def read_landmarks(path: str, K: int) -> np.ndarray:
    """(K, 2) or (n, K, 2) start points from a JSON file ``{"landmarks": ...}`` (see the module docstring)."""
    data = read_camera_json(path, ("landmarks",), "landmarks file")
    try:
        lm = np.array(data["landmarks"], dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: expected \"landmarks\" as {K} pairs of numbers [u, v]") from None
    if lm.shape != (K, 2) and not (lm.ndim == 3 and lm.shape[1:] == (K, 2)):
        raise ValueError(f"{path}: expected \"landmarks\" of shape ({K}, 2) or (n, {K}, 2), got {lm.shape}")
    return lm


def track_recording(device, video: str, out, *, camera: Camera | None = None, landmarks=None, model=None,
                    config: FaceConfig | None = None, save: str | None = None, progress=None) -> int:  # fmt: skip
    """Track ``video`` and write one JSON line per frame to ``out``; return the number of frames.

    landmarks: (K, 2) or (n, K, 2) start points, or None (Haar); model: a face model (default: the
    multilinear model from the ICT data); ``progress(k, estimate)`` per frame. Raises
    FileNotFoundError / ValueError naming what is wrong (unreadable video, too few frames, frames of
    mixed sizes, no face found)."""
    from ...models.face import FaceModel

    config = FaceConfig() if config is None else config
    model = FaceModel.from_ict() if model is None else model
    n = config.keyframes
    it = iter(read_frames(video))
    first = []
    for img in it:
        first.append(img)
        if len(first) == n:
            break
    if len(first) < n:
        raise ValueError(f"{video}: expected at least n={n} frames to start on (FaceConfig.keyframes), got {len(first)}")
    H, W = first[0].shape
    for k, img in enumerate(first):
        if img.shape != (H, W):
            raise ValueError(f"{video}: expected frames of one size {(H, W)}, got {img.shape} at frame {k}")
    if camera is None:
        camera = Camera(float(W), float(W), (W - 1) / 2.0, (H - 1) / 2.0)
    trk = FaceTracker(device, model, camera, config)
    if save:
        os.makedirs(save, exist_ok=True)
    k = 0

    def emit(est, last=False):
        nonlocal k
        rec = {"frame": k, "rvec": est.rvec.tolist(), "rotation": est.rotation.tolist(),
               "translation": est.translation.tolist(),
               "euler_deg": np.degrees(euler_from_rotation(est.rotation)).tolist(),
               "expression": est.expression.tolist(), "landmarks": est.landmarks.tolist(),
               "confidence": est.confidence, "lost": est.lost}  # fmt: skip
        out.write(json.dumps(rec) + "\n")
        if progress is not None:
            progress(k, est)
        k += 1

    ests = trk.start(np.array(first), landmarks=landmarks)
    for img, est in zip(first, ests):
        _picture(save, k, img, est, camera)
        emit(est)
    for img in it:
        if img.shape != (H, W):
            raise ValueError(f"{video}: expected frames of one size {(H, W)}, got {img.shape} at frame {k}")
        est = trk.track(img)
        _picture(save, k, img, est, camera)
        emit(est)
    out.write(json.dumps({"frames": k, "identity": trk.identity.tolist(), "keyframes": trk.keyframes.tolist()}) + "\n")
    return k


def _picture(save, k, img, est, camera) -> None:
    if not save or k % 10:
        return
    import cv2

    from .pictures import draw_estimate

    cv2.imwrite(os.path.join(save, f"frame_{k:05d}.png"), draw_estimate(img, est, camera))

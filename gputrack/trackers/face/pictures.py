"""Pictures of paper 003's tracking (OpenCV): a frame with the feature points and the head's axes; the
templates' sources."""

from __future__ import annotations

import numpy as np

from ...models.camera import Camera
from ...models.pose import euler_from_rotation, project, rodrigues

__all__ = ["draw_estimate", "draw_template_sources"]

#: axis length (mm) of the drawn head frame
AXIS_MM = 60.0


def draw_estimate(gray, estimate, camera: Camera, *, truth=None) -> np.ndarray:
    """A BGR uint8 picture of ``gray`` with the estimate's projected feature points (green), its
    re-localised points (yellow), the true points (``truth`` (K, 2), red crosses), the head's axes
    at the model origin (x red, y green, z blue) and the confidence."""
    import cv2

    img = cv2.cvtColor(np.clip(np.asarray(gray, np.float64), 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)
    axes = project(camera, estimate.rotation, estimate.translation,
                   np.array([[0, 0, 0], [AXIS_MM, 0, 0], [0, AXIS_MM, 0], [0, 0, AXIS_MM]], np.float64))  # fmt: skip
    if np.isfinite(axes).all() and np.abs(axes).max() < 1e5:
        o = tuple(int(round(v)) for v in axes[0])
        for k, colour in ((1, (0, 0, 255)), (2, (0, 200, 0)), (3, (255, 0, 0))):
            cv2.line(img, o, tuple(int(round(v)) for v in axes[k]), colour, 2, cv2.LINE_AA)
    if truth is not None:
        for u, v in np.asarray(truth, np.float64):
            if np.isfinite(u) and np.isfinite(v):
                cv2.drawMarker(img, (int(round(u)), int(round(v))), (0, 0, 255), cv2.MARKER_CROSS, 7, 1)
    for pts, colour in ((estimate.landmarks, (0, 220, 0)), (estimate.features, (0, 220, 220))):
        for u, v in np.asarray(pts, np.float64):
            if np.isfinite(u) and np.isfinite(v) and abs(u) < 1e5 and abs(v) < 1e5:
                cv2.circle(img, (int(round(u)), int(round(v))), 2, colour, -1, cv2.LINE_AA)
    text = "LOST" if estimate.lost else f"confidence {estimate.confidence:.2f}"
    cv2.putText(img, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 255, 255), 1, cv2.LINE_AA)
    return img


def draw_template_sources(views, *, scale: int = 3) -> np.ndarray:
    """A BGR uint8 picture of the templates' sources (:class:`~gputrack.trackers.face.templates.TemplateViews`):
    a row per source with its face direction (yaw, pitch in degrees) and its K patches as cut at its
    points (unwarped, ``scale`` times enlarged), blank where a point did not match."""
    import cv2

    from ...ops.face_relocate import sample_patches

    S, K = views.size, len(views.sources[0][1])
    side, label = S * scale, 140
    cell = side + 4
    img = np.full((cell * len(views) + 4, label + cell * K, 3), 40, np.uint8)
    for r, (image, points, pose, _) in enumerate(views.sources):
        _, pitch, yaw = np.degrees(euler_from_rotation(rodrigues(np.asarray(pose[0], np.float64))))
        y = 4 + r * cell
        cv2.putText(img, f"yaw {yaw:+.0f} pitch {pitch:+.0f}", (6, y + side // 2 + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (220, 220, 220), 1, cv2.LINE_AA)  # fmt: skip
        ok = np.flatnonzero(np.isfinite(points).all(axis=1))
        if not len(ok):
            continue
        for k, patch in zip(ok, sample_patches(image, points[ok], S)):
            tile = cv2.resize(np.clip(patch, 0, 255).astype(np.uint8), (side, side), interpolation=cv2.INTER_NEAREST)
            x = label + k * cell
            img[y : y + side, x : x + side] = tile[:, :, None]
    return img

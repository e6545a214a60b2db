"""Pictures of paper 002's tracking: a top view of the tracks and the frame's segments (paper Fig. 10)
and the depth image colour-mapped with the segments drawn on it.

:func:`top_view` needs matplotlib (the ``plot`` extra, imported when called); :func:`depth_picture`
uses OpenCV. Coordinates as :mod:`.metrics`: camera mm, the ground plane is (x, z).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["depth_picture", "top_view"]


def _colour(k: int) -> tuple[float, float, float]:
    """A distinct colour (RGB in [0, 1]) for id k (golden-ratio hues)."""
    import colorsys

    return colorsys.hsv_to_rgb((0.61803398875 * k) % 1.0, 0.75, 0.9)


def top_view(ids, positions, segments=None, *, history=None, truth_positions=None, hfov_deg: float = 59.0,
             max_depth: float = 5000.0, ax=None, title: str | None = None):  # fmt: skip
    """Draw one frame's top view (x right, z away from the camera, metres) and return the Axes.

    ids (M,), positions (M, 3): the tracks' ids and positions this frame (a dot and the id);
    segments (S, 4): ground-plane boxes [x_min, x_max, z_min, z_max] (grey, outlined);
    history: {id: (n, 3) earlier positions} drawn as lines; truth_positions (K, 3): crosses;
    the camera's field of view (``hfov_deg``) out to ``max_depth`` as two lines.
    """
    try:
        import matplotlib.pyplot as plt
        from matplotlib.patches import Rectangle
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("top_view needs matplotlib: pip install matplotlib (or gputrack[plot])") from e
    ids = np.asarray(ids).reshape(-1)
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(ids) != len(pos):
        raise ValueError(f"ids and positions: expected the same length, got {len(ids)} and {len(pos)}")
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 5))
    t = math.tan(math.radians(hfov_deg) / 2) * max_depth / 1000
    ax.plot([-t, 0, t], [max_depth / 1000, 0, max_depth / 1000], color="0.5", lw=0.8, ls="--")
    if segments is not None:
        for x0, x1, z0, z1 in np.asarray(segments, dtype=np.float64).reshape(-1, 4) / 1000:
            ax.add_patch(Rectangle((x0, z0), x1 - x0, z1 - z0, facecolor="0.75", edgecolor="0.2", lw=1.0))
    for k, track in (history or {}).items():
        h = np.asarray(track, dtype=np.float64).reshape(-1, 3) / 1000
        ax.plot(h[:, 0], h[:, 2], color=_colour(int(k)), lw=1.2)
    for k, p in zip(ids.tolist(), pos / 1000):
        ax.plot(p[0], p[2], "o", color=_colour(int(k)), ms=6)
        ax.annotate(str(k), (p[0], p[2]), xytext=(4, 4), textcoords="offset points", fontsize=10)
    if truth_positions is not None:
        tp = np.asarray(truth_positions, dtype=np.float64).reshape(-1, 3) / 1000
        ax.plot(tp[:, 0], tp[:, 2], "x", color="k", ms=6, label="truth")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_xlim(-t - 0.5, t + 0.5)
    ax.set_ylim(0, max_depth / 1000 + 0.5)
    ax.set_aspect("equal")
    if title:
        ax.set_title(title)
    return ax


def depth_picture(depth, boxes=None, ids=None, *, max_depth: float = 5000.0) -> np.ndarray:
    """A depth image (H, W) in mm (0 = no reading) as a (H, W, 3) uint8 BGR picture: near = red, far =
    blue (OpenCV's turbo map over 0..``max_depth``), no reading or beyond ``max_depth`` black; with
    image boxes (S, 4) [row0, row1, col0, col1) outlined in white and labelled with ``ids`` (S,)."""
    import cv2

    d = np.asarray(depth)
    if d.dtype.kind not in "iuf" or d.ndim != 2:
        raise ValueError(f"depth: expected a real (H, W) image, got {d.dtype.name} {d.shape}")
    if not (np.isfinite(max_depth) and max_depth > 0):
        raise ValueError(f"max_depth: expected a finite number > 0, got {max_depth!r}")
    d = d.astype(np.float32)
    valid = (d > 0) & (d <= max_depth)
    g = np.clip(255.0 * (1.0 - d / max_depth), 0, 255).astype(np.uint8)
    img = cv2.applyColorMap(g, cv2.COLORMAP_TURBO)
    img[~valid] = 0
    if boxes is not None:
        b = np.asarray(boxes).reshape(-1, 4).astype(np.int64)
        lab = [None] * len(b) if ids is None else list(np.asarray(ids).reshape(-1))
        if len(lab) != len(b):
            raise ValueError(f"ids: expected one per box ({len(b)}), got {len(lab)}")
        scale = max(0.3, d.shape[1] / 1280)
        for (r0, r1, c0, c1), k in zip(b, lab):
            cv2.rectangle(img, (int(c0), int(r0)), (int(c1) - 1, int(r1) - 1), (255, 255, 255), 1)
            if k is not None:
                cv2.putText(img, str(k), (int(c0), max(int(r0) - 3, 8)), cv2.FONT_HERSHEY_SIMPLEX, 0.8 * scale,
                            (255, 255, 255), 1, cv2.LINE_AA)  # fmt: skip
    return img

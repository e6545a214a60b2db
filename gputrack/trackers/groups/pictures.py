"""Pictures of paper 001's results: the left image with the observation points coloured by group and
each group's 2D ellipse (Fig. 4, 6, 8) with OpenCV, and the top view (x-z) of the groups' 3D
trajectories with their ids (Fig. 5, 7, 9) with matplotlib (the ``plot`` extra, imported only
here, when a figure is drawn).
"""

from __future__ import annotations

import numpy as np

__all__ = ["colour", "draw_groups", "group_ellipses", "plot_trajectories"]

# BGR, well apart; ids cycle through them (-1, unassigned points: grey)
_PALETTE = (
    (255, 255, 0),  # cyan
    (255, 0, 255),  # magenta
    (0, 0, 255),  # red
    (0, 200, 0),  # green
    (255, 0, 0),  # blue
    (0, 200, 255),  # orange
    (0, 255, 255),  # yellow
    (200, 100, 255),  # pink
)


def colour(group_id: int) -> tuple:
    """The BGR colour of group ``group_id`` (grey for -1)."""
    return (160, 160, 160) if group_id < 0 else _PALETTE[int(group_id) % len(_PALETTE)]


def _uv_labels(uv, labels):
    uv = np.asarray(uv, dtype=np.float64)
    labels = np.asarray(labels)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv: expected an (N, 2) array of pixel positions, got shape {uv.shape}")
    if labels.shape != (len(uv),) or (labels.size and labels.dtype.kind not in "iu"):
        raise ValueError(f"labels: expected ({len(uv)},) integers (one group per point), got "
                         f"{labels.dtype.name} {labels.shape}")  # fmt: skip
    return uv, labels.astype(np.int64)


def group_ellipses(uv, labels) -> dict:
    """{group id: (mean (2,), covariance (2, 2))} of each group's image points (ids >= 0, two or
    more points)."""
    uv, labels = _uv_labels(uv, labels)
    out = {}
    for g in np.unique(labels[labels >= 0]):
        p = uv[labels == g]
        if len(p) >= 2:
            out[int(g)] = (p.mean(axis=0), np.cov(p.T))
    return out


def draw_groups(image, uv, labels, *, ellipses=None, sigma=2.0, radius=2):
    """The image (H, W) gray or (H, W, 3) BGR uint8 as a BGR copy with each point drawn in its
    group's colour, each group's ``sigma``-sigma ellipse (``ellipses`` as :func:`group_ellipses`
    returns, e.g. the tracker's projected covariances; default: the points' own) and its id."""
    import cv2

    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise ValueError(f"image: expected an (H, W) or (H, W, 3) uint8 image, got {img.dtype.name} {img.shape}")
    uv, labels = _uv_labels(uv, labels)
    out = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
    for (u, v), g in zip(uv, labels):
        cv2.circle(out, (int(round(u)), int(round(v))), radius, colour(int(g)), -1, lineType=cv2.LINE_AA)
    for g, (mean, cov) in (group_ellipses(uv, labels) if ellipses is None else ellipses).items():
        w, vec = np.linalg.eigh(np.asarray(cov, dtype=np.float64))
        axes = sigma * np.sqrt(np.maximum(w, 0.0))
        angle = float(np.degrees(np.arctan2(vec[1, 1], vec[0, 1])))
        centre = (int(round(mean[0])), int(round(mean[1])))
        cv2.ellipse(out, centre, (int(round(axes[1])), int(round(axes[0]))), angle, 0, 360, colour(g), 2,
                    lineType=cv2.LINE_AA)  # fmt: skip
        cv2.putText(out, str(g), (centre[0] + 4, centre[1] - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour(g), 2,
                    cv2.LINE_AA)  # fmt: skip
    return out


def plot_trajectories(tracks, *, truth=None, ax=None, title=None):
    """Top view (camera x right, z forward, mm) of the groups' 3D mean trajectories: ``tracks``
    {group id: (T, 3) camera-coordinate means, NaN rows where the group is not reported}, each in
    its group's colour with its id at the end; ``truth`` (same form) dashed in grey. Returns the
    matplotlib Figure (``ax``: draw into these axes instead of a new figure)."""
    try:
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("the trajectory plot needs matplotlib: pip install 'gputrack[plot]'") from e
    if ax is None:
        fig, ax = plt.subplots(figsize=(6, 5))
    else:
        fig = ax.figure
    for name, group in (("truth", truth or {}), ("tracks", tracks)):
        for g, xyz in group.items():
            p = np.asarray(xyz, dtype=np.float64)
            if p.ndim != 2 or p.shape[1] != 3:
                raise ValueError(f"{name}[{g}]: expected a (T, 3) array of camera-coordinate means, got {p.shape}")
            ok = np.isfinite(p).all(axis=1)
            if not ok.any():
                continue
            if name == "truth":
                ax.plot(p[ok, 0], p[ok, 2], "--", color="0.6", lw=1)
                continue
            bgr = colour(int(g))
            rgb = (bgr[2] / 255, bgr[1] / 255, bgr[0] / 255)
            ax.plot(p[:, 0], p[:, 2], "-", color=rgb, lw=2, label=f"group {g}")
            last = p[ok][-1]
            ax.annotate(str(g), (last[0], last[2]), color=rgb, fontsize=11, weight="bold")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_aspect("equal", adjustable="datalim")
    if title:
        ax.set_title(title)
    if tracks:
        ax.legend(loc="best", fontsize=8)
    return fig

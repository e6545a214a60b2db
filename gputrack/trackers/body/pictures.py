"""Pictures of paper 000's tracking: a frame with the model drawn at the estimate (OpenCV), and the
per-part arm-axis errors over the frames (matplotlib, the ``plot`` extra, imported only when the
plot is drawn).

The frame picture (:func:`draw_estimate`) shows, over the gray image:

- the model's silhouette at the estimate (each part's outline in its colour over a light tint),
  ray-cast with :func:`gputrack.models.render.render` (the model alone, no background);
- each part's axes at its joint (x red, y green, z blue; the arms' x axis runs along the limb, the
  axis of the accuracy measure) and, with ``truth``, the true arms' x axes (white, thin);
- the template points where the estimate puts them: the RGB template (eq. 17) as green dots, the
  depth template (eq. 18) as magenta dots;
- the frame number, cost and confidence.
"""

from __future__ import annotations

import numpy as np

from ...models.camera import Camera
from ...models.chain import Chain
from ...models.render import render

__all__ = ["draw_estimate", "error_plot", "template_uv"]

#: BGR outline colour per part (torso, right upper arm, left upper arm, right forearm, left forearm, ...)
PART_COLOURS = ((255, 200, 0), (0, 140, 255), (0, 230, 255), (0, 80, 200), (120, 220, 255))
#: length (mm) of the drawn axes
AXIS_MM = 100.0
RGB_COLOUR = (0, 220, 0)
DEPTH_COLOUR = (255, 0, 255)


def _transforms(chain: Chain, params, name: str) -> np.ndarray:
    p = np.asarray(params, dtype=np.float64)
    if p.shape != (chain.n_params,):
        raise ValueError(f"{name}: expected shape ({chain.n_params},), got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError(f"{name}: expected finite values, got NaN or inf")
    return chain.transforms(p[None])[0]


def _project(camera: Camera, xyz: np.ndarray) -> np.ndarray:
    """(N, 2) pixel positions of camera points (N, 3); NaN where Z <= 0."""
    z = xyz[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([camera.fx * xyz[:, 0] / z + camera.cx, camera.fy * xyz[:, 1] / z + camera.cy], axis=1)
    uv[~(z > 0)] = np.nan
    return uv


def template_uv(chain: Chain, params, template, camera: Camera) -> np.ndarray:
    """(N, 2) pixel positions (u, v) of a :class:`gputrack.SparseTemplate`'s points under pose ``params``
    (P,): each point through its part's camera-from-part transform, then the pinhole (NaN behind the
    camera)."""
    T = _transforms(chain, params, "params")
    part = np.asarray(template.part, dtype=np.int64)
    if part.size and part.max() >= chain.n_parts:
        raise ValueError(f"template: expected part indices < {chain.n_parts} (the chain's parts), got {part.max()}")
    xyz = np.asarray(template.xyz, dtype=np.float64)
    cam = np.einsum("nij,nj->ni", T[part, :, :3], xyz) + T[part, :, 3]
    return _project(camera, cam)


def _pt(uv) -> tuple[int, int] | None:
    u, v = float(uv[0]), float(uv[1])
    if not (np.isfinite(u) and np.isfinite(v)) or abs(u) > 1e5 or abs(v) > 1e5:
        return None
    return round(u), round(v)


def draw_estimate(gray, chain: Chain, params, camera: Camera, *, templates=None, truth=None, label: str = "",
                  silhouette: bool = True) -> np.ndarray:  # fmt: skip
    """A BGR uint8 picture (H, W, 3) of ``gray`` (H, W) (float in [0, 1], or uint8) with the model at the
    estimate ``params`` (P,): silhouette, axes and the (RGB, depth) ``templates`` (SparseTemplate pair,
    e.g. the ones the tracker matched in this frame) where the estimate puts them; ``truth`` (P,): the
    true pose, whose arm axes are drawn thin in white; ``label``: a line of text at the top left."""
    import cv2

    g = np.asarray(gray)
    if g.ndim != 2:
        raise ValueError(f"gray: expected an (H, W) image, got shape {g.shape}")
    if g.dtype != np.uint8:
        g = np.clip(np.nan_to_num(g.astype(np.float64), nan=0.0) * 255.0, 0, 255).astype(np.uint8)
    img = cv2.cvtColor(g, cv2.COLOR_GRAY2BGR)
    H, W = g.shape
    T = _transforms(chain, params, "params")
    if silhouette and any(p.shape is not None for p in chain.parts):
        part = render(chain, transforms=T, camera=camera, size=(W, H), background=None, depth_step=0.0).part
        tint = img.copy()
        for j in range(chain.n_parts):
            mask = (part == j).astype(np.uint8)
            if not mask.any():
                continue
            colour = PART_COLOURS[j % len(PART_COLOURS)]
            tint[mask.astype(bool)] = colour
            contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(img, contours, -1, colour, 1, cv2.LINE_AA)
        img = cv2.addWeighted(img, 0.8, tint, 0.2, 0.0)
    # each part's axes at its joint
    axes = np.array([[0, 0, 0], [AXIS_MM, 0, 0], [0, AXIS_MM, 0], [0, 0, AXIS_MM]], np.float64)
    for j in range(chain.n_parts):
        uv = _project(camera, axes @ T[j, :, :3].T + T[j, :, 3])
        o = _pt(uv[0])
        for k, colour in ((1, (0, 0, 255)), (2, (0, 200, 0)), (3, (255, 0, 0))):
            e = _pt(uv[k])
            if o is not None and e is not None:
                cv2.line(img, o, e, colour, 2, cv2.LINE_AA)
    if truth is not None:
        Tt = _transforms(chain, truth, "truth")
        for j, p in enumerate(chain.parts):
            if p.parent < 0 or p.shape is None:
                continue
            end = np.array([[0, 0, 0], [p.shape.end, 0, 0]], np.float64)
            uv = _project(camera, end @ Tt[j, :, :3].T + Tt[j, :, 3])
            a, b = _pt(uv[0]), _pt(uv[1])
            if a is not None and b is not None:
                cv2.line(img, a, b, (255, 255, 255), 1, cv2.LINE_AA)
    for template, colour in zip(templates or (), (RGB_COLOUR, DEPTH_COLOUR)):
        for uv in template_uv(chain, params, template, camera):
            p = _pt(uv)
            if p is not None:
                cv2.circle(img, p, 2, colour, -1, cv2.LINE_AA)
    if label:
        cv2.putText(img, label, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 255, 255), 1, cv2.LINE_AA)
    return img


def error_plot(frames, errors, names, *, title: str = ""):
    """The per-part errors over the frames: ``frames`` (F,) frame numbers, ``errors`` (F, K) degrees
    (e.g. :func:`arm_axis_errors`), ``names`` K labels. Returns the matplotlib Figure; raises
    ImportError with the install line when matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("the error plot needs matplotlib: pip install 'gputrack[plot]'") from e
    x = np.asarray(frames, dtype=np.float64)
    e = np.asarray(errors, dtype=np.float64)
    if e.ndim != 2 or e.shape != (len(x), len(names)):
        raise ValueError(f"errors: expected shape ({len(x)}, {len(names)}) (frames x parts), got {e.shape}")
    fig, ax = plt.subplots(figsize=(8, 4))
    for k, name in enumerate(names):
        ax.plot(x, e[:, k], lw=1.0, marker="." if len(x) < 40 else None, label=name)
    ax.set_xlabel("frame")
    ax.set_ylabel("arm-axis angle error (deg)")
    ax.set_ylim(bottom=0.0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return fig

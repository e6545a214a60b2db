"""The 3D sparse template of paper 000 (sec. 2.3) on the host: the model's, or a real frame's.

The rule (render the textured model alone at a pose with hidden-surface removal, then pick N local
intensity extrema and N' local z-buffer extrema on its visible surface, spread over the parts and
filled where a part has too few) is the op :mod:`gputrack.ops.model_template`, which runs it on any
device; the tracker calls it on its own device every frame. This module keeps the host forms: the
model's template at a pose (:func:`sparse_template`, the NumPy reference run on the host, e.g. for
pictures and tests) and the rigid case, a real RGB-D frame's template (:func:`frame_template`).
Each point belongs to the part whose surface it lies on and is stored in that part's coordinates,
so that any pose maps it to the camera (``transforms[b, part] @ [x, y, z, 1]``). The RGB template's
value is the intensity T_i; the depth template's value is the point's camera depth Z at the
rendered pose (mm).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ...models.camera import DEFAULT_SIZE
from ...models.chain import Chain
from ...models.render import Rendering, Texture
from ...ops.model_template import model_images, model_template, select_template
from ...ops.template import SparseTemplate
from ...registry import device as _device

__all__ = ["frame_template", "sparse_template"]


def _host(templates) -> tuple[SparseTemplate, SparseTemplate]:
    return tuple(SparseTemplate(t.xyz, t.part, t.value) for t in templates)


def sparse_template(
    chain: Chain,
    params=None,
    n: int = 128,
    n_depth: int = 128,
    *,
    camera=None,
    size: tuple[int, int] = DEFAULT_SIZE,
    rendering: Rendering | None = None,
    texture: Texture | None = None,
    shading: float = 0.2,
    window: int = 5,
    border: int = 2,
    spacing: float = 4.0,
) -> tuple[SparseTemplate, SparseTemplate]:
    """(RGB template, depth template) of ``chain`` at pose ``params`` (P,), made on the host.

    :func:`gputrack.ops.model_template.model_template` on the ``numpy`` device (the reference), or,
    when ``rendering`` (a rendering of the model alone with exact depth, as
    ``render(..., background=None, depth_step=0)`` makes) is given, the points picked on it. The
    RGB template has ``n`` points with value T_i = the intensity; the depth template ``n_depth``
    points with value Z_i = camera depth (mm). Raises ValueError when the model is not visible.
    """
    ref = _device("numpy")
    opts = dict(window=window, border=border, spacing=spacing)
    if rendering is None:
        return _host(model_template(ref, chain, params, camera, size, n, n_depth, texture=texture, shading=shading,
                                    **opts))  # fmt: skip
    if not (rendering.part >= 0).any():
        raise ValueError("sparse_template: no visible model surface at this pose (the model is out of view)")
    images = model_images(ref, rendering.part, np.stack([rendering.gray, rendering.depth]), rendering.local,
                          chain.n_parts)  # fmt: skip
    return _host(select_template(ref, images, n, n_depth, **opts))


def frame_template(gray, depth, camera, n: int = 128, n_depth: int = 128, *, edge: float = 0.02,
                   **select) -> tuple[SparseTemplate, SparseTemplate]:  # fmt: skip
    """(RGB, depth) templates of a rigid scene from a real RGB-D frame, in that frame's camera coordinates.

    The rigid case of sec. 2.3: the "model" is the measured surface itself, one part (0). Points
    are local extrema of the gray image and of the depth map among the pixels with a depth
    measurement (> 0 and finite) away from depth discontinuities (a 3x3 depth span over ``edge``
    times the depth), back-projected with ``camera``
    (X = (u - cx) Z / fx, Y = (v - cy) Z / fy, in the depth unit). Tracking the pose of this
    part in a later frame (:func:`gputrack.models.rigid`, start at identity) gives the camera
    motion between the two frames. ``select`` passes ``window``, ``border``, ``spacing`` to
    :func:`gputrack.ops.model_template.select_template`.
    """
    gray = np.asarray(gray, dtype=np.float32)
    depth = np.asarray(depth, dtype=np.float32)
    if gray.shape != depth.shape or gray.ndim != 2:
        raise ValueError(f"gray and depth: expected the same (H, W) shape, got {gray.shape} and {depth.shape}")
    valid = np.isfinite(depth) & (depth > 0)
    if not valid.any():
        raise ValueError("frame_template: expected a frame with depth measurements, got none")
    # depth discontinuities (occlusion edges) are not surface points: a small motion changes what
    # is seen there, so pixels whose 3x3 neighbourhood spans more than ``edge`` of their depth are
    # left out (with the selection's border, the points stay away from them)
    d = np.where(valid, depth, 0.0)
    span = ndimage.maximum_filter(d, 3) - ndimage.minimum_filter(np.where(valid, depth, np.inf), 3)
    smooth = valid & (span <= edge * np.where(valid, depth, 1.0))
    part_img = np.where(smooth, 0, -1).astype(np.int32)
    if not smooth.any():
        raise ValueError("frame_template: expected a frame with smooth depth somewhere, got edges only")
    z = np.where(smooth, depth, 0.0)
    v, u = np.indices(depth.shape)
    xyz = np.stack([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z], axis=-1)
    images = model_images(_device("numpy"), part_img, np.stack([np.where(smooth, gray, 0.0), z]), xyz, 1)
    return _host(select_template(_device("numpy"), images, n, n_depth, **select))

"""Zero-mean normalised cross-correlation of templates with image patches (paper 003 eq. 13).

The face tracker's particle filter scores B hypotheses, each placing K feature points in the
image, by N(u) = the sum over the K points of the NCC of the point's S x S template with the
image patch centred on it: :func:`patch_ncc` (B,), or per point :func:`patch_ncc_per_point`
(B, K), each one kernel launch.

Conventions (every backend, exactly): patch pixel (i, j) of a point (u, v) samples the image
bilinearly at (u + j - (S-1)/2, v + i - (S-1)/2), from the four pixels (x0, y0), (x0+1, y0),
(x0, y0+1), (x0+1, y0+1) with ``x0 = min(floor(u), W-2)``, ``y0 = min(floor(v), H-2)`` (as the
template ops sample, gputrack/ops/template.py). A patch that does not lie wholly inside
[0, W-1] x [0, H-1] scores 0, and so does a flat patch or template (standard deviation
<= 1e-6 (|mean| + 1)). Every image pixel and template value read is first clamped to
[-INTENSITY_MAX, INTENSITY_MAX] = +-2**48 (gputrack/abi.py, as the RGB-D cost clamps gray pixels;
NaN stays NaN), on every backend and in the reference: the bilinear differences and the float32
sums of squares of S x S values then cannot overflow, and the score is that of the unclamped input
whenever no value exceeds the limit (an image of +-3e38 scores as one of +-2**48; a template
scaled by 1e30 is clamped, mostly to one value, and scores as flat).
"""

from __future__ import annotations

from . import backend_module
from ._args import arg, check_device

__all__ = ["patch_ncc", "patch_ncc_per_point"]


def _ncc_args(device, points2d, templates, image):
    check_device(device)
    dims = {}
    pts = arg(device, points2d, "points2d", ("B", "K", 2), dims)
    tpl = arg(device, templates, "templates", ("K", "S", "S"), dims)
    img = arg(device, image, "image", ("H", "W"), dims)
    if dims["B"] == 0 or dims["K"] == 0:
        raise ValueError(f"points2d: expected at least one hypothesis and one point, got shape {pts.shape}")
    if dims["S"] == 0:
        raise ValueError(f"templates: expected patches of at least 1 x 1 pixels, got shape {tpl.shape}")
    if dims["H"] < 2 or dims["W"] < 2:
        raise ValueError(f"image: expected an image of at least 2 x 2 pixels, got {img.shape}")
    return pts, tpl, img


def patch_ncc_per_point(device, points2d, templates, image):
    """Zero-mean NCC of each template with the image patch at each point: (B, K) float32 in [-1, 1].

    points2d: (B, K, 2) float32 (u, v) patch centres; templates: (K, S, S) float32; image: (H, W)
    float32. Patch pixel (i, j) samples the image bilinearly at (u + j - (S-1)/2, v + i - (S-1)/2).
    A patch that does not lie wholly inside [0, W-1] x [0, H-1] scores 0, and so does a flat patch
    or template (standard deviation <= 1e-6 (|mean| + 1): zero variance to float32 rounding).
    Values beyond +-2**48 are clamped to it first (gputrack.abi.INTENSITY_MAX; module docstring).
    """
    pts, tpl, img = _ncc_args(device, points2d, templates, image)
    return backend_module(device, "ncc").patch_ncc(device, pts, tpl, img, per_point=True)


def patch_ncc(device, points2d, templates, image):
    """Sum over the K points of :func:`patch_ncc_per_point`: (B,) float32 in [-K, K] (paper 003 N(u), eq. 13)."""
    pts, tpl, img = _ncc_args(device, points2d, templates, image)
    return backend_module(device, "ncc").patch_ncc(device, pts, tpl, img, per_point=False)

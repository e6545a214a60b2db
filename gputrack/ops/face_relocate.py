"""Feature-point re-localisation of paper 003 sec. 4.2 (eq. 14), on the device.

The face tracker's particle filter gives points m'_k (the projection of its estimate) that are only
as right as the identity (Fig. 5). The true points m-hat_k minimise, per feature point k (eq. 14),

    E_k(m) = sum_ROI { rho (I_t(m + x) - I_{t-1}(m_{t-1} + x))^2 + (I_t(m + x) - I_1(m_1 + x))^2 }
             + eps ||m - m'_k||^2,

the ROI an S x S patch (x over its pixel offsets): the appearance of the previous frame and of the
first frame (against drift) around the point, held near the prediction. Gauss-Newton on the
linearised patch I_t(m + d + x) ~ I_t(m + x) + G d (G the patch's image gradient by central
differences), per point:

    ((rho + 1) G^T G + eps I) d = -( G^T (rho (I_t - I_{t-1}) + (I_t - I_1)) + eps (m - m'_k) ),

a 2 x 2 solve; each step is at most ``max_step`` px long; a point whose system is singular
(|det| <= 1e-12) or whose step is not finite does not move in that iteration. Each point iterates
on its own, ``iterations`` times or until its step is shorter than ``tol`` px in both coordinates.

Beyond the paper, ``contrast`` c > 0 compares the patches photometrically normalised: each (I_t's at
the current point, I_{t-1}'s, I_1's) brought to zero mean and a standard deviation of c gray levels
(I_t's one-pixel ring and so its gradient scaled alike), so that a change of the light between the
frames (a gain and an offset of a patch's intensities) does not pull the points; eps keeps its
meaning against patches of contrast c. A patch of less than ``MIN_STD`` gray levels of standard
deviation is scaled as one of ``MIN_STD``. With ``shading`` (and c > 0) the comparison with the
first frame's patch takes each patch's least-squares intensity ramp b_x x + b_y y (x, y its pixel
offsets from the patch's centre) off too, before the scaling to c (the ring alike, so I_t's gradient
loses (b_x, b_y) in that term): light that has come round to one side since the first frame shades
a patch across its width, and the ramp would otherwise pull the point along it. The comparison with
the previous frame (lit alike) keeps the ramp: it is part of the patch's texture. The 2 x 2 system
then sums the two terms with their own gradients, (rho G_a^T G_a + G_b^T G_b + eps I) d =
-(rho G_a^T e_a + G_b^T e_b + eps (m - m'_k)): G_a and e_a = I_t - I_{t-1} of the patches normalised
for the previous frame's term, G_b and e_b = I_t - I_1 for the first frame's (without ``shading``
both are the same, and this is the system above).

Patches sample the image bilinearly: pixel (i, j) of the S x S patch at (u, v) is the image at
(u + j - (S-1)/2, v + i - (S-1)/2), each coordinate first clipped into [0, W-1] x [0, H-1] (samples
outside the image take the nearest border pixel), then interpolated from the pixels x0 = min(floor(x),
W-2), y0 = min(floor(y), H-2) and their right and lower neighbours; :func:`sample_patches` is the same
on the host in float64 (the tracker's templates).

:func:`relocate_points` also returns the S x S patches of the image at the points it found (the
next frame's I_{t-1}) and how well each matches its first-frame template: the zero-mean normalised
cross-correlation of the two patches with each one's least-squares intensity plane (its mean and
its ramp b_x x + b_y y) taken off, in [-1, 1], 0 where either is flat (the residual's standard
deviation at most 1e-6 (|mean| + 1), as :func:`gputrack.ops.ncc.patch_ncc`). Light that has come
round to one side shades a patch across its width and does not lower the match; a point that has
slipped onto other texture, or is hidden behind the nose, does (the face tracker leaves such points
out of its fits, ``FaceConfig.min_match``). One launch does every point; the tracker's image,
templates and patches stay on the device, only the K points and their matches go up and come down. The NumPy backend computes in float64 (the
oracle), the device kernels in float32.
"""

from __future__ import annotations

import numpy as np

from . import backend_module
from ._args import arg, check_device, out_arrays, real

__all__ = ["MIN_STD", "relocate_points", "sample_patches"]

#: the least standard deviation (gray levels) a patch is normalised by (``contrast`` > 0): a flat
#: patch's noise is not blown up
MIN_STD = 1.0
#: |det| of the 2 x 2 system at or below which a point does not move
SINGULAR = 1e-12


def relocate_points(device, image, predicted, previous, first, *, rho: float = 4.0, eps: float = 4000.0,
                    iterations: int = 5, max_step: float = 3.0, contrast: float = 0.0, shading: bool = False,
                    tol: float = 0.01, out=None):  # fmt: skip
    """(points (K, 2) float32 px, patches (K, S, S) float32, match (K,) float32): the K feature points
    minimising eq. 14 in ``image`` (H, W) float32, the image's S x S patches at them and each patch's
    match with its template in ``first`` (see the module docstring).

    predicted: (K, 2) float32 m'_k, where each point starts; previous, first: (K, S, S) float32 the
    patches I_{t-1} and I_1; rho, eps: eq. 14's weights; iterations: Gauss-Newton steps at most;
    max_step: px per step at most; contrast: 0 compares raw intensities (the paper), c > 0 patches
    normalised to zero mean and standard deviation c; shading: with c > 0, the comparison with the
    first frame takes each patch's intensity ramp off too; tol: a point whose step is shorter than this
    (px, in both coordinates) stops. Inputs NumPy or on the device; ``out``: (points, patches, match)
    on the device to write into."""
    check_device(device)
    dims: dict = {}
    dtype = (np.float32, np.float64) if device.backend == "numpy" else np.float32
    img = arg(device, image, "image", ("H", "W"), dims, dtype=dtype)
    if dims["H"] < 2 or dims["W"] < 2:
        raise ValueError(f"image: expected an image of at least 2 x 2 pixels, got shape {tuple(img.shape)}")
    prev = arg(device, previous, "previous", ("K", "S", "S"), dims, dtype=dtype)
    if dims["K"] < 1 or dims["S"] < 2:
        raise ValueError(f"previous: expected shape (K >= 1, S >= 2, S), got {tuple(prev.shape)}")
    fst = arg(device, first, "first", ("K", "S", "S"), dims, dtype=dtype)
    pred = arg(device, predicted, "predicted", ("K", 2), dims, dtype=dtype)
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or iterations < 0:
        raise ValueError(f"iterations: expected an int >= 0, got {iterations!r}")
    if not isinstance(shading, (bool, np.bool_)):
        raise TypeError(f"shading: expected a bool, got {type(shading).__name__}")
    consts = np.array([real("rho", rho, low=0.0), real("eps", eps, low=0.0), real("max_step", max_step, positive=True),
                       real("contrast", contrast, low=0.0), real("tol", tol, low=0.0), MIN_STD, SINGULAR,
                       float(shading)])  # fmt: skip
    if shading and consts[3] == 0:
        raise ValueError("shading: expected contrast > 0 (the ramp is taken off normalised patches), got contrast 0")
    K, S = dims["K"], dims["S"]
    points, patches, match = out_arrays(device, out, (("points", (K, 2), np.float32), ("patches", (K, S, S), np.float32),
                                                      ("match", (K,), np.float32)))  # fmt: skip
    backend_module(device, "face_relocate").relocate_points(device, img, pred, prev, fst, consts, int(iterations),
                                                            points, patches, match)  # fmt: skip
    return points, patches, match


def sample_patches(image, points, size: int, warp=None, index=None) -> np.ndarray:
    """(K, size, size) float64 bilinear patches of ``image`` (H, W) (NumPy, any real dtype) centred on
    the finite ``points`` (K, 2), on the host, with the convention of the module docstring (samples
    outside the image take the nearest border pixel). ``warp`` (K, 2, 2), optional: patch k's pixel at
    offset d = (x, y) from its centre samples the image at points[k] + warp[k] @ d (a template seen
    turned or scaled; the identity gives the plain patches). ``index`` (K,) ints, optional: ``image``
    is a stack of images (n, H, W) and patch k is cut from image index[k] (the same values as cutting
    each from its own image)."""
    from ..backends.reference.face_relocate import patches_at

    img = np.asarray(image)
    want = 2 if index is None else 3
    if img.ndim != want or min(img.shape[-2:]) < 2 or img.dtype.kind not in "uif":
        what = "a (H, W) image" if index is None else "a stack of images (n, H, W)"
        raise ValueError(f"image: expected {what} of real values, at least 2 x 2, got {img.dtype.name} "
                         f"{img.shape}")  # fmt: skip
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if index is not None:
        index = np.asarray(index)
        if index.shape != (len(pts),) or index.dtype.kind not in "iu" or (index < 0).any() or (index >= len(img)).any():
            raise ValueError(f"index: expected {len(pts)} ints in [0, {len(img)}), got {index!r}")
    if not np.isfinite(pts).all():
        raise ValueError(f"points: expected finite pixel coordinates, got {pts[~np.isfinite(pts).all(axis=1)][:3]}")
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
        raise ValueError(f"size: expected an int >= 1, got {size!r}")
    if warp is not None:
        warp = np.asarray(warp, dtype=np.float64)
        if warp.shape != (len(pts), 2, 2) or not np.isfinite(warp).all():
            raise ValueError(f"warp: expected ({len(pts)}, 2, 2) finite matrices, got shape {warp.shape}")
    return patches_at(img, pts, int(size), warp, index)

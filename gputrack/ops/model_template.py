"""The 3D sparse template of paper 000 (sec. 2.3) made on the device: render the model, pick its points.

:func:`model_template` renders a kinematic chain's textured parts at a pose and picks the RGB
template (N points at local extrema of the gray image) and the depth template (N' points at
local extrema of the z-buffer), all in device kernels; the host sends the part transforms and a
plan of a few integers per part, and receives a few counts per part (one wait). The templates
stay on the device as :class:`DeviceTemplate` objects that the cost ops (``rgbd_cost``,
``pose_residuals``, ``pf_stage``) read in place. :func:`select_template` picks the points on given
images (a part-id image, the two value images, the 3D point of each pixel): the rigid case of
sec. 2.3, where the "model" is a measured RGB-D frame.

The rule, exactly (every backend; the NumPy reference is gputrack/backends/reference/model_template.py):

1. **Render** (one ray per pixel centre, d = ((u - cx)/fx, (v - cy)/fy, 1), so a hit's ray
   parameter is its camera depth Z): each part's shape (:class:`gputrack.models.Shape`) is
   intersected analytically in the part's coordinates, only at the pixels of the part's box (the
   projection of its bounding box, :func:`gputrack.models.render.part_boxes`), and the nearest
   hit wins (ties: the lower part index). Per pixel: the part id (-1: nothing), the gray value
   (the procedural :class:`gputrack.models.render.Texture` of the part-local point under mild
   Lambertian shading, as :func:`gputrack.models.render.render`), the depth Z and the part-local
   point. The devices render in float32, the reference in float64: they agree to rounding except
   for a few pixels on silhouettes and occlusion edges.
2. **Values as integers**: value image k (0: gray, 1: depth) is read as q = v s_k (64-bit) with s_k a
   power of two such that |q| < 2**40 (for the model: gray <= 1, depth <= the farthest point of a
   part's bounding sphere): a float32 value times s_k is an integer, so q keeps every value's order
   and every tie exactly (a coarser q would tie neighbours a float32 depth tells apart and turn a
   limb's ridge into a line of extrema). Every comparison below is then exact 64-bit integer
   arithmetic, so every backend picks the same pixels from the same images.
3. **Per pixel** of part j: *interior* if every pixel within ``border`` (a square; outside the
   image counts as no part) belongs to j; over the ``window`` x ``window`` neighbourhood's pixels of
   the same part (the pixel itself included): c = their count, S = the sum of their q, hi and lo
   their largest and smallest q. The pixel is an *extremum* when hi > lo and q = hi or q = lo; its
   strength is |c q - S| / c (its distance from the neighbourhood's mean; compared exactly, by
   cross-multiplying: |c q - S| < 2**47, c <= 49). Pixel a is *stronger* than b when its strength is larger, or
   equal and the PCG hash of its index r W + c (gputrack.backends.reference.particles.pcg) is smaller,
   or that too equal and its index is smaller. The hash scrambles exact ties: the pixels of a ridge
   of equal depth steps (an upright torso's z-buffer) are then taken spread along it, not from its
   top down (taken in pixel order, the torso's depth points bunched in its top rows, and the
   particle filter alone lost a forearm in the first frames of sequence 0).
4. **Pools**: part j's pool is its interior pixels, or all its pixels when it has no interior pixel
   (a part too thin for the border). available_j = the pool's size, area_j = the part's pixel count.
   The candidates are the pool's extrema.
5. **Quotas** (on the host, from the counts): n points split over the parts, half equally among
   the parts with a pool, half by area, largest remainders first, capped by availability with the
   excess going to the parts with room, largest area first. A template has min(n, sum available)
   points.
6. **Extrema, spread**: within part j, the candidates strongest first, each taken unless a taken
   one lies closer than ``spacing`` pixels (d^2 < spacing^2), until the quota is met.
7. **Fill**: where the extrema fall short of the quota (the z-buffer of a smooth limb has few:
   mostly the ridge nearest the camera), the rest are pool pixels by farthest-point sampling: each
   the pool pixel farthest (d^2) from every point taken so far, among those whose row and column no
   point has yet (rook-spread), else those with a new row or a new column, else any; the first in
   pixel order among ties. With no extremum taken, the first is the pool pixel nearest the pool's
   centroid (n r - sum r, n c - sum c in integers). So the points still cover the part, and fall on
   as many image rows and columns as they can: a surface whose depth changes along one image
   direction only (an upright torso seen from the front) gives as many distinct depths, and as many
   positions relative to a quantised sensor's steps, as there are points (on the simulator's 5 mm
   depth, Table 7's protocol with ``depth_tol=2.5``, 6 trials: the torso's mean turn error 0.18 ->
   0.11 deg against a fill of a few columns).
8. The point's 3D position is the pixel's part-local point; its value the gray value (RGB
   template, T_i) or the depth Z (depth template). Points are grouped by part (the layout the
   cost kernels read): part by part, the extrema in the order taken, then the fill points.

On the devices the steps run as one render launch (a thread per pixel), one classification launch
(steps 2-4: a thread per pixel; per-part counts by atomics; the candidates binned per part), then,
after the host's quota plan, one launch of a thread per kind and part for steps 6-7: they are
sequential by nature (each pick depends on the ones before), and a part's loops touch only its
own candidates and pool (a few thousand pixels). Where a thread's loops are bounded (Taichi on
Vulkan: lavapipe runs at most 65535 passes per invocation) the fill instead takes one launch per
fill point, a thread per pixel (gputrack/backends/taichi/model_template.py).
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ..backends.reference.model_template import STATS
from ..device import Device, per_device_cache
from ..models.camera import DEFAULT_CAMERA, DEFAULT_SIZE, Camera
from ..models.chain import Chain
from ..models.render import Texture, image_size, part_boxes, pose_transforms
from ..uploads import constant
from . import backend_module
from ._args import check_device
from .template import SparseTemplate

__all__ = ["DeviceTemplate", "ModelImages", "model_template", "render_model", "select_template"]

#: |q| < 2**VALUE_BITS for the integer values of step 2 (int64: a window's sum of 49 and the
#: cross-multiplied strengths, < 2**53, fit)
VALUE_BITS = 40


class ModelImages:
    """Per-pixel images of a rendered (or given) model, on a device, and the region that holds it.

    ``part`` (H, W) int32 (-1: no part), ``values`` (2, H, W) float32 (gray, depth Z), ``local``
    (H, W, 3) float32 part-local points; ``crop`` = (r0, r1, c0, c1), half-open, a box outside which
    no pixel belongs to a part (pixels outside it are never read: they may hold anything);
    ``value_max`` (2,) bounds of |value| over the model's pixels (the integer scale of step 2);
    ``n_parts`` the number of parts J.
    """

    def __init__(self, device, part, values, local, crop, value_max, n_parts):
        self.device, self.part, self.values, self.local = device, part, values, local
        self.crop = tuple(int(c) for c in crop)
        self.value_max = tuple(float(v) for v in value_max)
        self.n_parts = int(n_parts)

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.part.shape)


class DeviceTemplate(SparseTemplate):
    """A :class:`SparseTemplate` whose points were written on a device (by :func:`select_template`).

    The cost ops read it there in place; ``xyz``, ``value`` and ``packed`` download the points the
    first time they are read (pictures, tests). ``part`` (N,) is known on the host without a
    download (the points are grouped by part: ``start`` from the quotas).
    """

    def __init__(self, device: Device, pts, counts: np.ndarray):
        counts = np.asarray(counts, np.int64)
        self._device = device
        self._pts = pts
        self.part = np.repeat(np.arange(len(counts), dtype=np.int32), counts)
        self._n_parts = len(counts)
        self.perm = np.arange(len(self.part), dtype=np.int32)
        self.sorted_part = self.part
        self.start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        self._host = None
        self._on = per_device_cache()
        self._on[device] = {
            "pts": pts,
            "part": constant(device, self.part),
            "index": constant(device, np.concatenate([self.start, self.perm]).astype(np.int32)),
            "parts": self._n_parts,
        }

    @property
    def n(self) -> int:
        return len(self.part)  # known on the host: no download

    @property
    def packed(self) -> np.ndarray:
        if self._host is None:
            self._host = np.ascontiguousarray(self._device.to_numpy(self._pts), dtype=np.float32)
            self._host.setflags(write=False)
        return self._host

    @property
    def xyz(self) -> np.ndarray:
        return self.packed[:, :3]

    @property
    def value(self) -> np.ndarray:
        return self.packed[:, 3]

    def __repr__(self) -> str:
        return f"DeviceTemplate(N={self.n}, parts={self.n_parts}, on {self._device.spec})"


# -- arguments -------------------------------------------------------------------------------------
def _count(name, value, low=1):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name}: expected an integer, got {type(value).__name__}")
    if int(value) < low:
        raise ValueError(f"{name}: expected an integer >= {low}, got {value}")
    return int(value)


def _selection_args(n, n_depth, window, border, spacing):
    n, n_depth = _count("n", n), _count("n_depth", n_depth)
    window = _count("window", window, 3)
    if window % 2 == 0 or window > 7:
        raise ValueError(f"window: expected an odd size in 3 .. 7, got {window}")
    border = _count("border", border, 0)
    if border > 8:
        raise ValueError(f"border: expected 0 .. 8 pixels, got {border}")
    if isinstance(spacing, bool) or not isinstance(spacing, (int, float, np.integer, np.floating)):
        raise TypeError(f"spacing: expected a number of pixels, got {type(spacing).__name__}")
    if not 1.0 <= float(spacing) <= 16.0:
        raise ValueError(f"spacing: expected 1 .. 16 pixels, got {spacing}")
    return n, n_depth, window, border, float(spacing)


def _scale(vmax: float) -> float:
    """The power of two s with |v| s < 2**VALUE_BITS for |v| <= vmax (step 2)."""
    vmax = max(float(vmax), 2.0**-60)  # s <= 2**100: a float32 (an all-zero image has any s)
    return float(2.0 ** math.floor(math.log2((2**VALUE_BITS - 1) / vmax)))


def quotas(n: int, available: np.ndarray, area: np.ndarray) -> np.ndarray:
    """Step 6: split n points over parts: half equally among parts with a pool, half by area;
    largest remainders first; capped by availability, the excess to parts with room (largest area
    first)."""
    available = np.asarray(available, np.int64)
    area = np.asarray(area, np.float64)
    q = np.zeros(len(area), dtype=np.int64)
    visible = available > 0
    if not visible.any():
        return q
    nv = int(visible.sum())
    want = np.where(visible, 0.5 * n / nv + 0.5 * n * area / max(area[visible].sum(), 1), 0.0)
    q = np.floor(want).astype(np.int64)
    order = np.argsort(-(want - q), kind="stable")  # largest remainders first
    for j in order[: n - int(q.sum())]:
        q[j] += 1
    while True:
        excess = int(np.maximum(q - available, 0).sum())
        q = np.minimum(q, available)
        if excess == 0:
            return q
        room = np.flatnonzero(q < available)
        if room.size == 0:
            return q
        for j in room[np.argsort(-area[room], kind="stable")]:
            take = min(excess, int(available[j] - q[j]))
            q[j] += take
            excess -= take
            if excess == 0:
                break


# -- scratch buffers, kept per device and image size ------------------------------------------------
_SCRATCH = per_device_cache()


class _Scratch:
    """Buffers of one (H, W, J): the images, the per-pixel classes, the survivors' bins, the counts."""

    def __init__(self, device, H, W, J):
        e = device.empty
        self.part = e((H, W), np.int32)
        self.values = e((2, H, W), np.float32)
        self.local = e((H, W, 3), np.float32)
        self.interior = e((H, W), np.int32)  # the interior flag (step 3)
        self.num = e((2, H, W), np.int64)  # per kind the extremum strength numerator |c q - S| (-1: none)
        self.cnt = e((H, W), np.int32)  # same-part window count c
        self.dist = e((2, H, W), np.int32)  # the fill's squared distances (step 7), per kind
        self.used = e((2, J, H + W), np.int32)  # the fill's used rows and columns, per kind and part
        self.bins = e((2, H * W), np.int32)  # candidates per kind, binned by part (offsets: area prefix)
        self.stats = e((J, len(STATS)), np.int32)
        self.surv = e((2, J), np.int32)  # candidates per kind and part


def _scratch(device, H, W, J) -> _Scratch:
    per_device = _SCRATCH.setdefault(device, {})
    key = (H, W, J)
    if key not in per_device:
        if len(per_device) >= 4:
            per_device.clear()
        per_device[key] = _Scratch(device, H, W, J)
    return per_device[key]


# -- the op -------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=16)
def _texture_table(texture: Texture, n_parts: int) -> np.ndarray:
    """(J, waves, 4) float64: each part's plane waves (k_x, k_y, k_z, phase) of Texture.sample (made
    once per texture and J; read-only)."""
    table = np.zeros((n_parts, texture.waves, 4), np.float64)
    for j in range(n_parts):
        k, phase = texture._waves(j)
        table[j, :, :3], table[j, :, 3] = k, phase
    table.setflags(write=False)
    return table


def render_model(device, chain: Chain, params, camera: Camera | None = None, size=DEFAULT_SIZE, *,
                 texture: Texture | None = None, shading: float = 0.2) -> ModelImages:  # fmt: skip
    """Step 1: render ``chain`` at ``params`` (P,) on ``device`` -> :class:`ModelImages`.

    Raises ValueError when no part's box is in view (the model is out of view).
    """
    device = check_device(device)
    if not isinstance(chain, Chain):
        raise TypeError(f"chain: expected a gputrack.models.Chain, got {type(chain).__name__}")
    camera = camera or DEFAULT_CAMERA
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a gputrack.Camera, got {type(camera).__name__}")
    texture = texture or Texture()
    if not isinstance(texture, Texture):
        raise TypeError(f"texture: expected a gputrack.models.render.Texture, got {type(texture).__name__}")
    if isinstance(shading, bool) or not isinstance(shading, (int, float)) or not 0.0 <= shading <= 1.0:
        raise ValueError(f"shading: expected a number in [0, 1], got {shading!r}")
    width, height = image_size(size)
    transforms = pose_transforms(chain, params)
    boxes, zmax = part_boxes(chain, transforms, camera, width, height)
    live = [b for b in boxes if b is not None]
    if not live:
        raise ValueError("model_template: no visible model surface at this pose (the model is out of view)")
    crop = (min(b[2] for b in live), max(b[3] for b in live), min(b[0] for b in live), max(b[1] for b in live))
    J = chain.n_parts
    s = _scratch(device, height, width, J)
    # per part, in float64 (a backend that renders in float32 rounds them): the ray transform into
    # part coordinates (R^T, o = -R^T t, as the reference renderer computes them), its box, its shape
    table = np.zeros((J, 24), np.float64)
    for j, pt in enumerate(chain.parts):
        r, t = transforms[j, :, :3], transforms[j, :, 3]
        table[j, 0:9] = r.T.ravel()  # d_part = R^T d_cam
        table[j, 9:12] = -(r.T @ t)
        b = boxes[j] if boxes[j] is not None and pt.shape is not None else (0, 0, 0, 0)
        table[j, 12:16] = (b[2], b[3], b[0], b[1])  # rows r0, r1, columns c0, c1 (half-open)
        if pt.shape is not None:
            sh = pt.shape
            table[j, 16:22] = (0.0 if sh.kind == "capsule" else 1.0, sh.axis, sh.start, sh.end, *sh.radii)
    consts = np.array([camera.fx, camera.fy, camera.cx, camera.cy,
                       texture.contrast * np.sqrt(2.0 / texture.waves), shading], np.float64)  # fmt: skip
    backend_module(device, "model_template").render(
        device, chain, transforms, texture, table, _texture_table(texture, J), consts, crop, s.part, s.values, s.local,
    )
    return ModelImages(device, s.part, s.values, s.local, crop, (1.0, max(zmax, 1.0)), J)


def select_template(device, images: ModelImages, n: int = 128, n_depth: int = 128, *, window: int = 5,
                    border: int = 2, spacing: float = 4.0) -> tuple[DeviceTemplate, DeviceTemplate]:  # fmt: skip
    """Steps 2-8 on ``images`` (from :func:`render_model`, or :func:`model_images` of given arrays):
    (RGB template of up to ``n`` points, depth template of up to ``n_depth``), on the device.

    Fewer points than asked only when the pools hold fewer pixels. Raises ValueError when no pixel
    belongs to a part.
    """
    device = check_device(device)
    if not isinstance(images, ModelImages) or images.device is not device:
        got = type(images).__name__ if not isinstance(images, ModelImages) else f"images on {images.device.spec}"
        raise TypeError(f"images: expected gputrack ModelImages on {device.spec}, got {got}")
    n, n_depth, window, border, spacing = _selection_args(n, n_depth, window, border, spacing)
    H, W = images.shape
    J = images.n_parts
    s = _scratch(device, H, W, J)
    be = backend_module(device, "model_template")
    scales = np.array([_scale(v) for v in images.value_max], np.float32)
    be.classify(device, images.part, images.values, images.crop, scales, window, border, s.interior, s.num, s.cnt,
                s.bins, s.stats, s.surv)  # fmt: skip
    stats = device.to_numpy(s.stats).astype(np.int64)  # the one wait: a few integers per part
    area, interior = stats[:, 0], stats[:, 1]
    if area.sum() == 0:
        raise ValueError("model_template: no visible model surface at this pose (the model is out of view)")
    available = np.where(interior > 0, interior, area)
    plan = np.zeros((2, J, 4), np.int32)  # per kind and part: offset, quota, bin start, 0
    counts = []
    for k, want in enumerate((n, n_depth)):
        q = quotas(want, available, area)
        plan[k, :, 0] = np.concatenate([[0], np.cumsum(q)[:-1]])
        plan[k, :, 1] = q
        plan[k, :, 2] = np.concatenate([[0], np.cumsum(area)[:-1]])
        counts.append(q)
    outs = [device.empty((int(c.sum()), 4), np.float32) for c in counts]
    be.emit(device, images.part, images.values, images.local, images.crop, constant(device, plan), s.stats, s.surv,
            s.bins, s.interior, s.num, s.cnt, s.dist, s.used, float(spacing) ** 2, *outs)  # fmt: skip
    return DeviceTemplate(device, outs[0], counts[0]), DeviceTemplate(device, outs[1], counts[1])


def model_images(device, part, values, local, n_parts: int | None = None) -> ModelImages:
    """:class:`ModelImages` of given host arrays (a measured frame as the "model", sec. 2.3's rigid
    case): ``part`` (H, W) int (-1: not part of the model), ``values`` (2, H, W) (gray, depth),
    ``local`` (H, W, 3) the 3D point of each pixel."""
    device = check_device(device)
    part = np.ascontiguousarray(part, np.int32)
    values = np.ascontiguousarray(values, np.float32)
    local = np.ascontiguousarray(local, np.float32)
    if part.ndim != 2 or values.shape != (2, *part.shape) or local.shape != (*part.shape, 3):
        raise ValueError(f"part, values, local: expected (H, W), (2, H, W), (H, W, 3), got {part.shape}, "
                         f"{values.shape}, {local.shape}")  # fmt: skip
    ys, xs = np.nonzero(part >= 0)
    if ys.size == 0:
        raise ValueError("model_images: expected pixels of the model (part >= 0), got none")
    if not (np.isfinite(values[:, ys, xs]).all() and np.isfinite(local[ys, xs]).all()):
        raise ValueError("values, local: expected finite values at the model's pixels")
    J = int(part.max()) + 1 if n_parts is None else int(n_parts)
    if J <= int(part.max()):
        raise ValueError(f"n_parts: expected more than the largest part id {int(part.max())}, got {J}")
    crop = (int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1)
    vmax = np.abs(values[:, ys, xs]).max(axis=1)
    s = _scratch(device, *part.shape, J)
    for dst, src in ((s.part, part), (s.values, values), (s.local, local)):
        if device.backend == "numpy":
            np.copyto(dst, src)
        else:
            device.asarray(src, out=dst)
    return ModelImages(device, s.part, s.values, s.local, crop, vmax, J)


def model_template(device, chain: Chain, params, camera: Camera | None = None, size=DEFAULT_SIZE, n: int = 128,
                   n_depth: int = 128, *, texture: Texture | None = None, shading: float = 0.2, window: int = 5,
                   border: int = 2, spacing: float = 4.0) -> tuple[DeviceTemplate, DeviceTemplate]:  # fmt: skip
    """(RGB template, depth template) of ``chain`` at ``params`` (P,), rendered and picked on ``device``.

    The composition ``select_template(device, render_model(device, chain, params, ...), n, n_depth, ...)``;
    see the module docstring for the rule. Raises ValueError when the model is out of view.
    """
    images = render_model(device, chain, params, camera, size, texture=texture, shading=shading)
    return select_template(device, images, n, n_depth, window=window, border=border, spacing=spacing)

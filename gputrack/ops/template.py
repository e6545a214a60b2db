"""Per-hypothesis x per-point block reductions: the RGB-D sparse-template cost and residuals.

The hot path of the particle filters (paper 000 eq. 17-21, paper 003 eq. 13): score B
hypotheses against N template points in one kernel launch per call.

Conventions (every backend, exactly):

- A template point ``xyz`` (in its part's coordinates) goes to the camera through its part's
  transform, ``X = T[b, part] @ [x, y, z, 1]`` with ``transforms`` (B, J, 3, 4) camera-from-part,
  and projects with the pinhole :class:`gputrack.models.Camera`: ``u = fx X/Z + cx``, ``v = fy Y/Z + cy``
  (pixel (u, v) is the centre of column u, row v).
- Images are sampled bilinearly from the four pixels (x0, y0), (x0+1, y0), (x0, y0+1),
  (x0+1, y0+1) with ``x0 = min(floor(u), W-2)``, ``y0 = min(floor(v), H-2)`` (so u = W-1 uses
  columns W-2 and W-1 with weight 1 on the latter). Images are at least 2 x 2. Gray pixels are
  clamped to [-INTENSITY_MAX, INTENSITY_MAX] (2**48, :mod:`gputrack.abi`) before sampling, on
  every backend: the float32 sums of eq. 17 cannot overflow, and since beta makes the cost
  invariant to the image's scale an image of larger values (e.g. 3e38 everywhere) scores as its
  clamped copy. Template values are limited to the same range.
- A point is valid when Z > 0 and 0 <= u <= W-1 and 0 <= v <= H-1; a depth point also needs all
  four neighbouring depth pixels to be measurements (> 0 and finite).
- eq. 17: alpha = 1 / sum T_i and beta = alpha sum T_i^2 / sum T_i I_i, the sums over the valid
  RGB points; beta = 0 when sum T_i I_i <= 1e-12 (and alpha = 0 when sum T_i <= 1e-12).
  d_i = beta I_i - alpha T_i, eps_C = sum rho_c(d_i), rho_c(x) = x^2 / (c^2 + x^2).
- eq. 18: d'_i = Zhat_i - Z_i where Zhat_i is the measured depth (bilinear) at the projection
  and Z_i the point's depth under the hypothesis (the camera-frame Z above; the paper's depth
  template holds 3D points M'_i, so the depth template's ``value`` is not used by the cost).
  With ``depth_tol`` = t > 0 the difference e = Zhat_i - Z_i is first shrunk towards 0 by t,
  d'_i = sign(e) max(|e| - t, 0): a sensor that quantises depth in steps of q only says the
  surface lies within q/2 of its reading, and the plain difference pulls a pose towards the
  steps (e.g. the flat front of a torso reads as one step, up to q/2 off). t = 0 (the
  default) is the paper's eq. 18.
- An invalid point adds rho's limit, 1, to its cost, and its residual (eq. 20-21) is
  sqrt(1 - lam) (RGB) or sqrt(lam) (depth).
- Reductions are accurate in float32 for N up to thousands of points (blocked/pairwise sums).

Transforms given as NumPy arrays are checked and rejected when not finite. Transforms already
on the device are not checked (that would cost a download): a point under a non-finite
transform is invalid (it adds 1), so such a hypothesis scores badly, never NaN.

What the hypotheses are scored against, besides the frame's two images, is one
:class:`RgbdScene`: the two templates, the camera and eq. 17-19's constants, checked once when it
is made (a filter makes about 20 cost and residual calls a frame against the same scene).

Steady-state use (a filter stage every frame): make the scene once per template, upload the
frame once, and reuse the result buffers::

    scene = RgbdScene(rgb, depth, cam, lam=0.9).to(dev)              # once per template
    gray_d, depth_d = dev.asarray(gray), dev.asarray(depth_mm)        # once per frame
    cost = rgbd_cost(dev, transforms_d, scene, gray_d, depth_d)
    cost = rgbd_cost(dev, transforms_d, scene, gray_d, depth_d, out=cost)  # no allocation
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..abi import INTENSITY_MAX
from ..device import Device, DeviceArray, per_device_cache
from ..models.camera import Camera
from . import backend_module
from ._args import arg, check_device, out_array, real, shape_of

__all__ = [
    "RgbdCost",
    "RgbdScene",
    "SparseTemplate",
    "rgbd_cost",
    "rgbd_residuals",
]

#: sums at or below this count as zero (eq. 17's alpha and beta)
TINY = 1e-12
#: part indices of a template are below this (a chain's parts; the kernels read one index entry per
#: part, so the index array is sized by the largest part index)
MAX_PARTS = 1 << 16


class SparseTemplate:
    """A 3D sparse template (paper 000 sec. 2.3): N points, each in its part's coordinates.

    ``xyz`` (N, 3) float32, ``part`` (N,) int32 (in [0, MAX_PARTS); checked against J when used),
    ``value`` (N,) float32 with |value| <= INTENSITY_MAX: the intensity T_i of an RGB template (a
    depth template's value is not used by the cost, see the module docstring; it defaults to
    zeros). float64 and integer coordinates are converted to float32, integer parts of another
    width to int32. N = 0 raises.

    The template is uploaded to a device the first time an op uses it there and kept (one
    upload per device); ``template.to(device)`` does that upload now and returns the template.
    """

    def __init__(self, xyz, part, value=None):
        # shapes first (nothing converted), then dtypes, then values: the work is linear in N
        shape = _shape(xyz, "xyz")
        if len(shape) != 2 or shape[1] != 3:
            raise ValueError(f"xyz: expected shape (N, 3), got {shape}")
        n = shape[0]
        if n == 0:
            raise ValueError("xyz: expected a template with at least one point, got N = 0 (an empty template)")
        if _shape(part, "part") != (n,):
            raise ValueError(f"part: expected shape (N={n},), got {_shape(part, 'part')}")
        if value is not None and _shape(value, "value") != (n,):
            raise ValueError(f"value: expected shape (N={n},), got {_shape(value, 'value')}")
        xyz = _host(xyz, "xyz", np.float32)
        part = _host(part, "part", np.int32)
        value = np.zeros(n, np.float32) if value is None else _host(value, "value", np.float32)
        for name, a in (("xyz", xyz), ("value", value)):
            if not np.isfinite(a).all():
                bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
                raise ValueError(f"{name}: expected finite values, got {a[bad]} at index {bad}")
        if np.abs(value).max() > INTENSITY_MAX:  # eq. 17's float32 sums of T_i^2 stay finite
            i = int(np.argmax(np.abs(value)))
            raise ValueError(
                f"value: expected |values| <= INTENSITY_MAX = 2**48, got {float(value[i]):g} at index ({i},)"
            )
        if part.min() < 0:
            raise ValueError(f"part: expected indices >= 0, got {int(part.min())}")
        if part.max() >= MAX_PARTS:  # checked before anything is sized by the part index
            raise ValueError(f"part: expected indices < MAX_PARTS = {MAX_PARTS}, got {int(part.max())}")
        self.xyz = xyz
        self.part = part
        self.value = value
        self._n_parts = int(part.max()) + 1
        # The layout the kernels read: points grouped by part (so a kernel loads each part's
        # transform once), (N, 4) [x, y, z, value]; ``perm[k]`` is the original index of sorted
        # point k (residuals are written in the original order); part j owns sorted points
        # start[j]:start[j+1].
        order = np.argsort(part, kind="stable").astype(np.int32)
        self.perm = order
        self.packed = np.ascontiguousarray(np.concatenate([xyz, value[:, None]], axis=1)[order], dtype=np.float32)
        self.sorted_part = np.ascontiguousarray(part[order])
        self.start = np.searchsorted(self.sorted_part, np.arange(self.n_parts + 1)).astype(np.int32)
        self._on = per_device_cache()

    @property
    def n(self) -> int:
        return self.xyz.shape[0]

    def __len__(self) -> int:
        return self.n

    @property
    def n_parts(self) -> int:
        """1 + the largest part index (the smallest J the template fits)."""
        return self._n_parts

    def __repr__(self) -> str:
        return f"SparseTemplate(N={self.n}, parts={self.n_parts})"

    def to(self, device: Device) -> SparseTemplate:
        """Upload to ``device`` now (once; later ops reuse the copy) and return this template."""
        self.on(device)
        return self

    def on(self, device: Device) -> dict:
        """The device copies, uploaded once: {"pts": (N, 4) f32 grouped by part, "part": (N,) i32
        (grouped), "index": (n_parts + 1 + N,) i32 = [start, perm], "parts": n_parts} (see ``packed``)."""
        check_device(device)
        found = self._on.get(device)
        if found is None:
            found = {
                "pts": device.asarray(self.packed),
                "part": device.asarray(self.sorted_part),
                "index": device.asarray(np.concatenate([self.start, self.perm]).astype(np.int32)),
                "parts": self.n_parts,
            }
            self._on[device] = found
        return found


def _shape(x, name) -> tuple:
    if isinstance(x, DeviceArray):
        raise TypeError(
            f"{name}: expected a NumPy array (templates are built on the host), got an array on {x.device.spec}"
        )
    return shape_of(x, name)


def _host(x, name, dtype):
    _shape(x, name)
    a = np.asarray(x)
    want = np.dtype(dtype)
    if a.dtype.kind == "b" or a.dtype.kind not in "iuf":
        raise TypeError(f"{name}: expected a numeric array ({want.name}), got {a.dtype.name}")
    if want.kind == "i" and a.dtype.kind == "f":
        raise TypeError(f"{name}: expected integer part indices ({want.name}), got {a.dtype.name}")
    if want.kind == "i" and a.size and (a.max() > np.iinfo(np.int32).max):
        raise ValueError(f"{name}: expected indices that fit int32, got {a.max()}")
    return np.ascontiguousarray(a, dtype=want)


@dataclasses.dataclass
class RgbdCost:
    """eq. 17-19 per hypothesis, each (B,): ``total`` = (1-lam) ``rgb`` + lam ``depth``.

    DeviceArrays on a device, NumPy arrays on the numpy device.
    """

    total: object
    rgb: object
    depth: object


def _check_template(t, name):
    if not isinstance(t, SparseTemplate):
        raise TypeError(f"{name}: expected a gputrack.SparseTemplate, got {type(t).__name__}")
    return t


class RgbdScene:
    """What B hypotheses are scored against besides the frame's images (paper 000 eq. 17-21).

    rgb, depth: :class:`SparseTemplate` (N and N' points); camera: :class:`gputrack.models.Camera`;
    ``lam`` in [0, 1] weighs the depth cost (eq. 19); ``c_rgb`` (> 0, None: 0.5/N, eq. 17) and
    ``c_depth`` (> 0, mm) are the robust functions' scales; ``depth_tol`` (mm, >= 0): the depth
    difference that counts as none (0: the paper's eq. 18; see the module docstring).

    Everything is checked here, once; the ops check only that the hypotheses' parts cover the
    templates' (``n_parts``) and the frame's images. ``scene.to(device)`` uploads the templates now
    (otherwise the first op on the device does, once). ``with_templates`` gives the scene of new
    templates with the same camera and constants (a tracker's template of the next frame).
    """

    def __init__(self, rgb, depth, camera, *, lam=0.9, c_rgb=None, c_depth=5.0, depth_tol=0.0):
        if not isinstance(camera, Camera):
            raise TypeError(f"camera: expected a gputrack.Camera, got {type(camera).__name__}")
        checked = {
            "rgb": _check_template(rgb, "rgb"),
            "depth": _check_template(depth, "depth"),
            "camera": camera,
            "lam": real("lam", lam, low=0.0, high=1.0),
            "_c_rgb": None if c_rgb is None else real("c_rgb", c_rgb, positive=True),
            "c_depth": real("c_depth", c_depth, positive=True),
            "depth_tol": real("depth_tol", depth_tol, low=0.0),
            "_camera": camera.as_array(),
        }
        for name, value in checked.items():
            object.__setattr__(self, name, value)

    def __setattr__(self, name, value):  # checked once, so read-only: make another scene instead
        raise AttributeError(f"RgbdScene is read-only (its values were checked when it was made): cannot set "
                             f"{name!r}; make a new scene (RgbdScene(...) or scene.with_templates(...))")  # fmt: skip

    @property
    def c_rgb(self) -> float:
        return 0.5 / self.rgb.n if self._c_rgb is None else self._c_rgb  # eq. 17: c = 0.5/N

    @property
    def n(self) -> int:
        """N + N': the residuals per hypothesis (RGB points, then depth points)."""
        return self.rgb.n + self.depth.n

    @property
    def n_parts(self) -> int:
        """The smallest J the templates fit (1 + their largest part index)."""
        return max(self.rgb.n_parts, self.depth.n_parts)

    def with_templates(self, rgb, depth) -> RgbdScene:
        """This scene with other templates (camera and constants kept)."""
        return RgbdScene(rgb, depth, self.camera, lam=self.lam, c_rgb=self._c_rgb, c_depth=self.c_depth,
                         depth_tol=self.depth_tol)  # fmt: skip

    def to(self, device: Device) -> RgbdScene:
        """Upload the templates to ``device`` now (once) and return this scene."""
        self.rgb.to(device)
        self.depth.to(device)
        return self

    def __repr__(self) -> str:
        return (f"RgbdScene(rgb={self.rgb!r}, depth={self.depth!r}, lam={self.lam:g}, c_rgb={self.c_rgb:g}, "
                f"c_depth={self.c_depth:g}, depth_tol={self.depth_tol:g})")  # fmt: skip

    def kernel_args(self, device: Device) -> tuple:
        """(rgb on device, depth on device, camera (4,) f32, constants) as the backends take them."""
        consts = {"lam": self.lam, "c_rgb": self.c_rgb, "c_depth": self.c_depth, "depth_tol": self.depth_tol}
        return self.rgb.on(device), self.depth.on(device), self._camera, consts


def frame_args(device, scene, gray, depth_image, n_parts):
    """Check a scene for hypotheses of ``n_parts`` parts and the frame's images on ``device``; return
    (gray, depth image) on the device."""
    if not isinstance(scene, RgbdScene):
        raise TypeError(f"scene: expected a gputrack.RgbdScene, got {type(scene).__name__}")
    if n_parts == 0:
        raise ValueError("transforms: expected at least one part, got J = 0")
    for t, name in ((scene.rgb, "rgb"), (scene.depth, "depth")):
        if t.n_parts > n_parts:
            raise ValueError(f"scene.{name}.part: expected part indices in [0, J={n_parts}), got {t.n_parts - 1}")
    img = {}
    # depth images may hold non-finite values: they mean "no measurement"
    g = arg(device, gray, "gray", ("H", "W"), img)
    d = arg(device, depth_image, "depth_image", ("H", "W"), img, finite=False)
    if img["H"] < 2 or img["W"] < 2:
        raise ValueError(f"gray: expected an image of at least 2 x 2 pixels, got {img['H']} x {img['W']}")
    return g, d


def _rgbd_args(device, transforms, scene, gray, depth_image):
    check_device(device)
    dims = {}
    tf = arg(device, transforms, "transforms", ("B", "J", 3, 4), dims)
    if dims["B"] == 0:
        raise ValueError("transforms: expected at least one hypothesis, got B = 0")
    g, d = frame_args(device, scene, gray, depth_image, dims["J"])
    return tf, g, d


def rgbd_cost(device, transforms, scene, gray, depth_image, *, out=None) -> RgbdCost:
    """RGB-D sparse-template cost of B hypotheses (paper 000 eq. 17-19), one kernel launch.

    transforms: (B, J, 3, 4) float32 camera-from-part transforms; scene: :class:`RgbdScene` (the
    templates' part indices < J); gray: (H, W) float32 intensities; depth_image: (H, W) float32
    depth in the units of the template (mm), 0 or non-finite = no measurement. Returns
    :class:`RgbdCost` (total, rgb, depth), each (B,) float32. ``out``: an RgbdCost of (B,) float32
    arrays on the device (e.g. an earlier result) to write into instead of allocating (a filter
    stage that runs every frame saves the allocations). See the module docstring for the exact
    conventions.
    """
    tf, g, d = _rgbd_args(device, transforms, scene, gray, depth_image)
    nb = tf.shape[0]
    if out is not None and not isinstance(out, RgbdCost):
        raise TypeError(f"out: expected a gputrack.RgbdCost (e.g. an earlier result), got {type(out).__name__}")
    outs = tuple(
        out_array(device, None if out is None else getattr(out, f), f"out.{f}", (nb,))
        for f in ("total", "rgb", "depth")
    )
    rgb, dep, cam, p = scene.kernel_args(device)
    backend_module(device, "template").rgbd_cost(device, tf, rgb, dep, g, d, cam, *outs, **p)
    return out if out is not None else RgbdCost(*outs)


def rgbd_residuals(device, transforms, scene, gray, depth_image, *, out=None):
    """Residuals of eq. 20-21 for B hypotheses: (B, N + N') float32, RGB points then depth points.

    r_i = sqrt(1-lam) d_i / sqrt(c^2 + d_i^2), r'_i = sqrt(lam) d'_i / sqrt(c'^2 + d'_i^2); an
    invalid point's residual is sqrt(1-lam) (RGB) or sqrt(lam) (depth), so that
    sum(r**2, axis=1) equals ``rgbd_cost(...).total``. Same arguments as :func:`rgbd_cost`;
    ``out``: a (B, N + N') float32 array on the device to write into.
    """
    tf, g, d = _rgbd_args(device, transforms, scene, gray, depth_image)
    res = out_array(device, out, "out", (tf.shape[0], scene.n))
    rgb, dep, cam, p = scene.kernel_args(device)
    backend_module(device, "template").rgbd_residuals(device, tf, rgb, dep, g, d, cam, res, **p)
    return res

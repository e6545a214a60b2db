"""Per-hypothesis x per-point block reductions: the RGB-D sparse-template cost and NCC patches.

The hot path of the particle filters (paper 000 eq. 17-21, paper 003 eq. 13): score B
hypotheses against N template points in one kernel launch per call.

Conventions (every backend, exactly):

- A template point ``xyz`` (in its part's coordinates) goes to the camera through its part's
  transform, ``X = T[b, part] @ [x, y, z, 1]`` with ``transforms`` (B, J, 3, 4) camera-from-part,
  and projects with the pinhole :class:`Camera`: ``u = fx X/Z + cx``, ``v = fy Y/Z + cy``
  (pixel (u, v) is the centre of column u, row v).
- Images are sampled bilinearly from the four pixels (x0, y0), (x0+1, y0), (x0, y0+1),
  (x0+1, y0+1) with ``x0 = min(floor(u), W-2)``, ``y0 = min(floor(v), H-2)`` (so u = W-1 uses
  columns W-2 and W-1 with weight 1 on the latter). Images are at least 2 x 2.
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

Steady-state use (a filter stage every frame): upload the frame once, keep the templates on
the device, and reuse the result buffers::

    rgb.to(dev); depth.to(dev)                         # once per template (cached per device)
    gray_d, depth_d = dev.asarray(gray), dev.asarray(depth_mm)   # once per frame
    cost = rgbd_cost(dev, transforms_d, rgb, depth, gray_d, depth_d, cam)
    cost = rgbd_cost(dev, transforms_d, rgb, depth, gray_d, depth_d, cam, out=cost)  # no allocation
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from .. import tuning
from ..device import Device, DeviceArray, per_device_cache
from . import backend_module
from ._args import arg, check_device, out_array

__all__ = [
    "Camera",
    "RgbdCost",
    "SparseTemplate",
    "patch_ncc",
    "patch_ncc_per_point",
    "rgbd_cost",
    "rgbd_residuals",
]

#: sums at or below this count as zero (eq. 17's alpha and beta)
TINY = 1e-12


@dataclasses.dataclass(frozen=True)
class Camera:
    """Pinhole camera: u = fx X/Z + cx, v = fy Y/Z + cy (pixels; (u, v) = centre of column u, row v)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self):
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
                raise TypeError(f"Camera.{name}: expected a real number, got {type(value).__name__}")
            if not math.isfinite(float(value)):
                raise ValueError(f"Camera.{name}: expected a finite number, got {value}")
            object.__setattr__(self, name, float(value))
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"Camera: expected fx > 0 and fy > 0, got fx={self.fx}, fy={self.fy}")

    def as_array(self) -> np.ndarray:
        """(4,) float32 [fx, fy, cx, cy]."""
        return np.array([self.fx, self.fy, self.cx, self.cy], dtype=np.float32)


class SparseTemplate:
    """A 3D sparse template (paper 000 sec. 2.3): N points, each in its part's coordinates.

    ``xyz`` (N, 3) float32, ``part`` (N,) int32 (>= 0; checked against J when used), ``value``
    (N,) float32: the intensity T_i of an RGB template (a depth template's value is not used by
    the cost, see the module docstring; it defaults to zeros). float64 and integer coordinates
    are converted to float32, integer parts of another width to int32. N = 0 raises.

    The template is uploaded to a device the first time an op uses it there and kept (one
    upload per device); ``template.to(device)`` does that upload now and returns the template.
    """

    def __init__(self, xyz, part, value=None):
        xyz = _host(xyz, "xyz", np.float32)
        part = _host(part, "part", np.int32)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"xyz: expected shape (N, 3), got {xyz.shape}")
        n = xyz.shape[0]
        if n == 0:
            raise ValueError("xyz: expected a template with at least one point, got N = 0 (an empty template)")
        if part.shape != (n,):
            raise ValueError(f"part: expected shape (N={n},), got {part.shape}")
        if value is None:
            value = np.zeros(n, np.float32)
        value = _host(value, "value", np.float32)
        if value.shape != (n,):
            raise ValueError(f"value: expected shape (N={n},), got {value.shape}")
        for name, a in (("xyz", xyz), ("value", value)):
            if not np.isfinite(a).all():
                bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
                raise ValueError(f"{name}: expected finite values, got {a[bad]} at index {bad}")
        if part.min() < 0:
            raise ValueError(f"part: expected indices >= 0, got {int(part.min())}")
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


def _host(x, name, dtype):
    if isinstance(x, DeviceArray):
        raise TypeError(
            f"{name}: expected a NumPy array (templates are built on the host), got an array on {x.device.spec}"
        )
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


def _check_scalar(value, name, *, low=None, high=None, positive=False):
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise TypeError(f"{name}: expected a real number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name}: expected a finite number, got {value}")
    if positive and v <= 0:
        raise ValueError(f"{name}: expected a number > 0, got {value}")
    if low is not None and v < low or high is not None and v > high:
        want = f"in [{low}, {high}]" if high is not None else f">= {low}"
        raise ValueError(f"{name}: expected a number {want}, got {value}")
    return v


def _rgbd_args(device, transforms, rgb, depth, gray, depth_image, camera, lam, c_rgb, c_depth, depth_tol):
    check_device(device)
    dims = {}
    tf = arg(device, transforms, "transforms", ("B", "J", 3, 4), dims)
    if dims["B"] == 0:
        raise ValueError("transforms: expected at least one hypothesis, got B = 0")
    g, d, p = scene_args(device, rgb, depth, gray, depth_image, camera, lam, c_rgb, c_depth, depth_tol, dims["J"])
    return tf, g, d, p


def scene_args(device, rgb, depth, gray, depth_image, camera, lam, c_rgb, c_depth, depth_tol, n_parts):
    """Check what the RGB-D cost scores against (templates on ``n_parts`` parts, images, camera,
    eq. 17-19 constants); return (gray, depth image) on the device and the constants."""
    _check_template(rgb, "rgb")
    _check_template(depth, "depth")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a gputrack.Camera, got {type(camera).__name__}")
    lam = _check_scalar(lam, "lam", low=0.0, high=1.0)
    c_rgb = 0.5 / rgb.n if c_rgb is None else _check_scalar(c_rgb, "c_rgb", positive=True)  # eq. 17: c = 0.5/N
    c_depth = _check_scalar(c_depth, "c_depth", positive=True)
    depth_tol = _check_scalar(depth_tol, "depth_tol", low=0.0)
    if n_parts == 0:
        raise ValueError("transforms: expected at least one part, got J = 0")
    for t, name in ((rgb, "rgb"), (depth, "depth")):
        if t.n_parts > n_parts:
            raise ValueError(f"{name}.part: expected part indices in [0, J={n_parts}), got {t.n_parts - 1}")
    img = {}
    # depth images may hold non-finite values: they mean "no measurement"
    g = arg(device, gray, "gray", ("H", "W"), img)
    d = arg(device, depth_image, "depth_image", ("H", "W"), img, finite=False)
    if img["H"] < 2 or img["W"] < 2:
        raise ValueError(f"gray: expected an image of at least 2 x 2 pixels, got {img['H']} x {img['W']}")
    return g, d, {"lam": lam, "c_rgb": c_rgb, "c_depth": c_depth, "depth_tol": depth_tol}


def rgbd_cost(
    device, transforms, rgb, depth, gray, depth_image, camera, *, lam=0.9, c_rgb=None, c_depth=5.0, depth_tol=0.0,
    out=None,
) -> RgbdCost:
    """RGB-D sparse-template cost of B hypotheses (paper 000 eq. 17-19), one kernel launch.

    transforms: (B, J, 3, 4) float32 camera-from-part transforms; rgb, depth: SparseTemplate
    (N and N' points, part indices < J); gray: (H, W) float32 intensities; depth_image: (H, W)
    float32 depth in the units of the template (mm), 0 or non-finite = no measurement;
    camera: Camera. ``c_rgb=None`` means 0.5/N; ``depth_tol`` (mm, >= 0): the depth difference
    that counts as none (0: the paper's eq. 18). Returns :class:`RgbdCost` (total, rgb, depth),
    each (B,) float32. ``out``: an RgbdCost of (B,) float32 arrays on the device (e.g. an earlier
    result) to write into instead of allocating (a filter stage that runs every frame saves the
    allocations). See the module docstring for the exact conventions.
    """
    tf, g, d, p = _rgbd_args(device, transforms, rgb, depth, gray, depth_image, camera, lam, c_rgb, c_depth,
                              depth_tol)  # fmt: skip
    nb = tf.shape[0]
    if out is not None and not isinstance(out, RgbdCost):
        raise TypeError(f"out: expected a gputrack.RgbdCost (e.g. an earlier result), got {type(out).__name__}")
    outs = tuple(
        out_array(device, None if out is None else getattr(out, f), f"out.{f}", (nb,))
        for f in ("total", "rgb", "depth")
    )
    _tuned(device, "rgbd_cost", p, nb, rgb, depth)
    backend_module(device, "template").rgbd_cost(
        device, tf, rgb.on(device), depth.on(device), g, d, camera.as_array(), *outs, **p
    )
    return out if out is not None else RgbdCost(*outs)


def rgbd_residuals(
    device, transforms, rgb, depth, gray, depth_image, camera, *, lam=0.9, c_rgb=None, c_depth=5.0, depth_tol=0.0,
    out=None,
):
    """Residuals of eq. 20-21 for B hypotheses: (B, N + N') float32, RGB points then depth points.

    r_i = sqrt(1-lam) d_i / sqrt(c^2 + d_i^2), r'_i = sqrt(lam) d'_i / sqrt(c'^2 + d'_i^2); an
    invalid point's residual is sqrt(1-lam) (RGB) or sqrt(lam) (depth), so that
    sum(r**2, axis=1) equals ``rgbd_cost(...).total``. Same arguments as :func:`rgbd_cost`;
    ``out``: a (B, N + N') float32 array on the device to write into.
    """
    tf, g, d, p = _rgbd_args(device, transforms, rgb, depth, gray, depth_image, camera, lam, c_rgb, c_depth,
                              depth_tol)  # fmt: skip
    res = out_array(device, out, "out", (tf.shape[0], rgb.n + depth.n))
    _tuned(device, "rgbd_residuals", p, tf.shape[0], rgb, depth)
    backend_module(device, "template").rgbd_residuals(
        device, tf, rgb.on(device), depth.on(device), g, d, camera.as_array(), res, **p
    )
    return res


# -- tuning (gputrack tune) ----------------------------------------------------------------------
# The launch parameters of the rgbd kernels: ``lanes`` = hypotheses per thread / work-item (the
# kernels' LANES), and on OpenCL ``work_group`` = the work-group size. Results are identical
# whatever the choice (each lane computes its own hypothesis with the same sums); only the speed
# differs. The defaults are the backends' own (lanes(device): 8 on CPU devices, 1 on GPUs).
_TAICHI_SOURCE = str(Path(__file__).resolve().parent.parent / "backends" / "taichi" / "template.py")
_CANDIDATES = {
    "taichi": {"lanes": [1, 2, 4, 8, 16]},
    "opencl": {"lanes": [1, 4, 8, 16], "work_group": [1, 2, 4, 8, 16, 32, 64, 128]},
}
_SOURCES = {"taichi": (_TAICHI_SOURCE,), "opencl": ("gt_template.cl", "gt_lanes.clh")}
#: representative sizes: a particle-filter stage (paper 000: K = 1500, N = N' = 128) and the
#: batched LM's residuals (B = 280 .. 400 perturbed poses share the bucket B=512)
_SIZES = {"rgbd_cost": ({"B": 1500, "N": 128},), "rgbd_residuals": ({"B": 400, "N": 128},)}


def _default_params(device) -> dict:
    return backend_module(device, "template").default_params(device)


def _size(nb, rgb, depth) -> dict:
    return {"B": int(nb), "N": max(rgb.n, depth.n)}


def _tuned(device, op, kwargs, nb, rgb, depth) -> None:
    """Add the launch parameters for this device and size (cached choice, else default) to ``kwargs``."""
    t = TUNABLES.get((device.backend, op))
    if t is not None:
        kwargs["params"] = tuning.choose(device, t, _size(nb, rgb, depth))


def _problem(op):
    def problem(device, size, params):
        """One ``op`` call on a particle-filter-like scene of ``size``, launched with ``params``."""
        from ..benchmarks.template import pf_scene

        rng = np.random.default_rng(0)
        tf, rgb, dep, gray, depth, cam = pf_scene(rng, size["B"], size["N"], size["N"])
        tf_d, g, d = device.asarray(tf), device.asarray(gray), device.asarray(depth)
        r, dd, c = rgb.on(device), dep.on(device), cam.as_array()
        p = {"lam": 0.9, "c_rgb": 0.5 / rgb.n, "c_depth": 5.0, "depth_tol": 0.0, "params": dict(params)}
        mod = backend_module(device, "template")
        if op == "rgbd_cost":
            outs = tuple(device.empty((size["B"],), np.float32) for _ in range(3))
            return lambda: mod.rgbd_cost(device, tf_d, r, dd, g, d, c, *outs, **p)
        res = device.empty((size["B"], rgb.n + dep.n), np.float32)
        return lambda: mod.rgbd_residuals(device, tf_d, r, dd, g, d, c, res, **p)

    return problem


#: (backend, op) -> Tunable, read by the ops at every call and swept by ``gputrack tune``
TUNABLES = {
    (backend, op): tuning.Tunable(
        op=op,
        backend=backend,
        candidates=_CANDIDATES[backend],
        default=_default_params,
        sizes=_SIZES[op],
        problem=_problem(op),
        sources=_SOURCES[backend],
    )
    for backend in ("taichi", "opencl")
    for op in ("rgbd_cost", "rgbd_residuals")
}


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
    """
    pts, tpl, img = _ncc_args(device, points2d, templates, image)
    return backend_module(device, "template").patch_ncc(device, pts, tpl, img, per_point=True)


def patch_ncc(device, points2d, templates, image):
    """Sum over the K points of :func:`patch_ncc_per_point`: (B,) float32 in [-K, K] (paper 003 N(u), eq. 13)."""
    pts, tpl, img = _ncc_args(device, points2d, templates, image)
    return backend_module(device, "template").patch_ncc(device, pts, tpl, img, per_point=False)


# -- self-test (host/doctor.py) -----------------------------------------------------------------
def _selftest_scene(rng, b=7, j=2, n=29, m=23, h=24, w=32):
    cam = Camera(20.0, 20.0, (w - 1) / 2, (h - 1) / 2)
    rgb = SparseTemplate(rng.uniform(-0.3, 0.3, (n, 3)), rng.integers(0, j, n), rng.uniform(10, 200, n))
    dep = SparseTemplate(rng.uniform(-0.3, 0.3, (m, 3)), rng.integers(0, j, m))
    tf = np.zeros((b, j, 3, 4), np.float32)
    tf[..., :3, :3] = np.eye(3)
    tf[..., :, 3] = rng.normal(0, 0.05, (b, j, 3)) + [0, 0, 2.0]
    gray = rng.uniform(0, 255, (h, w)).astype(np.float32)
    depth = rng.uniform(1.8, 2.2, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.05] = 0
    return tf, rgb, dep, gray, depth, cam


def _selftest(device) -> None:
    """Tiny rgbd_cost and patch_ncc on ``device`` against the NumPy reference (AssertionError with the max error)."""
    from ..registry import device as get_device
    from ..device import to_numpy

    rng = np.random.default_rng(3)
    tf, rgb, dep, gray, depth, cam = _selftest_scene(rng)
    ref_dev = get_device("numpy")
    want = rgbd_cost(ref_dev, tf, rgb, dep, gray, depth, cam, c_depth=0.05)
    got = rgbd_cost(device, tf, rgb, dep, gray, depth, cam, c_depth=0.05)
    for field in ("total", "rgb", "depth"):
        err = float(np.max(np.abs(to_numpy(getattr(got, field)) - getattr(want, field))))
        assert err <= 1e-3, f"rgbd_cost.{field} differs from the reference by {err:g}"
    pts = rng.uniform(6, 20, (5, 3, 2)).astype(np.float32)
    tpl = rng.uniform(0, 1, (3, 5, 5)).astype(np.float32)
    want = patch_ncc(ref_dev, pts, tpl, gray)
    got = to_numpy(patch_ncc(device, pts, tpl, gray))
    err = float(np.max(np.abs(got - want)))
    assert err <= 1e-4, f"patch_ncc differs from the reference by {err:g}"

"""Ray-cast renderer for articulated models: gray, depth (z-buffer), part ids, 3D points.

One ray per pixel centre through the pinhole camera, d = ((u - cx)/fx, (v - cy)/fy, 1), so the
ray parameter of a hit is its camera depth Z. Each part's shape (:class:`gputrack.models.Shape`)
is intersected analytically in the part's coordinates (rays restricted to the projection of the
part's bounding box); the nearest hit wins (z-buffer, hidden-surface removal). Surfaces carry
a procedural solid texture of the part-local point (it moves with the part) with many intensity
extrema, under mild Lambertian shading from a light at the camera. A textured wall parallel to
the image plane is the background. Depth is in millimetres, quantised to ``depth_step`` (Kinect-
like 5 mm) unless ``depth_step=0``; 0 means no measurement.

Model machinery, not only simulation: the body tracker renders its sparse template with it
(gputrack/trackers/body/), the simulator renders its frames (gputrack/sim/).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from .camera import DEFAULT_CAMERA, DEFAULT_SIZE, Camera
from .chain import Chain, Shape

__all__ = ["Rendering", "Texture", "Wall", "image_size", "part_boxes", "pose_transforms", "render"]


@dataclasses.dataclass(frozen=True)
class Texture:
    """Procedural solid texture: per part a sum of ``waves`` plane waves of random direction,
    wavelength in ``wavelength`` (mm) and phase, from ``numpy.random.default_rng([seed, part])``.

    Gray value = clip(0.5 + contrast * sqrt(2/waves) * sum_k sin(2 pi dir_k . x / lambda_k + phi_k)).
    """

    seed: int = 2015
    waves: int = 12
    wavelength: tuple[float, float] = (30.0, 80.0)
    contrast: float = 0.3

    def _waves(self, key: int):
        rng = np.random.default_rng([self.seed, key])
        dirs = rng.normal(size=(self.waves, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        lam = rng.uniform(*self.wavelength, size=self.waves)
        phase = rng.uniform(0.0, 2.0 * np.pi, size=self.waves)
        return dirs * (2.0 * np.pi / lam)[:, None], phase

    def sample(self, key: int, xyz: np.ndarray) -> np.ndarray:
        """Texture ``key`` (a part index; walls use 1000 + i) at points (M, 3) -> (M,) in [0.02, 0.98]."""
        k, phase = self._waves(key)
        s = np.sin(np.asarray(xyz, np.float64) @ k.T + phase).sum(axis=-1)
        return np.clip(0.5 + self.contrast * np.sqrt(2.0 / self.waves) * s, 0.02, 0.98)


@dataclasses.dataclass(frozen=True)
class Wall:
    """A textured background plane Z = ``z`` mm (parallel to the image plane)."""

    z: float = 2800.0
    texture_key: int = 1000
    brightness: float = 0.85
    texture: Texture = Texture(seed=1729, waves=8, wavelength=(150.0, 450.0), contrast=0.3)


@functools.lru_cache(maxsize=8)
def _wall_image(wall: Wall, camera: Camera, width: int, height: int) -> np.ndarray:
    """The wall's gray image (static camera, static wall: computed once per setting, read-only)."""
    x = (np.arange(width) - camera.cx) / camera.fx * wall.z
    y = (np.arange(height) - camera.cy) / camera.fy * wall.z
    gy, gx = np.meshgrid(y, x, indexing="ij")
    xyz = np.stack([gx, gy, np.full_like(gx, wall.z)], axis=-1).reshape(-1, 3)
    img = (wall.brightness * wall.texture.sample(wall.texture_key, xyz)).reshape(height, width)
    img.setflags(write=False)
    return img


@dataclasses.dataclass(frozen=True)
class Rendering:
    """One rendered frame. Images are (H, W); ``part`` is -1 on the background / nothing.

    gray: float32 in [0, 1]. depth: float32 mm (quantised unless depth_step=0; 0 = no surface).
    points: (H, W, 3) float32 camera-space hit points (0 where nothing was hit). local: (H, W, 3)
    float32 hit points in their part's coordinates (0 off the model).
    """

    gray: np.ndarray
    depth: np.ndarray
    part: np.ndarray
    points: np.ndarray
    local: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.gray.shape


def _other_axes(k: int) -> tuple[int, int]:
    return tuple(a for a in range(3) if a != k)


def _first_root(a, b_half, c):
    """Smaller root of a t^2 + 2 b_half t + c = 0 (inf where none or a = 0)."""
    disc = b_half * b_half - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b_half - np.sqrt(disc)) / a
    return np.where((disc >= 0) & (a > 0), t, np.inf)


def intersect(shape: Shape, o: np.ndarray, d: np.ndarray):
    """First hit of rays o + t d (o (3,), d (M, 3), part coordinates) with ``shape``.

    Returns (t (M,) with inf for a miss or a hit behind the origin, normal (M, 3) unit outward).
    """
    k = shape.axis
    ia, ib = _other_axes(k)
    s0, s1 = shape.start, shape.end
    ou, ov, ok = o[ia], o[ib], o[k]
    du, dv, dk = d[:, ia], d[:, ib], d[:, k]
    ra, rb = shape.radii
    if shape.kind == "capsule":
        r = ra
        t = _first_root(du * du + dv * dv, ou * du + ov * dv, ou * ou + ov * ov - r * r)
        s = ok + t * dk
        t = np.where((s >= s0) & (s <= s1), t, np.inf)
        for end in (s0, s1):  # hemispherical caps
            oc = o.copy()
            oc[k] -= end
            ts = _first_root((d * d).sum(axis=1), d @ oc, float(oc @ oc) - r * r)
            t = np.minimum(t, ts)
        t = np.where(t > 0, t, np.inf)
        p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        n = p.copy()
        n[:, k] -= np.clip(p[:, k], s0, s1)  # from the closest point on the axis segment
        n /= r
        return t, n
    # elliptic cylinder with flat caps
    t = _first_root(
        (du / ra) ** 2 + (dv / rb) ** 2, ou * du / ra**2 + ov * dv / rb**2, (ou / ra) ** 2 + (ov / rb) ** 2 - 1.0
    )
    s = ok + t * dk
    side = np.where((s >= s0) & (s <= s1), t, np.inf)
    best, which = side, np.zeros(len(d), np.int8)
    with np.errstate(divide="ignore", invalid="ignore"):
        for code, end in ((1, s0), (2, s1)):
            tc = (end - ok) / dk
            inside = ((ou + tc * du) / ra) ** 2 + ((ov + tc * dv) / rb) ** 2 <= 1.0
            tc = np.where(inside & np.isfinite(tc), tc, np.inf)
            closer = tc < best
            best = np.where(closer, tc, best)
            which = np.where(closer, code, which)
    best = np.where(best > 0, best, np.inf)
    p = o + np.where(np.isfinite(best), best, 0.0)[:, None] * d
    n = np.zeros_like(p)
    n[:, ia] = p[:, ia] / ra**2
    n[:, ib] = p[:, ib] / rb**2
    n[which == 1] = 0.0
    n[which == 2] = 0.0
    n[which == 1, k] = -1.0
    n[which == 2, k] = 1.0
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return best, n


def _pixel_box(transform, shape: Shape, camera: Camera, width: int, height: int):
    """(u0, u1, v0, v1) half-open pixel box that contains the part's projection (None if empty): the
    projection of the shape's bounding box in part coordinates (tighter than its bounding sphere's
    for a long limb); the whole image when a corner is within 1 mm of the camera plane or behind it."""
    lo = np.zeros(3)
    hi = np.zeros(3)
    cap = shape.radii[0] if shape.kind == "capsule" else 0.0
    lo[shape.axis], hi[shape.axis] = shape.start - cap, shape.end + cap
    a, b = _other_axes(shape.axis)
    lo[a], hi[a] = -shape.radii[0], shape.radii[0]
    lo[b], hi[b] = -shape.radii[1], shape.radii[1]
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    c = corners @ transform[:, :3].T + transform[:, 3]
    if c[:, 2].min() <= 1.0:
        return 0, width, 0, height
    u = camera.fx * c[:, 0] / c[:, 2] + camera.cx
    v = camera.fy * c[:, 1] / c[:, 2] + camera.cy
    u0 = int(np.floor(u.min())) - 1
    u1 = int(np.ceil(u.max())) + 2
    v0 = int(np.floor(v.min())) - 1
    v1 = int(np.ceil(v.max())) + 2
    u0, u1 = max(u0, 0), min(u1, width)
    v0, v1 = max(v0, 0), min(v1, height)
    if u0 >= u1 or v0 >= v1:
        return None
    return u0, u1, v0, v1


def image_size(size) -> tuple[int, int]:
    """``size`` = (width, height) as ints, checked: at least 2 x 2."""
    width, height = (int(s) for s in size)
    if width < 2 or height < 2:
        raise ValueError(f"size: expected (width, height) of at least 2 x 2, got {size}")
    return width, height


def pose_transforms(chain: Chain, params) -> np.ndarray:
    """Camera-from-part transforms (J, 3, 4) float64 of one pose ``params`` (P,), checked: shape, finite."""
    p = np.asarray(params, dtype=np.float64)
    if p.shape != (chain.n_params,):
        raise ValueError(f"params: expected shape ({chain.n_params},), got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError("params: expected finite values, got non-finite entries")
    return chain.transforms(p[None])[0]


def part_boxes(chain: Chain, transforms, camera: Camera, width: int, height: int) -> tuple[list, float]:
    """Per part the half-open pixel box (u0, u1, v0, v1) that holds its projection (None: out of
    view or no shape), and the largest camera depth of the parts' bounding spheres (mm)."""
    boxes, zmax = [], 0.0
    for j, pt in enumerate(chain.parts):
        if pt.shape is None:
            boxes.append(None)
            continue
        boxes.append(_pixel_box(transforms[j], pt.shape, camera, width, height))
        centre, radius = pt.shape.bounding_sphere()
        zmax = max(zmax, float(transforms[j, 2, :3] @ centre + transforms[j, 2, 3]) + radius)
    return boxes, zmax


def render(
    chain: Chain,
    params=None,
    camera: Camera | None = None,
    size: tuple[int, int] = DEFAULT_SIZE,
    *,
    transforms=None,
    texture: Texture | None = None,
    background: Wall | None = Wall(),
    depth_step: float = 5.0,
    shading: float = 0.2,
    noise: float = 0.0,
    rng: np.random.Generator | None = None,
) -> Rendering:
    """Render ``chain`` at pose ``params`` (P,) (or given camera-from-part ``transforms`` (J, 3, 4)).

    ``size`` = (width, height). ``background=None`` renders the model alone (depth 0 and part -1
    elsewhere), as the template needs. ``depth_step`` quantises depth (0: exact z-buffer).
    ``shading`` in [0, 1] is the Lambertian share of the brightness. ``noise`` adds Gaussian gray
    noise of that standard deviation, drawn from ``rng`` (required then).
    """
    if not isinstance(chain, Chain):
        raise TypeError(f"chain: expected a gputrack.models.Chain, got {type(chain).__name__}")
    camera = camera or DEFAULT_CAMERA
    texture = texture or Texture()
    width, height = image_size(size)
    if transforms is None:
        if params is None:
            raise ValueError("params: expected a (P,) parameter vector or transforms, got neither")
        transforms = pose_transforms(chain, params)
    transforms = np.asarray(transforms, dtype=np.float64)
    if transforms.shape != (chain.n_parts, 3, 4):
        raise ValueError(f"transforms: expected shape ({chain.n_parts}, 3, 4), got {transforms.shape}")
    if noise > 0 and rng is None:
        raise ValueError("rng: expected a numpy.random.Generator when noise > 0, got None")

    boxes = [
        _pixel_box(transforms[j], pt.shape, camera, width, height) if pt.shape is not None else None
        for j, pt in enumerate(chain.parts)
    ]
    # work only where something can be seen: the whole image with a wall, else the parts' boxes
    if background is not None:
        region = (0, width, 0, height)
    else:
        live = [b for b in boxes if b is not None]
        region = None
        if live:
            u0s, u1s, v0s, v1s = zip(*live)
            region = (min(u0s), max(u1s), min(v0s), max(v1s))
    gray_full = np.zeros((height, width), np.float32)
    depth_full = np.zeros((height, width), np.float32)
    part_full = np.full((height, width), -1, np.int32)
    points_full = np.zeros((height, width, 3), np.float32)
    local_full = np.zeros((height, width, 3), np.float32)
    if region is not None:
        ru0, ru1, rv0, rv1 = region
        rh, rw = rv1 - rv0, ru1 - ru0
        ray_x = (np.arange(ru0, ru1) - camera.cx) / camera.fx
        ray_y = (np.arange(rv0, rv1) - camera.cy) / camera.fy
        zbuf = np.full((rh, rw), np.inf if background is None else background.z)
        part = np.full((rh, rw), -1, np.int32)
        local = np.zeros((rh, rw, 3))
        cos_view = np.ones((rh, rw))
        for j, pt in enumerate(chain.parts):
            if boxes[j] is None:
                continue
            u0, u1, v0, v1 = boxes[j][0] - ru0, boxes[j][1] - ru0, boxes[j][2] - rv0, boxes[j][3] - rv0
            gy, gx = np.meshgrid(ray_y[v0:v1], ray_x[u0:u1], indexing="ij")
            d_cam = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], axis=1)
            r, t = transforms[j, :, :3], transforms[j, :, 3]
            d = d_cam @ r  # R^T d: the rays in part coordinates (|d| and the ray parameter are kept)
            o = -(r.T @ t)
            hit, normal = intersect(pt.shape, o, d)
            sub = zbuf[v0:v1, u0:u1].ravel()
            idx = np.flatnonzero(hit < sub)  # z-buffer test
            if idx.size == 0:
                continue
            sub[idx] = hit[idx]
            zbuf[v0:v1, u0:u1] = sub.reshape(v1 - v0, u1 - u0)
            rows, cols = np.divmod(idx, u1 - u0)
            rows += v0
            cols += u0
            part[rows, cols] = j
            local[rows, cols] = o + hit[idx, None] * d[idx]
            dn = d[idx] / np.linalg.norm(d[idx], axis=1, keepdims=True)
            cos_view[rows, cols] = np.abs((dn * normal[idx]).sum(axis=1))

        z = np.where(np.isfinite(zbuf), zbuf, 0.0)
        gray = np.zeros((rh, rw))
        for j in range(chain.n_parts):
            m = part == j
            if m.any():
                gray[m] = texture.sample(j, local[m]) * (1.0 - shading + shading * cos_view[m])
        if background is not None:
            m = part < 0
            gray[m] = _wall_image(background, camera, width, height)[m]
        win = (slice(rv0, rv1), slice(ru0, ru1))
        gray_full[win] = gray
        depth_full[win] = z if not depth_step else np.round(z / depth_step) * depth_step
        part_full[win] = part
        points_full[win] = np.stack([ray_x[None, :] * z, ray_y[:, None] * z, z], axis=-1)
        local_full[win] = local
    if noise > 0:
        gray_full = np.clip(gray_full + rng.normal(0.0, noise, gray_full.shape), 0.0, 1.0).astype(np.float32)
    return Rendering(gray=gray_full, depth=depth_full, part=part_full, points=points_full, local=local_full)

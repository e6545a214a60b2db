"""Paper 001's simulated input: groups of people seen by a rectified stereo rig, with ground truth.

``scene(name, rng, ...)`` (``name`` in :data:`SCENES`) returns a :class:`GroupScene`; frames are
rendered on demand (``scene[k]`` or iteration, a :class:`StereoFrame`: left and right uint8 images,
the left camera's person-id image and depth, the background pair, the ground truth), and
``scene.observations(k, rng)`` gives the points a stereo + KLT front end would measure, without
rendering::

    from gputrack.sim.groups import scene
    sc = scene("merging", np.random.default_rng(0))
    fr = sc[40]                       # fr.left, fr.right (480, 640) uint8, fr.person_id, fr.truth
    xyz, vel, pid = sc.observations(40, np.random.default_rng(1))

The rig (paper 001 sec. 4): Bumblebee2, f = 3.8 mm on 7.4 um pixels (513.5 px), b = 120 mm,
640 x 480, 48 fps, 5.1 m above the floor and pitched 40 deg down (2.1 m, 15 deg for the stairs).

Frames: the first ``empty_frames`` frames (default 24, half a second) show the scene without
people (for a background model to be learnt); the people appear at frame ``empty_frames`` at
their start positions, inside the view. Every frame also carries the static background pair
(the scene without people, with the frame's exposure and without sensor noise). A frame's
``time`` is counted from the people's appearance (negative in the empty frames). Rendering a
640 x 480 pair takes about 27 ms (NumPy: ray casting in each person's bounding box over the
static background, which is ray cast once per scene).

Coordinates (mm): world X right, Y forward along the floor, Z up, the camera above the world
origin; camera x right, y down, z forward (left camera; the right camera sits b to the right),
as :class:`gputrack.models.camera.StereoCamera`, so that a surface point at camera depth z
appears in the right image d = b f / z pixels left of its left-image column (eq. 6).

People: an elliptic vertical cylinder (the body, with a flat top: the shoulders) and a sphere (the
head), each person 1.5-1.9 m tall and 0.4-0.5 m wide, with a clothing texture fixed to the body
(shirt, trousers, hair and face), Lambertian shading, a little gait bob and sway. A person's true
position is the point on the body axis at half the person's height (the centre of the person);
the true group mean is the mean of its members' positions, its velocity the mean of theirs.

Scenes (:data:`SCENES`), seconds after the people appear:

- ``"crossing"``: group 0 (2 people) walks right, group 1 (3 people) walks left, each abreast
  (side by side, so one behind the other as the camera sees them), group 1's nearest member
  0.6-1.2 m behind group 0's farthest; they pass each other at t = 2.5 s at the image centre
  with partial occlusion (paper Fig. 4-5);
- ``"merging"``: group 0 (2) from the left, group 1 (3) from the right converge and at
  t_merge = 2.2 s form group 2 (all 5), which walks on away from the camera (Fig. 6-7);
  :attr:`GroupScene.merge_frame` is the first frame with group 2;
- ``"stairs"``: group 0 (3) walks away from the camera and climbs a staircase (10 steps,
  rise 170 mm, tread 300 mm) from Y = 6 m (camera 2.1 m, 15 deg; Fig. 8-9).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..models.camera import StereoCamera

__all__ = [
    "BUMBLEBEE2",
    "FPS",
    "SCENES",
    "SIZE",
    "FrameTruth",
    "StereoFrame",
    "GroupScene",
    "Rig",
    "rig",
    "scene",
]

FPS = 48.0
#: (width, height) of the Bumblebee2's VGA images
SIZE = (640, 480)
#: Bumblebee2: f = 3.8 mm / 7.4 um = 513.5 px, b = 120 mm, principal point at the image centre
BUMBLEBEE2 = StereoCamera(f=3.8 / 0.0074, cx=319.5, cy=239.5, b=120.0)
SCENES = ("crossing", "merging", "stairs")

_NB, _NH, _NC = 80, 24, 64  # person texture: body rows, head rows, columns (around the body)
_TEX_MM = 20.0  # background texture: mm per texel
_LIGHT = np.array([0.3, -0.5, 1.0]) / np.linalg.norm([0.3, -0.5, 1.0])  # world, towards the light


# -- the rig -------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Rig:
    """A rectified stereo camera ``camera`` (f, cx, cy in px, b in mm) with images of ``size`` =
    (width, height), mounted ``mount_mm`` above the floor at world (0, 0, mount_mm), pitched
    ``tilt_deg`` down, looking along world +Y."""

    camera: StereoCamera
    size: tuple
    mount_mm: float
    tilt_deg: float

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) world -> camera rotation: rows are the camera's x, y, z axes in world coordinates."""
        s, c = math.sin(math.radians(self.tilt_deg)), math.cos(math.radians(self.tilt_deg))
        return np.array([[1.0, 0.0, 0.0], [0.0, -s, -c], [0.0, c, -s]])

    def centre(self, side: str = "left") -> np.ndarray:
        """(3,) world position of the ``"left"`` or ``"right"`` camera's centre."""
        if side not in ("left", "right"):
            raise ValueError(f"side: expected 'left' or 'right', got {side!r}")
        c = np.array([0.0, 0.0, self.mount_mm])
        return c + (self.camera.b * self.rotation[0] if side == "right" else 0.0)

    def to_camera(self, points_world) -> np.ndarray:
        """(..., 3) world points (mm) -> left-camera coordinates (mm)."""
        return (np.asarray(points_world, np.float64) - self.centre()) @ self.rotation.T

    def to_world(self, points_camera) -> np.ndarray:
        """(..., 3) left-camera points (mm) -> world coordinates (mm)."""
        return np.asarray(points_camera, np.float64) @ self.rotation + self.centre()

    def rays(self, supersample: int = 1) -> np.ndarray:
        """(H s, W s, 3) world directions of the pixels' rays (sub-pixel grid for ``s`` > 1), scaled
        so that t along a ray is the camera depth z of the point o + t d."""
        w, h = self.size
        cam = self.camera
        off = (np.arange(supersample) + 0.5) / supersample - 0.5
        u = (np.arange(w)[:, None] + off[None, :]).ravel()
        v = (np.arange(h)[:, None] + off[None, :]).ravel()
        d = np.empty((len(v), len(u), 3))
        d[..., 0] = ((u - cam.cx) / cam.f)[None, :]
        d[..., 1] = ((v - cam.cy) / cam.f)[:, None]
        d[..., 2] = 1.0
        return d @ self.rotation


def rig(mount_mm: float = 5100.0, tilt_deg: float = 40.0, scale: float = 1.0) -> Rig:
    """The paper's Bumblebee2 rig mounted ``mount_mm`` high, ``tilt_deg`` down; ``scale`` < 1 renders
    smaller images (focal length and image size scaled, for fast tests)."""
    if not (np.isfinite(scale) and 0.05 <= scale <= 1.0):
        raise ValueError(f"scale: expected a number in [0.05, 1], got {scale!r}")
    w, h = int(round(SIZE[0] * scale)), int(round(SIZE[1] * scale))
    cam = StereoCamera(f=BUMBLEBEE2.f * scale, cx=(w - 1) / 2.0, cy=(h - 1) / 2.0, b=BUMBLEBEE2.b)
    return Rig(cam, (w, h), float(mount_mm), float(tilt_deg))


# -- textures ------------------------------------------------------------------------------------------
def _smooth_noise(rng, shape, sigma, wrap=True) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    n = gaussian_filter(rng.standard_normal(shape), sigma, mode="wrap" if wrap else "reflect")
    return n / n.std()


def _bilinear(tex, r, c, wrap_rows=False):
    """Sample ``tex`` at float (row, col); columns wrap, rows wrap or clamp."""
    nr, nc = tex.shape
    r0 = np.floor(r)
    c0 = np.floor(c)
    fr, fc = r - r0, c - c0
    r0 = r0.astype(np.int64)
    c0 = c0.astype(np.int64)
    if wrap_rows:
        r0, r1 = r0 % nr, (r0 + 1) % nr
    else:
        r0, r1 = np.clip(r0, 0, nr - 1), np.clip(r0 + 1, 0, nr - 1)
    c0, c1 = c0 % nc, (c0 + 1) % nc
    top = tex[r0, c0] * (1 - fc) + tex[r0, c1] * fc
    bot = tex[r1, c0] * (1 - fc) + tex[r1, c1] * fc
    return top * (1 - fr) + bot * fr


# -- the static world: axis-aligned textured rectangles -----------------------------------------------
@dataclasses.dataclass(frozen=True)
class _Rect:
    axis: int  # the world axis of the normal (1: Y = value, a wall or riser; 2: Z = value, floor)
    value: float
    lo: tuple  # bounds of the two other axes (in increasing axis order), mm
    hi: tuple
    albedo: float
    tiles: float  # tile size (mm) of a grout grid, 0 for none
    shade: float


def _trace(rects, origin, d):
    """First hits of the rays o + t d (d: (n, 3) world) on the rectangles: t (n,) (inf: none) and the
    index of the rectangle hit (-1: none)."""
    best = np.full(len(d), np.inf)
    idx = np.full(len(d), -1)
    for i, rc in enumerate(rects):
        k = rc.axis
        a0, a1 = (a for a in range(3) if a != k)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (rc.value - origin[k]) / d[:, k]
        p0 = origin[a0] + t * d[:, a0]
        p1 = origin[a1] + t * d[:, a1]
        hit = (t > 0) & (t < best) & (p0 >= rc.lo[0]) & (p0 <= rc.hi[0]) & (p1 >= rc.lo[1]) & (p1 <= rc.hi[1])
        best[hit] = t[hit]
        idx[hit] = i
    return best, idx


def _background(rig_: Rig, rects, noise, coarse, origin, supersample):
    """Radiance (H, W) float32 (mean over s x s rays per pixel) and camera depth (H, W) float64 (of
    the pixel centre's ray; inf where nothing is hit) of the static world seen from ``origin``."""
    d = rig_.rays(supersample).reshape(-1, 3)
    t, idx = _trace(rects, origin, d)
    rad = np.full(len(d), 60.0)
    for i, rc in enumerate(rects):
        sel = idx == i
        if not sel.any():
            continue
        k = rc.axis
        a0, a1 = (a for a in range(3) if a != k)
        a = origin[a0] + t[sel] * d[sel, a0]
        b = origin[a1] + t[sel] * d[sel, a1]
        alb = rc.albedo + 32.0 * _bilinear(noise, b / _TEX_MM + 37 * k, a / _TEX_MM, True)
        alb += 22.0 * _bilinear(coarse, b / (8 * _TEX_MM), a / (8 * _TEX_MM) + 11 * k, True)
        if rc.tiles > 0:  # grout lines, about 24 mm wide with soft edges
            ga = np.abs((a + 0.5 * rc.tiles) % rc.tiles - 0.5 * rc.tiles)
            gb = np.abs((b + 0.5 * rc.tiles) % rc.tiles - 0.5 * rc.tiles)
            alb -= 45.0 * np.clip((18.0 - np.minimum(ga, gb)) / 6.0, 0.0, 1.0)
        rad[sel] = rc.shade * alb
    w, h = rig_.size
    s = supersample
    rad = rad.reshape(h, s, w, s).mean(axis=(1, 3))
    depth = t.reshape(h, w) if s == 1 else _trace(rects, origin, rig_.rays(1).reshape(-1, 3))[0].reshape(h, w)
    return rad.astype(np.float32), depth


def _world(name: str, rng) -> tuple:
    """The static rectangles of scene ``name`` and its ground height function."""
    floor_alb, wall_alb = rng.uniform(105, 135), rng.uniform(130, 170)
    big = 60000.0
    if name != "stairs":
        back = 16000.0
        rects = [
            _Rect(2, 0.0, (-big, -big), (big, back), floor_alb, 600.0, 1.0),
            _Rect(1, back, (-big, 0.0), (big, 8000.0), wall_alb, 0.0, 0.9),
        ]
        return rects, lambda x, y: np.zeros_like(np.asarray(y, np.float64)), None
    ys, rise, tread, n = 6000.0, 170.0, 300.0, 10
    back = ys + n * tread + 3000.0
    rects = [_Rect(2, 0.0, (-big, -big), (big, ys), floor_alb, 600.0, 1.0)]
    for i in range(1, n + 1):
        y0 = ys + (i - 1) * tread
        rects.append(_Rect(1, y0, (-big, (i - 1) * rise), (big, i * rise), floor_alb - 25.0, 0.0, 0.75))
        y1 = y0 + tread if i < n else back
        rects.append(_Rect(2, i * rise, (-big, y0), (big, y1), floor_alb + 10.0, 300.0 if i < n else 600.0, 1.0))
    rects.append(_Rect(1, back, (-big, n * rise), (big, 8000.0), wall_alb, 0.0, 0.9))

    def ground(x, y):
        """The feet's height: the line through the treads' middles (within rise / 2 of a tread),
        its corners at the foot and the top of the stairs rounded over about 150 mm (smooth)."""
        s = np.asarray(y, np.float64) - (ys - 0.5 * tread)

        def relu(v):  # smooth max(v, 0)
            return 0.5 * (v + np.sqrt(v * v + 150.0**2))

        return rise / tread * (relu(s) - relu(s - n * tread))

    return rects, ground, dict(start=ys, rise=rise, tread=tread, steps=n)


# -- people ------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class _Person:
    height: float
    half_width: float  # body semi-axis across the walking direction
    half_depth: float  # body semi-axis along it
    head: float  # head radius
    texture: np.ndarray  # (_NB + _NH, _NC) albedo

    @property
    def body_top(self) -> float:
        return self.height - 2.0 * self.head


def _person(rng) -> _Person:
    h = rng.uniform(1500.0, 1900.0)
    hw = rng.uniform(200.0, 250.0)
    hd = rng.uniform(110.0, 150.0)
    head = rng.uniform(95.0, 112.0)
    tex = np.empty((_NB + _NH, _NC))
    hip = int(_NB * 0.48 * h / (h - 2 * head))
    shirt, trousers = rng.uniform(50, 220), rng.uniform(30, 150)
    tex[:hip] = trousers
    tex[hip:_NB] = shirt
    if rng.random() < 0.5:  # stripes on the shirt
        rows = np.arange(hip, _NB)
        tex[hip:_NB] += 30.0 * np.sign(np.sin(2 * np.pi * rows / rng.uniform(5, 9)))[:, None]
    tex[:_NB] += 28.0 * _smooth_noise(rng, (_NB, _NC), 1.3)
    hair, skin = rng.uniform(20, 80), rng.uniform(140, 200)
    elev = (np.arange(_NH) + 0.5) / _NH  # 0 = chin, 1 = crown
    ang = (np.arange(_NC) + 0.5) / _NC * 2 * np.pi - np.pi  # 0 = front
    face = (elev[:, None] < 0.62) & (np.abs(ang)[None, :] < 1.1)
    tex[_NB:] = np.where(face, skin, hair) + 12.0 * _smooth_noise(rng, (_NH, _NC), 1.0)
    return _Person(h, hw, hd, head, tex)


def _hit_people(origin, d, persons, base, heading, need_shading=False):
    """First hits of rays o + t d (d: (n, 3) world) on each person (P persons at ``base`` (P, 3),
    ``heading`` (P,)): t (P, n) (inf for a miss) and, with ``need_shading``, the radiance (P, n)."""
    n = len(d)
    ts = np.full((len(persons), n), np.inf)
    rad = np.zeros((len(persons), n)) if need_shading else None
    for p, (per, b, th) in enumerate(zip(persons, base, heading)):
        hx, hy = math.cos(th), math.sin(th)
        rel = origin - b
        oa, ol = rel[0] * hx + rel[1] * hy, -rel[0] * hy + rel[1] * hx  # along heading, lateral
        da, dl = d[:, 0] * hx + d[:, 1] * hy, -d[:, 0] * hy + d[:, 1] * hx
        c2, a2 = per.half_depth**2, per.half_width**2
        # body: (along / c)^2 + (lateral / a)^2 = 1, 0 <= z <= body_top (side), z = body_top (top)
        qa = da * da / c2 + dl * dl / a2
        qb = 2.0 * (oa * da / c2 + ol * dl / a2)
        qc = oa * oa / c2 + ol * ol / a2 - 1.0
        disc = qb * qb - 4.0 * qa * qc
        with np.errstate(invalid="ignore", divide="ignore"):
            t_side = (-qb - np.sqrt(disc)) / (2.0 * qa)
            z_side = rel[2] + t_side * d[:, 2]
            t_side = np.where((disc > 0) & (t_side > 0) & (z_side >= 0) & (z_side <= per.body_top), t_side, np.inf)
            t_top = (per.body_top - rel[2]) / d[:, 2]
            ea, el = oa + t_top * da, ol + t_top * dl
            in_top = (t_top > 0) & (ea * ea / c2 + el * el / a2 <= 1.0)
            t_top = np.where(in_top, t_top, np.inf)
            # head: sphere of radius r on top of the body
            hc = rel - np.array([0.0, 0.0, per.body_top + per.head])
            sb = d @ hc
            sa = np.einsum("ij,ij->i", d, d)
            sdisc = sb * sb - sa * (hc @ hc - per.head**2)
            t_head = (-sb - np.sqrt(sdisc)) / sa
            t_head = np.where((sdisc > 0) & (t_head > 0), t_head, np.inf)
        t = np.minimum(np.minimum(t_side, t_top), t_head)
        ts[p] = t
        if not need_shading:
            continue
        hit = np.isfinite(t)
        if not hit.any():
            continue
        part = np.where(t_head <= np.minimum(t_side, t_top), 2, np.where(t_top <= t_side, 1, 0))
        th_ = t[hit]
        pa, pl, pz = oa + th_ * da[hit], ol + th_ * dl[hit], rel[2] + th_ * d[hit, 2]
        pr = part[hit]
        na, nl, nz = pa / c2, pl / a2, np.zeros_like(pa)
        col = (np.arctan2(pl / per.half_width, pa / per.half_depth) / (2 * np.pi) + 0.5) * _NC
        row = np.clip(pz / per.body_top, 0.0, 1.0) * (_NB - 1)
        top = pr == 1
        na[top], nl[top], nz[top] = 0.0, 0.0, 1.0
        row[top] = _NB - 1.0
        hd = pr == 2
        if hd.any():
            va, vl, vz = pa[hd], pl[hd], pz[hd] - per.body_top - per.head
            na[hd], nl[hd], nz[hd] = va, vl, vz
            col[hd] = (np.arctan2(vl, va) / (2 * np.pi) + 0.5) * _NC
            row[hd] = _NB + (np.arcsin(np.clip(vz / per.head, -1, 1)) / np.pi + 0.5) * (_NH - 1)
        nx, ny = na * hx - nl * hy, na * hy + nl * hx
        nn = np.sqrt(nx * nx + ny * ny + nz * nz)
        lam = np.maximum((nx * _LIGHT[0] + ny * _LIGHT[1] + nz * _LIGHT[2]) / nn, 0.0)
        rad[p, hit] = _bilinear(per.texture, row, col) * (0.55 + 0.45 * lam)
    return ts, rad


# -- scenes: paths -------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class _Walker:
    person: _Person
    key_t: np.ndarray  # (K,) s
    key_xy: np.ndarray  # (K, 2) mm
    key_group: np.ndarray  # (K,) true group from each key time on
    wander: np.ndarray  # (2, 3): amplitude mm, period s, phase per world axis X, Y
    step_hz: float
    gait_phase: float


def _walk(w: _Walker, t, ground):
    """World base (feet) positions (T, 3) incl. wander, sway and bob, and headings (T,) at times t."""
    from scipy.interpolate import CubicHermiteSpline

    # C1 path through the keys; at an inner key the velocity is the mean velocity between its
    # neighbours (Catmull-Rom), at the ends the segment's: walkers keep their pace through turns
    kt, kx = w.key_t, w.key_xy
    kv = np.empty_like(kx)
    kv[1:-1] = (kx[2:] - kx[:-2]) / (kt[2:] - kt[:-2])[:, None]
    kv[0] = (kx[1] - kx[0]) / (kt[1] - kt[0])
    kv[-1] = (kx[-1] - kx[-2]) / (kt[-1] - kt[-2])
    path = CubicHermiteSpline(kt, kx, kv, axis=0, extrapolate=True)
    xy = path(t)
    v = path.derivative()(t)
    heading = np.arctan2(v[:, 1], v[:, 0])
    amp, per, ph = w.wander[:, 0], w.wander[:, 1], w.wander[:, 2]
    xy = xy + amp * np.sin(2 * np.pi * t[:, None] / per + ph)
    g = 2 * np.pi * w.step_hz * t + w.gait_phase
    sway = 22.0 * np.sin(0.5 * g)  # sideways, one period per two steps
    xy = xy + sway[:, None] * np.stack([-np.sin(heading), np.cos(heading)], axis=1)
    z = ground(xy[:, 0], xy[:, 1]) + 15.0 * np.cos(g)  # bob, one period per step
    return np.column_stack([xy, z]), heading


def _group_keys(rng, centre_keys, directions, offsets):
    """Per-member key positions: the group centre's keys plus each member's formation offset
    (lateral, along) rotated to the walking direction given per key (radians)."""
    out = []
    for lat, along in offsets:
        pts = []
        for c, th in zip(centre_keys, directions):
            h = np.array([math.cos(th), math.sin(th)])
            l = np.array([-h[1], h[0]])
            pts.append(np.asarray(c) + lat * l + along * h + rng.normal(0.0, 25.0, 2))
        out.append(np.array(pts))
    return out


def _scene_walkers(name: str, rng, duration: float):
    T = max(duration, 0.1) + 1.0
    walkers = []

    def add(keys_t, keys_xy, groups):
        wander = np.column_stack([rng.uniform(20, 70, 2), rng.uniform(2.5, 5.0, 2), rng.uniform(0, 2 * np.pi, 2)])
        walkers.append(
            _Walker(_person(rng), np.asarray(keys_t, float), keys_xy, np.asarray(groups), wander,
                    rng.uniform(1.7, 2.1), rng.uniform(0, 2 * np.pi))  # fmt: skip
        )

    if name == "crossing":
        tc = 2.5
        for g, (n, y, sign) in enumerate(((2, 4800.0, 1.0), (3, 5900.0 + rng.uniform(0, 200) + 450.0, -1.0))):
            v = rng.uniform(1000.0, 1400.0)
            yy = y + rng.uniform(-100, 100)
            keys = [(-sign * v * tc, yy), (sign * v * (T - tc), yy)]
            th = 0.0 if sign > 0 else np.pi
            offs = [(-300.0, 0.0), (300.0, 0.0)] if n == 2 else [(-450.0, 0.0), (0.0, 60.0), (450.0, 0.0)]
            for kx in _group_keys(rng, keys, [th, th], offs):
                add([0.0, T], kx, [g, g])
        return walkers, None
    if name == "merging":
        tm = 2.2
        ym = 6000.0 + rng.uniform(-150, 150)
        vm = rng.uniform(1000.0, 1200.0)
        for g, (n, start, end) in enumerate(((2, (-3000.0, 5200.0), (-550.0, ym)), (3, (3000.0, 5600.0), (750.0, ym)))):
            start = np.asarray(start) + rng.uniform(-150, 150, 2)
            end = np.asarray(end)
            th = math.atan2(end[1] - start[1], end[0] - start[0])
            app = end - 700.0 * np.array([math.cos(th), math.sin(th)])  # still in formation 0.6 s before
            keys = [start, app, end, end + (0.0, vm * (T - tm))]
            # the formation keeps its orientation through the turn (abreast while converging, two
            # files side by side after the merge): members never cut through each other
            offs = [(-300.0, 0.0), (300.0, 0.0)] if n == 2 else [(-450.0, 0.0), (0.0, 60.0), (450.0, 0.0)]
            for kx in _group_keys(rng, keys, [th] * 4, offs):
                add([0.0, tm - 0.6, tm, T], kx, [g, g, 2, 2])
        return walkers, tm
    if name == "stairs":
        t1 = 1.8
        v_up = rng.uniform(480.0, 620.0)
        x0 = rng.uniform(-300, 300)
        keys = [(x0, 4000.0), (x0, 6000.0), (x0, 6000.0 + v_up * (T - t1))]
        th = np.pi / 2
        offs = [(-350.0, 0.0), (350.0, 0.0), (0.0, -650.0)]
        for kx in _group_keys(rng, keys, [th] * 3, offs):
            add([0.0, t1, T], kx, [0, 0, 0])
        return walkers, None
    raise ValueError(f"scene: expected one of {', '.join(SCENES)}, got {name!r}")


# -- ground truth and frames -----------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class FrameTruth:
    """Ground truth of one frame (mm, mm/frame; camera = the left camera's coordinates).

    - ``present`` (P,) bool: the people in the scene this frame (all False in the empty frames);
    - ``position`` (P, 3) camera coords of each person's centre, ``position_world`` (P, 3) world;
    - ``velocity`` (P, 3) camera coords, mm/frame;
    - ``group`` (P,) int64 true group of each person (-1 when absent);
    - ``group_ids`` (G,) the true groups present (ascending), ``group_mean`` (G, 3) the mean of their
      members' positions (camera coords), ``group_velocity`` (G, 3) mean of their velocities.
    """

    frame: int
    present: np.ndarray
    position: np.ndarray
    position_world: np.ndarray
    velocity: np.ndarray
    group: np.ndarray
    group_ids: np.ndarray
    group_mean: np.ndarray
    group_velocity: np.ndarray

    @property
    def person_group(self) -> dict:
        """{person id: true group} of the people present."""
        return {int(p): int(g) for p, g in enumerate(self.group) if g >= 0}


@dataclasses.dataclass(frozen=True)
class StereoFrame:
    """One rendered frame: ``left``, ``right`` (H, W) uint8; ``person_id`` (H, W) int32 (the left
    image's person at each pixel, -1 = background); ``depth`` (H, W) float32 left camera depth z
    (mm, inf where nothing is hit); ``background_left``/``background_right`` (H, W) uint8 (the scene
    without people, this frame's exposure, no noise); ``gain``, ``offset`` the exposure
    (image = gain * radiance + offset + noise); ``truth`` the :class:`FrameTruth`."""

    index: int
    time: float
    left: np.ndarray
    right: np.ndarray
    person_id: np.ndarray
    depth: np.ndarray
    background_left: np.ndarray
    background_right: np.ndarray
    gain: float
    offset: float
    truth: FrameTruth


class GroupScene:
    """A simulated group scene: the rig, the ground truth of every frame (arrays below, computed at
    construction) and frames rendered on demand (``scene[k]``).

    Arrays over frames F and people P: ``present`` (F, P), ``positions`` / ``positions_world`` /
    ``velocities`` (F, P, 3) (camera coords mm, world mm, camera mm/frame; NaN when absent),
    ``groups`` (F, P) int64 (-1 when absent). ``merge_frame``: the first frame of the merged group
    (``"merging"``), else None (also when the merge falls after the last frame); ``merged_group``:
    its id. ``persons``: each person's shape
    (``height``, ``half_width``, ``half_depth``, ``head`` radius, mm; ``body_top`` = height - 2 head);
    ``rig``, ``camera`` (the :class:`StereoCamera`), ``size`` (width, height); ``stairs``: the
    staircase (``start`` Y, ``rise``, ``tread``, ``steps``) or None.
    """

    def __init__(self, name, rng, *, frames=None, empty_frames=24, scale=1.0, noise=2.0, exposure=0.03,
                 supersample=2):  # fmt: skip
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng: expected a numpy.random.Generator (np.random.default_rng(seed)), got "
                            f"{type(rng).__name__}")  # fmt: skip
        if name not in SCENES:
            raise ValueError(f"scene: expected one of {', '.join(SCENES)}, got {name!r}")
        dur = {"crossing": 5.0, "merging": 5.0, "stairs": 6.0}[name]
        for nm, v in (("empty_frames", empty_frames), ("frames", 1 if frames is None else frames),
                      ("supersample", supersample)):  # fmt: skip
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < (0 if nm == "empty_frames" else 1):
                raise ValueError(f"{nm}: expected a {'non-negative' if nm == 'empty_frames' else 'positive'} "
                                 f"integer, got {v!r}")  # fmt: skip
        for nm, v in (("noise", noise), ("exposure", exposure)):
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{nm}: expected a finite number >= 0, got {v!r}")
        n_frames = int(frames) if frames is not None else int(empty_frames) + int(round(dur * FPS))
        self.name = name
        self.fps = FPS
        self.empty_frames = int(empty_frames)
        self.noise = float(noise)
        self.exposure = float(exposure)
        self.rig = rig(2100.0, 15.0, scale) if name == "stairs" else rig(5100.0, 40.0, scale)
        self.camera = self.rig.camera
        self.size = self.rig.size
        self._seed = int(rng.integers(2**62))
        rects, self._ground, self.stairs = _world(name, rng)
        self._walkers, t_merge = _scene_walkers(name, rng, max(dur, (n_frames - self.empty_frames) / FPS))
        self.persons = [w.person for w in self._walkers]
        noise_tex, coarse = _smooth_noise(rng, (512, 512), 1.2), _smooth_noise(rng, (256, 256), 1.5)
        self._bg = {}
        for side in ("left", "right"):
            self._bg[side] = _background(self.rig, rects, noise_tex, coarse, self.rig.centre(side), supersample)
        self._rays = self.rig.rays(1)
        self._truth(n_frames, t_merge)

    # ground truth
    def _truth(self, n_frames, t_merge):
        P = len(self._walkers)
        k = np.arange(n_frames)
        t = (k - self.empty_frames) / FPS
        self.present = np.broadcast_to((k >= self.empty_frames)[:, None], (n_frames, P)).copy()
        base = np.full((n_frames, P, 3), np.nan)
        heading = np.zeros((n_frames, P))
        vel_w = np.full((n_frames, P, 3), np.nan)
        groups = np.full((n_frames, P), -1, np.int64)
        on = k >= self.empty_frames
        h = 1e-3
        for p, w in enumerate(self._walkers):
            b, th = _walk(w, t[on], self._ground)
            base[on, p], heading[on, p] = b, th
            vel_w[on, p] = (_walk(w, t[on] + h, self._ground)[0] - _walk(w, t[on] - h, self._ground)[0]) / (2 * h) / FPS
            idx = np.searchsorted(w.key_t, t[on], side="right") - 1
            groups[on, p] = w.key_group[np.clip(idx, 0, len(w.key_t) - 1)]
        self._base, self._heading = base, heading
        centre = base + np.stack([np.zeros(P), np.zeros(P), [0.5 * pp.height for pp in self.persons]], -1)
        self.positions_world = centre
        self.positions = np.where(np.isnan(centre), np.nan, self.rig.to_camera(np.nan_to_num(centre)))
        self.velocities = vel_w @ self.rig.rotation.T
        self.groups = groups
        if t_merge is not None and (groups == 2).any():
            self.merged_group = 2
            self.merge_frame = int(np.argmax((groups == 2).any(axis=1)))
        else:  # no merge, or not within the frames simulated
            self.merged_group = self.merge_frame = None

    def truth(self, k: int) -> FrameTruth:
        """The ground truth of frame ``k``."""
        k = self._index(k)
        g = self.groups[k]
        ids = np.unique(g[g >= 0])
        mean = np.array([self.positions[k][g == i].mean(axis=0) for i in ids]).reshape(-1, 3)
        vel = np.array([self.velocities[k][g == i].mean(axis=0) for i in ids]).reshape(-1, 3)
        return FrameTruth(k, self.present[k].copy(), self.positions[k].copy(), self.positions_world[k].copy(),
                          self.velocities[k].copy(), g.copy(), ids, mean, vel)  # fmt: skip

    def __len__(self) -> int:
        return self.groups.shape[0]

    def __repr__(self) -> str:
        return f"GroupScene({self.name!r}, frames={len(self)}, people={len(self.persons)}, size={self.size})"

    def _index(self, k) -> int:
        n = len(self)
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not -n <= k < n:
            raise IndexError(f"frame index: expected an integer in [-{n}, {n}), got {k!r}")
        return int(k) % n

    # rendering
    def _render_side(self, side, k, with_id):
        rad, depth = self._bg[side]
        rad, depth = rad.copy(), depth.copy()
        pid = np.full(depth.shape, -1, np.int32) if with_id else None
        if not self.present[k].any():
            return rad, depth, pid
        origin = self.rig.centre(side)
        w, h = self.size
        cam = self.camera
        R = self.rig.rotation
        for p, per in enumerate(self.persons):
            b, th = self._base[k, p], self._heading[k, p]
            r = max(per.half_width, per.half_depth) + 40.0
            corners = np.array([[b[0] + sx * r, b[1] + sy * r, b[2] + z] for sx in (-1, 1) for sy in (-1, 1)
                                for z in (-20.0, per.height + 20.0)])  # fmt: skip
            c = (corners - origin) @ R.T
            if (c[:, 2] <= 1.0).any():
                continue
            u = cam.f * c[:, 0] / c[:, 2] + cam.cx
            v = cam.f * c[:, 1] / c[:, 2] + cam.cy
            u0, u1 = max(int(np.floor(u.min())), 0), min(int(np.ceil(u.max())) + 1, w)
            v0, v1 = max(int(np.floor(v.min())), 0), min(int(np.ceil(v.max())) + 1, h)
            if u0 >= u1 or v0 >= v1:
                continue
            d = self._rays[v0:v1, u0:u1].reshape(-1, 3)
            t = _hit_people(origin, d, [per], b[None], [th])[0][0].reshape(v1 - v0, u1 - u0)
            zb = depth[v0:v1, u0:u1]
            near = t < zb
            if not near.any():
                continue
            zb[near] = t[near]
            shade = _hit_people(origin, d[near.ravel()], [per], b[None], [th], need_shading=True)[1][0]
            rad[v0:v1, u0:u1][near] = shade
            if with_id:
                pid[v0:v1, u0:u1][near] = p
        return rad, depth, pid

    def __getitem__(self, k) -> StereoFrame:
        k = self._index(k)
        rng = np.random.default_rng([self._seed, k])
        gain = float(np.exp(rng.normal(0.0, self.exposure)))
        offset = float(rng.normal(0.0, 40.0 * self.exposure))
        out = {}

        def expose(rad, noise):  # in place: gain * radiance + offset (+ noise), rounded to uint8
            rad *= np.float32(gain)
            rad += np.float32(offset + 0.5)
            if noise:
                n = rng.standard_normal(rad.shape, dtype=np.float32)
                n *= np.float32(self.noise)
                rad += n
            return np.clip(rad, 0.0, 255.0, out=rad).astype(np.uint8)

        for side in ("left", "right"):
            rad, depth, pid = self._render_side(side, k, side == "left")
            out[side] = (expose(rad, self.noise > 0), expose(self._bg[side][0].copy(), False))
            if side == "left":
                out["pid"], out["depth"] = pid, depth.astype(np.float32)
        return StereoFrame(k, (k - self.empty_frames) / FPS, out["left"][0], out["right"][0], out["pid"], out["depth"],
                          out["left"][1], out["right"][1], gain, offset, self.truth(k))  # fmt: skip

    def __iter__(self):
        for k in range(len(self)):
            yield self[k]

    # observations without images
    def observations(self, k, rng, *, points_per_person=40, sigma_uv=0.3, sigma_d=0.15, window=4, p_lost=0.1):
        """The 3D points a stereo + KLT front end would give at frame ``k``, without rendering.

        Per present person ``points_per_person`` points are drawn on the surface facing the camera
        (within 81 deg of the horizontal direction to it, the grazing silhouette left out; body side
        75 %, shoulders 10 %, head 15 %); a point is lost when another surface (or its own body)
        hides it from the left camera (people and the static scene), when it falls outside
        either image, or at random with probability ``p_lost`` (a KLT track lost). The survivors'
        true (u, v, d) get Gaussian noise (``sigma_uv``, ``sigma_d`` px) and are back-projected, so
        that the depth noise grows as z^2 sigma_d / (b f); the velocity is the track's
        displacement over ``window`` frames: the true velocity plus (n_k - n_{k-window}) / window,
        n_k this frame's position noise and n_{k-window} a fresh draw at the position ``window``
        frames before. Points move with their person's velocity.

        Returns (xyz (N, 3), velocity (N, 3), person_id (N,) int64): left-camera coords, mm and
        mm/frame, float64.
        """
        k = self._index(k)
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng: expected a numpy.random.Generator, got {type(rng).__name__}")
        if isinstance(points_per_person, bool) or not isinstance(points_per_person, (int, np.integer)) \
                or points_per_person < 0:  # fmt: skip
            raise ValueError(f"points_per_person: expected a non-negative integer, got {points_per_person!r}")
        if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1:
            raise ValueError(f"window: expected a positive integer, got {window!r}")
        for nm, v in (("sigma_uv", sigma_uv), ("sigma_d", sigma_d)):
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{nm}: expected a finite number >= 0, got {v!r}")
        if not 0.0 <= p_lost <= 1.0:
            raise ValueError(f"p_lost: expected a probability in [0, 1], got {p_lost!r}")
        empty = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64))
        live = np.flatnonzero(self.present[k])
        if len(live) == 0 or points_per_person == 0:
            return empty
        origin = self.rig.centre()
        pts, pids = [], []
        n = int(points_per_person)
        for p in live:
            per, b, th = self.persons[p], self._base[k, p], self._heading[k, p]
            to_cam = math.atan2(origin[1] - b[1], origin[0] - b[0]) - th  # camera's direction, person frame
            part = rng.choice(3, size=n, p=[0.75, 0.10, 0.15])
            phi = to_cam + rng.uniform(-0.45 * np.pi, 0.45 * np.pi, n)  # not the grazing silhouette
            ca, sa = np.cos(phi), np.sin(phi)
            rho = np.where(part == 1, np.sqrt(rng.random(n)), 1.0)
            along, lat = per.half_depth * ca * rho, per.half_width * sa * rho
            z = np.where(part == 1, per.body_top, rng.uniform(0.0, per.body_top, n))
            el = np.arcsin(rng.uniform(-0.3, 1.0, n))
            hd = part == 2
            along[hd] = per.head * np.cos(el[hd]) * ca[hd]
            lat[hd] = per.head * np.cos(el[hd]) * sa[hd]
            z[hd] = per.body_top + per.head + per.head * np.sin(el[hd])
            hx, hy = math.cos(th), math.sin(th)
            pts.append(np.column_stack([b[0] + along * hx - lat * hy, b[1] + along * hy + lat * hx, b[2] + z]))
            pids.append(np.full(n, p, np.int64))
        pw, pid = np.concatenate(pts), np.concatenate(pids)
        d = pw - origin  # t = 1 at the point
        ts, _ = _hit_people(origin, d, [self.persons[p] for p in live], self._base[k, live], self._heading[k, live])
        visible = ts.min(axis=0) >= 1.0 - 1e-6
        xyz = self.rig.to_camera(pw)
        uvd = self.camera.project(xyz)
        w, h = self.size
        inside = (uvd[:, 0] >= 0) & (uvd[:, 0] <= w - 1) & (uvd[:, 1] >= 0) & (uvd[:, 1] <= h - 1)
        inside &= uvd[:, 0] - uvd[:, 2] >= 0
        ui = np.clip(np.rint(uvd[:, 0]).astype(int), 0, w - 1)
        vi = np.clip(np.rint(uvd[:, 1]).astype(int), 0, h - 1)
        visible &= inside & (self._bg["left"][1][vi, ui] > xyz[:, 2] - 30.0)
        keep = visible & (rng.random(len(pw)) >= p_lost)
        xyz, uvd, pid = xyz[keep], uvd[keep], pid[keep]
        vel = self.velocities[k][pid]
        sig = np.array([sigma_uv, sigma_uv, sigma_d])
        obs = self.camera.unproject(np.maximum(uvd + rng.normal(0.0, 1.0, uvd.shape) * sig, [-np.inf, -np.inf, 1e-3]))
        past = xyz - window * vel
        past_uvd = self.camera.project(past)
        past_obs = self.camera.unproject(
            np.maximum(past_uvd + rng.normal(0.0, 1.0, uvd.shape) * sig, [-np.inf, -np.inf, 1e-3]))  # fmt: skip
        v_obs = vel + ((obs - xyz) - (past_obs - past)) / window
        return obs, v_obs, pid


def scene(name: str, rng: np.random.Generator, **kwargs) -> GroupScene:
    """Scene ``name`` (one of :data:`SCENES`) drawn with ``rng``.

    Keyword arguments: ``frames`` (default: ``empty_frames`` + 5 s, 6 s for the stairs, at 48 fps),
    ``empty_frames`` (24: frames without people at the start), ``scale`` (1: 640 x 480; 0.5 renders
    320 x 240 with f halved), ``noise`` (2.0: sensor noise sigma, grey levels), ``exposure`` (0.03:
    the per-frame log-gain sigma; offset sigma 40 times it, grey levels), ``supersample`` (2:
    anti-aliasing of the static background, s x s rays per pixel, computed once).
    """
    return GroupScene(name, rng, **kwargs)

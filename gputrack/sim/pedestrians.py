"""Paper 002's simulated input: a level depth camera 1 m above the floor watching people walk across
an entrance hall, with ground truth.

Sensor (:class:`DepthSensor`, paper 002 sec. 5 Table 1, Structure Core): 1280 x 960 pixels, field
of view 59 x 46 deg, range 0.3-5 m (readings are reported up to ``max_reading_mm`` = 10 m, as the
real sensor does; the tracker drops those beyond 5 m, sec. 4.2), depth accuracy +-0.29 % of the
depth, read as a Gaussian with sigma = 0.29 % / 2 truncated at +-0.29 % (so every reading is within
+-0.29 % of the true depth, plus the 0.5 mm of rounding to whole millimetres). Each frame a random
``dropout`` share of the pixels has no reading (0), like the device-dependent missing values of
sec. 4.1, and sunlight makes blobs of missing readings: ``sun_blobs`` persistent ones (fixed image
position and shape for the whole sequence, each present in a frame with probability
``sun_persistence``) and Poisson(``sun_transient``) short-lived ones per frame. The blobs are in
image space: whatever is seen there (floor, wall or a person walking through the sunlight) has
no reading. ``scale`` renders smaller frames with the intrinsics scaled accordingly (same field
of view).

Scene (:class:`Hall`): camera at the origin, x right, y down, z forward (mm); the floor is the
plane y = ``camera_height`` (1000 mm, the camera level, sec. 5), a back wall z = ``back_wall``
(6 m: beyond the 5 m range but within the sensor's readings), a ceiling ``ceiling_height`` above
the floor and optional side walls x = +-``side_walls``. The empty scene's depth is computed once
per size (cached).

People (:class:`Pedestrian`): adults 1.55-1.9 m and children 1.0-1.4 m tall; the body is a set of
ellipsoids (head, torso, pelvis, two legs and two arms swinging with the gait; some carry a hand
bag or a backpack) scaled with the height. They walk mostly across the view (some diagonally),
1-5 m from the camera, entering and leaving the view, alone or side by side in groups of 2-3
(one beside the other, i.e. at different depths: the nearer occludes the farther), passing each
other, some stopping for a few seconds. At most ``max_in_view`` of them are (geometrically) in
the view at once. 5 fps.

Rendering: one ray per pixel centre, d = ((u - cx)/fx, (v - cy)/fy, 1), so a hit's ray parameter
is its depth z; each ellipsoid is intersected analytically inside the image box of its projected
3D bounding box; the nearest hit wins (hidden-surface removal against the other people and the
empty scene). Every pixel is ray-cast at the frame's own size (no down-scaled rendering). Cost
(NumPy, CPU time of one process, median over frames): 1280 x 960: 17 ms an empty frame (the sensor
model's noise and missing readings), 19-32 ms with 1-5 people; 640 x 480 (``scale=0.5``): 3-12 ms;
320 x 240: 1-8 ms. On a busy 2-core machine the wall time was up to twice that.

Ground truth per frame (:class:`PedestrianFrame`): for each *labelled* person (visible pixels >=
``min_visible`` of the image's pixels) the id, ``position`` = the body's centre axis at chest
height (x, y_chest, z) with y_chest = camera_height - 0.72 height, ``floor`` = the floor point
below it (x, camera_height, z), ``pixels`` (the person's pixels rendered alone, in the image and
in front of the empty scene), ``visible`` (those not occluded by a nearer person) and
``visibility`` = visible / pixels. The metrics (:mod:`gputrack.trackers.pedestrians.metrics`)
match in the ground plane (x, z), the same for both points. ``label`` is the (H, W) image of
person ids (-1: the empty scene), before the sensor's missing readings.

Usage::

    seq = pedestrian_sequence(np.random.default_rng(0), frames=851, people=32, max_in_view=5)
    bg = seq.background(30)                  # (30, H, W) uint16 empty-scene frames
    for f in seq:                            # rendered lazily, one frame at a time
        f.depth, f.ids, f.position, f.visibility

All randomness comes from the ``numpy.random.Generator`` passed in: the people are drawn from it
at construction, and a seed drawn from it makes the frames' sensor noise
(``default_rng([seed, 0, i])`` for frame i, ``[seed, 1, j]`` for background frame j), so frames
can be rendered in any order and twice with the same result.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from ..models.camera import DepthCamera

__all__ = [
    "FPS",
    "DepthSensor",
    "Hall",
    "Pedestrian",
    "PedestrianFrame",
    "PedestrianSequence",
    "body_ellipsoids",
    "pedestrian_sequence",
    "render_people",
]

#: frames per second of paper 002's data (sec. 5)
FPS = 5.0
#: chest height as a share of the body height (the ground-truth ``position``'s height)
CHEST = 0.72


def _check_real(name, v, lo=None, hi=None, lo_open=False):
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(v):
        raise ValueError(f"{name}: expected a finite number, got {v!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise ValueError(f"{name}: expected a number {'>' if lo_open else '>='} {lo}, got {v!r}")
    if hi is not None and v > hi:
        raise ValueError(f"{name}: expected a number <= {hi}, got {v!r}")
    return float(v)


def _check_int(name, v, lo=0):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
        raise ValueError(f"{name}: expected an integer >= {lo}, got {v!r}")
    return int(v)


# -- sensor ---------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class DepthSensor:
    """The depth camera's model (Structure Core, paper 002 Table 1); see the module docstring.

    ``scale`` multiplies the image size (1280 x 960 at 1.0); the field of view stays the same.
    """

    scale: float = 1.0
    base_width: int = 1280
    base_height: int = 960
    hfov_deg: float = 59.0
    vfov_deg: float = 46.0
    min_mm: float = 300.0
    max_mm: float = 5000.0
    max_reading_mm: float = 10000.0
    accuracy: float = 0.0029
    dropout: float = 0.02
    sun_blobs: int = 3
    sun_persistence: float = 0.9
    sun_transient: float = 0.3

    def __post_init__(self):
        _check_real("scale", self.scale, 0.0, 4.0, lo_open=True)
        _check_real("hfov_deg", self.hfov_deg, 1.0, 170.0)
        _check_real("vfov_deg", self.vfov_deg, 1.0, 170.0)
        _check_real("accuracy", self.accuracy, 0.0, 0.5)
        _check_real("dropout", self.dropout, 0.0, 1.0)
        _check_real("sun_persistence", self.sun_persistence, 0.0, 1.0)
        _check_real("sun_transient", self.sun_transient, 0.0)
        _check_int("sun_blobs", self.sun_blobs)
        _check_int("base_width", self.base_width, 1)
        _check_int("base_height", self.base_height, 1)
        if not 0 <= self.min_mm < self.max_mm <= self.max_reading_mm:
            raise ValueError(
                f"DepthSensor: expected 0 <= min_mm < max_mm <= max_reading_mm, got {self.min_mm}, {self.max_mm}, "
                f"{self.max_reading_mm}"
            )
        if self.width < 8 or self.height < 8:
            raise ValueError(f"scale: expected a frame of at least 8 x 8 pixels, got {self.width} x {self.height}")

    @property
    def width(self) -> int:
        return int(round(self.base_width * self.scale))

    @property
    def height(self) -> int:
        return int(round(self.base_height * self.scale))

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the depth image."""
        return self.height, self.width

    def camera(self, unit: str = "mm") -> DepthCamera:
        """The intrinsics as a :class:`DepthCamera` for 3D points in ``unit`` ("mm": depth_scale 1,
        range 300-5000; "m": depth_scale 0.001, range 0.3-5). fx = (W/2) / tan(hfov/2), likewise fy;
        the principal point is the image centre."""
        if unit not in ("mm", "m"):
            raise ValueError(f"unit: expected 'mm' or 'm', got {unit!r}")
        w, h = self.width, self.height
        fx = (w / 2.0) / math.tan(math.radians(self.hfov_deg) / 2.0)
        fy = (h / 2.0) / math.tan(math.radians(self.vfov_deg) / 2.0)
        k = 1.0 if unit == "mm" else 0.001
        return DepthCamera(fx, fy, (w - 1) / 2.0, (h - 1) / 2.0, depth_scale=k, min_depth=self.min_mm * k,
                           max_depth=self.max_mm * k)  # fmt: skip

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """(W,) x/z and (H,) y/z of the pixel centres' rays, float32."""
        return _rays(self.width, self.height, self.hfov_deg, self.vfov_deg)

    def measure(self, z: np.ndarray, rng: np.random.Generator, sun=()) -> np.ndarray:
        """The sensor's reading of a true depth image ``z`` (H, W) float32 mm (inf: nothing): uint16
        mm with noise, range limits, random missing readings and sunlight holes (``sun``: the
        persistent blobs present this frame, [(mask, (row0, col0))], see
        :meth:`PedestrianSequence.sun_blobs`; transient ones are drawn here).

        The noise factor 1 + accuracy/2 * g, g ~ N(0, 1) truncated at +-2, is drawn as one byte per
        pixel through a 256-entry table of the truncated normal's quantiles (a 4x faster draw than
        ``standard_normal``; the table's step, 1/64 sigma, is far below the 1 mm rounding)."""
        h, w = z.shape
        n = np.take(_noise_table(self.accuracy), rng.integers(0, 256, (h, w), dtype=np.uint8))
        n *= z
        np.minimum(n, np.float32(self.max_reading_mm + 1.0), out=n)  # inf (nothing) -> out of range
        n += np.float32(0.5)  # round to whole mm on the cast
        n *= (n >= self.min_mm + 0.5) & (n < self.max_reading_mm + 0.5)
        out = n.astype(np.uint16)
        k = int(rng.binomial(h * w, self.dropout)) if self.dropout > 0 else 0
        if k:
            out.reshape(-1)[rng.integers(0, h * w, k)] = 0
        blobs = list(sun) + [_blob(rng, h, w, small=True) for _ in range(int(rng.poisson(self.sun_transient)))]
        for m, (r0, c0) in blobs:
            out[r0:r0 + m.shape[0], c0:c0 + m.shape[1]][m] = 0
        return out


@functools.lru_cache(maxsize=8)
def _noise_table(accuracy: float) -> np.ndarray:
    """(256,) float32 1 + accuracy/2 * q_k, q_k the quantiles (k + 0.5)/256 of N(0, 1) truncated at +-2."""
    from scipy.special import ndtr, ndtri

    lo, hi = ndtr(-2.0), ndtr(2.0)
    q = ndtri(lo + (np.arange(256) + 0.5) / 256.0 * (hi - lo))
    t = (1.0 + accuracy / 2.0 * q).astype(np.float32)
    t.setflags(write=False)
    return t


@functools.lru_cache(maxsize=16)
def _rays(w, h, hfov, vfov):
    tx = math.tan(math.radians(hfov) / 2.0)
    ty = math.tan(math.radians(vfov) / 2.0)
    fx, fy = (w / 2.0) / tx, (h / 2.0) / ty
    xs = ((np.arange(w) - (w - 1) / 2.0) / fx).astype(np.float32)
    ys = ((np.arange(h) - (h - 1) / 2.0) / fy).astype(np.float32)
    xs.setflags(write=False)
    ys.setflags(write=False)
    return xs, ys


def _blob(rng, h, w, small=False):
    """A speckled elliptic blob of missing readings: (mask (bh, bw) bool, (row0, col0)). Radii in
    shares of the image width (persistent: 4-9 %, transient: 1.5-4 %); 85 % of the pixels inside
    are missing. The blob's centre is in the lower two thirds (the floor and the walls)."""
    r = rng.uniform(0.015, 0.04) if small else rng.uniform(0.04, 0.09)
    ru = max(1.0, r * w)
    rv = max(1.0, ru * rng.uniform(0.4, 1.0))
    uc = rng.uniform(0, w)
    vc = rng.uniform(h / 3.0, h)
    r0, r1 = max(0, int(vc - rv)), min(h, int(vc + rv) + 1)
    c0, c1 = max(0, int(uc - ru)), min(w, int(uc + ru) + 1)
    vv = (np.arange(r0, r1, dtype=np.float32)[:, None] - vc) / rv
    uu = (np.arange(c0, c1, dtype=np.float32)[None, :] - uc) / ru
    m = (vv * vv + uu * uu < 1.0) & (rng.random((r1 - r0, c1 - c0), dtype=np.float32) < 0.85)
    return m, (r0, c0)


# -- static scene ----------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Hall:
    """The empty entrance hall (mm, camera coordinates): floor y = camera_height, back wall
    z = back_wall (None: none), ceiling ceiling_height above the floor (None: none), side walls
    x = +-side_walls (None: open)."""

    camera_height: float = 1000.0
    back_wall: float | None = 6000.0
    ceiling_height: float | None = 2800.0
    side_walls: float | None = None

    def __post_init__(self):
        _check_real("camera_height", self.camera_height, 0.0, lo_open=True)
        if self.back_wall is not None:
            _check_real("back_wall", self.back_wall, 0.0, lo_open=True)
        if self.ceiling_height is not None:
            _check_real("ceiling_height", self.ceiling_height, self.camera_height, lo_open=True)
        if self.side_walls is not None:
            _check_real("side_walls", self.side_walls, 0.0, lo_open=True)

    def depth(self, sensor: DepthSensor) -> np.ndarray:
        """(H, W) float32 true depth (mm) of the empty scene, inf where a ray hits nothing. Cached,
        read-only."""
        return _hall_depth(self, sensor.width, sensor.height, sensor.hfov_deg, sensor.vfov_deg)


@functools.lru_cache(maxsize=8)
def _hall_depth(hall, w, h, hfov, vfov):
    xs, ys = _rays(w, h, hfov, vfov)
    x = xs[None, :].astype(np.float64)
    y = ys[:, None].astype(np.float64)
    z = np.full((h, w), np.inf)
    with np.errstate(divide="ignore"):
        floor = np.where(y > 0, hall.camera_height / y, np.inf)  # y = camera_height on the ray t d: t = ch / (y/z)
        z = np.minimum(z, np.broadcast_to(floor, (h, w)))
        if hall.ceiling_height is not None:
            up = hall.ceiling_height - hall.camera_height
            z = np.minimum(z, np.broadcast_to(np.where(y < 0, -up / y, np.inf), (h, w)))
        if hall.side_walls is not None:
            ax = np.abs(x)
            z = np.minimum(z, np.broadcast_to(np.where(ax > 0, hall.side_walls / ax, np.inf), (h, w)))
    if hall.back_wall is not None:
        z = np.minimum(z, hall.back_wall)
    z = z.astype(np.float32)
    z.setflags(write=False)
    return z


# -- people ----------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Pedestrian:
    """One person of a sequence: ``pid``, ``height`` (mm), ``child``, ``bag`` ("none", "hand" or
    "back"), ``group`` (people walking together share one), and per frame ``xz`` (F, 2) the floor
    position (nan while not in the scene), ``heading`` (F,) walking direction (rad, 0 = +x, pi/2 =
    +z), ``phase`` (F,) gait phase (rad) and ``moving`` (F,) bool (False while standing)."""

    pid: int
    height: float
    child: bool
    bag: str
    group: int
    xz: np.ndarray
    heading: np.ndarray
    phase: np.ndarray
    moving: np.ndarray


def _frame_axes(heading):
    f = np.array([math.cos(heading), 0.0, math.sin(heading)])
    lat = np.array([-f[2], 0.0, f[0]])
    up = np.array([0.0, -1.0, 0.0])
    return lat, up, f


def body_ellipsoids(x: float, z: float, height: float, heading: float, phase: float, *, moving: bool = True,
                    bag: str = "none", camera_height: float = 1000.0) -> tuple:  # fmt: skip
    """The body's ellipsoids in camera coordinates (mm) for a person standing at floor point (x, z).

    Returns (centres (P, 3), axes (P, 3, 3) columns = unit axes, semi (P, 3) semi-axis lengths),
    float64 arrays.
    Head, torso, pelvis, legs (swinging +-25 deg with the gait), arms (+-18 deg, opposite), and a
    hand bag or a backpack. Sizes scale with height / 1700 mm.
    """
    if bag not in ("none", "hand", "back"):
        raise ValueError(f"bag: expected 'none', 'hand' or 'back', got {bag!r}")
    if not (math.isfinite(height) and height > 0):
        raise ValueError(f"height: expected a finite number > 0 (mm), got {height!r}")
    s = height / 1700.0
    lat, up, fwd = _frame_axes(heading)
    base = np.array([x, camera_height, z])

    def at(l, h, f):
        return base + l * lat + h * up + f * fwd

    amp_leg = math.radians(25.0) if moving else 0.0
    amp_arm = math.radians(18.0) if moving else 0.0
    cs, ax, sm = [], [], []

    def add(c, theta, semi):
        a2 = math.cos(theta) * up - math.sin(theta) * fwd  # the long axis, tilted forward by theta at the bottom
        a3 = math.sin(theta) * up + math.cos(theta) * fwd
        cs.append(c)
        ax.append(np.stack([lat, a2, a3], axis=1))
        sm.append(semi)

    add(at(0, height - 110 * s, 0), 0.0, (80 * s, 110 * s, 95 * s))  # head
    add(at(0, 0.70 * height, 0), 0.0, (170 * s, 0.15 * height, 105 * s))  # torso
    add(at(0, 0.52 * height, 0), 0.0, (150 * s, 100 * s, 100 * s))  # pelvis
    leg = 0.49 * height
    for side in (-1.0, 1.0):
        th = side * amp_leg * math.sin(phase)
        hip = at(side * 85 * s, 0.50 * height, 0)
        add(hip + (leg / 2) * (-math.cos(th) * up + math.sin(th) * fwd), th, (65 * s, leg / 2, 70 * s))
    arm = 0.40 * height
    for side in (-1.0, 1.0):
        th = -side * amp_arm * math.sin(phase)
        if bag == "hand" and side > 0:
            th *= 0.3
        sh = at(side * 205 * s, 0.81 * height, 0)
        add(sh + (arm / 2) * (-math.cos(th) * up + math.sin(th) * fwd), th, (45 * s, arm / 2, 45 * s))
        if bag == "hand" and side > 0:
            hand = sh + arm * (-math.cos(th) * up + math.sin(th) * fwd)
            add(hand + 70 * lat - 120 * up, 0.0, (60.0, 150.0, 170.0))
    if bag == "back":
        add(at(0, 0.68 * height, -(105 * s + 85)), 0.0, (150.0, 190.0, 85.0))
    return np.array(cs), np.array(ax), np.array(sm, dtype=np.float64)


def _quadrics(centres, axes, semi):
    """M = R diag(1/semi^2) R^T per ellipsoid (P, 3, 3) and the camera-space AABB half extents (P, 3)."""
    m = np.einsum("pij,pj,pkj->pik", axes, 1.0 / semi**2, axes)
    half = np.sqrt(np.einsum("pij,pj->pi", axes**2, semi**2))
    return m, half


_SIGNS = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64)


def _boxes(centres, half, fx, fy, cx, cy, w, h):
    """Image boxes (P, 4) [r0, r1, c0, c1) of the projected 3D AABBs (the projection of a box is the
    hull of its projected corners); empty where behind the camera, the whole image where a box
    straddles the camera plane."""
    corners = centres[:, None, :] + _SIGNS[None] * half[:, None, :]  # (P, 8, 3)
    zc = corners[..., 2]
    front = zc.min(axis=1) > 1.0
    zs = np.where(front[:, None], zc, 1.0)
    u = fx * corners[..., 0] / zs + cx
    v = fy * corners[..., 1] / zs + cy
    out = np.stack([np.floor(v.min(axis=1)), np.ceil(v.max(axis=1)) + 1,
                    np.floor(u.min(axis=1)), np.ceil(u.max(axis=1)) + 1], axis=1)  # fmt: skip
    out = np.clip(out, 0, [h, h, w, w]).astype(np.int64)
    out[~front] = (0, h, 0, w)
    out[zc.max(axis=1) <= 1.0] = 0
    return out


def render_people(sensor: DepthSensor, hall: Hall, people) -> tuple[np.ndarray, np.ndarray, dict]:
    """Render people into the empty scene with hidden-surface removal.

    people: iterable of (pid, (centres, axes, semi)) from :func:`body_ellipsoids`.
    Returns (depth (H, W) float32 true depth mm, inf = nothing; label (H, W) int16 person id, -1 = the
    empty scene; counts {pid: (pixels alone, visible)}).
    """
    bg = hall.depth(sensor)
    h, w = bg.shape
    cam = sensor.camera()
    xs, ys = sensor.rays()
    depth = bg.copy()
    label = np.full((h, w), -1, dtype=np.int16)
    alone = {}
    boxes_of = {}
    for pid, (c, a, s) in people:
        m, half = _quadrics(c, a, s)
        boxes = _boxes(c, half, cam.fx, cam.fy, cam.cx, cam.cy, w, h)
        ok = (boxes[:, 1] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 2])
        if not ok.any():
            alone[pid] = 0
            continue
        R0, C0 = boxes[ok, 0].min(), boxes[ok, 2].min()
        R1, C1 = boxes[ok, 1].max(), boxes[ok, 3].max()
        own = np.full((R1 - R0, C1 - C0), np.inf, dtype=np.float32)
        for p in np.flatnonzero(ok):
            r0, r1, c0, c1 = boxes[p]
            _ellipsoid_depth(own[r0 - R0:r1 - R0, c0 - C0:c1 - C0], xs[c0:c1], ys[r0:r1], m[p], c[p])
        region = depth[R0:R1, C0:C1]
        mine = own < bg[R0:R1, C0:C1]
        alone[pid] = int(np.count_nonzero(mine))
        near = own < region
        region[near] = own[near]
        label[R0:R1, C0:C1][near] = pid
        boxes_of[pid] = (R0, R1, C0, C1)
    counts = {}
    for pid, n in alone.items():
        if n == 0:
            counts[pid] = (0, 0)
            continue
        R0, R1, C0, C1 = boxes_of[pid]
        counts[pid] = (n, int(np.count_nonzero(label[R0:R1, C0:C1] == pid)))
    return depth, label, counts


def _ellipsoid_depth(out, x, y, m, c):
    """Write min(out, depth of the ellipsoid's first hit) for rays (x[None], y[:, None], 1)."""
    # ray t d, d = (x, y, 1): (t d - c)^T M (t d - c) = 1  ->  a t^2 - 2 b t + cc = 0
    m = m.astype(np.float64)
    mc = m @ c
    cc = np.float32(c @ mc - 1.0)
    ax = (m[0, 0] * x * x + 2 * m[0, 2] * x + m[2, 2]).astype(np.float32)
    ay = (m[1, 1] * y * y + 2 * m[1, 2] * y).astype(np.float32)
    bx = (mc[0] * x + mc[2]).astype(np.float32)
    by = (mc[1] * y).astype(np.float32)
    a = np.multiply.outer(np.float32(2 * m[0, 1]) * y, x)
    a += ax[None, :]
    a += ay[:, None]
    b = bx[None, :] + by[:, None]
    disc = b * b
    disc -= a * cc
    hit = disc > 0
    np.maximum(disc, 0, out=disc)
    np.sqrt(disc, out=disc)
    b -= disc
    b /= a  # the nearer root t = (b - sqrt(b^2 - a cc)) / a, computed over the whole box (faster than gathers)
    hit &= b > 0
    np.minimum(out, np.where(hit, b, np.inf), out=out)


# -- frames and sequences ---------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class PedestrianFrame:
    """One frame: the sensor's ``depth`` (H, W) uint16 mm (0 = no reading), the ``label`` image
    (H, W) int16 (person id, -1 = the empty scene; before missing readings), and the ground truth of
    the labelled people (see the module docstring): ``ids`` (K,) int64 ascending, ``position``
    (K, 3) chest-height centre and ``floor`` (K, 3) floor point (mm, camera coordinates),
    ``pixels`` (K,), ``visible`` (K,) int64, ``visibility`` (K,) float64."""

    index: int
    time: float
    depth: np.ndarray
    label: np.ndarray
    ids: np.ndarray
    position: np.ndarray
    floor: np.ndarray
    pixels: np.ndarray
    visible: np.ndarray
    visibility: np.ndarray

    @property
    def in_view(self) -> int:
        """The number of labelled people in this frame."""
        return len(self.ids)


class PedestrianSequence:
    """A simulated sequence (see the module docstring); frames are rendered on demand."""

    def __init__(self, people, frames: int, sensor: DepthSensor, hall: Hall, seed: int, sun, min_visible: float):
        self.people = tuple(people)
        self.frames = frames
        self.sensor = sensor
        self.hall = hall
        self.fps = FPS
        self.seed = seed
        self.min_visible = min_visible
        self._sun = sun  # list of (mask, (r0, c0)) persistent blobs

    def __len__(self) -> int:
        return self.frames

    def __repr__(self) -> str:
        return (f"PedestrianSequence(frames={self.frames}, people={len(self.people)}, "
                f"size={self.sensor.width}x{self.sensor.height}, max_in_view={self.max_in_view})")  # fmt: skip

    @property
    def camera(self) -> DepthCamera:
        """The sensor's intrinsics, mm units (:meth:`DepthSensor.camera`)."""
        return self.sensor.camera()

    def in_view(self, i: int) -> np.ndarray:
        """The ids of the people geometrically in the view in frame i (body centre axis within the
        horizontal field of view widened by 0.6 m (a leg swings 0.35 m ahead of the body, a bag
        sticks out), depth 0.3-5.6 m), occlusion ignored: a cheap superset of the labelled people
        (no rendering)."""
        return np.array([p.pid for p in self.people if _in_view_xz(p.xz[i], self.sensor)], dtype=np.int64)

    @functools.cached_property
    def in_view_counts(self) -> np.ndarray:
        """(frames,) the number of people geometrically in the view (:meth:`in_view`)."""
        return np.array([len(self.in_view(i)) for i in range(self.frames)], dtype=np.int64)

    @property
    def max_in_view(self) -> int:
        """The largest number of people geometrically in the view at once (<= max_in_view asked)."""
        return int(self.in_view_counts.max()) if self.frames else 0

    def _index(self, i):
        n = self.frames
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not -n <= i < n:
            raise IndexError(f"frame index: expected an integer in [-{n}, {n}), got {i!r}")
        return int(i) % n

    def bodies(self, i: int) -> list:
        """[(pid, (centres, axes, semi))] of the people in the scene in frame i (in or out of the view)."""
        i = self._index(i)
        out = []
        for p in self.people:
            if np.isnan(p.xz[i, 0]):
                continue
            x, z = p.xz[i]
            if abs(x) > z * math.tan(math.radians(self.sensor.hfov_deg) / 2) + 1500 or z < 100:
                continue  # far outside the view: skip the rendering
            out.append((p.pid, body_ellipsoids(x, z, p.height, p.heading[i], p.phase[i], moving=bool(p.moving[i]),
                                               bag=p.bag, camera_height=self.hall.camera_height)))  # fmt: skip
        return out

    def sun_blobs(self, rng: np.random.Generator) -> list:
        """The persistent sunlight blobs present in a frame (each with probability
        ``sensor.sun_persistence``): [(mask (h, w) bool, (row0, col0))]."""
        return [b for b in self._sun if rng.random() < self.sensor.sun_persistence]

    def __getitem__(self, i) -> PedestrianFrame:
        i = self._index(i)
        z, label, counts = render_people(self.sensor, self.hall, self.bodies(i))
        rng = np.random.default_rng([self.seed, 0, i])
        depth = self.sensor.measure(z, rng, self.sun_blobs(rng))
        need = self.min_visible * self.sensor.width * self.sensor.height
        by_id = {p.pid: p for p in self.people}
        ids = sorted(pid for pid, (n, v) in counts.items() if v > 0 and v >= need)
        ch = self.hall.camera_height
        pos = np.array([[*(by_id[k].xz[i])] for k in ids], dtype=np.float64).reshape(-1, 2)
        hts = np.array([by_id[k].height for k in ids], dtype=np.float64)
        position = np.stack([pos[:, 0], ch - CHEST * hts, pos[:, 1]], axis=1)
        floor = np.stack([pos[:, 0], np.full(len(ids), ch), pos[:, 1]], axis=1)
        pixels = np.array([counts[k][0] for k in ids], dtype=np.int64)
        visible = np.array([counts[k][1] for k in ids], dtype=np.int64)
        return PedestrianFrame(i, i / self.fps, depth, label, np.array(ids, dtype=np.int64), position, floor,
                               pixels, visible, visible / np.maximum(pixels, 1))  # fmt: skip

    def __iter__(self):
        for i in range(self.frames):
            yield self[i]

    def background(self, n: int = 30) -> np.ndarray:
        """(n, H, W) uint16 frames of the empty scene from the same sensor model (sec. 4.1: the
        background is their per-pixel median)."""
        n = _check_int("n", n, 1)
        z = self.hall.depth(self.sensor)
        out = np.empty((n, *z.shape), dtype=np.uint16)
        for j in range(n):
            rng = np.random.default_rng([self.seed, 1, j])
            out[j] = self.sensor.measure(z, rng, self.sun_blobs(rng))
        return out


def _in_view_xz(xz, sensor: DepthSensor, margin: float = 600.0) -> bool:
    x, z = xz
    if np.isnan(x):
        return False
    return bool(sensor.min_mm <= z <= sensor.max_mm + margin
                and abs(x) < z * math.tan(math.radians(sensor.hfov_deg) / 2) + margin)  # fmt: skip


def _walk(rng, sensor, z_range, speed, stop_prob):
    """One group's path: (start xz, end xz, speed mm/s, stop (path share, seconds) or None)."""
    tx = math.tan(math.radians(sensor.hfov_deg) / 2)
    direction = 1.0 if rng.random() < 0.5 else -1.0
    z0 = rng.uniform(z_range[0] + 200, z_range[1] - 200)
    if rng.random() < 0.25:  # diagonal: towards or away from the camera while crossing
        z1 = rng.uniform(*z_range)
    else:
        z1 = float(np.clip(z0 + rng.normal(0.0, 300.0), *z_range))
    a = np.array([-direction * (z0 * tx + 900.0), z0])
    b = np.array([direction * (z1 * tx + 900.0), z1])
    stop = (rng.uniform(0.3, 0.7), rng.uniform(2.0, 8.0)) if rng.random() < stop_prob else None
    return a, b, rng.uniform(*speed), stop


def _trajectory(a, b, v, stop, t0, frames, fps, offset, height):
    """Per-frame (floor positions (F, 2), heading (F,), gait phase (F,), moving (F,)) of a walk from a
    to b at ``v`` mm/s starting at frame t0 (may be negative), with the optional stop, shifted by
    ``offset`` = (mm to the walker's left, mm ahead); nan outside the walk."""
    t = (np.arange(frames) - t0) / fps  # seconds since the start
    seg = b - a
    length = float(np.linalg.norm(seg))
    u = seg / length
    left = np.array([-u[1], u[0]])
    s = v * t
    moving = np.ones(frames, dtype=bool)
    if stop is not None:
        s_stop = stop[0] * length
        t_stop = s_stop / v
        s = np.where(t < t_stop, v * t, np.where(t < t_stop + stop[1], s_stop, v * (t - stop[1])))
        moving = ~((t >= t_stop) & (t < t_stop + stop[1]))
    s = s + offset[1]
    inside = (s >= 0) & (s <= length) & (t >= 0)
    stride = 1400.0 * height / 1700.0  # one gait cycle (two steps)
    phase = 2 * np.pi * s / stride
    sway = 25.0 * np.sin(phase) * moving
    xz = a[None] + s[:, None] * u[None] + (offset[0] + sway)[:, None] * left[None]
    xz[~inside] = np.nan
    heading = np.full(frames, math.atan2(u[1], u[0]))
    return xz, heading, phase, moving & inside


def pedestrian_sequence(
    rng: np.random.Generator,
    *,
    frames: int = 851,
    people: int = 32,
    max_in_view: int = 5,
    scale: float = 1.0,
    sensor: DepthSensor | None = None,
    hall: Hall | None = None,
    child_share: float = 0.2,
    bag_share: float = 0.3,
    group_share: float = 0.35,
    stop_prob: float = 0.2,
    burstiness: float = 0.6,
    depth_range: tuple[float, float] = (1000.0, 5000.0),
    min_visible: float = 0.002,
) -> PedestrianSequence:
    """Simulate paper 002's data (sec. 5: 851 labelled frames at 5 fps, 0-5 people a frame, 32 people).

    ``people`` people in groups (``group_share`` of the groups have 2-3 people walking side by side);
    each group starts at a random time, placed so that at most ``max_in_view`` people are in the
    view at once (:meth:`PedestrianSequence.in_view`) and each person is in the view in some frame;
    with probability ``burstiness`` a group starts within 4 s of an earlier group (busy periods,
    passing and occlusion). ``scale`` (or a ``sensor``) sets the image size; ``min_visible`` is the
    share of the image's pixels a person must show to be labelled. Raises ValueError when the people
    cannot be placed (too many for ``frames`` and ``max_in_view``).
    """
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng: expected a numpy.random.Generator (np.random.default_rng(seed)), got "
                        f"{type(rng).__name__}")  # fmt: skip
    frames = _check_int("frames", frames, 1)
    people = _check_int("people", people, 0)
    max_in_view = _check_int("max_in_view", max_in_view, 1)
    for name, v in (("child_share", child_share), ("bag_share", bag_share), ("group_share", group_share),
                    ("stop_prob", stop_prob), ("burstiness", burstiness), ("min_visible", min_visible)):  # fmt: skip
        _check_real(name, v, 0.0, 1.0)
    if sensor is None:
        sensor = DepthSensor(scale=scale)
    elif not isinstance(sensor, DepthSensor):
        raise TypeError(f"sensor: expected a DepthSensor, got {type(sensor).__name__}")
    hall = Hall() if hall is None else hall
    if not isinstance(hall, Hall):
        raise TypeError(f"hall: expected a Hall, got {type(hall).__name__}")
    lo, hi = (float(v) for v in depth_range)
    if not sensor.min_mm < lo < hi:
        raise ValueError(f"depth_range: expected min_mm < lo < hi, got {depth_range!r}")

    out: list[Pedestrian] = []
    counts = np.zeros(frames, dtype=np.int64)
    starts: list[float] = []
    pid = group = 0
    while pid < people:
        size = 1
        if rng.random() < group_share:
            size = 2 if rng.random() < 0.8 else 3
        size = min(size, people - pid)
        a, b, v, stop = _walk(rng, sensor, (lo, hi), (900.0, 1400.0), stop_prob)
        members = []
        for k in range(size):
            child = rng.random() < child_share
            height = rng.uniform(1000.0, 1400.0) if child else rng.uniform(1550.0, 1900.0)
            bag = "none" if rng.random() >= bag_share else ("hand" if rng.random() < 0.6 else "back")
            # side by side: alternately 0.6 m to the walker's left and right, a little ahead or behind
            side = 0.0 if k == 0 else (600.0 * ((k + 1) // 2) * (1 if k % 2 else -1))
            members.append((height, child, bag, (side, rng.normal(0.0, 150.0))))
        path_s = float(np.linalg.norm(b - a)) / v + (stop[1] if stop else 0.0)
        dur = int(math.ceil(path_s * FPS)) + 1
        for _attempt in range(400):
            if starts and rng.random() < burstiness:
                t0 = int(round(rng.choice(starts) + rng.uniform(-4.0, 4.0) * FPS))
            else:
                t0 = int(rng.integers(-dur + 2, frames - 2))
            tr = [_trajectory(a, b, v, stop, t0, frames, FPS, off, ht) for ht, _, _, off in members]
            seen = np.array([[_in_view_xz(xz[i], sensor) for i in range(frames)] for xz, *_ in tr])
            if seen.any(axis=1).all() and (counts + seen.sum(axis=0)).max() <= max_in_view:
                break
        else:
            raise ValueError(f"people: could not place {people} people in {frames} frames with at most "
                             f"{max_in_view} in view (placed {pid}); use more frames or fewer people")  # fmt: skip
        counts += seen.sum(axis=0)
        starts.append(t0)
        for (height, child, bag, _), (xz, heading, phase, moving) in zip(members, tr):
            for arr in (xz, heading, phase, moving):
                arr.setflags(write=False)
            out.append(Pedestrian(pid, height, bool(child), bag, group, xz, heading, phase, moving))
            pid += 1
        group += 1

    seed = int(rng.integers(0, 2**63 - 1))
    srng = np.random.default_rng([seed, 2])
    sun = [_blob(srng, sensor.height, sensor.width) for _ in range(sensor.sun_blobs)]
    return PedestrianSequence(out, frames, sensor, hall, seed, sun, float(min_visible))

"""Problem and scene generators shared by the tests, the benchmarks, the tuner and the self-tests.

Each generator takes a seeded ``numpy.random.Generator`` (or builds one from a fixed seed) and
returns host (NumPy) data, so that every caller sees the same problem for the same seed:

- :func:`kalman_tracks`: T constant-velocity tracks with position observations and a set of
  detections (paper 001's filter sizes: n = 6, m = 3);
- :func:`kalman_mixed`: a tiny batch exercising every Kalman op (mask, gain, stereo, gating);
- :func:`pf_scene`: a particle-filter stage of paper 000 (B hypotheses around 10 candidate poses
  of a body-sized surface, N and N' template points, a 640x480 gray + depth frame);
- :func:`template_scene`: a tiny random RGB-D scene for checks of the template ops;
- :func:`lm_body_scene`: the upper-body chain, templates on its parts, a synthetic frame and
  perturbed poses, for a whole RGB-D least-squares solve;
- :func:`lm_batch`, :func:`exponential_fit`: small batched least-squares problems.
"""

from __future__ import annotations

import numpy as np

from ..models.chain import rotation_zyx

__all__ = [
    "exponential_fit",
    "kalman_mixed",
    "kalman_tracks",
    "lm_batch",
    "lm_body_scene",
    "pf_scene",
    "template_scene",
]


# -- Kalman filters ------------------------------------------------------------------------------
def kalman_tracks(T, rng, detections=100):
    """(F, Q, H, R, x (T, 6), P (T, 6, 6), z (T, 3), det (detections, 3)), float32.

    Constant-velocity model at 30 fps (paper 001 eq. 1-3), positions in a 10 x 4 x 18 m volume
    in front of the camera, velocities ~ N(0, 1) m/s, an observation of each track's position
    with 0.2 m noise, and ``detections`` positions drawn uniformly in the same volume (gating)."""
    from ..ops.kalman import constant_velocity

    F, Q = constant_velocity(3, 1.0 / 30, 1.0)
    H = np.zeros((3, 6), np.float32)
    H[0, 0] = H[1, 2] = H[2, 4] = 1
    R = (0.05 * np.eye(3)).astype(np.float32)
    pos = rng.uniform([-5, -2, 2], [5, 2, 20], (T, 3))
    x = np.zeros((T, 6), np.float32)
    x[:, 0::2] = pos
    x[:, 1::2] = rng.normal(0, 1, (T, 3))
    P = np.tile(np.diag([0.1, 1.0] * 3).astype(np.float32), (T, 1, 1))
    z = (pos + rng.normal(0, 0.2, (T, 3))).astype(np.float32)
    det = rng.uniform([-5, -2, 2], [5, 2, 20], (detections, 3)).astype(np.float32)
    return F, Q, H, R, x, P, z, det


def kalman_mixed(rng, T=7, detections=4) -> dict:
    """A tiny batch for every Kalman op: {"F", "Q", "H", "R", "x", "P", "z", "zs", "mask", "gain",
    "det", "f", "b"}: random states with depth x[4] around 5, random SPD covariances, linear
    observations ``z``, stereo observations ``zs`` (u, v, d with focal ``f`` and baseline ``b``),
    a mask that skips every third track and gain scales from 0 to 1.5."""
    from ..ops.kalman import constant_velocity

    n, m = 6, 3
    F, Q = constant_velocity(3, 0.5, 0.2)
    A = rng.standard_normal((T, n, n)).astype(np.float32)
    P = (A @ np.swapaxes(A, 1, 2) / n + np.eye(n)).astype(np.float32)
    x = rng.standard_normal((T, n)).astype(np.float32)
    x[:, 4] += 5.0
    H = np.zeros((m, n), np.float32)
    H[0, 0] = H[1, 2] = H[2, 4] = 1
    R = (0.3 * np.eye(m)).astype(np.float32)
    z = rng.standard_normal((T, m)).astype(np.float32)
    f, b = 400.0, 0.1
    zs = np.stack([f * x[:, 0] / x[:, 4], f * x[:, 2] / x[:, 4], f * b / x[:, 4]], 1).astype(np.float32)
    mask = np.arange(T) % 3 != 1
    gain = np.linspace(0, 1.5, T).astype(np.float32)
    det = rng.standard_normal((detections, m)).astype(np.float32)
    return {"F": F, "Q": Q, "H": H, "R": R, "x": x, "P": P, "z": z, "zs": zs, "mask": mask, "gain": gain,
            "det": det, "f": f, "b": b}  # fmt: skip


# -- sparse templates ----------------------------------------------------------------------------
def _rot(a):
    """Rz(a[2]) Ry(a[1]) Rx(a[0])."""
    return rotation_zyx(a[2], a[1], a[0])


def pf_scene(rng, b=1500, n=128, m=128, *, parts=5, candidates=10, h=480, w=640):
    """(transforms (B, J, 3, 4), rgb template, depth template, gray, depth, camera) of a filter stage.

    A ``w`` x ``h`` gray + depth frame (depth in mm, 5 mm steps, 1% dropouts) of a body-sized
    surface about 2 m away; templates of ``n`` and ``m`` points on ``parts`` parts; ``b``
    hypotheses spread around ``candidates`` candidate poses (paper 000 Table 4 sized noise: a few
    mm, a few degrees), so that neighbouring hypotheses read neighbouring pixels as in a real
    filter stage."""
    from ..models.camera import Camera
    from ..ops.template import SparseTemplate

    cam = Camera(525.0, 525.0, 319.5, 239.5)
    # part frames (camera-from-part) of a person 2 m away: torso, two upper arms, two forearms
    base = np.array([[0, 0, 2000], [-250, -150, 2000], [250, -150, 2000], [-450, -150, 1950], [450, -150, 1950]], float)
    size = np.array([[200, 300], [110, 60], [110, 60], [110, 50], [110, 50]], float)  # half extents (mm)

    def points(k):
        part = rng.integers(0, parts, k)
        xyz = np.column_stack(
            [rng.uniform(-1, 1, k) * size[part, 0], rng.uniform(-1, 1, k) * size[part, 1], rng.uniform(-20, 0, k)]
        )
        return xyz, part

    xyz, part = points(n)
    rgb = SparseTemplate(xyz, part, rng.uniform(30, 220, n))
    xyz, part = points(m)
    dep = SparseTemplate(xyz, part)
    cand = np.zeros((candidates, parts, 3, 4))
    for c in range(candidates):
        for j in range(parts):
            cand[c, j, :, :3] = _rot(rng.normal(0, np.radians(3), 3))
            cand[c, j, :, 3] = base[j] + rng.normal(0, 10, 3)
    owner = np.arange(b) * candidates // b  # the samples of a candidate are consecutive
    tf = cand[owner].copy()
    for k in range(b):
        for j in range(parts):
            tf[k, j, :, :3] = _rot(rng.normal(0, np.radians([1, 3, 1]))) @ tf[k, j, :, :3]
    tf[..., :, 3] += rng.normal(0, 5, (b, parts, 3))
    yy, xx = np.mgrid[0:h, 0:w]
    gray = 110 + 60 * np.sin(xx / 6.0) * np.cos(yy / 8.0) + rng.normal(0, 3, (h, w))
    depth = np.full((h, w), 3000.0) + rng.normal(0, 2, (h, w))
    body = (np.abs(xx - 320) < 180) & (yy > 60) & (yy < 420)
    depth[body] = 2000 + 5 * np.sin(xx[body] / 11.0)
    depth = np.round(depth / 5) * 5  # Kinect-like 5 mm steps
    depth[rng.random((h, w)) < 0.01] = 0  # dropouts
    return tf.astype(np.float32), rgb, dep, gray.astype(np.float32), depth.astype(np.float32), cam


def template_scene(rng, b=7, j=2, n=29, m=23, h=24, w=32):
    """(transforms (b, j, 3, 4), rgb template, depth template, gray, depth, camera): a tiny random
    scene 2 units in front of a 20-pixel-focal camera, with 5% of the depth pixels missing."""
    from ..models.camera import Camera
    from ..ops.template import SparseTemplate

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


# -- least squares -------------------------------------------------------------------------------
def lm_body_scene(P, M, rng, batch=10):
    """(chain, rgb template, depth template, gray, depth, camera, x0 (batch, P)).

    The upper-body chain (P = 14, or 20 with the shoulders), M / 2 RGB and M / 2 depth template
    points on its parts (torso box; arms along x), a synthetic 640x480 frame and ``batch`` poses
    perturbed around the rest pose (0.05 rad, 20 mm, 0.1 rad, 10 mm)."""
    from ..models import upper_body
    from ..models.camera import Camera
    from ..ops.template import SparseTemplate

    chain = upper_body(shoulders=(P == 20))
    n = M // 2
    part = rng.integers(0, 5, 2 * n)
    xyz = np.empty((2 * n, 3))
    torso = part == 0
    xyz[torso] = rng.uniform([-150, -270, -90], [150, 290, 0], (int(torso.sum()), 3))
    arm = ~torso
    length = np.where(part[arm] <= 2, 290.0, 265.0)
    xyz[arm] = np.stack(
        [
            rng.uniform(0, 1, int(arm.sum())) * length,
            rng.uniform(-40, 40, int(arm.sum())),
            rng.uniform(-40, 0, int(arm.sum())),
        ],
        1,
    )
    rgb = SparseTemplate(xyz[:n], part[:n], rng.uniform(20, 230, n))
    dep = SparseTemplate(xyz[n:], part[n:])
    h, w = 480, 640
    yy, xx = np.mgrid[0:h, 0:w]
    gray = (128 + 60 * np.sin(xx / 23.0) * np.cos(yy / 31.0)).astype(np.float32)
    depth = (2000 + 80 * np.sin(xx / 57.0 + yy / 41.0)).astype(np.float32)
    cam = Camera(525.0, 525.0, 319.5, 239.5)
    rest = np.asarray(chain.rest_params(), dtype=np.float64)
    scale = np.r_[[0.05] * 3, [20.0] * 3, [0.1] * 8, [10.0] * (P - 14)]
    x0 = rest[None, :] + rng.normal(0, 1, (batch, P)) * scale[None, :]
    return chain, rgb, dep, gray, depth, cam, x0


def lm_batch(rng, B=3, M=9, P=4, dtype=np.float64):
    """(J (B, M, P), r (B, M), C (B,) = 1e-3): random normal equations for ``lm_solve``."""
    J = rng.normal(size=(B, M, P)).astype(dtype)
    r = rng.normal(size=(B, M)).astype(dtype)
    C = np.full(B, 1e-3, dtype)
    return J, r, C


def exponential_fit(n=12):
    """(residuals(X) for a batch X (B, 2) of (a, b), x0 (3, 2)): fits of y = a exp(b t) to
    y = 2 exp(-1.3 t) on t in [0, 1] from three starting points; ``residuals`` accepts host or
    device arrays and returns host arrays of X's dtype."""
    from ..device import to_numpy

    t = np.linspace(0, 1, n)
    y = 2.0 * np.exp(-1.3 * t)

    def residuals(X):
        Xn = to_numpy(X).astype(np.float64)
        out = Xn[:, :1] * np.exp(Xn[:, 1:2] * t[None, :]) - y[None, :]
        return out.astype(X.dtype)

    return residuals, np.array([[1.0, 0.0], [3.0, -2.0], [1.5, -1.0]])

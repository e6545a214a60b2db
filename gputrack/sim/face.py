"""Paper 003's simulated input: a textured face seen by a monocular camera, with ground truth.

``face_sequence(index_or_name, frames=None, seed=0)`` returns a :class:`FaceSequence`; frames are
rendered on demand (``seq[k]`` or iteration, a :class:`FaceFrame`)::

    from gputrack.sim.face import face_sequence
    seq = face_sequence("turns")              # 300 frames, 640 x 480, 30 fps
    fr = seq[40]                              # fr.gray (480, 640) uint8, fr.rotation, fr.translation,
                                              # fr.landmarks2d (K, 2), fr.visible (K,), fr.shape (K, 3)
    seq.identity, seq.camera, seq.euler       # (100,) ICT identity weights, Camera, (F, 3) deg

**Face** (:mod:`gputrack.models.face`): the ICT face model's V = 1177 mesh vertices of the person's
identity weights (100,) and the frame's expression weights (57,), in the *model frame* (mm; x to
the image's right for a face looking at the camera, y down, z into the head; origin near the
centroid of the K = 10 feature points). The mesh is triangulated once (:func:`face_triangles`):
Delaunay on a cylindrical unwrapping of the ICT neutral face, (s, y) with s = C atan2(x, C - z)
and C = :data:`CYLINDER_MM` (a vertical cylinder through the head, so that the cheeks and ears
at the sides are not folded onto the front), then boundary triangles with an edge longer than
:data:`MAX_EDGE_MM` in 3D are peeled off from the outside in (the outline's concave parts are
not bridged, the sparse neck keeps its interior), and only the largest connected piece is kept.
Every triangle is ordered so that (b - a) x (c - a) points out of the head. The ICT face also
samples the skin that runs into the mouth, the nostrils and under the eyelids; those vertices
(about 330, behind the outer skin seen along the cylinder's radius, :data:`INNER_MM`) are left out
of the about 1700 triangles. The 68-point landmarks 17-67 are added as vertices (:func:`face_vertices`), so
the surface passes through them.

**Pose**: rotation R (3, 3) and translation t (3,) mm map the model frame to the camera frame
(x right, y down, z forward): X_cam = R X_model + t. R = I is a face looking straight into the
camera. Angles (:func:`rotation_from_euler`, :func:`euler_from_rotation`) are in DEGREES, in the
order (roll, pitch, yaw), with R = Rz(roll) @ Ry(yaw) @ Rx(pitch) (right-handed rotations about
the camera axes): yaw > 0 turns the face towards the image's left (the nose tip moves left),
pitch > 0 tilts it down (the face looks down), roll > 0 turns it clockwise in the image. ``rvec``
is the Rodrigues vector of R (axis times angle, radians; :func:`rvec_from_rotation`, the same as
``cv2.Rodrigues``).

**Camera**: :data:`FACE_CAMERA` = Camera(fx = fy = 700, cx = 319.5, cy = 239.5), 640 x 480
pixels (:data:`SIZE`), :data:`FPS` = 30; pixel (u, v) is the centre of column u, row v, and
u = fx X / Z + cx.

**Texture** (:func:`face_texture`, cached per person): albedo in [0, 1] on a grid of
:data:`TEXEL_MM` = 0.5 mm in the person's own neutral (s, y) coordinates, so it moves and deforms
with the mesh: a skin tone with multi-scale noise, freckles and blotches; eye sockets a little
darker; brows, eyes (sclera, iris, pupil, lid lines), nostrils and lips (the inner lip line dark,
so an opened mouth shows a dark opening) drawn at the person's neutral landmark positions
(68-point layout: brows 17-26, eyes 36-47, nose 27-35, lips 48-67). Each level of the texture is
prefiltered for a pixel footprint (:data:`LEVEL_MM`); a frame blends the two levels around its
footprint z / fx (at the face's depth) and looks them up bilinearly.

**Rendering** (:func:`render_face`, :func:`rasterise`): the vertices are projected, back faces
culled, and all front triangles are rasterised at once in NumPy (the scanline span of every row of
every triangle, its pixels enumerated with ``np.repeat``; barycentric coordinates and the inverse
depth, exact for a planar triangle, step along the rows); the nearest fragment of each pixel wins,
the pixels covered more than once resolved by one sort of (pixel, depth) keys: hidden surfaces are
removed (the face occludes itself at large yaw). Shading is Lambertian per vertex,
interpolated over each triangle (Gouraud): albedo (ambient + diffuse max(0, n . l)) with the light
direction l (camera frame, towards the light); the background is a static textured image lit as
a wall facing the camera. A global exposure gain multiplies the image, then Gaussian sensor noise
(seeded; drawn as one random byte per pixel through a table of 256 normal quantiles) is added and
the result rounded to uint8. Cost (NumPy, CPU time of one process on a busy
2-core VM, median over a sequence's frames): 17-21 ms a frame at 600-700 mm, about 25 ms at 400 mm
(rasterisation 6-12 ms of it); building a person's texture takes about 0.25 s (cached).

**Ground truth** (:class:`FaceFrame`): the pose (R, t, rvec, euler), the expression weights, the
K feature points (:data:`gputrack.models.face.LANDMARKS`) as the ICT landmarks of the identity and
expression (``shape``, model frame), in the camera frame (``landmarks3d``) and projected
(``landmarks2d``); ``visible``: inside the image and not hidden by the rendered surface
(:func:`landmark_visibility`). The landmarks 17-67 are vertices of the rendered mesh and the
texture draws the features at their neutral (s, y), so a feature seen in the image sits at its
ground truth at every pose and expression.

**Sequences** (:data:`SEQUENCES`): smooth motion (sums of sinusoids) at 30 fps, 300 frames (10 s)
by default, the face (every landmark and the forehead) always inside the image. The motion is a
function of time only: a shorter sequence is a prefix of a longer one with the same seed. The
first 7 frames are near frontal with a few degrees and millimetres of variation (a tracker's
bundle adjustment starts from them); the sequence's own motion fades in over the next second.

- 0 ``"turns"``: yaw to +-40 deg, pitch +-20, roll +-15, at about 650 mm;
- 1 ``"depth"``: z from 650 to 400 mm, to 900 and back (z = 650 - 250 sin(2 pi t / 10 s)), small turns;
- 2 ``"expressions"``: the mouth stretched, brows raised with the jaw open, smiles, a surprised
  face and blinks (repeating every 10 s), with moderate head motion (yaw +-20, pitch +-10, roll +-8);
- 3 ``"lighting"``: the light's direction sweeps (azimuth +-55 deg, elevation 15-45 deg), its
  intensity (diffuse 0.3-0.8), the ambient light (0.2-0.36) and the exposure (gain 0.88-1.12)
  change, sensor noise sigma 6 gray levels (2 elsewhere), moderate motion;
- 4 ``"mixed"``: all of them: yaw +-40, pitch +-18, roll +-12, z 400-900, expressions, lighting,
  noise sigma 4.

The face is also shifted in the image (up to +-40 px across, +-20 px down; less in the sequences
that come to 400 mm).

The person of a sequence is NEW: identity weights ~ N(0, 1) from
``numpy.random.default_rng((seed, 1003, index))``, not one of the model's 26 people
(``default_rng(0)``); the texture, the background, the motion's phases and the sensor noise come
from generators seeded with ``(seed, 1003, index, j)`` for a fixed j per use (frame k's noise:
``(seed, 1003, index, 2, k)``), so frames can be rendered in any order, twice, with the same result.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from ..models.camera import Camera
from ..models import pose
from ..models.face import LANDMARKS, IctFace, load_ict

__all__ = [
    "CYLINDER_MM",
    "FACE_CAMERA",
    "FPS",
    "INNER_MM",
    "LEVEL_MM",
    "MAX_EDGE_MM",
    "SEQUENCES",
    "SIZE",
    "TEXEL_MM",
    "FaceFrame",
    "FaceSequence",
    "FaceTexture",
    "Fragments",
    "Light",
    "euler_from_rotation",
    "face_sequence",
    "face_texture",
    "face_triangles",
    "face_vertices",
    "landmark_visibility",
    "rasterise",
    "render_face",
    "rotation_from_euler",
    "rotation_from_rvec",
    "rvec_from_rotation",
]

FPS = 30.0
#: (width, height) of the images
SIZE = (640, 480)
#: the default camera: fx = fy = 700 px, principal point at the image centre
FACE_CAMERA = Camera(700.0, 700.0, 319.5, 239.5)
#: names, in index order
SEQUENCES = ("turns", "depth", "expressions", "lighting", "mixed")
#: the axis of the cylindrical unwrapping (triangulation and texture) is x = 0, z = CYLINDER_MM
CYLINDER_MM = 100.0
#: boundary triangles with a 3D edge longer than this are peeled off the triangulation
MAX_EDGE_MM = 30.0
#: a vertex more than this (plus its unwrapped distance) behind another is inside the mouth, nose or eyelids
INNER_MM = 1.0
#: texture grid spacing (mm)
TEXEL_MM = 0.5
#: pixel footprints (mm per pixel) the texture's levels are prefiltered for
LEVEL_MM = (0.5, 1.0, 2.0, 4.0)
#: feature-point depth tolerance (mm) of :func:`landmark_visibility`
VISIBILITY_MM = 3.0
#: frames near frontal at the start of every sequence
INTRO_FRAMES = 7

_K = len(LANDMARKS)
_LM0 = 17  # the landmarks from 17 on (not the jaw outline) are vertices of the rendered mesh
_NLM = 68 - _LM0
_NEAR_MM = 10.0


# -- checks ---------------------------------------------------------------------------------------------
def _real(name: str, value, lo=None, hi=None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name}: expected a real number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v) or (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ValueError(f"{name}: expected a finite number in [{lo}, {hi}], got {value!r}")
    return v


def _array(name: str, value, shape: tuple) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name}: expected a real array of shape {shape}, got {type(value).__name__}") from None
    if a.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: expected finite values, got {a.ravel()[~np.isfinite(a.ravel())][0]}")
    return a


def _rotation(R) -> np.ndarray:
    R = _array("R", R, (3, 3))
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > 1e-6 or np.linalg.det(R) < 0:
        raise ValueError(f"R: expected a rotation matrix (orthonormal, det +1), got one off by {err:.3g}, "
                         f"det {np.linalg.det(R):.3g}")  # fmt: skip
    return R


def _translation(t) -> np.ndarray:
    t = _array("t", t, (3,))
    if t[2] <= _NEAR_MM:
        raise ValueError(f"t: expected the face in front of the camera (t_z > {_NEAR_MM} mm), got t_z = {t[2]}")
    return t


def _camera(camera) -> Camera:
    if camera is None:
        return FACE_CAMERA
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a gputrack.models.Camera, got {type(camera).__name__}")
    return camera


def _size(size) -> tuple[int, int]:
    ok = isinstance(size, (tuple, list)) and len(size) == 2
    ok = ok and all(isinstance(s, (int, np.integer)) and not isinstance(s, bool) and 8 <= s <= 8192 for s in size)
    if not ok:
        raise ValueError(f"size: expected (width, height) integers in [8, 8192], got {size!r}")
    return int(size[0]), int(size[1])


# -- rotations ------------------------------------------------------------------------------------------
def rotation_from_euler(roll, pitch, yaw) -> np.ndarray:
    """R = Rz(roll) @ Ry(yaw) @ Rx(pitch), angles in DEGREES (scalars or arrays that broadcast):
    (..., 3, 3), :func:`gputrack.models.pose.rotation_from_euler` in degrees. About the camera's x
    (right), y (down) and z (forward) axes: yaw > 0 turns the face to the image's left, pitch > 0
    tilts it down, roll > 0 turns it clockwise in the image."""
    return pose.rotation_from_euler(*(np.radians(np.asarray(a, dtype=np.float64)) for a in (roll, pitch, yaw)))


def _rotations(R) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R: expected shape (..., 3, 3), got {R.shape}")
    return R


def euler_from_rotation(R) -> np.ndarray:
    """(..., 3) (roll, pitch, yaw) in DEGREES of rotations (..., 3, 3), the inverse of
    :func:`rotation_from_euler` for |yaw| < 90 deg (yaw in [-90, 90], roll and pitch in (-180, 180])."""
    return np.degrees(pose.euler_from_rotation(_rotations(R)))


def rvec_from_rotation(R) -> np.ndarray:
    """(..., 3) Rodrigues vectors (radians, angle in [0, pi]) of (..., 3, 3) rotations, as ``cv2.Rodrigues``."""
    return pose.rotation_vector(_rotations(R))


def rotation_from_rvec(rvec) -> np.ndarray:
    """(..., 3, 3) rotations of Rodrigues vectors (..., 3) (radians)."""
    r = np.asarray(rvec, dtype=np.float64)
    if r.shape[-1:] != (3,):
        raise ValueError(f"rvec: expected shape (..., 3), got {r.shape}")
    return pose.rodrigues(r)


# -- mesh -----------------------------------------------------------------------------------------------
def _unwrap(points) -> np.ndarray:
    """(..., 2) cylindrical coordinates (s, y) mm of model-frame points (..., 3): s = C atan2(x, C - z)."""
    p = np.asarray(points, dtype=np.float64)
    return np.stack([CYLINDER_MM * np.arctan2(p[..., 0], CYLINDER_MM - p[..., 2]), p[..., 1]], axis=-1)


def _outer(m: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(V,) bool: the vertices on the face's outer surface. The ICT face also samples the surfaces
    that run into the mouth, the nostrils and under the eyelids; seen along the cylinder's radius
    they lie behind the outer skin. A vertex is inner when another vertex at unwrapped distance d
    lies more than :data:`INNER_MM` + d (a slope of 45 deg) further out."""
    from scipy.spatial import cKDTree

    r = np.hypot(m[:, 0], CYLINDER_MM - m[:, 2])  # distance from the cylinder's axis
    tree = cKDTree(uv)
    pairs = tree.sparse_distance_matrix(tree, 12.0, output_type="ndarray")
    i, j, d = pairs["i"], pairs["j"], pairs["v"]
    inner = np.zeros(len(m), dtype=bool)
    inner[i[r[j] - r[i] > INNER_MM + d]] = True
    return ~inner


@functools.lru_cache(maxsize=4)
def _triangulate(neutral_bytes: bytes, forced: int) -> np.ndarray:
    """The triangulation of the neutral render vertices; the vertices from row ``forced`` on (the
    landmarks) are always used."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import Delaunay

    m_all = np.frombuffer(neutral_bytes, dtype=np.float64).reshape(-1, 3)
    uv_all = _unwrap(m_all)
    outer = _outer(m_all, uv_all)
    outer[forced:] = True
    near = np.linalg.norm(uv_all[:forced, None] - uv_all[None, forced:], axis=2).min(axis=1) < 0.5
    outer[:forced][near] = False  # a mesh vertex on a landmark (some coincide) gives way to it
    used = np.flatnonzero(outer)
    m, uv = m_all[used], uv_all[used]
    d = Delaunay(uv)
    tri, nb = d.simplices.astype(np.int64), d.neighbors
    edge = np.stack([np.linalg.norm(m[tri[:, i]] - m[tri[:, (i + 1) % 3]], axis=1) for i in range(3)], 1).max(1)
    alive = np.ones(len(tri), dtype=bool)
    while True:  # peel long boundary triangles from the outside in
        boundary = alive & ((nb < 0) | ~alive[np.maximum(nb, 0)]).any(axis=1)
        peel = boundary & (edge > MAX_EDGE_MM)
        if not peel.any():
            break
        alive &= ~peel
    keep = np.flatnonzero(alive)
    i, j = np.repeat(keep, 3), nb[keep].ravel()
    i, j = i[(j >= 0) & alive[np.maximum(j, 0)]], j[(j >= 0) & alive[np.maximum(j, 0)]]
    n = len(tri)
    _, label = connected_components(coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)), directed=False)
    main = np.bincount(label[keep]).argmax()
    tri = tri[keep[label[keep] == main]]
    a, b, c = uv[tri[:, 0]], uv[tri[:, 1]], uv[tri[:, 2]]
    ccw = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0] > 0
    tri[ccw] = tri[ccw][:, [0, 2, 1]]  # clockwise in (s, y) (y down): the 3D normal points out of the head
    n3 = np.cross(m[tri[:, 1]] - m[tri[:, 0]], m[tri[:, 2]] - m[tri[:, 0]])
    radial = m[tri].mean(axis=1) - np.array([0.0, 0.0, CYLINDER_MM])
    radial[:, 1] = 0.0
    if np.einsum("ij,ij->i", n3, radial).mean() < 0:  # the unwrapping's orientation, checked once
        tri = tri[:, [0, 2, 1]]
    tri = used[tri]
    tri.setflags(write=False)
    return tri


def face_vertices(ict: IctFace, identity, expression) -> np.ndarray:
    """(V + 51, 3) mm, model frame: the vertices the simulator renders, the ICT face mesh's V = 1177
    and the 68-point landmarks 17-67 (brows, nose, eyes, lips; landmark k is row V + k - 17), so that
    the rendered surface passes through every feature point."""
    return np.concatenate([ict.mesh(identity, expression), ict.landmarks(identity, expression)[..., _LM0:, :]], -2)


def _expression_part(ict: IctFace, expression) -> np.ndarray:
    """(V + 51, 3): the expression's displacement of :func:`face_vertices`."""
    e = np.asarray(expression, dtype=np.float64)
    return np.concatenate([np.einsum("e,evc->vc", e, ict.expression_mesh),
                           np.einsum("e,evc->vc", e, ict.expression_lm[:, _LM0:])])  # fmt: skip


def face_triangles(ict: IctFace) -> np.ndarray:
    """(T, 3) int64 rows of :func:`face_vertices` of the rendered triangles (about 1700; see the
    module docstring), each ordered so that (b - a) x (c - a) points out of the head. Read-only,
    cached."""
    neutral = np.concatenate([ict.neutral_mesh, ict.neutral_lm[_LM0:]])
    return _triangulate(np.ascontiguousarray(neutral, dtype=np.float64).tobytes(), ict.neutral_mesh.shape[0])


def _vertex_normals(verts: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(V, 3) unit outward normals: the area-weighted sum of the adjacent triangles' normals."""
    fn = np.cross(verts[tri[:, 1]] - verts[tri[:, 0]], verts[tri[:, 2]] - verts[tri[:, 0]])
    idx = tri.ravel()
    vn = np.stack([np.bincount(idx, np.repeat(fn[:, k], 3), minlength=len(verts)) for k in range(3)], axis=1)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


# -- rasterisation -------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, eq=False)
class Fragments:
    """The visible surface of a rasterised mesh: one fragment per covered pixel.

    pixel (n,) int64 flat index v W + u; triangle (n,) int64 row of ``triangles``; bary (n, 3)
    float32 barycentric weights of the triangle's vertices a, b, c; depth (n,) float32 mm (camera z).
    """

    pixel: np.ndarray
    triangle: np.ndarray
    bary: np.ndarray
    depth: np.ndarray

    def depth_image(self, size) -> np.ndarray:
        """(H, W) float32 depth (mm), inf where no surface."""
        w, h = size
        out = np.full(h * w, np.inf, dtype=np.float32)
        out[self.pixel] = self.depth
        return out.reshape(h, w)


def rasterise(points, triangles, camera: Camera, size=SIZE) -> Fragments:
    """Rasterise the triangles (T, 3) of camera-frame vertices ``points`` (V, 3) mm with a z-buffer.

    Front faces only (a triangle is front-facing when its image vertices run clockwise on the
    screen, i.e. its outward normal (b - a) x (c - a) faces the camera); triangles with a vertex
    nearer than 10 mm are dropped. Scanline spans: every row of every triangle's bounding box is
    cut with the triangle's edges, and the pixel centres within the span (widened by 1e-6 px, so
    that a centre on a shared edge is covered twice, never missed) are enumerated at once with
    ``np.repeat`` (no loop over triangles or pixels); barycentric coordinates and the inverse depth
    1/z (affine on the screen, exact for a planar triangle) step along each row; the nearest
    fragment of each pixel covered more than once is found by sorting int64 keys (pixel, depth,
    fragment). Fragments come in no particular pixel order.
    """
    w_img, h_img = _size(size)
    P = np.asarray(points, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    if P.ndim != 2 or P.shape[1] != 3 or tri.ndim != 2 or tri.shape[1] != 3:
        raise ValueError(f"points, triangles: expected shapes (V, 3) and (T, 3), got {P.shape} and {tri.shape}")
    z = P[:, 2]
    zs = np.where(z > _NEAR_MM, z, 1.0)
    u = camera.fx * P[:, 0] / zs + camera.cx
    v = camera.fy * P[:, 1] / zs + camera.cy
    ua, ub, uc = u[tri[:, 0]], u[tri[:, 1]], u[tri[:, 2]]
    va, vb, vc = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    D = (ub - ua) * (vc - va) - (vb - va) * (uc - ua)  # twice the signed image area; < 0: front
    v0 = np.maximum(np.ceil(np.minimum(np.minimum(va, vb), vc)), 0)
    v1 = np.minimum(np.floor(np.maximum(np.maximum(va, vb), vc)), h_img - 1)
    near = (z[tri] > _NEAR_MM).all(axis=1)
    umin = np.minimum(np.minimum(ua, ub), uc)
    umax = np.maximum(np.maximum(ua, ub), uc)
    ok = np.flatnonzero((D < -1e-9) & near & (v1 >= v0) & (umax >= 0) & (umin <= w_img - 1))
    if ok.size == 0:
        return _no_fragments()
    ua, ub, uc, va, vb, vc, D, v0 = ua[ok], ub[ok], uc[ok], va[ok], vb[ok], vc[ok], D[ok], v0[ok]
    # the rows: one per triangle and pixel row of its bounding box, cut by the long edge (top -> bottom
    # vertex) and the short edge beside it (top -> middle above the middle vertex, middle -> bottom below)
    nrow = (v1[ok] - v0 + 1).astype(np.int64)
    r_tri = np.repeat(np.arange(ok.size), nrow)
    vrow = np.repeat(v0, nrow) + (np.arange(r_tri.size) - np.repeat(np.cumsum(nrow) - nrow, nrow))
    us, vs = np.stack([ua, ub, uc], 1), np.stack([va, vb, vc], 1)
    by_v = np.argsort(vs, axis=1)
    (ut, um, ud), (vt, vm, vd) = np.take_along_axis(us, by_v, 1).T, np.take_along_axis(vs, by_v, 1).T

    def slope(du, dv):
        return np.where(dv > 0, du / np.where(dv > 0, dv, 1.0), 0.0)

    rep_row = functools.partial(np.repeat, repeats=nrow)
    long_edge = rep_row(ut) + (vrow - rep_row(vt)) * rep_row(slope(ud - ut, vd - vt))
    upper = vrow < rep_row(vm)
    short_edge = np.where(upper, rep_row(ut) + (vrow - rep_row(vt)) * rep_row(slope(um - ut, vm - vt)),
                          rep_row(um) + (vrow - rep_row(vm)) * rep_row(slope(ud - um, vd - vm)))  # fmt: skip
    lo, hi = np.minimum(long_edge, short_edge), np.maximum(long_edge, short_edge)
    u_start = np.maximum(np.ceil(lo - 1e-6), 0)
    cnt = np.maximum(np.minimum(np.floor(hi + 1e-6), w_img - 1) - u_start + 1, 0).astype(np.int64)
    n = int(cnt.sum())
    if n == 0:
        return _no_fragments()
    # barycentric weights la, lb of vertices a, b and the inverse depth, affine on the screen: at each
    # row's first pixel and their step per pixel
    Di = 1.0 / D
    ka_u, ka_v = (vb - vc) * Di, (uc - ub) * Di
    kb_u, kb_v = (vc - va) * Di, (ua - uc) * Di
    ia, ib, ic = (1.0 / zs[tri[ok, k]] for k in range(3))
    du = u_start - uc[r_tri]
    dvr = vrow - vc[r_tri]
    la0 = ka_u[r_tri] * du + ka_v[r_tri] * dvr
    lb0 = kb_u[r_tri] * du + kb_v[r_tri] * dvr
    step_i = (ia - ic) * ka_u + (ib - ic) * kb_u
    i0 = ic[r_tri] + (ia - ic)[r_tri] * la0 + (ib - ic)[r_tri] * lb0
    rep = functools.partial(np.repeat, repeats=cnt)
    col = (np.arange(n, dtype=np.int32) - rep((np.cumsum(cnt) - cnt).astype(np.int32))).astype(np.float32)
    la = rep(la0.astype(np.float32)) + rep(ka_u[r_tri].astype(np.float32)) * col
    lb = rep(lb0.astype(np.float32)) + rep(kb_u[r_tri].astype(np.float32)) * col
    inv = rep(i0.astype(np.float32)) + rep(step_i[r_tri].astype(np.float32)) * col
    pix = rep((vrow * w_img + u_start).astype(np.int64)) + col.astype(np.int64)
    eps = np.float32(1e-3)  # the spans are exact up to rounding: this drops only numerical strays
    keep = np.flatnonzero((la >= -eps) & (lb >= -eps) & (la + lb <= 1 + eps))
    if keep.size < n:
        la, lb, inv, pix = la[keep], lb[keep], inv[keep], pix[keep]
        frag_row = rep(np.arange(r_tri.size))[keep]
    else:
        frag_row = None
    order = _nearest_per_pixel(pix, inv, h_img * w_img)
    t_row = rep(r_tri)[order] if frag_row is None else r_tri[frag_row[order]]
    bary = np.empty((order.size, 3), dtype=np.float32)
    bary[:, 0] = la[order]
    bary[:, 1] = lb[order]
    bary[:, 2] = 1 - bary[:, 0] - bary[:, 1]
    return Fragments(pix[order], ok[t_row], bary, (1.0 / inv[order]).astype(np.float32))


def _no_fragments() -> Fragments:
    e = np.zeros(0, dtype=np.int64)
    return Fragments(e, e.copy(), np.zeros((0, 3), np.float32), np.zeros(0, np.float32))


def _nearest_per_pixel(pix: np.ndarray, inv: np.ndarray, pixels: int) -> np.ndarray:
    """Indices of the fragments with the largest inverse depth ``inv`` of each pixel (z-buffer): the
    pixels with one fragment directly (in their order), then the others, found by one sort of int64
    keys (pixel, quantised depth, fragment index), or a lexsort when those do not fit in 63 bits."""
    many = np.bincount(pix, minlength=pixels)[pix] > 1
    single = np.flatnonzero(~many)
    multi = np.flatnonzero(many)
    if multi.size == 0:
        return single
    mp, mi = pix[multi], inv[multi].astype(np.float64)
    n = multi.size
    bp = max(1, int(pixels - 1).bit_length())
    bi = max(1, int(n - 1).bit_length())
    bd = 63 - bp - bi
    if bd < 16:
        order = np.lexsort((-mi, mp))
        ps = mp[order]
    else:
        lo, hi = float(mi.min()), float(mi.max())
        scale = (2**bd - 1) / (hi - lo) if hi > lo else 0.0
        q = ((hi - mi) * scale).astype(np.int64)  # 0: nearest
        key = np.sort((mp << (bd + bi)) | (q << bi) | np.arange(n, dtype=np.int64))
        order = key & ((1 << bi) - 1)
        ps = key >> (bd + bi)
    first = np.ones(n, dtype=bool)
    first[1:] = ps[1:] != ps[:-1]
    return np.concatenate([single, multi[order[first]]])


# -- texture --------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, eq=False)
class FaceTexture:
    """A person's albedo texture (see the module docstring).

    levels: tuple of (Ht, Wt) float32 albedo in [0, 1], level i prefiltered for a pixel footprint
    of :data:`LEVEL_MM` [i] mm; origin (s0, y0) mm: the unwrapped coordinates of texel [0, 0]'s
    centre; texel: mm per texel; coords (V, 2): the mesh vertices' (s, y) mm (the person's neutral
    mesh unwrapped, :func:`face_triangles`' cylinder); landmarks (68, 2): the person's neutral
    landmarks' (s, y) mm, where the features are drawn.
    """

    levels: tuple
    origin: tuple
    texel: float
    coords: np.ndarray
    landmarks: np.ndarray
    _cache: dict = dataclasses.field(default_factory=dict, repr=False)

    def sample(self, st, footprint_mm: float = TEXEL_MM) -> np.ndarray:
        """Albedo (n,) float32 at unwrapped coordinates ``st`` (n, 2) mm, bilinear, on the texture
        prefiltered for ``footprint_mm`` (the size of a pixel on the face; :meth:`level`); clamped
        at the edges."""
        st = np.asarray(st, dtype=np.float32)
        return self.sample_st(st[:, 0].copy(), st[:, 1].copy(), footprint_mm)

    def sample_st(self, s: np.ndarray, y: np.ndarray, footprint_mm: float = TEXEL_MM) -> np.ndarray:
        """:meth:`sample` of the coordinates as two float32 arrays (n,) (overwritten)."""
        tex = self.level(footprint_mm)
        h, w = tex.shape
        s -= np.float32(self.origin[0])
        s *= np.float32(1.0 / self.texel)
        y -= np.float32(self.origin[1])
        y *= np.float32(1.0 / self.texel)
        np.clip(s, 0, w - 1.001, out=s)
        np.clip(y, 0, h - 1.001, out=y)
        x0 = s.astype(np.int32)
        y0 = y.astype(np.int32)
        s -= x0  # the fractions
        y -= y0
        flat = tex.ravel()
        i = y0 * np.int32(w) + x0
        a, b = flat[i], flat[i + 1]
        i += np.int32(w)
        c, d = flat[i], flat[i + 1]
        b -= a
        b *= s
        a += b  # top row
        d -= c
        d *= s
        c += d  # bottom row
        c -= a
        c *= y
        a += c
        return a

    def level(self, footprint_mm: float) -> np.ndarray:
        """(Ht, Wt) float32: the texture prefiltered for a pixel footprint of ``footprint_mm``, blended
        between the two nearest :data:`LEVEL_MM` levels in steps of 1/8 octave (cached)."""
        f = math.log2(max(float(footprint_mm), LEVEL_MM[0]) / LEVEL_MM[0])
        f = min(round(f * 8) / 8, len(self.levels) - 1.0)
        out = self._cache.get(f)
        if out is None:
            k = int(f)
            lo = self.levels[k]
            out = lo if f == k else lo + np.float32(f - k) * (self.levels[k + 1] - lo)
            out.setflags(write=False)
            if len(self._cache) >= 4:
                self._cache.pop(next(iter(self._cache)))
            self._cache[f] = out
        return out


def face_texture(ict: IctFace, identity, seed=0) -> FaceTexture:
    """The procedural texture of the person with identity weights (100,), drawn with
    ``numpy.random.default_rng(seed)`` (``seed``: anything ``default_rng`` takes). Cached (the last
    8 persons): the same identity and seed give the same (read-only) texture object."""
    identity = _array("identity", identity, (ict.identity_modes,))
    neutral = np.zeros(len(ict.expression_names))
    coords = _unwrap(face_vertices(ict, identity, neutral))
    lm = _unwrap(ict.landmarks(identity, neutral))
    seed_key = tuple(int(s) for s in np.atleast_1d(np.asarray(seed, dtype=np.int64)).ravel())
    return _texture_cached(coords.tobytes(), lm.tobytes(), seed_key)


@functools.lru_cache(maxsize=8)
def _texture_cached(coords_bytes: bytes, lm_bytes: bytes, seed: tuple) -> FaceTexture:
    coords = np.frombuffer(coords_bytes, dtype=np.float64).reshape(-1, 2).copy()
    lm = np.frombuffer(lm_bytes, dtype=np.float64).reshape(-1, 2).copy()
    rng = np.random.default_rng(seed)
    lo = np.floor(coords.min(axis=0) / TEXEL_MM) * TEXEL_MM - 8.0
    hi = coords.max(axis=0) + 8.0
    w, h = (np.ceil((hi - lo) / TEXEL_MM)).astype(int) + 1
    tex = _skin(rng, h, w)
    grid = _Grid(tuple(lo), TEXEL_MM, tex)
    _draw_features(grid, lm, rng)
    levels = _levels(np.clip(tex, 0.0, 1.0))
    for a in (coords, lm):
        a.setflags(write=False)
    return FaceTexture(levels, (float(lo[0]), float(lo[1])), TEXEL_MM, coords, lm)


def _smooth_noise(rng, shape, sigma) -> np.ndarray:
    """(h, w) float32 unit-std Gaussian noise smoothed with a Gaussian of ``sigma`` texels; a wide one
    is made on a grid ``sigma / 2`` times coarser and interpolated bilinearly."""
    from scipy.ndimage import gaussian_filter

    h, w = shape
    f = max(1, int(sigma // 2))
    n = gaussian_filter(rng.standard_normal((h // f + 3, w // f + 3)).astype(np.float32), sigma / f, mode="reflect")
    if f > 1:
        for axis, size in ((0, h), (1, w)):  # bilinear: linear along each axis in turn
            x = (np.arange(size, dtype=np.float32) + 0.5) / f + 0.5
            i = x.astype(np.int64)
            frac = (x - i).reshape((-1, 1) if axis == 0 else (1, -1))
            a, b = np.take(n, i, axis=axis), np.take(n, i + 1, axis=axis)
            n = a + frac * (b - a)
    else:
        n = n[:h, :w]
    return n / max(float(n.std()), 1e-12)


def _skin(rng, h, w) -> np.ndarray:
    """(h, w) float32 skin albedo: a tone and multi-scale noise (30, 6, 2 and 0.6 mm) with freckles
    and blotches (darker discs of 0.5-2.5 mm)."""
    tone = rng.uniform(0.5, 0.72)
    s = TEXEL_MM
    tex = np.full((h, w), tone, dtype=np.float32)
    for sigma_mm, amp in ((30.0, 0.035), (6.0, 0.03), (2.0, 0.035), (0.6, 0.03)):
        tex += np.float32(amp * tone / 0.6) * _smooth_noise(rng, (h, w), sigma_mm / s)
    spots = int(rng.integers(300, 700))
    r = rng.uniform(0.5, 2.5, spots) / s
    cy, cx = rng.uniform(0, h, spots), rng.uniform(0, w, spots)
    dark = rng.uniform(0.04, 0.14, spots) * tone
    ri = int(np.ceil(r.max())) + 1
    oy, ox = np.mgrid[-ri:ri + 1, -ri:ri + 1]
    Y = np.clip(np.floor(cy)[:, None, None] + oy, 0, h - 1).astype(np.int64)
    X = np.clip(np.floor(cx)[:, None, None] + ox, 0, w - 1).astype(np.int64)
    d = np.hypot(Y - cy[:, None, None], X - cx[:, None, None])
    a = np.clip(r[:, None, None] + 0.5 - d, 0.0, 1.0) * dark[:, None, None]
    np.subtract.at(tex, (Y.ravel(), X.ravel()), a.ravel().astype(np.float32))
    return tex


def _levels(tex: np.ndarray) -> tuple:
    """The texture prefiltered for pixel footprints :data:`LEVEL_MM` (Gaussian, sigma 0.4 footprint)."""
    from scipy.ndimage import gaussian_filter

    out = []
    for f in LEVEL_MM:
        sigma = math.sqrt(max(0.0, (0.4 * f) ** 2 - (0.4 * LEVEL_MM[0]) ** 2)) / TEXEL_MM
        lev = gaussian_filter(tex, sigma, mode="nearest") if sigma > 0 else tex.copy()
        lev = lev.astype(np.float32)
        lev.setflags(write=False)
        out.append(lev)
    return tuple(out)


@dataclasses.dataclass(frozen=True, eq=False)
class _Grid:
    """Paint on a texture (h, w) whose texel [0, 0] is at ``origin`` (s, y) mm."""

    origin: tuple
    texel: float
    tex: np.ndarray

    def window(self, lo, hi):
        """(slices, points (n, 2) mm) of the texels in the box [lo, hi] (mm), clipped to the texture."""
        h, w = self.tex.shape
        c0, r0 = np.maximum(np.floor((np.asarray(lo) - self.origin) / self.texel).astype(int), 0)
        c1, r1 = np.minimum(np.ceil((np.asarray(hi) - self.origin) / self.texel).astype(int) + 1, (w, h))
        sl = (slice(r0, max(r0, r1)), slice(c0, max(c0, c1)))
        ys = self.origin[1] + self.texel * np.arange(sl[0].start, sl[0].stop)
        xs = self.origin[0] + self.texel * np.arange(sl[1].start, sl[1].stop)
        X, Y = np.meshgrid(xs, ys)
        return sl, np.stack([X.ravel(), Y.ravel()], axis=1)

    def paint(self, sl, alpha, value) -> None:
        """Blend ``value`` (scalar or per texel) in with coverage ``alpha`` (n,) in [0, 1]."""
        patch = self.tex[sl]
        a = np.clip(alpha, 0.0, 1.0).reshape(patch.shape).astype(np.float32)
        val = np.broadcast_to(np.asarray(value, dtype=np.float32).reshape(-1), a.size).reshape(patch.shape)
        patch += a * (val - patch)


def _segment_distance(p: np.ndarray, poly: np.ndarray, closed: bool) -> np.ndarray:
    """(n,) distance of points (n, 2) to a polyline (m, 2) (closed: the last point joins the first)."""
    a = poly if closed else poly[:-1]
    b = np.roll(poly, -1, axis=0) if closed else poly[1:]
    ab = b - a
    t = np.clip(np.einsum("nmk,mk->nm", p[:, None, :] - a[None], ab) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
    q = a[None] + t[..., None] * ab[None]
    return np.sqrt(((p[:, None, :] - q) ** 2).sum(-1)).min(axis=1)


def _inside(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(n,) bool: points (n, 2) inside the closed polygon (m, 2) (even-odd rule)."""
    a, b = poly, np.roll(poly, -1, axis=0)
    x, y = p[:, 0:1], p[:, 1:2]
    cross = (a[None, :, 1] > y) != (b[None, :, 1] > y)
    xi = a[None, :, 0] + (y - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / np.where(
        b[:, 1] == a[:, 1], 1e-12, b[:, 1] - a[:, 1])[None]  # fmt: skip
    return ((cross & (x < xi)).sum(axis=1) % 2) == 1


def _box(points, margin):
    return points.min(axis=0) - margin, points.max(axis=0) + margin


def _fill(grid: _Grid, poly, value, soft=0.4, margin=2.0, scale=1.0) -> None:
    """A filled polygon with an anti-aliased edge ``soft`` mm wide; ``value`` may be a callable of the
    points (n, 2) giving per-texel values; ``scale`` multiplies the coverage."""
    sl, p = grid.window(*_box(poly, margin + soft))
    d = _segment_distance(p, poly, closed=True)
    sd = np.where(_inside(p, poly), -d, d)
    alpha = scale * np.clip(0.5 - sd / soft, 0.0, 1.0)
    grid.paint(sl, alpha, value(p) if callable(value) else value)


def _stroke(grid: _Grid, line, width, value, soft=0.4, closed=False) -> None:
    """A polyline ``width`` mm wide (scalar, or per vertex (m,) interpolated along the line); ``value``
    as in :func:`_fill`."""
    width = np.broadcast_to(np.asarray(width, dtype=np.float64), (len(line),))
    sl, p = grid.window(*_box(line, width.max() + soft))
    a = line if closed else line[:-1]
    b = np.roll(line, -1, axis=0) if closed else line[1:]
    wa = width if closed else width[:-1]
    wb = np.roll(width, -1) if closed else width[1:]
    ab = b - a
    t = np.clip(np.einsum("nmk,mk->nm", p[:, None, :] - a[None], ab) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
    d = np.sqrt(((p[:, None, :] - (a[None] + t[..., None] * ab[None])) ** 2).sum(-1))
    half = 0.5 * (wa[None] + t * (wb - wa)[None])
    alpha = np.clip((half - d) / soft + 0.5, 0.0, 1.0).max(axis=1)
    grid.paint(sl, alpha, value(p) if callable(value) else value)


def _blob(grid: _Grid, centre, radii, strength) -> None:
    """Darken by a Gaussian blob: tex *= 1 - strength exp(-|(p - centre) / radii|^2 / 2)."""
    radii = np.asarray(radii, dtype=np.float64)
    sl, p = grid.window(centre - 3 * radii, centre + 3 * radii)
    g = np.exp(-0.5 * (((p - centre) / radii) ** 2).sum(axis=1))
    grid.tex[sl] *= (1.0 - strength * g).reshape(grid.tex[sl].shape).astype(np.float32)


def _draw_features(grid: _Grid, lm: np.ndarray, rng) -> None:
    """Brows, eye sockets, eyes, nostrils and lips at the neutral landmarks ``lm`` (68, 2) (s, y) mm."""
    skin = float(np.median(grid.tex))
    # eye sockets and the shadow under the brows (Haar-like contrast: the eye band darker than the cheeks)
    for eye in (lm[36:42], lm[42:48]):
        c = eye.mean(axis=0)
        _blob(grid, c + (0.0, -2.0), (13.0, 8.0), rng.uniform(0.12, 0.2))
    # brows: a band along 17-21 / 22-26, thick at the inner end, hairy (fine noise)
    brow = rng.uniform(0.15, 0.4) * skin / 0.6
    for line in (lm[17:22], lm[22:27][::-1]):  # from the outer end to the inner end
        width = np.linspace(rng.uniform(2.5, 3.5), rng.uniform(5.0, 7.0), len(line))
        _stroke(grid, line + (0.0, 1.0), width, lambda p: brow * (1.0 + 0.3 * rng.standard_normal(len(p))))
    # eyes: sclera in the lid polygon, iris and pupil, lash line on the upper lid, a thin lower lid line
    iris = rng.uniform(0.12, 0.4)
    for eye in (lm[36:42], lm[42:48]):
        c = eye.mean(axis=0)
        _fill(grid, eye, 0.78 * min(1.0, skin / 0.55), soft=0.3)
        sl, p = grid.window(c - 7.0, c + 7.0)
        inside = _inside(p, eye).astype(np.float64)
        ring = np.hypot(*(p - c).T)
        grid.paint(sl, inside * np.clip(5.6 - ring, 0, 1), iris)
        grid.paint(sl, inside * np.clip(2.4 - ring, 0, 1), 0.04)
        grid.paint(sl, inside * np.clip(1.2 - np.hypot(*(p - c - (1.2, -1.2)).T), 0, 1), 0.9)  # catch light
        _stroke(grid, eye[[0, 1, 2, 3]], (0.8, 1.6, 1.6, 0.7), 0.06)
        _stroke(grid, eye[[3, 4, 5, 0]], 0.5, 0.6 * skin)
    # nose: nostrils between the alar points and the tip, a shadowed nose base
    nose = 0.05 + 0.06 * rng.random()
    for al, mid in ((lm[31], lm[32]), (lm[35], lm[34])):
        c = 0.55 * al + 0.45 * mid + (0.0, -1.2)
        sl, p = grid.window(c - 5.0, c + 5.0)
        e = np.hypot((p[:, 0] - c[0]) / 3.2, (p[:, 1] - c[1]) / 1.8)
        grid.paint(sl, np.clip((1.0 - e) * 4.0, 0, 1), nose)
    _blob(grid, lm[33] + (0.0, 2.0), (11.0, 3.0), 0.12)
    # lips: the outer lip polygon darker, the inner line dark (an opened mouth shows it), darker corners
    lip = skin * rng.uniform(0.62, 0.8)
    _fill(grid, lm[48:60], lip, soft=0.6)
    inner = lm[[60, 61, 62, 63, 64, 65, 66, 67]]
    _stroke(grid, inner, 2.2, 0.07, closed=True, soft=0.8)
    for k in (48, 54):
        _blob(grid, lm[k], (2.5, 2.0), 0.35)


# -- background -----------------------------------------------------------------------------------------
def _background(rng, size) -> np.ndarray:
    """(H, W) float32 reflectance in [0.05, 0.95]: multi-scale noise (sigma 1.5, 6, 25 and 80 px) and a
    few soft-edged textured rectangles (a static room behind the person)."""
    w, h = size
    bg = np.full((h, w), rng.uniform(0.35, 0.55), dtype=np.float32)
    for sigma, amp in ((80.0, 0.1), (25.0, 0.07), (6.0, 0.05), (1.5, 0.035)):
        bg += np.float32(amp) * _smooth_noise(rng, (h, w), sigma)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    for _ in range(int(rng.integers(3, 7))):
        x0, y0 = rng.uniform(-0.2, 1.0) * w, rng.uniform(-0.2, 1.0) * h
        x1, y1 = x0 + rng.uniform(0.1, 0.5) * w, y0 + rng.uniform(0.1, 0.5) * h
        a = np.clip(np.minimum.reduce([xx - x0, x1 - xx, yy - y0, y1 - yy]) / 2.0 + 0.5, 0.0, 1.0)
        bg += a * np.float32(rng.uniform(-0.15, 0.15))
    return np.clip(bg, 0.05, 0.95)


# -- rendering ------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Light:
    """A directional light in the camera frame: ``direction`` (3,) towards the light (normalised
    here; (0, 0, -1) shines from the camera), ``diffuse`` and ``ambient`` intensities. A surface of
    albedo a and unit normal n has radiance a (ambient + diffuse max(0, n . l))."""

    direction: tuple = (0.35, -0.45, -0.82)
    diffuse: float = 0.65
    ambient: float = 0.35

    def __post_init__(self):
        d = _array("Light.direction", self.direction, (3,))
        norm = float(np.linalg.norm(d))
        if norm < 1e-9:
            raise ValueError(f"Light.direction: expected a non-zero vector, got {tuple(d)}")
        object.__setattr__(self, "direction", tuple(float(x) for x in d / norm))
        object.__setattr__(self, "diffuse", _real("Light.diffuse", self.diffuse, 0.0, 10.0))
        object.__setattr__(self, "ambient", _real("Light.ambient", self.ambient, 0.0, 10.0))


def render_face(ict: IctFace, identity, expression, R, t, camera: Camera | None = None, *, light: Light | None = None,
                gain: float = 1.0, noise: float = 0.0, rng: np.random.Generator | None = None,
                texture: FaceTexture | None = None, background=None, size=SIZE) -> tuple[np.ndarray, np.ndarray]:
    """Render the face of identity weights (100,) and expression weights (57,) at pose (R, t)
    (model -> camera, mm) with ``camera`` (default :data:`FACE_CAMERA`) into an image of ``size``
    (width, height).

    Returns (gray (H, W) uint8, depth (H, W) float32 mm: the face's camera z, inf where the
    background shows). ``light``: :class:`Light` (default ``Light()``); ``gain``: exposure,
    multiplies the radiance (1.0: radiance 1 is 255); ``noise``: std of the Gaussian sensor noise
    in gray levels, drawn from ``rng`` (required when noise > 0); ``texture``: the person's
    :class:`FaceTexture` (default ``face_texture(ict, identity)``); ``background``: (H, W)
    reflectance in [0, 1] lit as a wall facing the camera (default a uniform 0.4).
    """
    gray, depth, _ = _render(ict, identity, expression, R, t, camera, light, gain, noise, rng, texture, background,
                             size)  # fmt: skip
    return gray, depth


@functools.lru_cache(maxsize=1)
def _normal_table() -> np.ndarray:
    """(256,) float32 standard normal quantiles at (i + 0.5) / 256, scaled to unit std: sensor noise
    drawn as one random byte per pixel (ten times faster than ``standard_normal``)."""
    from scipy.special import ndtri

    q = ndtri((np.arange(256) + 0.5) / 256.0)
    out = (q / q.std()).astype(np.float32)
    out.setflags(write=False)
    return out


def _render(ict, identity, expression, R, t, camera, light, gain, noise, rng, texture, background, size, base=None):
    """render_face, also returning the camera-frame vertices (V, 3); ``base``: the person's neutral
    vertices (V + 51, 3), ``face_vertices(ict, identity, 0)``, when the caller has them."""
    if not isinstance(ict, IctFace):
        raise TypeError(f"ict: expected an IctFace (gputrack.models.face.load_ict), got {type(ict).__name__}")
    camera = _camera(camera)
    w, h = _size(size)
    identity = _array("identity", identity, (ict.identity_modes,))
    expression = _array("expression", expression, (len(ict.expression_names),))
    R, t = _rotation(R), _translation(t)
    light = Light() if light is None else light
    if not isinstance(light, Light):
        raise TypeError(f"light: expected a Light, got {type(light).__name__}")
    gain = _real("gain", gain, 0.0, 100.0)
    noise = _real("noise", noise, 0.0, 255.0)
    if noise > 0 and not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng: expected a numpy.random.Generator when noise > 0, got {type(rng).__name__}")
    texture = face_texture(ict, identity) if texture is None else texture
    if not isinstance(texture, FaceTexture) or texture.coords.shape != (ict.neutral_mesh.shape[0] + _NLM, 2):
        raise TypeError(f"texture: expected a FaceTexture of this model's mesh, got {type(texture).__name__}")
    if background is None:
        bg = np.full((h, w), 0.4, dtype=np.float32)
    else:
        bg = np.asarray(background, dtype=np.float32)
        if bg.shape != (h, w):
            raise ValueError(f"background: expected shape {(h, w)}, got {bg.shape}")
    tri = face_triangles(ict)
    model = face_vertices(ict, identity, expression) if base is None else base + _expression_part(ict, expression)
    verts = model @ R.T + t
    frag = rasterise(verts, tri, camera, (w, h))
    l = np.asarray(light.direction)
    shade_v = light.ambient + light.diffuse * np.maximum(_vertex_normals(model, tri) @ (R.T @ l), 0.0)
    # (s, y, shade) per fragment: each triangle's attributes are affine in its barycentric weights,
    # attribute = A_c + (A_a - A_c) la + (A_b - A_c) lb
    A = np.concatenate([texture.coords, shade_v[:, None]], axis=1).T.astype(np.float32)  # (3, V)
    Aa, Ab, Ac = A[:, tri[:, 0]], A[:, tri[:, 1]], A[:, tri[:, 2]]
    g = np.take(np.concatenate([Ac, Aa - Ac, Ab - Ac]), frag.triangle, axis=1)  # (9, n)
    la, lb = np.ascontiguousarray(frag.bary[:, 0]), np.ascontiguousarray(frag.bary[:, 1])
    s_, y_, shade = (g[j] + g[3 + j] * la + g[6 + j] * lb for j in range(3))
    albedo = texture.sample_st(s_, y_, footprint_mm=float(t[2]) / camera.fx)
    wall = light.ambient + light.diffuse * max(0.0, -l[2])
    img = bg * np.float32(255.0 * gain * wall)
    albedo *= shade
    albedo *= np.float32(255.0 * gain)
    img.reshape(-1)[frag.pixel] = albedo
    if noise > 0:
        img += np.take(_normal_table() * np.float32(noise), rng.integers(0, 256, (h, w), dtype=np.uint8))
    np.clip(img + np.float32(0.5), 0.0, 255.0, out=img)
    return img.astype(np.uint8), frag.depth_image((w, h)), verts


def landmark_visibility(points, depth, camera: Camera, tol: float = VISIBILITY_MM) -> np.ndarray:
    """(K,) bool: camera-frame points (K, 3) mm on the rendered surface (vertices of
    :func:`face_vertices`) that are inside the image (projection within [0, W - 1] x [0, H - 1]) and
    not hidden: z <= ``tol`` mm + the farthest rendered depth of the 3 x 3 pixels around the
    projection (a point in a crease, e.g. an eye corner, is seen in a dip of the surface a pixel
    wide; an occluder, e.g. the nose in front of the far eye, covers all nine pixels)."""
    p = _array("points", points, np.shape(points))
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points: expected shape (K, 3), got {p.shape}")
    h, w = depth.shape
    z = p[:, 2]
    zs = np.where(z > _NEAR_MM, z, 1.0)
    u = camera.fx * p[:, 0] / zs + camera.cx
    v = camera.fy * p[:, 1] / zs + camera.cy
    ok = (z > _NEAR_MM) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    ui = np.clip(np.rint(u), 0, w - 1).astype(np.int64)
    vi = np.clip(np.rint(v), 0, h - 1).astype(np.int64)
    farthest = np.full(len(p), -np.inf)
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            farthest = np.maximum(farthest, depth[np.clip(vi + dv, 0, h - 1), np.clip(ui + du, 0, w - 1)])
    return ok & (z <= farthest + tol)


# -- sequences ------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class _Script:
    """One named sequence's motion: (amplitude deg, period s) of yaw, pitch and roll; depth (centre mm,
    amplitude mm, period s, random phase: else z = centre - amplitude sin(2 pi t / period)); the image
    shift (amplitude px, period s) in u and v; expressions, lighting changes, sensor noise (gray levels)."""

    yaw: tuple
    pitch: tuple
    roll: tuple
    depth: tuple
    shift_u: tuple = (40.0, 6.7)
    shift_v: tuple = (20.0, 5.3)
    expressions: bool = False
    lighting: bool = False
    noise: float = 2.0


_SCRIPTS = {
    "turns": _Script(yaw=(40.0, 4.0), pitch=(20.0, 3.0), roll=(15.0, 5.0), depth=(650.0, 40.0, 7.0, True)),
    "depth": _Script(yaw=(10.0, 4.4), pitch=(6.0, 3.3), roll=(5.0, 5.6), depth=(650.0, 250.0, 10.0, False),
                     shift_u=(30.0, 6.7), shift_v=(15.0, 5.3)),
    "expressions": _Script(yaw=(20.0, 4.6), pitch=(10.0, 3.4), roll=(8.0, 5.8), depth=(600.0, 50.0, 8.0, True),
                           expressions=True),
    "lighting": _Script(yaw=(20.0, 4.2), pitch=(10.0, 3.6), roll=(8.0, 6.2), depth=(650.0, 60.0, 7.5, True),
                        lighting=True, noise=6.0),
    "mixed": _Script(yaw=(40.0, 5.0), pitch=(18.0, 3.2), roll=(12.0, 6.4), depth=(650.0, 250.0, 9.0, False),
                     shift_u=(30.0, 6.7), shift_v=(15.0, 5.3), expressions=True, lighting=True, noise=4.0),
}

#: the expression script (repeats every :data:`EXPRESSION_PERIOD` s): (centre s, half width s, weights)
EXPRESSION_EVENTS = (
    (1.6, 0.7, {"mouthStretch_L": 1.0, "mouthStretch_R": 1.0}),
    (3.2, 0.8, {"browInnerUp_L": 1.0, "browInnerUp_R": 1.0, "browOuterUp_L": 1.0, "browOuterUp_R": 1.0,
                "jawOpen": 0.8}),
    (4.9, 0.8, {"mouthSmile_L": 1.0, "mouthSmile_R": 1.0, "cheekSquint_L": 0.4, "cheekSquint_R": 0.4}),
    (6.6, 0.8, {"eyeWide_L": 0.7, "eyeWide_R": 0.7, "browInnerUp_L": 0.8, "browInnerUp_R": 0.8,
                "browOuterUp_L": 0.6, "browOuterUp_R": 0.6, "jawOpen": 0.5}),
    (8.3, 0.8, {"mouthSmile_L": 0.8, "mouthStretch_R": 0.6, "browDown_L": 0.6, "browDown_R": 0.6}),
    (0.95, 0.12, {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0}),
    (2.45, 0.12, {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0}),
    (4.05, 0.12, {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0}),
    (5.75, 0.12, {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0}),
    (7.45, 0.12, {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0}),
    (9.3, 0.12, {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0}),
)
EXPRESSION_PERIOD = 10.0


def _ramp(t: np.ndarray, fps: float) -> np.ndarray:
    """0 for the first :data:`INTRO_FRAMES` frames, then a smoothstep to 1 over one second."""
    x = np.clip((t - INTRO_FRAMES / fps) / 1.0, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _wave(t, amplitude, period, phase):
    return amplitude * np.sin(2.0 * np.pi * t / period + phase)


def _expressions(ict: IctFace, t: np.ndarray) -> np.ndarray:
    """(F, 57) weights of :data:`EXPRESSION_EVENTS` at times t: raised-cosine bumps, summed, clipped to [0, 1]."""
    tau = np.mod(t, EXPRESSION_PERIOD)[:, None]
    out = np.zeros((len(t), len(ict.expression_names)))
    for centre, half, weights in EXPRESSION_EVENTS:
        x = np.clip(np.abs(tau - centre) / half, 0.0, 1.0)
        out += 0.5 * (1.0 + np.cos(np.pi * x)) * ict.expression(weights)[None]
    return np.clip(out, 0.0, 1.0)


def _motion(script: _Script, t: np.ndarray, fps: float, camera: Camera, rng) -> dict:
    """The per-frame pose, light and exposure of a script at times t (s)."""
    ramp = _ramp(t, fps)
    fade = 1.0 - ramp
    ph = rng.uniform(0.0, 2.0 * np.pi, 16)
    angles = []
    for k, ((amp, period), intro) in enumerate(zip((script.roll, script.pitch, script.yaw), (2.0, 3.0, 4.0))):
        angles.append(ramp * _wave(t, amp, period, ph[k]) + fade * _wave(t, intro, 0.8 + 0.15 * k, ph[3 + k]))
    mid, amp, period, random_phase = script.depth
    z = mid + ramp * _wave(t, amp, period, ph[6]) if random_phase else mid - _wave(t, amp, period, 0.0)
    z = z + fade * _wave(t, 8.0, 0.9, ph[7])
    du = ramp * _wave(t, *script.shift_u, ph[8]) + fade * _wave(t, 4.0, 1.0, ph[9])
    dv = ramp * _wave(t, *script.shift_v, ph[10]) + fade * _wave(t, 3.0, 1.1, ph[11])
    translation = np.stack([du * z / camera.fx, dv * z / camera.fy, z], axis=1)
    n = len(t)
    if script.lighting:
        az = np.radians(_wave(t, 55.0, 7.0, ph[12]))
        el = np.radians(30.0 + _wave(t, 15.0, 5.1, ph[13]))
        direction = np.stack([np.sin(az) * np.cos(el), -np.sin(el), -np.cos(az) * np.cos(el)], axis=1)
        diffuse = 0.55 + _wave(t, 0.25, 4.3, ph[14])
        ambient = 0.28 + _wave(t, 0.08, 6.1, ph[15])
        gain = 1.0 + _wave(t, 0.12, 3.7, ph[0] + ph[1])
    else:
        direction = np.tile(np.asarray(Light().direction), (n, 1))
        diffuse, ambient, gain = np.full(n, Light().diffuse), np.full(n, Light().ambient), np.ones(n)
    return {"euler": np.stack(angles, axis=1), "translation": translation, "direction": direction,
            "diffuse": diffuse, "ambient": ambient, "gain": gain}


@dataclasses.dataclass(frozen=True, eq=False)
class FaceFrame:
    """One rendered frame and its ground truth (see the module docstring).

    gray (H, W) uint8; depth (H, W) float32 mm of the face (inf: background); rotation (3, 3),
    translation (3,) mm: model -> camera; rvec (3,) rad (Rodrigues); euler (3,) deg (roll, pitch,
    yaw); expression (57,) ICT weights; shape (K, 3) mm: the K feature points in the model frame
    (identity and expression applied); landmarks3d (K, 3) mm: R shape + t (camera frame);
    landmarks2d (K, 2) px: their projection; visible (K,) bool (:func:`landmark_visibility`);
    light (3,): the light's direction (camera frame, towards the light), diffuse, ambient, gain.
    """

    index: int
    time: float
    gray: np.ndarray
    depth: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    rvec: np.ndarray
    euler: np.ndarray
    expression: np.ndarray
    shape: np.ndarray
    landmarks3d: np.ndarray
    landmarks2d: np.ndarray
    visible: np.ndarray
    light: np.ndarray
    diffuse: float
    ambient: float
    gain: float


class FaceSequence:
    """A simulated face sequence (see the module docstring): ground truth for every frame as arrays,
    frames rendered on demand (``seq[k]``, iteration), deterministic from the seed.

    Arrays (F = len(seq)): ``rotation`` (F, 3, 3), ``translation`` (F, 3) mm, ``euler`` (F, 3) deg
    (roll, pitch, yaw), ``rvec`` (F, 3), ``expression`` (F, 57), ``shapes`` (F, K, 3) model frame,
    ``landmarks3d`` (F, K, 3), ``landmarks2d`` (F, K, 2); the lighting: ``light`` (F, 3), ``diffuse``,
    ``ambient``, ``gain`` (F,); ``noise`` (gray levels). The person: ``identity`` (100,) ICT weights,
    ``texture``; ``camera``, ``size`` (640, 480), ``fps`` 30.
    """

    def __init__(self, index: int, frames: int, seed: int, ict: IctFace, camera: Camera):
        self.index, self.name = index, SEQUENCES[index]
        self.seed = seed
        self.ict = ict
        self.camera = camera
        self.size = SIZE
        self.fps = FPS
        script = _SCRIPTS[self.name]
        self.noise = script.noise
        self.identity = np.random.default_rng((seed, 1003, index)).standard_normal(ict.identity_modes)
        t = np.arange(frames) / self.fps
        m = _motion(script, t, self.fps, camera, np.random.default_rng((seed, 1003, index, 3)))
        self.times = t
        self.euler = m["euler"]
        self.rotation = rotation_from_euler(*self.euler.T)
        self.rvec = rvec_from_rotation(self.rotation)
        self.translation = m["translation"]
        self.light, self.diffuse, self.ambient, self.gain = m["direction"], m["diffuse"], m["ambient"], m["gain"]
        n_exp = len(ict.expression_names)
        self.expression = _expressions(ict, t) if script.expressions else np.zeros((frames, n_exp))
        self.shapes = ict.landmarks(self.identity, self.expression)[:, list(LANDMARKS)]
        self.landmarks3d = np.einsum("fij,fkj->fki", self.rotation, self.shapes) + self.translation[:, None, :]
        p = self.landmarks3d
        self.landmarks2d = np.stack([camera.fx * p[..., 0] / p[..., 2] + camera.cx,
                                     camera.fy * p[..., 1] / p[..., 2] + camera.cy], axis=-1)  # fmt: skip
        for a in (self.identity, self.times, self.euler, self.rotation, self.rvec, self.translation, self.light,
                  self.diffuse, self.ambient, self.gain, self.expression, self.shapes, self.landmarks3d,
                  self.landmarks2d):  # fmt: skip
            a.setflags(write=False)
        self._base = face_vertices(ict, self.identity, np.zeros(n_exp))

    def __len__(self) -> int:
        return len(self.times)

    def __repr__(self) -> str:
        return f"FaceSequence({self.index} {self.name!r}, frames={len(self)}, seed={self.seed})"

    @functools.cached_property
    def texture(self) -> FaceTexture:
        """The person's texture (:func:`face_texture` with seed ``(seed, 1003, index, 0)``)."""
        return face_texture(self.ict, self.identity, seed=(self.seed, 1003, self.index, 0))

    @functools.cached_property
    def background(self) -> np.ndarray:
        """(H, W) float32 reflectance of the static background."""
        bg = _background(np.random.default_rng((self.seed, 1003, self.index, 1)), self.size)
        bg.setflags(write=False)
        return bg

    def vertices(self, k: int) -> np.ndarray:
        """(V + 51, 3) mm: the rendered vertices (:func:`face_vertices`) of frame k in the camera frame."""
        k = self._frame(k)
        model = self._base + _expression_part(self.ict, self.expression[k])
        return model @ self.rotation[k].T + self.translation[k]

    def _frame(self, k) -> int:
        n = len(self)
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
            raise TypeError(f"frame index: expected an integer, got {type(k).__name__}")
        if not -n <= k < n:
            raise IndexError(f"frame index: expected an integer in [-{n}, {n}), got {k}")
        return int(k) % n

    def __getitem__(self, k) -> FaceFrame:
        k = self._frame(k)
        light = Light(tuple(self.light[k]), float(self.diffuse[k]), float(self.ambient[k]))
        rng = np.random.default_rng((self.seed, 1003, self.index, 2, k))
        gray, depth, _ = _render(self.ict, self.identity, self.expression[k], self.rotation[k], self.translation[k],
                                 self.camera, light, float(self.gain[k]), self.noise, rng, self.texture,
                                 self.background, self.size, base=self._base)  # fmt: skip
        visible = landmark_visibility(self.landmarks3d[k], depth, self.camera)
        return FaceFrame(k, float(self.times[k]), gray, depth, self.rotation[k].copy(), self.translation[k].copy(),
                         self.rvec[k].copy(), self.euler[k].copy(), self.expression[k].copy(), self.shapes[k].copy(),
                         self.landmarks3d[k].copy(), self.landmarks2d[k].copy(), visible, self.light[k].copy(),
                         float(self.diffuse[k]), float(self.ambient[k]), float(self.gain[k]))  # fmt: skip

    def __iter__(self):
        for k in range(len(self)):
            yield self[k]


def _sequence_index(index_or_name) -> int:
    if isinstance(index_or_name, str):
        if index_or_name not in SEQUENCES:
            raise ValueError(f"sequence: expected one of {', '.join(SEQUENCES)}, got {index_or_name!r}")
        return SEQUENCES.index(index_or_name)
    if isinstance(index_or_name, bool) or not isinstance(index_or_name, (int, np.integer)):
        raise TypeError(f"sequence: expected a name ({', '.join(SEQUENCES)}) or an index, "
                        f"got {type(index_or_name).__name__}")  # fmt: skip
    if not 0 <= index_or_name < len(SEQUENCES):
        raise ValueError(f"sequence index: expected 0..{len(SEQUENCES) - 1}, got {index_or_name}")
    return int(index_or_name)


def face_sequence(index_or_name, *, frames: int | None = None, seed: int = 0, ict: IctFace | None = None,
                  camera: Camera | None = None) -> FaceSequence:  # fmt: skip
    """Sequence ``index_or_name`` (0..4 or a name in :data:`SEQUENCES`) of ``frames`` frames (default
    300: 10 s at 30 fps) of a new person drawn with ``seed`` (an int >= 0). ``ict``: the face data
    (default :func:`gputrack.models.face.load_ict`, which raises FileNotFoundError where it is
    absent); ``camera``: default :data:`FACE_CAMERA` (another camera keeps the motion in mm, so the
    face may leave the image)."""
    index = _sequence_index(index_or_name)
    frames = 300 if frames is None else frames
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)):
        raise TypeError(f"frames: expected an integer, got {type(frames).__name__}")
    if not 1 <= frames <= 1_000_000:
        raise ValueError(f"frames: expected an integer in [1, 1000000], got {frames}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed: expected an integer, got {type(seed).__name__}")
    if seed < 0:
        raise ValueError(f"seed: expected an integer >= 0, got {seed}")
    if ict is None:
        ict = load_ict()
    elif not isinstance(ict, IctFace):
        raise TypeError(f"ict: expected an IctFace (gputrack.models.face.load_ict), got {type(ict).__name__}")
    return FaceSequence(index, int(frames), int(seed), ict, _camera(camera))

"""Paper 003's simulator (gputrack.sim.face): rotations, the rasteriser, the rendered face and the
sequences' ground truth (host code, no device)."""

import itertools

import numpy as np
import pytest

from gputrack.models import Camera
from gputrack.models.face import LANDMARKS, sample_people
from gputrack.sim.face import (
    FACE_CAMERA,
    INTRO_FRAMES,
    SEQUENCES,
    SIZE,
    euler_from_rotation,
    face_sequence,
    face_texture,
    face_triangles,
    face_vertices,
    landmark_visibility,
    rasterise,
    render_face,
    rotation_from_euler,
    rotation_from_rvec,
    rvec_from_rotation,
)


@pytest.fixture(scope="module")
def turns(ict):
    return face_sequence("turns", ict=ict)


def project(p, cam=FACE_CAMERA):
    p = np.asarray(p, dtype=np.float64)
    return np.stack([cam.fx * p[..., 0] / p[..., 2] + cam.cx, cam.fy * p[..., 1] / p[..., 2] + cam.cy], axis=-1)


def frontal(ict, seq, z, expression=None):
    """A frontal render of the sequence's person at depth z (mm), with its texture and background."""
    e = np.zeros(len(ict.expression_names)) if expression is None else expression
    t = np.array([0.0, 0.0, z])
    gray, depth = render_face(ict, seq.identity, e, np.eye(3), t, texture=seq.texture, background=seq.background,
                              noise=2.0, rng=np.random.default_rng(0))  # fmt: skip
    pts = ict.landmarks(seq.identity, e)[list(LANDMARKS)] + t
    return gray, depth, pts


# -- rotations ---------------------------------------------------------------------------------------------
def test_euler_convention_and_round_trip():
    R = rotation_from_euler(10.0, -20.0, 30.0)
    def c(a):
        return np.cos(np.radians(a))

    def s(a):
        return np.sin(np.radians(a))

    Rz = np.array([[c(10), -s(10), 0], [s(10), c(10), 0], [0, 0, 1]])
    Ry = np.array([[c(30), 0, s(30)], [0, 1, 0], [-s(30), 0, c(30)]])
    Rx = np.array([[1, 0, 0], [0, c(-20), -s(-20)], [0, s(-20), c(-20)]])
    np.testing.assert_allclose(R, Rz @ Ry @ Rx, atol=1e-12)
    nose = np.array([0.0, 0.0, -30.0])  # in front of the face (model z points into the head)
    assert (rotation_from_euler(0, 0, 20) @ nose)[0] < 0  # yaw > 0: the nose moves to the image's left
    assert (rotation_from_euler(0, 20, 0) @ nose)[1] > 0  # pitch > 0: the face looks down
    assert (rotation_from_euler(20, 0, 0) @ np.array([0.0, -100.0, 0.0]))[0] > 0  # roll > 0: clockwise
    rng = np.random.default_rng(1)
    angles = np.stack([rng.uniform(-170, 170, 50), rng.uniform(-170, 170, 50), rng.uniform(-85, 85, 50)], 1)
    Rs = rotation_from_euler(*angles.T)
    assert Rs.shape == (50, 3, 3)
    np.testing.assert_allclose(euler_from_rotation(Rs), angles, atol=1e-9)
    np.testing.assert_allclose(np.einsum("nji,njk->nik", Rs, Rs), np.broadcast_to(np.eye(3), (50, 3, 3)), atol=1e-12)


def test_rodrigues_round_trip_and_opencv():
    rng = np.random.default_rng(2)
    axes = rng.standard_normal((40, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi - 0.01, 36), [0.0, 1e-9, np.pi - 1e-5, np.pi]])
    rvec = axes * angles[:, None]
    R = rotation_from_rvec(rvec)
    back = rvec_from_rotation(R)
    np.testing.assert_allclose(rotation_from_rvec(back), R, atol=1e-9)
    np.testing.assert_allclose(back[:37], rvec[:37], atol=1e-9)
    cv2 = pytest.importorskip("cv2")
    for r in R[:10]:
        np.testing.assert_allclose(rvec_from_rotation(r), cv2.Rodrigues(r)[0].ravel(), atol=1e-9)


# -- rasteriser --------------------------------------------------------------------------------------------
def test_rasterise_coverage_depth_and_culling():
    cam = Camera(100.0, 100.0, 0.0, 0.0)
    # a triangle in the plane z = 100 covering image x in [10, 20], y in [10, 20] below the diagonal;
    # clockwise on the screen (y down), so front-facing
    tri = np.array([[0, 2, 1]])
    far = np.array([[10.0, 10.0, 100.0], [20.0, 10.0, 100.0], [10.0, 20.0, 100.0]])
    f = rasterise(far, tri, cam, (32, 24))
    u, v = f.pixel % 32, f.pixel // 32
    expect = {(x, y) for x in range(10, 21) for y in range(10, 21) if (x - 10) + (y - 10) <= 10}
    assert set(zip(u.tolist(), v.tolist())) == expect
    np.testing.assert_allclose(f.depth, 100.0, rtol=1e-5)
    np.testing.assert_allclose(f.bary.sum(axis=1), 1.0, atol=1e-5)
    assert (f.bary > -1e-3).all()
    # the reversed order faces away: culled
    assert rasterise(far, tri[:, ::-1], cam, (32, 24)).pixel.size == 0
    # a nearer, larger triangle in front wins everywhere it covers
    near = np.array([[5.0, 5.0, 50.0], [15.0, 5.0, 50.0], [5.0, 15.0, 50.0]])  # image x, y in [10, 30]
    both = rasterise(np.concatenate([far, near]), np.array([[0, 2, 1], [3, 5, 4]]), cam, (32, 24))
    assert len(np.unique(both.pixel)) == len(both.pixel)
    d = both.depth_image((32, 24))
    assert d[12, 12] == pytest.approx(50.0) and d[19, 11] == pytest.approx(50.0)  # the near one in front
    assert np.isinf(d[0, 0]) and np.isinf(d[23, 31])
    # barycentric weights interpolate the vertices: u at a fragment equals the pixel column
    corners = np.array([[0, 2, 1], [3, 5, 4]])[both.triangle]
    uu = (both.bary * project(np.concatenate([far, near]), cam)[corners, 0]).sum(axis=1)
    np.testing.assert_allclose(uu, both.pixel % 32, atol=1e-3)


def test_triangulation_is_one_outward_piece(ict):
    tri = face_triangles(ict)
    verts = face_vertices(ict, np.zeros(100), np.zeros(57))
    assert verts.shape == (ict.neutral_mesh.shape[0] + 51, 3)
    np.testing.assert_allclose(verts[-51:], ict.neutral_lm[17:])
    assert tri.ndim == 2 and tri.shape[1] == 3 and 1000 < len(tri) < 3000
    assert np.isin(np.arange(ict.neutral_mesh.shape[0], len(verts)), tri).all()  # every landmark 17-67 is used
    n = np.cross(verts[tri[:, 1]] - verts[tri[:, 0]], verts[tri[:, 2]] - verts[tri[:, 0]])
    front = (verts[tri].mean(axis=1)[:, 2] < 20) & (np.abs(verts[tri].mean(axis=1)[:, 0]) < 40)
    assert (n[front, 2] < 0).mean() > 0.95  # the front of the face faces the camera (-z)


# -- rendering ---------------------------------------------------------------------------------------------
def test_render_is_deterministic_and_the_face_covers_its_feature_points(ict, turns):
    a = face_sequence(0, frames=12, ict=ict)[10]
    b = face_sequence(0, frames=12, ict=ict)[10]
    np.testing.assert_array_equal(a.gray, b.gray)
    np.testing.assert_array_equal(a.depth, b.depth)
    c = turns[10]  # a longer sequence with the same seed: the same frame
    np.testing.assert_array_equal(a.gray, c.gray)
    d = face_sequence(0, frames=12, seed=1, ict=ict)[10]
    assert not np.array_equal(a.gray, d.gray)
    assert a.gray.shape == (480, 640) and a.gray.dtype == np.uint8
    assert a.depth.shape == (480, 640) and a.depth.dtype == np.float32
    for f in (a, turns[60], turns[150]):
        uv = np.rint(f.landmarks2d).astype(int)
        z = f.depth[uv[:, 1], uv[:, 0]]
        assert np.isfinite(z[f.visible]).all()  # the rendered face covers its visible feature points
        # the points are vertices of the rendered surface: a pixel beside each has its depth
        near = np.stack([f.depth[uv[:, 1] + dv, uv[:, 0] + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], 1)
        assert (np.abs(near - f.landmarks3d[:, 2:]).min(axis=1)[f.visible] < 1.5).all()
    assert a.visible.all()


def test_ground_truth_is_consistent(ict, turns):
    for k in (0, 50, 137, 299):
        f = turns[k] if k == 137 else None
        R, t, shape = turns.rotation[k], turns.translation[k], turns.shapes[k]
        np.testing.assert_allclose(shape, ict.landmarks(turns.identity, turns.expression[k])[list(LANDMARKS)])
        np.testing.assert_allclose(turns.landmarks3d[k], shape @ R.T + t, atol=1e-9)
        np.testing.assert_allclose(turns.landmarks2d[k], project(turns.landmarks3d[k]), atol=1e-9)
        np.testing.assert_allclose(rotation_from_rvec(turns.rvec[k]), R, atol=1e-12)
        np.testing.assert_allclose(rotation_from_euler(*turns.euler[k]), R, atol=1e-12)
        if f is not None:
            np.testing.assert_array_equal(f.rotation, R)
            np.testing.assert_array_equal(f.landmarks2d, turns.landmarks2d[k])
            np.testing.assert_array_equal(f.shape, shape)
            assert f.time == pytest.approx(k / 30.0) and f.index == k
    assert turns.camera == FACE_CAMERA and turns.size == SIZE == (640, 480) and turns.fps == 30.0


def test_self_occlusion_at_40_degrees_yaw(ict, turns):
    k = int(np.argmax(turns.euler[:, 2]))
    assert turns.euler[k, 2] > 39.5
    f = turns[k]
    assert not f.visible.all()  # the far eye's outer corner is behind the face
    assert f.visible[[1, 2, 6, 7]].all()  # the inner eye corners and mouth corners are seen
    # the hidden ones project onto nearer surface: the z-buffer there is well in front of them
    uv = np.rint(f.landmarks2d[~f.visible]).astype(int)
    assert (f.depth[uv[:, 1], uv[:, 0]] < f.landmarks3d[~f.visible, 2] - 3.0).all()
    # landmark_visibility: a point outside the image is not visible; a point in front of the surface is
    pts = f.landmarks3d.copy()
    pts[0, 0] += 1e4
    pts[1, 2] -= 50.0
    vis = landmark_visibility(pts, f.depth, FACE_CAMERA)
    assert not vis[0] and vis[1]


def test_texture_has_structure_at_the_feature_points(ict, turns):
    f = turns[0]
    for (u, v) in np.rint(f.landmarks2d).astype(int):
        patch = f.gray[v - 8:v + 8, u - 8:u + 8].astype(np.float64)
        assert patch.std() > 8.0
    tex = turns.texture
    assert face_texture(ict, turns.identity, seed=(0, 1003, 0, 0)) is tex  # cached per person
    assert all(lev.shape == tex.levels[0].shape for lev in tex.levels)
    # finer levels carry more detail
    stds = [np.diff(lev, axis=1).std() for lev in tex.levels]
    assert all(a > b for a, b in itertools.pairwise(stds))


def test_haar_cascade_finds_the_frontal_face(ict, turns):
    cv2 = pytest.importorskip("cv2")
    if not hasattr(cv2, "CascadeClassifier"):
        pytest.skip(f"OpenCV {cv2.__version__} has no CascadeClassifier (OpenCV 5 moved the Haar cascades out)")
    cascade = cv2.CascadeClassifier(cv2.data.haarcascades + "haarcascade_frontalface_default.xml")
    assert not cascade.empty()
    for z in (400.0, 650.0, 900.0):
        gray, _, pts = frontal(ict, turns, z)
        uv = project(pts)
        boxes = cascade.detectMultiScale(gray, scaleFactor=1.1, minNeighbors=3, minSize=(40, 40))
        inside = [(uv[:, 0] >= x).all() and (uv[:, 0] <= x + w).all() and (uv[:, 1] >= y).all()
                  and (uv[:, 1] <= y + h).all() for x, y, w, h in boxes]  # fmt: skip
        assert any(inside), f"no face box around the feature points at {z} mm: {boxes}"


def test_expression_and_lighting_change_the_image(ict, turns):
    e = ict.expression({"jawOpen": 1.0})
    closed, _, _ = frontal(ict, turns, 500.0)
    opened, _, pts1 = frontal(ict, turns, 500.0, e)
    mouth = project(pts1)[[6, 7]].mean(axis=0).astype(int)
    assert opened[mouth[1] + 5:mouth[1] + 25, mouth[0] - 5:mouth[0] + 5].mean() < \
        closed[mouth[1] + 5:mouth[1] + 25, mouth[0] - 5:mouth[0] + 5].mean() - 10  # a dark open mouth
    from gputrack.sim.face import Light

    args = (ict, turns.identity, np.zeros(57), np.eye(3), np.array([0.0, 0.0, 600.0]))
    left, depth = render_face(*args, light=Light((-1.0, 0.0, -0.3), 0.8, 0.2), texture=turns.texture)
    right, _ = render_face(*args, light=Light((1.0, 0.0, -0.3), 0.8, 0.2), texture=turns.texture)
    face = np.isfinite(depth)
    cols = np.nonzero(face.any(axis=0))[0]
    mid = (cols.min() + cols.max()) // 2
    lf, rf = face.copy(), face.copy()
    lf[:, mid:] = False
    rf[:, :mid] = False
    assert left[lf].mean() > left[rf].mean() + 15 and right[rf].mean() > right[lf].mean() + 15
    dim, _ = render_face(*args, gain=0.5, texture=turns.texture)
    bright, _ = render_face(*args, texture=turns.texture)
    np.testing.assert_allclose(dim[face].astype(float), bright[face] * 0.5, atol=1.0)


# -- sequences ---------------------------------------------------------------------------------------------
def test_sequence_ranges_and_smoothness(ict, turns):
    e = turns.euler
    assert e[:, 2].max() > 39.5 and e[:, 2].min() < -39.5 and np.abs(e[:, 2]).max() <= 40.0 + 1e-9
    assert e[:, 1].max() > 19.5 and e[:, 1].min() < -19.5
    assert e[:, 0].max() > 14.5 and e[:, 0].min() < -14.5
    depth = face_sequence("depth", ict=ict)
    z = depth.translation[:, 2]
    assert z.min() == pytest.approx(400.0, abs=0.5) and z.max() == pytest.approx(900.0, abs=0.5)
    assert z[0] == pytest.approx(650.0, abs=15.0) and z[-1] == pytest.approx(650.0, abs=30.0)
    for name in SEQUENCES:
        s = turns if name == "turns" else face_sequence(name, ict=ict, seed=1)
        assert len(s) == 300
        intro = s.euler[:INTRO_FRAMES]
        assert np.abs(intro).max() < 6.0  # near frontal ...
        assert np.ptp(intro, axis=0).max() > 0.5  # ... with some variation
        assert np.abs(np.diff(s.euler, axis=0)).max() < 3.0  # smooth: < 3 deg per frame
        assert np.abs(np.diff(s.translation, axis=0)).max() < 15.0  # < 15 mm per frame
        # the face (every landmark, the mesh down to the chin) stays inside the image
        lm = ict.landmarks(s.identity, s.expression)
        uv = project(np.einsum("fij,fkj->fki", s.rotation, lm) + s.translation[:, None])
        assert uv.min() > 0 and (uv[..., 0] < 639).all() and (uv[..., 1] < 479).all()
        for k in range(0, 300, 25):
            v = s.vertices(k)
            face = v[face_vertices(ict, s.identity, s.expression[k])[:, 1] < 90]
            uv = project(face)
            assert uv.min() > 0 and (uv[:, 0] < 639).all() and (uv[:, 1] < 479).all()


def test_expression_and_lighting_scripts(ict, turns):
    assert not turns.expression.any()
    assert np.ptp(turns.diffuse) == 0 and np.ptp(turns.gain) == 0
    ex = face_sequence("expressions", ict=ict)
    names = ict.expression_names
    for name, least in (("jawOpen", 0.79), ("mouthStretch_L", 0.99), ("mouthSmile_R", 0.99), ("eyeBlink_L", 0.99),
                        ("browInnerUp_R", 0.99)):  # fmt: skip
        assert ex.expression[:, names.index(name)].max() >= least
    assert (ex.expression >= 0).all() and (ex.expression <= 1).all()
    assert not ex.expression[:INTRO_FRAMES].any()
    assert np.abs(np.diff(ex.expression, axis=0)).max() < 0.5
    lit = face_sequence("lighting", ict=ict)
    assert np.ptp(lit.diffuse) > 0.3 and np.ptp(lit.gain) > 0.15 and np.ptp(lit.ambient) > 0.1
    az = np.degrees(np.arctan2(lit.light[:, 0], -lit.light[:, 2]))
    assert az.max() > 40 and az.min() < -40
    assert lit.noise > turns.noise
    mixed = face_sequence("mixed", ict=ict)
    assert mixed.expression.any() and np.ptp(mixed.diffuse) > 0.3
    assert np.abs(mixed.euler[:, 2]).max() > 39.5 and np.ptp(mixed.translation[:, 2]) > 490


def test_people_are_new(ict, turns):
    model_people = sample_people(ict, 26, 0)
    ids = np.array([face_sequence(i, frames=1, seed=s, ict=ict).identity for i in range(5) for s in range(3)])
    assert ids.shape == (15, 100)
    dist = np.linalg.norm(ids[:, None, :] - model_people[None], axis=-1)
    assert dist.min() > 5.0  # none is one of the model's 26 people
    pair = np.linalg.norm(ids[:, None, :] - ids[None], axis=-1)
    assert pair[~np.eye(15, dtype=bool)].min() > 5.0  # and all differ from each other
    assert np.array_equal(turns.identity, face_sequence(0, frames=1, ict=ict).identity)


# -- bad input ---------------------------------------------------------------------------------------------
def test_bad_input(ict, turns):
    with pytest.raises(ValueError, match="expected one of turns, depth"):
        face_sequence("spin", ict=ict)
    with pytest.raises(ValueError, match="expected 0..4, got 5"):
        face_sequence(5, ict=ict)
    with pytest.raises(TypeError, match="got float"):
        face_sequence(1.0, ict=ict)
    with pytest.raises(ValueError, match="frames: expected an integer in"):
        face_sequence(0, frames=0, ict=ict)
    with pytest.raises(TypeError, match="frames: expected an integer, got str"):
        face_sequence(0, frames="10", ict=ict)
    with pytest.raises(ValueError, match="seed: expected an integer >= 0"):
        face_sequence(0, seed=-1, ict=ict)
    with pytest.raises(TypeError, match="camera: expected"):
        face_sequence(0, camera=(700, 700, 320, 240), ict=ict)
    with pytest.raises(TypeError, match="ict: expected an IctFace"):
        face_sequence(0, ict="ict")
    with pytest.raises(IndexError, match="frame index"):
        turns[300]
    with pytest.raises(TypeError, match="frame index"):
        turns[1.0]
    ident, e = turns.identity, np.zeros(57)
    with pytest.raises(ValueError, match="t: expected finite values"):
        render_face(ict, ident, e, np.eye(3), [0.0, np.nan, 600.0])
    with pytest.raises(ValueError, match="R: expected finite values"):
        render_face(ict, ident, e, np.full((3, 3), np.inf), [0.0, 0.0, 600.0])
    with pytest.raises(ValueError, match="R: expected a rotation matrix"):
        render_face(ict, ident, e, 2 * np.eye(3), [0.0, 0.0, 600.0])
    with pytest.raises(ValueError, match="t: expected the face in front of the camera"):
        render_face(ict, ident, e, np.eye(3), [0.0, 0.0, -600.0])
    with pytest.raises(ValueError, match=r"identity: expected shape \(100,\), got \(99,\)"):
        render_face(ict, ident[:99], e, np.eye(3), [0.0, 0.0, 600.0])
    with pytest.raises(ValueError, match=r"expression: expected shape \(57,\)"):
        render_face(ict, ident, np.zeros(10), np.eye(3), [0.0, 0.0, 600.0])
    with pytest.raises(TypeError, match="rng: expected a numpy.random.Generator"):
        render_face(ict, ident, e, np.eye(3), [0.0, 0.0, 600.0], noise=2.0)
    with pytest.raises(ValueError, match="gain: expected a finite number"):
        render_face(ict, ident, e, np.eye(3), [0.0, 0.0, 600.0], gain=float("nan"))
    with pytest.raises(ValueError, match="size: expected"):
        render_face(ict, ident, e, np.eye(3), [0.0, 0.0, 600.0], size=(0, 480))
    with pytest.raises(ValueError, match="euler|R: expected shape"):
        euler_from_rotation(np.eye(2))

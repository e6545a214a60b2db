"""Simulator, 3D sparse template and the arm-axis metric (paper 000): host code, one run."""

import numpy as np
import pytest

import gputrack
from gputrack.backends.reference.kinematics import forward_kinematics
from gputrack.trackers.body.metrics import ARM_PARTS, arm_axis_errors, axis_angle, mean_arm_errors, shoulder_errors
from gputrack.models import upper_body
from gputrack.ops.template import SparseTemplate
from gputrack.models.camera import DEFAULT_CAMERA
from gputrack.models.render import intersect, render
from gputrack.sim import SEQUENCES, sequence, sequence_params
from gputrack.ops.model_template import model_images, select_template
from gputrack.trackers import sparse_template
REF = gputrack.device("numpy")

DEG = np.pi / 180
CHAIN = upper_body()


def crossed_pose():
    """Forearms folded in front of the chest: the left forearm occludes the torso."""
    p = CHAIN.rest_params()
    p[8:10] = [95 * DEG, 45 * DEG]  # left shoulder: down, forward
    p[12:14] = [75 * DEG, 20 * DEG]  # left elbow: across the chest
    p[6:8] = [85 * DEG, 35 * DEG]
    p[10:12] = [-75 * DEG, 25 * DEG]
    return p


def project(points, camera=DEFAULT_CAMERA):
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    return camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy


# -- renderer ----------------------------------------------------------------------------------------
def test_render_shapes_and_determinism():
    p = CHAIN.rest_params()
    a, b = render(CHAIN, p), render(CHAIN, p)
    assert a.gray.shape == a.depth.shape == a.part.shape == (480, 640)
    assert a.points.shape == a.local.shape == (480, 640, 3)
    assert a.gray.dtype == a.depth.dtype == np.float32 and a.part.dtype == np.int32
    for name in ("gray", "depth", "part", "points", "local"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert set(np.unique(a.part)) == {-1, 0, 1, 2, 3, 4}
    assert 0.0 <= a.gray.min() and a.gray.max() <= 1.0
    # the wall fills the background at 2.8 m
    np.testing.assert_array_equal(a.depth[a.part < 0], 2800.0)
    # another pose gives another image
    q = p.copy()
    q[9] += 10 * DEG
    assert not np.array_equal(render(CHAIN, q).gray, a.gray)


def test_depth_quantised_to_5mm():
    r = render(CHAIN, crossed_pose())
    exact = render(CHAIN, crossed_pose(), depth_step=0)
    model = r.part >= 0
    assert model.sum() > 5000
    np.testing.assert_array_equal(np.mod(r.depth, 5.0), 0.0)
    assert np.abs(r.depth - exact.depth).max() <= 2.5 + 1e-3
    assert len(np.unique(exact.depth[model] % 5.0)) > 100  # the exact z-buffer is not quantised
    np.testing.assert_allclose(exact.depth, exact.points[..., 2], rtol=1e-6)
    # the points lie on the camera rays of their pixels
    u, v = project(exact.points[model])
    rows, cols = np.nonzero(model)
    np.testing.assert_allclose(u, cols, atol=2e-3)
    np.testing.assert_allclose(v, rows, atol=2e-3)


def test_zbuffer_occlusion_by_brute_force():
    """Each pixel shows the nearest of all parts, checked by intersecting every part with every ray."""
    p = crossed_pose()
    r = render(CHAIN, p, background=None, depth_step=0)
    t = forward_kinematics(None, CHAIN, p[None])[0]
    cam = DEFAULT_CAMERA
    gy, gx = np.mgrid[0:480, 0:640]
    d_cam = np.stack([(gx.ravel() - cam.cx) / cam.fx, (gy.ravel() - cam.cy) / cam.fy, np.ones(gx.size)], axis=1)
    hits = np.stack(
        [intersect(pt.shape, -(t[j, :, :3].T @ t[j, :, 3]), d_cam @ t[j, :, :3])[0] for j, pt in enumerate(CHAIN.parts)]
    )
    nearest = np.where(np.isfinite(hits).any(axis=0), hits.argmin(axis=0), -1).reshape(480, 640)
    np.testing.assert_array_equal(r.part, nearest)
    zmin = np.where(np.isfinite(hits.min(axis=0)), hits.min(axis=0), 0.0).reshape(480, 640)
    np.testing.assert_allclose(r.depth, zmin, rtol=1e-6)
    # the left forearm is in front of the torso: where both are hit, the forearm is seen and nearer
    both = np.isfinite(hits[0]) & np.isfinite(hits[4])
    assert both.sum() > 300
    seen = r.part.ravel()[both]
    assert (seen != 0).all() and (seen == 4).mean() > 0.5  # the rest is the right forearm, nearer still
    assert np.all(hits[4][both][seen == 4] < hits[0][both][seen == 4])
    # the visible torso area shrinks by the occluded pixels
    assert (r.part == 0).sum() == (nearest == 0).sum() < np.isfinite(hits[0]).sum()


def test_render_bad_input():
    with pytest.raises(ValueError, match=r"params: expected shape \(14,\)"):
        render(CHAIN, np.zeros(13))
    with pytest.raises(ValueError, match="params: expected finite"):
        render(CHAIN, np.full(14, np.nan))
    with pytest.raises(TypeError, match="chain: expected a gputrack.models.Chain"):
        render("body", np.zeros(14))
    with pytest.raises(ValueError, match="rng"):
        render(CHAIN, CHAIN.rest_params(), noise=0.01)
    # nothing in view: an empty rendering, not an error
    far = CHAIN.rest_params()
    far[3] = 1e5
    r = render(CHAIN, far, background=None)
    assert (r.part == -1).all() and (r.depth == 0).all()


# -- sequences ---------------------------------------------------------------------------------------
def test_sequences_distinct_seeded_and_in_view():
    assert len(SEQUENCES) >= 7
    truths = [sequence_params(i, frames=90, seed=0) for i in range(len(SEQUENCES))]
    for i, p in enumerate(truths):
        assert p.shape == (90, 14)
        np.testing.assert_array_equal(p, sequence_params(i, frames=90, seed=0))  # reproducible
        assert not np.allclose(p, sequence_params(i, frames=90, seed=1))  # the seed matters
        assert np.ptp(p, axis=0).max() > 20 * DEG  # it moves
        # 30 fps, human speeds: under 6 deg and 15 mm a frame
        step = np.abs(np.diff(p, axis=0))
        assert step[:, [0, 1, 2, *range(6, 14)]].max() < 6 * DEG
        assert step[:, 3:6].max() < 15.0
        assert 1500 <= p[:, 5].min() and p[:, 5].max() <= 2500
        for j in range(i):
            assert np.abs(p - truths[j]).max() > 10 * DEG, (i, j)
    for i in range(len(SEQUENCES)):
        seq = sequence(i, frames=90, seed=3)
        for f in (0, 30, 60, 89):
            frame = seq[f]
            model = frame.part >= 0
            assert set(np.unique(frame.part[model])) == {0, 1, 2, 3, 4}, (i, f)
            # fully in view: no model pixel on the image border
            assert not (model[0].any() or model[-1].any() or model[:, 0].any() or model[:, -1].any()), (i, f)


def test_sequence_frames():
    seq = sequence("arm_swing", frames=5, seed=2)
    assert len(seq) == 5 and seq.name == "arm_swing" and seq.index == 0
    frames = list(seq)
    assert [f.index for f in frames] == list(range(5))
    f = frames[3]
    assert f.gray.shape == f.depth.shape == (480, 640) and f.gray.dtype == f.depth.dtype == np.float32
    np.testing.assert_array_equal(f.params, seq.params[3])
    np.testing.assert_array_equal(sequence(0, frames=5, seed=2)[3].gray, f.gray)
    assert f.time == pytest.approx(3 / 30)
    noisy = sequence(0, frames=5, seed=2, noise=0.02)
    a, b = noisy[1].gray, noisy[1].gray
    np.testing.assert_array_equal(a, b)
    assert 0.005 < np.std(a - frames[1].gray) < 0.03
    s20 = sequence(0, frames=3, shoulders=True)
    assert s20.params.shape == (3, 20)
    np.testing.assert_array_equal(s20.params[:, :14], sequence_params(0, frames=3))
    with pytest.raises(ValueError, match="sequence index"):
        sequence(len(SEQUENCES))
    with pytest.raises(ValueError, match="expected one of"):
        sequence("dance")
    with pytest.raises(ValueError, match="frames: expected a positive integer"):
        sequence(0, frames=0)
    with pytest.raises(IndexError, match="frame index"):
        seq[5]


# -- 3D sparse template ------------------------------------------------------------------------------
@pytest.mark.parametrize("index, frame", [(0, 0), (2, 45), (4, 20), (6, 70)])
def test_template_reprojects_onto_its_part(index, frame):
    seq = sequence(index, frames=90, seed=0)
    truth = seq.params[frame]
    rgb, dep = sparse_template(CHAIN, truth, n=128, n_depth=128)
    assert all(isinstance(x, SparseTemplate) for x in (rgb, dep))
    assert rgb.n == dep.n == 128
    f = seq[frame]  # the input frame: wall, quantised depth
    t = forward_kinematics(None, CHAIN, truth[None])[0]
    for tmpl in (rgb, dep):
        assert set(np.unique(tmpl.part)) == {0, 1, 2, 3, 4}  # every visible part has points
        cam = np.einsum("nij,nj->ni", t[tmpl.part, :, :3], tmpl.xyz) + t[tmpl.part, :, 3]
        u, v = project(cam)
        cols, rows = np.rint(u).astype(int), np.rint(v).astype(int)
        assert np.abs(u - cols).max() < 0.02 and np.abs(v - rows).max() < 0.02  # pixel centres
        np.testing.assert_array_equal(f.part[rows, cols], tmpl.part)
        assert np.abs(f.depth[rows, cols] - cam[:, 2]).max() <= 2.5 + 0.01
        if tmpl is rgb:
            np.testing.assert_allclose(f.gray[rows, cols], tmpl.value, atol=1e-5)  # T_i
        else:
            np.testing.assert_allclose(tmpl.value, cam[:, 2], rtol=1e-5)  # Z_i


def _pick(values, part, n, k=0, n_parts=None, **select):
    """select_template on given images whose part-local point is (row, column, 0): the picked
    pixels of template k (0: RGB from ``values``, 1: depth from ``values``) as (rows, cols)."""
    rows, cols = np.indices(part.shape)
    local = np.stack([rows, cols, np.zeros_like(rows)], -1).astype(np.float32)
    images = model_images(REF, part, np.stack([values, values]), local, n_parts)
    t = select_template(REF, images, n, n, **select)[k]
    return t.xyz[:, 0].astype(int), t.xyz[:, 1].astype(int), t.part


def test_template_points_are_extrema_spread_and_deterministic():
    p = crossed_pose()
    a = sparse_template(CHAIN, p, n=128, n_depth=96)
    b = sparse_template(CHAIN, p, n=128, n_depth=96)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.xyz, y.xyz)
        np.testing.assert_array_equal(x.part, y.part)
        np.testing.assert_array_equal(x.value, y.value)
    assert a[1].n == 96
    r = render(CHAIN, p, background=None, depth_step=0)
    rows, cols, part = _pick(r.gray, r.part, 128, n_parts=5)
    # intensity points are 5x5 same-part extrema (all of them on the torso, which has plenty;
    # the narrow forearms may need filling)
    from scipy import ndimage

    ext = np.zeros(len(rows), bool)
    for j in range(5):
        m = r.part == j
        hi = ndimage.maximum_filter(np.where(m, r.gray, -np.inf), size=5)[rows, cols]
        lo = ndimage.minimum_filter(np.where(m, r.gray, np.inf), size=5)[rows, cols]
        g = r.gray[rows, cols]
        ext |= (part == j) & ((g >= hi) | (g <= lo))
    assert ext[part == 0].all()
    assert ext.mean() > 0.75
    # at least 2 px inside their part, no two closer than 4 px (measured on this pose: the rule
    # promises it between extrema and between an extremum and a fill point)
    for dy in (-2, 0, 2):
        for dx in (-2, 0, 2):
            np.testing.assert_array_equal(r.part[rows + dy, cols + dx], part)
    d2 = (rows[:, None] - rows[None]) ** 2 + (cols[:, None] - cols[None]) ** 2
    same = part[:, None] == part[None]
    assert d2[same & ~np.eye(len(rows), dtype=bool)].min() >= 16
    # a part hidden entirely gets no points, the others share N
    hidden = CHAIN.rest_params()
    hidden[1] = 90 * DEG  # side view: the right arm hangs behind the torso
    hidden[[11, 13]] = 0.0
    rr = render(CHAIN, hidden, background=None, depth_step=0)
    assert set(np.unique(rr.part)) == {-1, 0, 2, 4}
    rgb, dep = sparse_template(CHAIN, hidden, rendering=rr)
    assert rgb.n == dep.n == 128
    assert set(rgb.part.tolist()) == set(dep.part.tolist()) == {0, 2, 4}


def test_selection_takes_the_strongest_extrema_then_fills():
    """Isolated peaks of known height on a flat part: picked strongest first; then the fill."""
    part = np.full((60, 80), -1, np.int32)
    part[5:55, 5:75] = 0
    values = np.zeros((60, 80))
    peaks = [(10, 10, 5.0), (30, 40, 9.0), (30, 43, 8.0), (50, 70, 7.0), (20, 60, -6.0)]
    for r, c, h in peaks:
        values[r, c] = h
    rows, cols, _ = _pick(values, part, 4, window=5, border=2, spacing=4.0)
    # 9 (30,40), 7 (50,70), -6 (20,60), 5 (10,10); (30,43) is within 4 px of (30,40)
    assert list(zip(rows.tolist(), cols.tolist())) == [(30, 40), (50, 70), (20, 60), (10, 10)]
    # with no extrema (a flat part), farthest-point sampling still spreads the points
    rows, cols, _ = _pick(np.zeros((60, 80)), part, 5)
    d2 = (rows[:, None] - rows[None]) ** 2 + (cols[:, None] - cols[None]) ** 2
    assert len(rows) == 5 and d2[~np.eye(5, dtype=bool)].min() > 20**2
    # the fill is rook-spread: a row and a column of its own for every point while there are any
    # (the pool is 46 rows x 66 columns), still spread out
    rows, cols, _ = _pick(np.zeros((60, 80)), part, 60)
    d2 = (rows[:, None] - rows[None]) ** 2 + (cols[:, None] - cols[None]) ** 2
    assert len(set(rows.tolist())) == 46 and len(set(cols.tolist())) == 60
    assert d2[~np.eye(60, dtype=bool)].min() >= 4**2
    # a surface whose value changes along the columns only (an upright cylinder's depth): as many
    # distinct values as points
    z = np.tile(np.linspace(0.0, 1.0, 80) ** 2, (60, 1))
    rows, cols, _ = _pick(z, part, 30)
    assert len(np.unique(z[rows, cols])) == 30


def test_template_bad_input():
    far = CHAIN.rest_params()
    far[3] = 1e5
    with pytest.raises(ValueError, match="no visible model surface"):
        sparse_template(CHAIN, far)
    r = render(CHAIN, CHAIN.rest_params(), background=None)
    images = model_images(REF, r.part, np.stack([r.gray, r.depth]), r.local)
    with pytest.raises(ValueError, match="window: expected an odd size"):
        select_template(REF, images, 10, window=4)
    with pytest.raises(ValueError, match=r"expected \(H, W\), \(2, H, W\)"):
        model_images(REF, r.part[1:], np.stack([r.gray, r.depth]), r.local)
    with pytest.raises(TypeError, match="images: expected gputrack ModelImages"):
        select_template(REF, r.part, 10)
    # more points than visible pixels: all of them, no more
    tiny = np.full((20, 20), -1, np.int32)
    tiny[5:8, 5:9] = 0
    rows, cols, _ = _pick(np.random.default_rng(0).random((20, 20)), tiny, 50)
    assert len(rows) == 12 and len(set(zip(rows.tolist(), cols.tolist()))) == 12


def test_template_cost_is_lowest_at_the_true_pose():
    """With the block-reduction op: the template scores the true pose better than perturbed ones."""
    from gputrack.ops.template import RgbdScene, rgbd_cost

    dev = gputrack.device("numpy")
    seq = sequence(0, frames=30, seed=0)
    truth = seq.params[10]
    rgb, dep = sparse_template(CHAIN, seq.params[9])  # from the previous frame's pose, as tracking does
    f = seq[10]
    poses = np.tile(truth, (5, 1))
    poses[1, 9] += 5 * DEG  # left shoulder
    poses[2, 12] += 10 * DEG  # left elbow
    poses[3, 3] += 15.0  # torso x
    poses[4, 1] += 3 * DEG  # torso turn
    transforms = forward_kinematics(None, CHAIN, poses).astype(np.float32)
    cost = rgbd_cost(dev, transforms, RgbdScene(rgb, dep, DEFAULT_CAMERA), f.gray, f.depth)
    total = np.asarray(cost.total)
    assert np.argmin(total) == 0, total


# -- metric ------------------------------------------------------------------------------------------
def test_axis_angle_known_rotations():
    from gputrack.models import rotation

    a = np.array([0.0, 1e-4, 0.5, 30.0, 90.0, 179.0]) * DEG
    rz = rotation("z", a)
    got = axis_angle(rz, np.broadcast_to(np.eye(3), rz.shape))
    np.testing.assert_allclose(got, np.degrees(a), atol=1e-9)
    # rotating about the x axis itself does not move the x axis
    np.testing.assert_allclose(axis_angle(rotation("x", a), np.broadcast_to(np.eye(3), rz.shape)), 0.0, atol=1e-9)
    with pytest.raises(ValueError, match="same shape"):
        axis_angle(rz, np.eye(3))


def test_arm_axis_errors():
    truth = sequence_params(2, frames=13, seed=0)
    err = arm_axis_errors(CHAIN, truth, truth)
    assert err.shape == (13, 4)
    np.testing.assert_allclose(err, 0.0, atol=1e-6)
    est = truth.copy()
    est[:, 9] += 10 * DEG  # left shoulder elevation off by 10 deg
    err = arm_axis_errors(CHAIN, est, truth)
    # the left upper arm's axis moves by exactly 10 deg (a rotation of its elevation); the forearm moves with it
    np.testing.assert_allclose(err[:, 1], 10.0, atol=1e-6)
    assert (err[:, 3] > 0.1).all()
    np.testing.assert_allclose(err[:, [0, 2]], 0.0, atol=1e-6)
    # a torso error shows in every arm (the axes are compared in camera coordinates)
    est = truth.copy()
    est[:, 1] += 2 * DEG
    assert (arm_axis_errors(CHAIN, est, truth) > 0.05).all()
    means = mean_arm_errors(CHAIN, est, truth)
    assert list(means) == list(ARM_PARTS)
    assert arm_axis_errors(CHAIN, truth[0], truth[0]).shape == (1, 4)
    with pytest.raises(ValueError, match=r"estimated: expected shape \(B, 14\)"):
        arm_axis_errors(CHAIN, truth[:, :13], truth)
    with pytest.raises(ValueError, match="same number of poses"):
        arm_axis_errors(CHAIN, truth[:3], truth)
    c20 = upper_body(shoulders=True)
    t20 = c20.rest_params()
    e20 = t20.copy()
    e20[14:] += [0.1, -0.2, 0.3, 0, 0, -1]
    np.testing.assert_allclose(shoulder_errors(e20, t20), [[0.1, 0.2, 0.3, 0, 0, 1]], atol=1e-12)

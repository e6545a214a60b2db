"""Sparse-template RGB-D cost/residuals (paper 000 eq. 17-21); the NCC patches are in test_ncc.py.

Every backend is compared with the NumPy reference; the reference itself is pinned to a plain
per-point loop written from the conventions in gputrack/ops/template.py.
"""

import math
import re

import numpy as np
import pytest
from allocations import rejects_without_allocating
from tolerances import assert_matches

import gputrack
from gputrack.models.camera import Camera
from gputrack.models.chain import rotation_zyx
from gputrack.models.upper_body import upper_body
from gputrack.ops.pf import pf_stage
from gputrack.ops.pose_residuals import pose_residuals
from gputrack.ops.template import MAX_PARTS, RgbdScene, SparseTemplate, rgbd_cost, rgbd_residuals

REF = gputrack.device("numpy")


def make_scene(rng, b, n, m, *, j=3, h=48, w=64, holes=True, spread=0.05, candidates=4):
    """A PF-like scene: template points on a surface about 2 m away, hypotheses around candidates.

    Some points project off the image or behind the camera, and the depth image has holes
    (zeros in rectangles, NaN and inf in a band), so every validity rule is exercised.
    """
    f = 0.9 * w
    cam = Camera(f, f * 1.01, (w - 1) / 2 + 0.3, (h - 1) / 2 - 0.2)
    xyz = np.column_stack([rng.uniform(-1.3, 1.3, n), rng.uniform(-1.0, 1.0, n), rng.uniform(-0.05, 0.05, n)])
    rgb = SparseTemplate(xyz, rng.integers(0, j, n), rng.uniform(10, 240, n))
    xyz_d = np.column_stack([rng.uniform(-1.3, 1.3, m), rng.uniform(-1.0, 1.0, m), rng.uniform(-0.05, 0.05, m)])
    dep = SparseTemplate(xyz_d, rng.integers(0, j, m))
    cand = np.zeros((candidates, j, 3, 4))
    for c in range(candidates):
        for p in range(j):
            a = rng.normal(0, 0.1, 3)
            cand[c, p, :, :3] = _rot(a)
            cand[c, p, :, 3] = [rng.normal(0, 0.05), rng.normal(0, 0.05), 2.0 + rng.normal(0, 0.05)]
    owner = np.arange(b) * candidates // b
    tf = cand[owner].copy()
    tf[..., :, 3] += rng.normal(0, spread, (b, j, 3))
    if b > 2:
        tf[1, :, 2, 3] = -2.0  # hypothesis 1: every part behind the camera
        tf[2, 0, 0, 3] = 50.0  # hypothesis 2: part 0 far off the image
    yy, xx = np.mgrid[0:h, 0:w]
    gray = 120 + 80 * np.sin(xx / 3.1) * np.cos(yy / 4.3) + rng.normal(0, 4, (h, w))
    depth = 2.0 + 0.03 * np.sin(xx / 5.0) + rng.normal(0, 0.003, (h, w))
    if holes:
        depth[h // 4 : h // 3, w // 5 : w // 3] = 0.0
        depth[h // 2 : h // 2 + 3, :] = np.nan
        depth[h // 2 + 3, w // 2 : w // 2 + 9] = np.inf
        depth[-4:, -6:] = -1.0
    return tf.astype(np.float32), rgb, dep, gray.astype(np.float32), depth.astype(np.float32), cam


def _rot(a):
    """Rz(a[2]) Ry(a[1]) Rx(a[0])."""
    return rotation_zyx(a[2], a[1], a[0])


def run_cost(device, tf, rgb, dep, gray, depth, cam, *, out=None, **kw):
    """rgbd_cost against the scene of ``rgb``, ``dep``, ``cam`` with c_depth = 0.01 and the constants ``kw``."""
    return rgbd_cost(device, tf, RgbdScene(rgb, dep, cam, c_depth=0.01, **kw), gray, depth, out=out)


def run_res(device, tf, rgb, dep, gray, depth, cam, *, out=None, **kw):
    """rgbd_residuals as :func:`run_cost` calls rgbd_cost."""
    return rgbd_residuals(device, tf, RgbdScene(rgb, dep, cam, c_depth=0.01, **kw), gray, depth, out=out)


# -- the reference against a per-point loop ------------------------------------------------------
def _loop_cost(tf, rgb, dep, gray, depth, cam, lam, c_rgb, c_depth, depth_tol=0.0):
    """eq. 17-21 point by point, in Python floats, from the documented conventions."""
    h, w = gray.shape
    f32 = np.float32

    def project(m, p):
        x, y, z = (f32(v) for v in p)
        X = m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3]
        Y = m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3]
        Z = m[2, 0] * x + m[2, 1] * y + m[2, 2] * z + m[2, 3]
        if not Z > 0:
            return None
        u = f32(cam.fx) * (X / Z) + f32(cam.cx)
        v = f32(cam.fy) * (Y / Z) + f32(cam.cy)
        if not (0 <= u <= w - 1 and 0 <= v <= h - 1):
            return None
        x0, y0 = min(math.floor(u), w - 2), min(math.floor(v), h - 2)
        return float(Z), float(u - x0), float(v - y0), x0, y0

    def bil(img, a, b, x0, y0):
        top = img[y0, x0] * (1 - a) + img[y0, x0 + 1] * a
        bot = img[y0 + 1, x0] * (1 - a) + img[y0 + 1, x0 + 1] * a
        return float(top * (1 - b) + bot * b)

    out = []
    for t in tf:
        samples = []
        for p, j, T in zip(rgb.xyz, rgb.part, rgb.value):
            pr = project(t[j], p)
            samples.append(None if pr is None else (float(T), bil(gray, *pr[1:])))
        valid = [s for s in samples if s is not None]
        sT = sum(T for T, _ in valid)
        sTT = sum(T * T for T, _ in valid)
        sTI = sum(T * I for T, I in valid)
        alpha = 1 / sT if sT > 1e-12 else 0.0
        beta = alpha * sTT / sTI if sTI > 1e-12 else 0.0
        res = []
        for s in samples:
            if s is None:
                res.append(math.sqrt(1 - lam))
            else:
                d = beta * s[1] - alpha * s[0]
                res.append(math.sqrt(1 - lam) * d / math.sqrt(c_rgb**2 + d * d))
        eps_c = sum(
            1.0 if s is None else (beta * s[1] - alpha * s[0]) ** 2 / (c_rgb**2 + (beta * s[1] - alpha * s[0]) ** 2)
            for s in samples
        )
        eps_d = 0.0
        for p, j in zip(dep.xyz, dep.part):
            pr = project(t[j], p)
            if pr is not None:
                Z, a, b, x0, y0 = pr
                quad = depth[y0 : y0 + 2, x0 : x0 + 2]
                if not ((quad > 0) & np.isfinite(quad)).all():
                    pr = None
            if pr is None:
                eps_d += 1.0
                res.append(math.sqrt(lam))
            else:
                dd = bil(depth, a, b, x0, y0) - Z
                dd = math.copysign(max(abs(dd) - depth_tol, 0.0), dd)  # differences within depth_tol count as 0
                eps_d += dd * dd / (c_depth**2 + dd * dd)
                res.append(math.sqrt(lam) * dd / math.sqrt(c_depth**2 + dd * dd))
        out.append(((1 - lam) * eps_c + lam * eps_d, eps_c, eps_d, res))
    return out


def test_reference_matches_per_point_loop():
    rng = np.random.default_rng(11)
    tf, rgb, dep, gray, depth, cam = make_scene(rng, 9, 17, 19)
    got = run_cost(REF, tf, rgb, dep, gray, depth, cam, lam=0.8)
    res = run_res(REF, tf, rgb, dep, gray, depth, cam, lam=0.8)
    want = _loop_cost(tf, rgb, dep, gray, depth, cam, 0.8, 0.5 / 17, 0.01)
    np.testing.assert_allclose(got.total, [w[0] for w in want], rtol=1e-5)
    np.testing.assert_allclose(got.rgb, [w[1] for w in want], rtol=1e-5)
    np.testing.assert_allclose(got.depth, [w[2] for w in want], rtol=1e-5)
    np.testing.assert_allclose(res, [w[3] for w in want], rtol=1e-4, atol=1e-6)
    # the scene exercises every rule: invalid RGB points, invalid depth points, valid ones
    assert got.rgb[1] == pytest.approx(17) and got.depth[1] == pytest.approx(19)  # behind the camera
    assert (got.depth[3:] < 19).all() and (got.depth[3:] > 0.5).all()
    # depth_tol: the depth differences shrunk towards 0 (some points fall within it, some not)
    got_t = run_cost(REF, tf, rgb, dep, gray, depth, cam, lam=0.8, depth_tol=0.02)
    res_t = run_res(REF, tf, rgb, dep, gray, depth, cam, lam=0.8, depth_tol=0.02)
    want = _loop_cost(tf, rgb, dep, gray, depth, cam, 0.8, 0.5 / 17, 0.01, depth_tol=0.02)
    np.testing.assert_allclose(got_t.depth, [w[2] for w in want], rtol=1e-5)
    np.testing.assert_allclose(res_t, [w[3] for w in want], rtol=1e-4, atol=1e-6)
    np.testing.assert_array_equal(got_t.rgb, got.rgb)
    zeroed = (res_t[:, 17:] == 0) & (res[:, 17:] != 0)
    assert zeroed.any() and ((res_t[:, 17:] != 0) & (np.abs(res_t[:, 17:]) < np.abs(res[:, 17:]))).any()
    assert (got_t.depth[3:] < got.depth[3:]).all()


# -- every backend against the reference ---------------------------------------------------------
def _compare(device, tf, rgb, dep, gray, depth, cam, **kw):
    want = run_cost(REF, tf, rgb, dep, gray, depth, cam, **kw)
    got = run_cost(device, tf, rgb, dep, gray, depth, cam, **kw)
    for field in ("total", "rgb", "depth"):
        assert_matches(device, getattr(got, field), getattr(want, field), err_msg=field)
    want_r = run_res(REF, tf, rgb, dep, gray, depth, cam, **kw)
    got_r = run_res(device, tf, rgb, dep, gray, depth, cam, **kw)
    # residuals are single terms d / sqrt(c^2 + d^2) of magnitude <= 1
    assert_matches(device, got_r, want_r, scale=5.0, err_msg="residuals")
    return got, got_r


@pytest.mark.parametrize("b", [1, 13, 129, 1535])
def test_rgbd_matches_reference_batch_sizes(device, b):
    rng = np.random.default_rng(b)
    _compare(device, *make_scene(rng, b, 37, 29))


@pytest.mark.parametrize("n", [1, 13, 127, 128, 129, 1535, 4096])
def test_rgbd_matches_reference_template_sizes(device, n):
    rng = np.random.default_rng(n + 7)
    _got, res = _compare(device, *make_scene(rng, 11, n, max(n // 2, 1), j=5))
    assert res.shape == (11, n + max(n // 2, 1))


def _lane_spy(module, monkeypatch) -> list:
    """The lane counts the rgbd kernels of ``module`` (gputrack.backends.<backend>.template) are
    launched with, recorded as they are built or launched."""
    used = []
    if module.__name__.endswith("opencl.template"):
        real = module._kernel

        def kernel(device, name, **defines):
            used.append(defines["LANES"])
            return real(device, name, **defines)

        monkeypatch.setattr(module, "_kernel", kernel)
    else:
        real = module._common

        def common(*args):
            used.append(int(args[-1]["lanes"]))
            return real(*args)

        monkeypatch.setattr(module, "_common", common)
    return used


def test_rgbd_default_lanes_are_the_devices_choice(device, monkeypatch):
    """Without a tuning-cache entry the kernels run the device's own lane count (CPU_LANES on a CPU,
    1 on a GPU: ``lanes(device)``), whatever kind of device this is."""
    if device.backend == "numpy":
        pytest.skip("the reference has no lanes")
    module = __import__(f"gputrack.backends.{device.backend}.template", fromlist=["lanes"])
    want = 1 if device.info.kind == "gpu" else module.lanes(device)
    assert module.default_params(device)["lanes"] == module.lanes(device) == want
    used = _lane_spy(module, monkeypatch)
    rng = np.random.default_rng(3)
    _compare(device, *make_scene(rng, 37, 29, 31))
    assert used and set(used) == {want}, used


@pytest.mark.parametrize("lanes", [1, 4, 16])
def test_rgbd_other_lane_counts(device, monkeypatch, lanes):
    """The kernels' other hypotheses-per-thread variants agree too: each variant is forced through
    the launch parameters (as ``gputrack tune`` would choose it), so that it runs on a GPU as on a
    CPU, and the launches are checked to use it."""
    if device.backend == "numpy":
        pytest.skip("the reference has no lanes")
    module = __import__(f"gputrack.backends.{device.backend}.template", fromlist=["lanes"])
    if device.backend == "taichi" and module.lanes(device) == 1:
        pytest.skip("this Taichi arch always runs one hypothesis per thread")
    default = module.default_params(device)
    monkeypatch.setattr(module, "_tuned", lambda *args: {**default, "lanes": lanes})
    used = _lane_spy(module, monkeypatch)
    rng = np.random.default_rng(lanes)
    _compare(device, *make_scene(rng, 37, 29, 31))
    assert used and set(used) == {lanes}, used


def test_rgbd_depth_tolerance(device):
    """depth_tol (differences within it count as none) agrees with the reference on every backend."""
    rng = np.random.default_rng(33)
    scene = make_scene(rng, 129, 37, 61)
    got, _ = _compare(device, *scene, depth_tol=0.02)
    plain = run_cost(device, *scene)
    assert (gputrack.to_numpy(got.depth)[3:] < gputrack.to_numpy(plain.depth)[3:]).all()


def test_rgbd_paper_size(device):
    """B = 1500 hypotheses around 10 candidates, N = N' = 128 points, 640 x 480."""
    rng = np.random.default_rng(2024)
    tf, rgb, dep, gray, depth, cam = make_scene(rng, 1500, 128, 128, j=5, h=480, w=640, candidates=10, spread=0.01)
    got, _ = _compare(device, tf, rgb, dep, gray, depth, cam, lam=0.9)
    total = gputrack.to_numpy(got.total)
    assert np.isfinite(total).all() and (total > 0).all()


def test_residuals_square_sum_is_total(device):
    rng = np.random.default_rng(5)
    tf, rgb, dep, gray, depth, cam = make_scene(rng, 129, 129, 65)
    for lam in (0.0, 0.37, 0.9, 1.0):
        cost = run_cost(device, tf, rgb, dep, gray, depth, cam, lam=lam, c_rgb=0.01)
        res = gputrack.to_numpy(run_res(device, tf, rgb, dep, gray, depth, cam, lam=lam, c_rgb=0.01)).astype(np.float64)
        np.testing.assert_allclose((res**2).sum(axis=1), gputrack.to_numpy(cost.total), rtol=2e-5, atol=1e-5)


def test_residual_order_follows_the_callers_points(device):
    """Residual k belongs to point k of the template as given (not the kernels' part grouping)."""
    rng = np.random.default_rng(8)
    tf, rgb, dep, gray, depth, cam = make_scene(rng, 5, 12, 9, j=3)
    res = gputrack.to_numpy(run_res(device, tf, rgb, dep, gray, depth, cam))
    for i in range(12):
        one = SparseTemplate(rgb.xyz[i : i + 1], rgb.part[i : i + 1], rgb.value[i : i + 1])
        single = gputrack.to_numpy(run_res(device, tf, one, dep, gray, depth, cam, c_rgb=0.5 / 12))
        # a one-point template has alpha T = beta I: d = 0 or the point is invalid
        assert np.all((np.abs(single[:, 0]) < 1e-5) | np.isclose(single[:, 0], math.sqrt(0.1)))
    want = run_res(REF, tf, rgb, dep, gray, depth, cam)
    assert_matches(device, res, want, scale=5.0)
    for i in range(9):
        one = SparseTemplate(dep.xyz[i : i + 1], dep.part[i : i + 1])
        single = gputrack.to_numpy(run_res(device, tf, rgb, one, gray, depth, cam))
        np.testing.assert_allclose(single[:, 12], res[:, 12 + i], rtol=1e-4, atol=1e-6)


def test_invalid_points_add_one(device):
    rng = np.random.default_rng(3)
    tf, rgb, dep, gray, depth, cam = make_scene(rng, 4, 20, 30, holes=False)
    tf[0, :, 2, 3] = -5.0  # behind the camera
    tf[1, :, 0, 3] = 100.0  # off the image
    depth_all_holes = np.zeros_like(depth)
    cost = run_cost(device, tf, rgb, dep, gray, depth_all_holes, cam)
    d = gputrack.to_numpy(cost.depth)
    c = gputrack.to_numpy(cost.rgb)
    np.testing.assert_allclose(d, 30.0, rtol=1e-6)  # every depth point on a hole
    np.testing.assert_allclose(c[:2], 20.0, rtol=1e-6)
    assert (c[2:] < 20).all()
    res = gputrack.to_numpy(run_res(device, tf, rgb, dep, gray, depth_all_holes, cam, lam=0.75))
    np.testing.assert_allclose(res[:, 20:], math.sqrt(0.75), rtol=1e-6)
    np.testing.assert_allclose(res[:2, :20], math.sqrt(0.25), rtol=1e-6)


def test_exact_pose_scores_zero_depth_cost(device):
    """A depth image rendered from the hypothesis itself gives d' = 0 at every valid point."""
    h, w = 40, 50
    cam = Camera(40.0, 40.0, 24.5, 19.5)
    z0 = 3.0
    depth = np.full((h, w), z0, np.float32)
    xs = np.linspace(-1, 1, 10)
    xyz = np.column_stack([xs, xs[::-1] * 0.5, np.zeros(10)])
    dep = SparseTemplate(xyz, np.zeros(10, np.int32))
    rgb = SparseTemplate(xyz, np.zeros(10, np.int32), np.linspace(1, 2, 10))
    tf = np.zeros((2, 1, 3, 4), np.float32)
    tf[:, 0, :, :3] = np.eye(3)
    tf[0, 0, 2, 3] = z0
    tf[1, 0, 2, 3] = z0 + 0.2
    cost = rgbd_cost(device, tf, RgbdScene(rgb, dep, cam, c_depth=0.05), np.ones((h, w), np.float32), depth)
    d = gputrack.to_numpy(cost.depth)
    assert d[0] == pytest.approx(0.0, abs=1e-6)
    assert d[1] == pytest.approx(10 * 0.04 / (0.0025 + 0.04), rel=1e-5)
    # a flat gray image matches any template up to the brightness normalisation only
    assert gputrack.to_numpy(cost.rgb)[0] > 0


def test_nonfinite_transforms_on_device_give_max_cost(device):
    if device.backend == "numpy":
        pytest.skip("host transforms are checked at the boundary (see test_bad_input)")
    rng = np.random.default_rng(4)
    tf, rgb, dep, gray, depth, cam = make_scene(rng, 6, 16, 12)
    tf[0, 0, 0, 0] = np.nan
    tf[1, :, 2, 3] = np.inf
    tf[2, :, 0, 3] = -np.inf
    cost = run_cost(device, device.asarray(tf), rgb, dep, gray, depth, cam)
    total = gputrack.to_numpy(cost.total)
    assert np.isfinite(total).all()
    assert gputrack.to_numpy(cost.depth)[1] == pytest.approx(12) and gputrack.to_numpy(cost.rgb)[2] == pytest.approx(16)


def test_template_is_uploaded_once(device):
    if device.backend == "numpy":
        pytest.skip("the numpy device has no transfers")
    rng = np.random.default_rng(6)
    tf, rgb, dep, gray, depth, cam = make_scene(rng, 33, 40, 20)
    d_tf, d_gray, d_depth = device.asarray(tf), device.asarray(gray), device.asarray(depth)
    scene = RgbdScene(rgb, dep, cam, c_depth=0.01).to(device)
    before = device.transfers.copy()
    for _ in range(3):
        rgbd_cost(device, d_tf, scene, d_gray, d_depth)
        rgbd_residuals(device, d_tf, scene, d_gray, d_depth)
    moved = device.transfers - before
    assert (moved.h2d, moved.d2h) == (0, 0)


def test_out_buffers_are_written_in_place(device):
    rng = np.random.default_rng(12)
    tf, rgb, dep, gray, depth, cam = make_scene(rng, 21, 33, 17)
    first = run_cost(device, tf, rgb, dep, gray, depth, cam)
    tf2 = tf.copy()
    tf2[..., 0, 3] += 0.02
    want = run_cost(REF, tf2, rgb, dep, gray, depth, cam)
    again = run_cost(device, tf2, rgb, dep, gray, depth, cam, out=first)
    assert again is first
    for field in ("total", "rgb", "depth"):
        assert_matches(device, getattr(first, field), getattr(want, field), err_msg=field)
    res = run_res(device, tf, rgb, dep, gray, depth, cam)
    got = run_res(device, tf2, rgb, dep, gray, depth, cam, out=res)
    assert got is res
    assert_matches(device, res, run_res(REF, tf2, rgb, dep, gray, depth, cam), scale=5.0)
    with pytest.raises(ValueError, match=r"out: expected a float32 array of shape \(21, 50\), got float32 \(21, 49\)"):
        run_res(device, tf, rgb, dep, gray, depth, cam, out=device.empty((21, 49), np.float32))
    with pytest.raises(ValueError, match=r"out.total: expected a float32 array of shape \(20,\)"):
        run_cost(device, tf[:20], rgb, dep, gray, depth, cam, out=first)
    with pytest.raises(TypeError, match="out: expected a gputrack.RgbdCost"):
        run_cost(device, tf, rgb, dep, gray, depth, cam, out=res)
    if device.backend != "numpy":
        with pytest.raises(TypeError, match="out: expected a writable array on"):
            run_res(device, tf, rgb, dep, gray, depth, cam, out=np.zeros((21, 50), np.float32))


def test_cost_accuracy_many_points(device):
    """N = 4096 points with tiny, equal terms: a single running float32 sum would drift."""
    h, w = 64, 64
    cam = Camera(30.0, 30.0, 31.5, 31.5)
    n = 4096
    rng = np.random.default_rng(9)
    xyz = np.column_stack([rng.uniform(-0.9, 0.9, n), rng.uniform(-0.9, 0.9, n), np.zeros(n)])
    dep = SparseTemplate(xyz, np.zeros(n, np.int32))
    rgb = SparseTemplate(xyz, np.zeros(n, np.int32), np.full(n, 7.0))
    tf = np.zeros((3, 1, 3, 4), np.float32)
    tf[:, 0, :, :3] = np.eye(3)
    tf[:, 0, 2, 3] = [1.0, 1.001, 1.0003]
    depth = np.full((h, w), 1.0, np.float32)
    cost = rgbd_cost(device, tf, RgbdScene(rgb, dep, cam, c_depth=0.1), np.full((h, w), 3.0, np.float32), depth)
    dz = np.float64(np.float32([1.0, 1.001, 1.0003])) - 1.0  # d' = 1 - Z with Z as float32 holds it
    want = n * dz**2 / (0.01 + dz**2)
    np.testing.assert_allclose(gputrack.to_numpy(cost.depth), want, rtol=2e-5, atol=1e-6)
    np.testing.assert_allclose(gputrack.to_numpy(cost.rgb), 0.0, atol=1e-3)


# -- bad input -----------------------------------------------------------------------------------
def test_bad_input(device):
    rng = np.random.default_rng(0)
    tf, rgb, dep, gray, depth, cam = make_scene(rng, 4, 10, 10, j=3)
    scene = RgbdScene(rgb, dep, cam)
    ok = {"transforms": tf, "gray": gray, "depth_image": depth}

    def call(**kw):
        args = {**ok, **kw}
        return rgbd_cost(device, args["transforms"], scene, args["gray"], args["depth_image"])

    with pytest.raises(ValueError, match=r"transforms: expected shape \(B=4, J=3, 3, 4\), got \(4, 3, 3, 3\)"):
        call(transforms=tf[:, :, :, :3])
    with pytest.raises(TypeError, match="transforms: expected dtype float32, got float64"):
        call(transforms=tf.astype(np.float64))
    bad = tf.copy()
    bad[2, 1, 0, 0] = np.nan
    with pytest.raises(ValueError, match="transforms: expected finite values"):
        call(transforms=bad)
    with pytest.raises(ValueError, match="B = 0"):
        call(transforms=tf[:0])
    with pytest.raises(ValueError, match=r"scene\.rgb\.part: expected part indices in \[0, J=2\)"):
        call(transforms=np.ascontiguousarray(tf[:, :2]))
    with pytest.raises(ValueError, match=r"depth_image: expected shape \(H=48, W=64\)"):
        call(depth_image=depth[:-1])
    with pytest.raises(TypeError, match="gray: expected dtype float32, got uint8"):
        call(gray=gray.astype(np.uint8))
    with pytest.raises(ValueError, match="gray: expected finite values"):
        g = gray.copy()
        g[3, 3] = np.inf
        call(gray=g)
    with pytest.raises(ValueError, match="at least 2 x 2"):
        call(gray=gray[:1], depth_image=depth[:1])
    # the templates, the camera and the constants are checked once, when the scene is made
    with pytest.raises(TypeError, match="rgb: expected a gputrack.SparseTemplate"):
        RgbdScene(rgb.xyz, dep, cam)
    with pytest.raises(TypeError, match="camera: expected a gputrack.Camera"):
        RgbdScene(rgb, dep, (1, 1, 0, 0))
    with pytest.raises(ValueError, match=r"lam: expected a number in \[0.0, 1.0\]"):
        RgbdScene(rgb, dep, cam, lam=1.5)
    with pytest.raises(ValueError, match="c_depth: expected a number > 0"):
        RgbdScene(rgb, dep, cam, c_depth=0.0)
    with pytest.raises(ValueError, match="depth_tol: expected a number >= 0.0, got -1"):
        RgbdScene(rgb, dep, cam, depth_tol=-1.0)
    with pytest.raises(TypeError, match="expected a gputrack.Device"):
        rgbd_cost("numpy", tf, scene, gray, depth)
    if device.backend != "numpy":
        with pytest.raises(ValueError, match="transforms: expected an array on numpy"):
            rgbd_cost(REF, device.asarray(tf), scene, gray, depth)


def test_bad_templates_and_cameras():
    with pytest.raises(ValueError, match="empty template"):
        SparseTemplate(np.zeros((0, 3)), np.zeros(0, np.int32), np.zeros(0))
    with pytest.raises(ValueError, match=r"xyz: expected shape \(N, 3\)"):
        SparseTemplate(np.zeros((4, 2)), np.zeros(4, np.int32))
    with pytest.raises(ValueError, match=r"part: expected shape \(N=4,\)"):
        SparseTemplate(np.zeros((4, 3)), np.zeros(3, np.int32))
    with pytest.raises(ValueError, match="part: expected indices >= 0"):
        SparseTemplate(np.zeros((2, 3)), np.array([0, -1]))
    with pytest.raises(TypeError, match="part: expected integer part indices"):
        SparseTemplate(np.zeros((2, 3)), np.array([0.0, 1.0]))
    with pytest.raises(ValueError, match=r"value: expected shape \(N=2,\)"):
        SparseTemplate(np.zeros((2, 3)), np.zeros(2, np.int32), np.zeros(3))
    with pytest.raises(ValueError, match="xyz: expected finite values"):
        SparseTemplate(np.array([[0, 0, np.nan]]), np.zeros(1, np.int32))
    with pytest.raises(ValueError, match="Camera: expected fx > 0"):
        Camera(0.0, 1.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="Camera.cx: expected a finite number"):
        Camera(1.0, 1.0, np.nan, 0.0)
    t = SparseTemplate(np.zeros((3, 3)), np.array([2, 0, 2], np.int64), [1, 2, 3])
    assert t.n == 3 and t.n_parts == 3 and t.xyz.dtype == np.float32 and t.part.dtype == np.int32
    assert list(t.start) == [0, 1, 1, 3] and list(t.perm) == [1, 0, 2]


def test_part_indices_are_checked_before_anything_is_sized_by_them():
    """A part index of 2e9 made the template size its index by it (> 15 GB touched)."""
    xyz, part = np.zeros((1, 3)), np.array([2_000_000_000])
    rejects_without_allocating(ValueError, r"^part: expected indices < MAX_PARTS = 65536, got 2000000000\Z",
                               lambda: SparseTemplate(xyz, part))  # fmt: skip
    rows = np.broadcast_to(np.zeros(1), (2**32, 3))
    rejects_without_allocating(ValueError, r"^part: expected shape \(N=4294967296,\), got \(1,\)\Z",
                               lambda: SparseTemplate(rows, np.zeros(1, np.int32)))  # fmt: skip
    assert SparseTemplate(xyz, np.array([MAX_PARTS - 1])).n_parts == MAX_PARTS
    with pytest.raises(ValueError, match=r"^value: expected \|values\| <= INTENSITY_MAX = 2\*\*48, got -3e\+38 at index \(1,\)\Z"):
        SparseTemplate(np.zeros((2, 3)), np.zeros(2, np.int32), np.array([1.0, -3e38]))


@pytest.mark.parametrize("image", ["3e38", "gray x 1e36", "+-3e38"])
def test_extreme_gray_values_give_the_references_cost(device, image):
    """Every backend clamps gray pixels to +-INTENSITY_MAX (gputrack/abi.py) as the reference does:
    gray = 3e38 gave 23.2 on the devices against 11.1 (their float32 sums of T I overflowed). An
    image whose pixels all exceed the limit scores as a constant image (beta: scale invariance)."""
    rng = np.random.default_rng(21)
    tf, rgb, dep, gray, depth, cam = make_scene(rng, 13, 57, 31)
    big = {"3e38": np.full_like(gray, 3e38), "gray x 1e36": gray * np.float32(1e36),
           "+-3e38": np.where((np.indices(gray.shape).sum(axis=0) % 2) == 0, 3e38, -3e38).astype(np.float32)}[image]
    want = run_cost(REF, tf, rgb, dep, big, depth, cam)
    got = run_cost(device, tf, rgb, dep, big, depth, cam)
    for f in ("total", "rgb", "depth"):
        assert np.isfinite(getattr(want, f)).all()
        assert_matches(device, getattr(got, f), getattr(want, f), err_msg=f)
    if image == "+-3e38":
        return  # a sample between +-2**48 pixels is ill-conditioned: single residuals differ by ~1e-3
    res = run_res(device, tf, rgb, dep, big, depth, cam)
    assert_matches(device, res, run_res(REF, tf, rgb, dep, big, depth, cam), scale=5.0)
    flat = run_cost(REF, tf, rgb, dep, np.full_like(gray, 7.0), depth, cam)
    np.testing.assert_allclose(want.rgb, flat.rgb, rtol=1e-5)


# -- the scene (templates, camera, eq. 17-19's constants) ------------------------------------------
def whole(message: str) -> str:
    """A ``pytest.raises(match=...)`` pattern that matches ``message`` whole, nothing more or less."""
    return "^" + re.escape(message) + r"\Z"


@pytest.mark.parametrize(
    "args,kw,error,message",
    [
        ("xyz", {}, TypeError, "rgb: expected a gputrack.SparseTemplate, got ndarray"),
        ("no depth", {}, TypeError, "depth: expected a gputrack.SparseTemplate, got NoneType"),
        ("camera as depth", {}, TypeError, "depth: expected a gputrack.SparseTemplate, got Camera"),
        ("tuple camera", {}, TypeError, "camera: expected a gputrack.Camera, got tuple"),
        ("ok", {"lam": 2}, ValueError, "lam: expected a number in [0.0, 1.0], got 2"),
        ("ok", {"lam": -0.25}, ValueError, "lam: expected a number in [0.0, 1.0], got -0.25"),
        ("ok", {"lam": float("nan")}, ValueError, "lam: expected a finite number, got nan"),
        ("ok", {"lam": "0.9"}, TypeError, "lam: expected a real number, got str"),
        ("ok", {"lam": True}, TypeError, "lam: expected a real number, got bool"),
        ("ok", {"c_rgb": 0}, ValueError, "c_rgb: expected a number > 0, got 0"),
        ("ok", {"c_rgb": -0.5}, ValueError, "c_rgb: expected a number > 0, got -0.5"),
        ("ok", {"c_rgb": np.inf}, ValueError, "c_rgb: expected a finite number, got inf"),
        ("ok", {"c_depth": -1}, ValueError, "c_depth: expected a number > 0, got -1"),
        ("ok", {"c_depth": 0.0}, ValueError, "c_depth: expected a number > 0, got 0.0"),
        ("ok", {"c_depth": None}, TypeError, "c_depth: expected a real number, got NoneType"),
        ("ok", {"depth_tol": -1}, ValueError, "depth_tol: expected a number >= 0.0, got -1"),
        ("ok", {"depth_tol": -1e-3}, ValueError, "depth_tol: expected a number >= 0.0, got -0.001"),
    ],
)
def test_scene_rejects_bad_input(args, kw, error, message):
    rng = np.random.default_rng(0)
    _tf, rgb, dep, _gray, _depth, cam = make_scene(rng, 4, 10, 6)
    positional = {"ok": (rgb, dep, cam), "xyz": (rgb.xyz, dep, cam), "no depth": (rgb, None, cam),
                  "camera as depth": (rgb, cam, cam), "tuple camera": (rgb, dep, tuple(cam.as_array()))}[args]  # fmt: skip
    with pytest.raises(error, match=whole(message)):
        RgbdScene(*positional, **kw)


def test_scene_accepts_the_ranges_edges():
    rng = np.random.default_rng(0)
    _tf, rgb, dep, _gray, _depth, cam = make_scene(rng, 4, 10, 6, j=3)
    for lam in (0, 1, 0.0, 1.0, np.float32(0.5), np.int64(1)):
        assert RgbdScene(rgb, dep, cam, lam=lam).lam == float(lam)
    scene = RgbdScene(rgb, dep, cam, c_rgb=np.float64(1e-9), c_depth=7, depth_tol=0)
    assert (scene.c_rgb, scene.c_depth, scene.depth_tol) == (1e-9, 7.0, 0.0)
    assert all(type(v) is float for v in (scene.lam, scene.c_rgb, scene.c_depth, scene.depth_tol))
    assert scene.rgb is rgb and scene.depth is dep and scene.camera is cam
    assert scene.n == 16 and scene.n_parts == max(rgb.n_parts, dep.n_parts) == 3
    with pytest.raises(AttributeError, match="RgbdScene is read-only"):  # checked once: no unchecked values later
        scene.lam = 2
    assert scene.lam == 0.9


def test_scene_default_c_rgb_is_half_over_n(device):
    """c_rgb=None (the default) is eq. 17's 0.5/N, N the RGB template's points: it scores as that number."""
    rng = np.random.default_rng(17)
    tf, rgb, dep, gray, depth, cam = make_scene(rng, 9, 23, 11)
    scene = RgbdScene(rgb, dep, cam)
    assert scene.c_rgb == 0.5 / 23
    assert RgbdScene(rgb, dep, cam, c_rgb=None).c_rgb == 0.5 / 23
    assert RgbdScene(rgb, dep, cam, c_rgb=0.25).c_rgb == 0.25
    explicit = RgbdScene(rgb, dep, cam, c_rgb=0.5 / 23)
    got, want = rgbd_cost(device, tf, scene, gray, depth), rgbd_cost(device, tf, explicit, gray, depth)
    for f in ("total", "rgb", "depth"):
        np.testing.assert_array_equal(gputrack.to_numpy(getattr(got, f)), gputrack.to_numpy(getattr(want, f)))
    np.testing.assert_array_equal(gputrack.to_numpy(rgbd_residuals(device, tf, scene, gray, depth)),
                                  gputrack.to_numpy(rgbd_residuals(device, tf, explicit, gray, depth)))  # fmt: skip
    # a c_rgb of another value scores otherwise (the constant reaches the kernels)
    other = gputrack.to_numpy(rgbd_cost(device, tf, RgbdScene(rgb, dep, cam, c_rgb=0.25), gray, depth).rgb)
    assert (other[3:] != gputrack.to_numpy(got.rgb)[3:]).all()


def test_scene_with_templates_keeps_the_camera_and_constants(device):
    rng = np.random.default_rng(19)
    tf, rgb, dep, gray, depth, cam = make_scene(rng, 7, 20, 12)
    _tf2, rgb2, dep2, _gray2, _depth2, _cam2 = make_scene(rng, 7, 31, 9)
    scene = RgbdScene(rgb, dep, cam, lam=0.3, c_rgb=0.02, c_depth=0.07, depth_tol=0.01)
    other = scene.with_templates(rgb2, dep2)
    assert isinstance(other, RgbdScene) and other is not scene
    assert other.rgb is rgb2 and other.depth is dep2 and other.camera is cam and other.n == 40
    assert (other.lam, other.c_rgb, other.c_depth, other.depth_tol) == (0.3, 0.02, 0.07, 0.01)
    assert scene.rgb is rgb and scene.depth is dep and scene.n == 32  # the scene itself is unchanged
    want = rgbd_cost(device, tf, RgbdScene(rgb2, dep2, cam, lam=0.3, c_rgb=0.02, c_depth=0.07, depth_tol=0.01),
                     gray, depth)  # fmt: skip
    got = rgbd_cost(device, tf, other, gray, depth)
    for f in ("total", "rgb", "depth"):
        np.testing.assert_array_equal(gputrack.to_numpy(getattr(got, f)), gputrack.to_numpy(getattr(want, f)))
    # the default c_rgb stays eq. 17's rule, 0.5/N of the new RGB template
    assert RgbdScene(rgb, dep, cam).with_templates(rgb2, dep2).c_rgb == 0.5 / 31
    # the new templates are checked as a new scene's
    with pytest.raises(TypeError, match=whole("rgb: expected a gputrack.SparseTemplate, got ndarray")):
        scene.with_templates(rgb2.xyz, dep2)
    with pytest.raises(TypeError, match=whole("depth: expected a gputrack.SparseTemplate, got NoneType")):
        scene.with_templates(rgb2, None)


def _four_ops(device, scene, gray, depth, *, j):
    """The four ops that score against a scene, each called as a function of nothing (chain of j parts)."""
    chain = upper_body()
    assert chain.n_parts == j
    params = np.repeat(chain.rest_params(np.float32)[None], 3, axis=0)
    sigma = np.full(chain.n_params, 0.01, np.float32)
    tf = gputrack.to_numpy(gputrack.forward_kinematics(REF, chain, params))
    return {
        "rgbd_cost": lambda: rgbd_cost(device, tf, scene, gray, depth),
        "rgbd_residuals": lambda: rgbd_residuals(device, tf, scene, gray, depth),
        "pose_residuals": lambda: pose_residuals(device, chain, params, scene, gray, depth),
        "pf_stage": lambda: pf_stage(device, chain, params, sigma, 12, 1, scene, gray, depth),
    }


@pytest.mark.parametrize("op", ["rgbd_cost", "rgbd_residuals", "pose_residuals", "pf_stage"])
def test_every_op_takes_a_scene(device, op):
    j = upper_body().n_parts
    rng = np.random.default_rng(23)
    _tf, rgb, dep, gray, depth, cam = make_scene(rng, 3, 10, 6, j=j)
    assert _four_ops(device, RgbdScene(rgb, dep, cam), gray, depth, j=j)[op]() is not None  # a scene: fine
    for thing, name in ((rgb, "SparseTemplate"), ((rgb, dep), "tuple"), (None, "NoneType"), (cam, "Camera")):
        with pytest.raises(TypeError, match=whole(f"scene: expected a gputrack.RgbdScene, got {name}")):
            _four_ops(device, thing, gray, depth, j=j)[op]()


@pytest.mark.parametrize("op", ["rgbd_cost", "rgbd_residuals", "pose_residuals", "pf_stage"])
def test_every_op_rejects_a_scene_with_parts_beyond_j(device, op):
    """A template point on part J (the hypotheses' parts are 0..J-1) is refused, RGB or depth."""
    j = upper_body().n_parts
    rng = np.random.default_rng(29)
    _tf, rgb, dep, gray, depth, cam = make_scene(rng, 3, 10, 6, j=j)
    rgb_over = SparseTemplate(rgb.xyz, np.where(np.arange(rgb.n) == 4, j, rgb.part), rgb.value)
    dep_over = SparseTemplate(dep.xyz, np.where(np.arange(dep.n) == 2, j + 2, dep.part))
    for scene, message in (
        (RgbdScene(rgb_over, dep, cam), f"scene.rgb.part: expected part indices in [0, J={j}), got {j}"),
        (RgbdScene(rgb, dep_over, cam), f"scene.depth.part: expected part indices in [0, J={j}), got {j + 2}"),
    ):
        assert scene.n_parts > j
        with pytest.raises(ValueError, match=whole(message)):
            _four_ops(device, scene, gray, depth, j=j)[op]()


def test_selftest(device):
    from gputrack.selftest import check_template

    check_template(device)

"""Tiny numerical self-tests, one per primitive, run on a device against the NumPy reference.

Used by the doctor (:mod:`gputrack.doctor`, ``gputrack doctor``). Every check goes through the public API only: it runs the same
public ops on ``device`` and on the ``numpy`` device with the same inputs (from
:mod:`gputrack.sim.problems`) and raises (AssertionError naming the largest error, or any
exception) when they disagree. A primitive's check is listed in :data:`CHECKS` when the
primitive lands.
"""

from __future__ import annotations

import time

import numpy as np

from .device import Device, to_numpy
from .registry import device as get_device
from .sim import problems


def check_arrays(device: Device) -> None:
    """Upload, write into an existing array, download: bit-exact round trips of every float dtype."""
    for dtype in (np.float32, np.float64) if device.fp64 else (np.float32,):
        x = np.linspace(-3, 3, 1000, dtype=dtype)
        y = np.cos(x).astype(dtype)
        a = device.asarray(x)
        got = to_numpy(a)
        assert got.dtype == dtype and np.array_equal(got, x), f"{np.dtype(dtype).name} round trip differs"
        b = device.asarray(y, out=a)
        assert np.array_equal(to_numpy(b), y), f"{np.dtype(dtype).name} upload into an existing array differs"


def check_kinematics(device: Device) -> None:
    """forward_kinematics of the 20-parameter upper body (float32, and float64 where the device has it)."""
    from .models import upper_body
    from .ops.kinematics import forward_kinematics

    chain = upper_body(shoulders=True)
    rng = np.random.default_rng(0)
    scale = np.r_[[1.0] * 3, [50.0] * 3, [1.0] * 8, [20.0] * 6]  # rad, mm, rad, mm
    params = chain.rest_params()[None, :] + rng.normal(0.0, 0.3, (7, chain.n_params)) * scale
    ref = get_device("numpy")
    for dtype, tol in ((np.float32, 2e-3), (np.float64, 1e-9)):
        if dtype == np.float64 and not device.fp64:
            continue
        p = params.astype(dtype)
        got = to_numpy(forward_kinematics(device, chain, p))
        want = forward_kinematics(ref, chain, p)
        err = float(np.max(np.abs(got - want)))
        name = np.dtype(dtype).name
        assert err <= tol, f"forward_kinematics ({name}) differs from the reference by {err:g} (> {tol:g})"


def check_template(device: Device) -> None:
    """rgbd_cost and patch_ncc of a tiny scene."""
    from .ops.ncc import patch_ncc
    from .ops.template import RgbdScene, rgbd_cost

    rng = np.random.default_rng(3)
    tf, rgb, dep, gray, depth, cam = problems.template_scene(rng)
    scene = RgbdScene(rgb, dep, cam, c_depth=0.05)
    ref = get_device("numpy")
    want = rgbd_cost(ref, tf, scene, gray, depth)
    got = rgbd_cost(device, tf, scene, gray, depth)
    for field in ("total", "rgb", "depth"):
        err = float(np.max(np.abs(to_numpy(getattr(got, field)) - getattr(want, field))))
        assert err <= 1e-3, f"rgbd_cost.{field} differs from the reference by {err:g}"
    pts = rng.uniform(6, 20, (5, 3, 2)).astype(np.float32)
    tpl = rng.uniform(0, 1, (3, 5, 5)).astype(np.float32)
    want = patch_ncc(ref, pts, tpl, gray)
    got = to_numpy(patch_ncc(device, pts, tpl, gray))
    err = float(np.max(np.abs(got - want)))
    assert err <= 1e-4, f"patch_ncc differs from the reference by {err:g}"


def check_lm(device: Device) -> None:
    """lm_solve of small normal equations, and least_squares of a batch of exponential fits."""
    from .ops.lm import least_squares, lm_solve

    ref = get_device("numpy")
    dt = np.float64 if device.fp64 else np.float32
    J, r, C = problems.lm_batch(np.random.default_rng(7), dtype=dt)
    want_d, want_ok = lm_solve(ref, J, r, C)
    got_d, got_ok = lm_solve(device, J, r, C)
    err = float(np.max(np.abs(to_numpy(got_d) - want_d)))
    tol = 1e-8 if dt == np.float64 else 1e-3
    if not err <= tol or not np.array_equal(to_numpy(got_ok), want_ok):
        raise AssertionError(f"lm_solve on {device.spec}: max error {err:.3g} > {tol:g} or ok flags differ")

    res, x0 = problems.exponential_fit()
    a = least_squares(res, x0, device=device, max_iter=30)
    b = least_squares(res, x0, device=ref, max_iter=30, dtype=a.dtype)
    err = float(np.max(np.abs(a.x - b.x)))
    tol = 1e-7 if a.dtype == np.float64 else 1e-2
    if not err <= tol or not np.array_equal(a.status, b.status):
        raise AssertionError(
            f"least_squares on {device.spec}: max error {err:.3g} > {tol:g} vs reference or statuses differ"
        )


def check_kalman(device: Device) -> None:
    """kf_predict, kf_update (mask, gain scale, fused predict), ekf_update_stereo and mahalanobis."""
    from .ops.kalman import ekf_update_stereo, kf_predict, kf_update, mahalanobis

    p = problems.kalman_mixed(np.random.default_rng(1))
    x, P, F, Q, H, R = p["x"], p["P"], p["F"], p["Q"], p["H"], p["R"]
    runs = {
        "predict": lambda dev: kf_predict(dev, x, P, F, Q),
        "update": lambda dev: kf_update(dev, x, P, p["z"], H, R, mask=p["mask"], gain_scale=p["gain"],
                                        predict=(F, Q))[:2],  # fmt: skip
        "stereo": lambda dev: ekf_update_stereo(dev, x, P, p["zs"] + 0.5, R, f=p["f"], b=p["b"])[:2],
        "gating": lambda dev: (mahalanobis(dev, x, P, H, R, p["det"]),),
    }
    ref = get_device("numpy")
    worst, where = 0.0, ""
    for key, run in runs.items():
        for g, w in zip(run(device), run(ref)):
            g, w = to_numpy(g).astype(np.float64), np.asarray(w, np.float64)
            err = float(np.max(np.abs(g - w) / (1.0 + np.abs(w))))
            if not err <= worst:
                worst, where = err, key
    if not worst <= 1e-3:
        raise AssertionError(f"kalman self-test on {device.spec}: max relative error {worst:.3g} in {where}")


def check_gating(device: Device) -> None:
    """gate_pairs (full scan and the sorted strip) and scatter_rows of the track table's row shapes."""
    from .ops.gating import gate_pairs
    from .ops.rows import scatter_rows

    rng = np.random.default_rng(2)
    T, D, n, m = 37, 29, 4, 2
    x = rng.uniform(0, 10, (T, n)).astype(np.float32)
    A = rng.standard_normal((T, n, n)).astype(np.float32)
    P = (0.1 * A @ np.swapaxes(A, 1, 2) + 0.2 * np.eye(n)).astype(np.float32)
    H = np.zeros((m, n), np.float32)
    H[0, 0] = H[1, 2] = 1
    R = (0.1 * np.eye(m)).astype(np.float32)
    z = rng.uniform(0, 10, (D, m)).astype(np.float32)
    z = z[np.argsort(z[:, 0], kind="stable")]
    active = (np.arange(T) % 5 != 3).astype(np.uint8)
    ref = get_device("numpy")
    want = gate_pairs(ref, x, P, H, R, z, 9.0, active=active, max_pairs=4)
    for sz in (False, True):
        got = [to_numpy(a) for a in gate_pairs(device, x, P, H, R, z, 9.0, active=active, max_pairs=4, sorted_z=sz)]
        assert np.array_equal(got[0], want[0]), f"gate_pairs counts differ (sorted_z={sz})"
        keep = np.arange(4)[None, :] < np.minimum(want[0], 4)[:, None]
        assert np.array_equal(got[1][keep], want[1][keep]), f"gate_pairs pairs differ (sorted_z={sz})"
        err = np.max(np.abs(got[2][keep] - want[2][keep]) / (1 + np.abs(want[2][keep])), initial=0.0)
        err = max(err, float(np.max(np.abs(got[3] - want[3]) / (1 + np.abs(want[3])))))
        assert err <= 1e-4, f"gate_pairs differs from the reference by {err:.3g} (sorted_z={sz})"
    for shape, dtype in (((13, 6), np.float32), ((13, 6, 6), np.float32), ((13,), np.uint8), ((13, 3), np.int32)):
        base = (rng.standard_normal(shape) * 10).astype(dtype)
        idx = rng.permutation(shape[0])[:5].astype(np.int32)
        src = (rng.standard_normal((5, *shape[1:])) * 10).astype(dtype)
        want_rows = base.copy()
        want_rows[idx] = src
        got = to_numpy(scatter_rows(device, device.asarray(base.copy()), idx, src))
        assert np.array_equal(got, want_rows), f"scatter_rows differs from the reference for rows of shape {shape}"


def check_point_groups(device: Device) -> None:
    """assign_points: points to groups (gate, tie-break) and each group's moments (paper 001 eq. 7-11)."""
    from .ops.point_groups import assign_points

    rng = np.random.default_rng(3)
    T, N = 7, 301
    means = np.zeros((T, 6), np.float32)
    means[:, [0, 2, 4]] = rng.uniform(-3000, 3000, (T, 3)) + [0, 0, 8000]
    means[:, [1, 3, 5]] = rng.normal(0, 10, (T, 3))
    S = np.tile(np.diag([2e5, 16, 2e5, 16, 2e5, 16]).astype(np.float32), (T, 1, 1))
    owner = rng.integers(0, T, N)
    y = (means[owner][:, [0, 2, 4]] + rng.normal(0, 400, (N, 3))).astype(np.float32)
    lam = (means[owner][:, [1, 3, 5]] + rng.normal(0, 3, (N, 3))).astype(np.float32)
    active = (np.arange(T) != 4).astype(np.uint8)
    want = assign_points(get_device("numpy"), y, lam, means, S, 11.34, active=active)
    got = [to_numpy(a) for a in assign_points(device, y, lam, means, S, 11.34, active=active)]
    assert np.array_equal(got[0], want[0]), "assign_points labels differ from the reference"
    assert np.array_equal(got[1], want[1]), "assign_points counts differ from the reference"
    for g, w, name in ((got[2], want[2], "means"), (got[3], want[3], "covariances")):
        err = float(np.max(np.abs(g - w) / (1.0 + np.abs(w)), initial=0.0))
        assert err <= 1e-3, f"assign_points {name} differ from the reference by {err:.3g}"


def check_stereo(device: Device) -> None:
    """stereo_match of a small random pair (uint8, masked and not): the same pixels with a value
    and the same disparities as the reference."""
    from .ops.stereo import stereo_match

    rng = np.random.default_rng(4)
    base = rng.integers(0, 256, (24, 60)).astype(np.uint8)
    left, right = base[:, :52], base[:, 5:57]  # disparity 5
    mask = rng.random(left.shape) < 0.5
    ref = get_device("numpy")
    for m in (None, mask):
        want = stereo_match(ref, left, right, mask=m, max_disparity=12, block=5)
        got = to_numpy(stereo_match(device, left, right, mask=m, max_disparity=12, block=5))
        assert np.array_equal(np.isnan(got), np.isnan(want)), "stereo_match: other pixels have a value than in the reference"
        err = float(np.nanmax(np.abs(got - want))) if np.isfinite(want).any() else 0.0
        assert err <= 1e-5, f"stereo_match differs from the reference by {err:g}"



def check_background(device: Device) -> None:
    """background_median, update_background, foreground_mask and depth_points of a small uint16
    depth scene (papers 001, 002): bit for bit (the median, the mask, the chosen points' pixels)."""
    from .models.camera import Camera
    from .ops.background import background_median, foreground_mask, update_background
    from .ops.depth_points import depth_points

    rng = np.random.default_rng(3)
    frames = rng.integers(0, 4000, (6, 13, 29)).astype(np.uint16)
    ref = get_device("numpy")
    want = background_median(ref, frames, missing=0)
    got = to_numpy(background_median(device, frames, missing=0))
    assert np.array_equal(got, want, equal_nan=True), "background_median differs from the reference"
    mask = foreground_mask(ref, frames[0], want, 100.0, missing=0)
    assert np.array_equal(to_numpy(foreground_mask(device, frames[0], want, 100.0, missing=0)), mask), (
        "foreground_mask differs from the reference"
    )
    upd = update_background(ref, want, frames[1], rate=0.1, mask=mask, missing=0)
    err = np.nanmax(np.abs(to_numpy(update_background(device, want, frames[1], rate=0.1, mask=mask, missing=0)) - upd))
    assert err <= 1e-3, f"update_background differs from the reference by {err:.3g}"
    cam = Camera(52.5, 52.5, 14.0, 6.0)
    p_ref, n_ref = depth_points(ref, frames[0], want, cam, n_points=64, seed=5)
    p, n = depth_points(device, frames[0], want, cam, n_points=64, seed=5)
    p = to_numpy(p)
    assert n == n_ref, f"depth_points counts {n} foreground points, the reference {n_ref}"
    assert np.array_equal(np.isnan(p), np.isnan(p_ref)), "depth_points returns another number of points"
    err = float(np.nanmax(np.abs(p - p_ref) / (1 + np.abs(p_ref)), initial=0.0))
    assert err <= 1e-4, f"depth_points differs from the reference by {err:.3g}"


def check_clusters(device: Device) -> None:
    """dbscan (core, border and noise points, a NaN row) of 2D points against the reference."""
    from .ops.clusters import dbscan

    ref = get_device("numpy")
    rng = np.random.default_rng(5)
    p = np.concatenate([rng.normal(0.0, 0.1, (40, 2)), rng.normal(1.0, 0.1, (40, 2)), rng.uniform(-1, 2, (20, 2))])
    p = p.astype(np.float32)
    p[7] = np.nan
    want = dbscan(ref, p, 0.1, 5)
    got = to_numpy(dbscan(device, p, 0.1, 5))
    assert np.array_equal(got, want), f"dbscan labels differ from the reference at {np.flatnonzero(got != want)[:5]}"


def _body_scene(rng, n=48, m=40, h=120, w=160):
    """(chain, params (1, 14) float32, scene, gray, depth): the upper body of simulated sequence 0
    at frame 0 before a small camera, an :class:`~gputrack.ops.template.RgbdScene` of template
    points scattered around its parts' origins, and a smooth gray frame with a depth frame 2 m
    away (a few missing readings), so that every hypothesis reads pixels of its own."""
    from .models import Camera, upper_body
    from .ops.template import RgbdScene, SparseTemplate
    from .sim.body import sequence_params

    chain = upper_body()
    params = sequence_params(0, frames=1)[:1].astype(np.float32)
    cam = Camera(60.0, 60.0, (w - 1) / 2, (h - 1) / 2)
    rgb = SparseTemplate(rng.uniform(-80, 80, (n, 3)), rng.integers(0, chain.n_parts, n), rng.uniform(30, 220, n))
    dep = SparseTemplate(rng.uniform(-80, 80, (m, 3)), rng.integers(0, chain.n_parts, m))
    yy, xx = np.mgrid[0:h, 0:w]
    gray = (110 + 60 * np.sin(xx / 3.0) * np.cos(yy / 4.0) + rng.normal(0, 3, (h, w))).astype(np.float32)
    depth = (2000 + 40 * np.sin(xx / 5.0) + rng.normal(0, 2, (h, w))).astype(np.float32)
    depth[rng.random((h, w)) < 0.02] = 0
    return chain, params, RgbdScene(rgb, dep, cam), gray, depth


def check_particles(device: Device) -> None:
    """sample_around (per-parameter and per-candidate sigma) and best_k with rows: the same
    samples, indices, scores and rows as the reference."""
    from .ops.particles import best_k, sample_around

    rng = np.random.default_rng(6)
    ref = get_device("numpy")
    cand = rng.normal(0, 1, (3, 7)).astype(np.float32)
    sig = rng.uniform(0.01, 0.3, 7).astype(np.float32)
    per = rng.uniform(0.01, 0.3, (3, 7)).astype(np.float32)
    for s, keep in ((sig, True), (per, False)):
        want = sample_around(ref, cand, s, 61, 12345, keep_candidates=keep)
        got = to_numpy(sample_around(device, cand, s, 61, 12345, keep_candidates=keep))
        err = float(np.max(np.abs(got - want)))
        assert err <= 1e-5, f"sample_around differs from the reference by {err:g} (keep_candidates={keep})"
    scores = rng.normal(0, 1, 203).astype(np.float32)
    scores[[5, 77]] = scores[9]  # ties keep the lower index first
    scores[11] = np.nan  # NaN ranks after every number
    rows = rng.normal(0, 1, (203, 5)).astype(np.float32)
    want = best_k(ref, scores, 13, rows)
    got = best_k(device, scores, 13, rows)
    assert np.array_equal(to_numpy(got.indices), want.indices), "best_k indices differ from the reference"
    assert np.array_equal(to_numpy(got.scores), want.scores), "best_k scores differ from the reference"
    assert np.array_equal(to_numpy(got.rows), want.rows), "best_k rows differ from the reference"


def check_pf_stage(device: Device) -> None:
    """pf_stage (sample, pose, score, best k as one op) of the upper body: the same kept samples as
    the reference, their scores to float32 rounding."""
    from .models.upper_body import pf_sigma
    from .ops.pf import pf_stage

    rng = np.random.default_rng(8)
    chain, params, scene, gray, depth = _body_scene(rng)
    cand = (params + rng.normal(0, 0.01, (4, chain.n_params))).astype(np.float32)
    sigma = pf_sigma(chain).astype(np.float32)
    ref = get_device("numpy")
    want = pf_stage(ref, chain, cand, sigma, 64, 99, scene, gray, depth, k=5)
    got = pf_stage(device, chain, cand, sigma, 64, 99, scene, gray, depth, k=5)
    assert np.array_equal(to_numpy(got.indices), want.indices), (
        f"pf_stage keeps samples {to_numpy(got.indices)}, the reference {want.indices}"
    )
    err = float(np.max(np.abs(to_numpy(got.scores) - want.scores) / (1 + np.abs(want.scores))))
    err = max(err, float(np.max(np.abs(to_numpy(got.rows) - want.rows))))
    assert err <= 1e-4, f"pf_stage differs from the reference by {err:.3g}"


def check_pose_residuals(device: Device) -> None:
    """pose_residuals of a few poses of the upper body, and of the central-difference stack the LM
    evaluates (the rows it reads): against the reference to float32 rounding."""
    from .ops.pose_residuals import pose_residuals

    rng = np.random.default_rng(9)
    chain, params, scene, gray, depth = _body_scene(rng)
    P = chain.n_params
    poses = (params + rng.normal(0, 0.02, (3, P))).astype(np.float32)
    ref = get_device("numpy")
    want = pose_residuals(ref, chain, poses, scene, gray, depth)
    got = to_numpy(pose_residuals(device, chain, poses, scene, gray, depth))
    err = float(np.max(np.abs(got - want)))
    assert err <= 1e-4, f"pose_residuals differs from the reference by {err:.3g}"
    h = np.float32(1e-3)
    stack = np.repeat(poses[:1], 2 * P + 1, axis=0)
    stack[1 : P + 1] += h * np.eye(P, dtype=np.float32)
    stack[P + 1 :] -= h * np.eye(P, dtype=np.float32)
    want = pose_residuals(ref, chain, stack, scene, gray, depth)
    got = to_numpy(pose_residuals(device, chain, stack, scene, gray, depth, central=True))
    read = np.vstack([np.ones((1, want.shape[1]), bool), np.tile(chain.jacobian_sparsity(
        np.concatenate([scene.rgb.part, scene.depth.part])).T, (2, 1))])  # fmt: skip
    err = float(np.max(np.abs(got - want)[read]))
    assert err <= 1e-4, f"pose_residuals (central differences) differs from the reference by {err:.3g}"


def check_face_bundle(device: Device) -> None:
    """landmark_residuals of a small random face model and two parameter vectors: residuals and
    Jacobian against the reference (float64 where the device has it)."""
    from .models.camera import Camera
    from .ops.face_bundle import LandmarkFrames, LandmarkModel, landmark_residuals

    rng = np.random.default_rng(11)
    K, A, S, n = 4, 2, 3, 2
    model = LandmarkModel(rng.normal(0, 40, (K, 3)), rng.normal(0, 3, (K, 3, A)), rng.normal(0, 1, (K, 3, S, A)),
                          Camera(500.0, 500.0, 160.0, 120.0))  # fmt: skip
    frames = LandmarkFrames(rng.uniform(50, 250, (n, K, 2)), rng.uniform(0.5, 1.5, (n, K)),
                            scale=rng.uniform(0.5, 2.0, n * (6 + A) + S), prior=np.ones(S), prior_mean=np.zeros(S))
    x = np.concatenate([np.concatenate([rng.normal(0, 0.3, 3), [0.0, 0.0, 500.0], rng.normal(0, 1, A)])
                        for _ in range(n)] + [rng.normal(0, 1, S)])  # fmt: skip
    y = np.stack([x, x * 1.01]) / frames.scale
    dt = np.float64 if device.fp64 else np.float32
    want = landmark_residuals(get_device("numpy"), y, model, frames)
    got = landmark_residuals(device, device.asarray(y.astype(dt)) if device.backend != "numpy" else y, model, frames)
    for name, g, w in zip(("residuals", "Jacobian"), got, want):
        err = float(np.max(np.abs(to_numpy(g) - w)) / max(np.max(np.abs(w)), 1.0))
        assert err <= (1e-10 if dt == np.float64 else 1e-5), f"landmark_residuals ({name}) differs by {err:.3g} (relative)"


def check_face_points(device: Device) -> None:
    """project_faces of a few face hypotheses: points and facing against the reference to float32
    rounding."""
    from .models.camera import Camera
    from .ops.face_points import project_faces

    rng = np.random.default_rng(12)
    N, K, D = 16, 5, 2
    states = np.concatenate([rng.normal(0, 0.3, (N, 3)), rng.normal([0, 0, 600], [20, 20, 50], (N, 3)),
                             rng.normal(0, 1, (N, D))], axis=1).astype(np.float32)  # fmt: skip
    model = np.concatenate([rng.normal(0, 40, (K, 3, 1)), rng.normal(0, 3, (K, 3, D))], axis=2).astype(np.float32)
    cam = Camera(500.0, 500.0, 160.0, 120.0)
    want_p, want_f = project_faces(get_device("numpy"), states, model, cam)
    got_p, got_f = project_faces(device, states, model, cam)
    err = float(np.max(np.abs(to_numpy(got_p) - want_p)))
    assert err <= 1e-2, f"project_faces (points) differs from the reference by {err:.3g} px"
    err = float(np.max(np.abs(to_numpy(got_f) - want_f)))
    assert err <= 1e-5, f"project_faces (facing) differs from the reference by {err:.3g}"


def check_face_relocate(device: Device) -> None:
    """relocate_points of a few feature points on a smooth texture: points, patches and matches against
    the reference to float32 rounding."""
    from .ops.face_relocate import relocate_points, sample_patches

    rng = np.random.default_rng(13)
    y, x = np.mgrid[0:60, 0:80]
    img = (120 + 60 * np.sin(x / 4.0) * np.cos(y / 5.0) + 20 * np.sin((x + y) / 7.0)).astype(np.float32)
    true = rng.uniform(15, 45, (4, 2))
    tpl = sample_patches(img, true, 8).astype(np.float32)
    start = (true + rng.normal(0, 1.0, true.shape)).astype(np.float32)
    want = relocate_points(get_device("numpy"), img, start, tpl, tpl, iterations=3, contrast=30.0)
    got = relocate_points(device, img, start, tpl, tpl, iterations=3, contrast=30.0)
    for name, g, w in zip(("points", "patches", "match"), got, want):
        err = float(np.max(np.abs(to_numpy(g) - w)))
        assert err <= 2e-3, f"relocate_points ({name}) differs from the reference by {err:.3g}"


CHECKS = [
    ("arrays", check_arrays),
    ("kinematics", check_kinematics),
    ("template", check_template),
    ("particles", check_particles),
    ("pf_stage", check_pf_stage),
    ("pose_residuals", check_pose_residuals),
    ("lm", check_lm),
    ("kalman", check_kalman),
    ("gating", check_gating),
    ("point_groups", check_point_groups),
    ("stereo", check_stereo),
    ("background", check_background),
    ("clusters", check_clusters),
    ("face_bundle", check_face_bundle),
    ("face_points", check_face_points),
    ("face_relocate", check_face_relocate),
]


def run(device: Device) -> list[dict]:
    """Run every check on ``device``: [{"check", "ok", "detail", "ms"}]."""
    rows = []
    for name, check in CHECKS:
        t0 = time.perf_counter()
        try:
            check(device)
            ok, detail = True, ""
        except Exception as e:  # noqa: BLE001 - reported per check
            ok, detail = False, f"{type(e).__name__}: {' '.join(str(e).split())[:300]}"
        rows.append({"check": name, "ok": ok, "detail": detail, "ms": (time.perf_counter() - t0) * 1e3})
    return rows

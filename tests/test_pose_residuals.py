"""pose_residuals (gputrack.ops.pose_residuals) against its composition and the reference.

The composition forward_kinematics -> rgbd_residuals is what the op promises; with ``central=True``
on a least_squares central-difference stack it computes the entries of paper 000's block-sparse
Jacobian (Fig. 2) and may leave the others, and every computed entry must equal the composition
to float rounding, whatever rows it is given.
"""

import numpy as np
import pytest
from tolerances import assert_close

import gputrack
from gputrack.ops.kinematics import forward_kinematics
from gputrack.ops.pose_residuals import _plan, pose_residuals
from gputrack.ops.template import RgbdScene, rgbd_residuals
from gputrack.sim import sequence
from gputrack.models.camera import DEFAULT_CAMERA as CAM
from gputrack.trackers.body.template import sparse_template

REF = gputrack.device("numpy")
SENTINEL = 1e9  # entries a central call may leave as they were


@pytest.fixture(scope="session", params=[False, True], ids=["14 params", "20 params"])
def scene(request):
    seq = sequence("arm_cross", frames=2, seed=0, shoulders=request.param)
    rgb, dep = sparse_template(seq.chain, seq.params[0], 64, 48)
    return seq.chain, seq[1], RgbdScene(rgb, dep, CAM)


def _stack(chain, problems, seed=0):
    """A least_squares central-difference stack around ``problems`` points near the rest pose."""
    rng = np.random.default_rng(seed)
    P = chain.n_params
    S = 2 * P + 1
    x = np.asarray(chain.rest_params())[None] + rng.normal(0, 0.02, (problems, P)) * np.r_[[1] * 14, [50] * (P - 14)]
    X = np.repeat(x, S, axis=0)
    for n in range(P):
        h = 2e-3 if n < 14 else 1.0
        X[1 + 2 * n :: S, n] += h
        X[2 + 2 * n :: S, n] -= h
    return X.astype(np.float32)


def _needed(chain, sc, problems):
    """(rows, M) bool: the entries a central call must compute (Fig. 2 and the problems' points)."""
    mask = chain.jacobian_sparsity(np.concatenate([sc.rgb.part, sc.depth.part]))  # (M, P)
    block = np.ones((2 * chain.n_params + 1, mask.shape[0]), bool)
    block[1::2] = mask.T
    block[2::2] = mask.T
    return np.tile(block, (problems, 1))


def _composed(device, chain, X, frame, sc):
    tf = forward_kinematics(device, chain, X)
    return gputrack.to_numpy(rgbd_residuals(device, tf, sc, frame.gray, frame.depth))


def test_plain_call_equals_composition_and_reference(device, scene):
    chain, frame, sc = scene
    X = _stack(chain, 3)[:50]
    got = gputrack.to_numpy(pose_residuals(device, chain, X, sc, frame.gray, frame.depth))
    assert got.shape == (50, sc.n) and got.dtype == np.float32
    assert_close(device, got, _composed(device, chain, X, frame, sc), atol=1e-6)
    # the reference at the device's poses, per row as the cost the LM sees (sum r^2, eq. 19): a
    # rendered frame has depth edges at the silhouette, where the float32 rounding of a projection
    # moves single residuals by up to ~1e-2 (rgbd_residuals is pinned entry by entry on smooth
    # scenes in test_template.py)
    tf = gputrack.to_numpy(forward_kinematics(device, chain, X))
    want = rgbd_residuals(REF, tf, sc, frame.gray, frame.depth).astype(np.float64)
    np.testing.assert_allclose((got.astype(np.float64) ** 2).sum(axis=1), (want**2).sum(axis=1), rtol=1e-4)


@pytest.mark.parametrize("problems", [1, 10])
def test_central_computes_the_block_sparse_entries(device, scene, problems):
    chain, frame, sc = scene
    X = _stack(chain, problems)
    want = _composed(device, chain, X, frame, sc)
    out = device.asarray(np.full(want.shape, SENTINEL, np.float32)) if device.backend != "numpy" else np.full(
        want.shape, SENTINEL, np.float32)  # fmt: skip
    got = gputrack.to_numpy(pose_residuals(device, chain, X, sc, frame.gray, frame.depth, central=True,
                                           out=out))  # fmt: skip
    need = _needed(chain, sc, problems)
    assert_close(device, got[need], want[need], atol=5e-5)
    if device.backend != "numpy":  # the plan's backends write nothing else
        assert (got[~need] == SENTINEL).all()


@pytest.mark.parametrize("lanes", [1, 4, 8, 16])
def test_opencl_plan_at_every_lane_width(device, scene, lanes):
    """OpenCL's plan (kernels/gt_template.cl REUSE=3) at each width ``gputrack tune`` may choose (1:
    the GPUs' build): the block-sparse entries as the composition's, nothing else written, also
    where a work-item's rows include a broken layout."""
    if device.backend != "opencl":
        pytest.skip("OpenCL kernel variants")
    from gputrack.backends.opencl import template as ocl
    from gputrack.ops.pose_residuals import _device_plan

    chain, frame, sc = scene
    X = _stack(chain, 3)
    X[4] += np.float32(0.01)  # row 4 (parameter 1's) moves every parameter: computed in full
    want = _composed(device, chain, X, frame, sc)
    tf = forward_kinematics(device, chain, X)
    rgb, dep, cam, p = sc.kernel_args(device)
    g, d = device.asarray(frame.gray.astype(np.float32)), device.asarray(frame.depth.astype(np.float32))
    out = device.asarray(np.full(want.shape, SENTINEL, np.float32))
    ocl.rgbd_residuals(device, tf, rgb, dep, g, d, cam, out, plan=_device_plan(device, chain, 3, lanes),
                       params={"lanes": lanes, "work_group": 4}, **p)  # fmt: skip
    got = gputrack.to_numpy(out)
    need = _needed(chain, sc, 3)
    need[4] = True
    assert_close(device, got[need], want[need], atol=5e-5)
    assert (got[~need] == SENTINEL).all()


@pytest.mark.parametrize("rows", [1, 10, 50])
def test_central_hint_on_rows_that_are_no_stack_computes_every_entry(device, scene, rows):
    """``central=True`` on rows that are not a central-difference stack (a solve's last step: its
    points only) computes every entry, as the plain call does."""
    chain, frame, sc = scene
    X = _stack(chain, 3)[:rows]
    want = _composed(device, chain, X, frame, sc)
    got = gputrack.to_numpy(pose_residuals(device, chain, X, sc, frame.gray, frame.depth, central=True))
    assert got.shape == want.shape
    assert_close(device, got, want, atol=5e-5)


def test_depth_tolerance_reaches_every_path(device, scene):
    """depth_tol in the plain and the block-sparse (central) evaluation equals the composition's."""
    chain, frame, sc = scene
    X = _stack(chain, 2)
    tol = RgbdScene(sc.rgb, sc.depth, CAM, depth_tol=2.0)
    want = _composed(device, chain, X, frame, tol)
    assert (want != _composed(device, chain, X, frame, sc)).any()
    for central in (False, True):
        got = gputrack.to_numpy(pose_residuals(device, chain, X, tol, frame.gray, frame.depth, central=central))
        need = _needed(chain, sc, 2) if central else np.ones(want.shape, bool)
        assert_close(device, got[need], want[need], atol=5e-5)


def test_central_with_a_broken_layout_is_still_exact(device, scene):
    """Rows that differ from their problem's point in more than their parameter are computed in full."""
    chain, frame, sc = scene
    X = _stack(chain, 2)
    rng = np.random.default_rng(5)
    X[3] += rng.normal(0, 0.01, X.shape[1]).astype(np.float32)  # row 3 (parameter 1's) moves everything
    want = _composed(device, chain, X, frame, sc)
    got = gputrack.to_numpy(pose_residuals(device, chain, X, sc, frame.gray, frame.depth, central=True))
    need = _needed(chain, sc, 2)
    need[3] = True
    assert_close(device, got[need], want[need], atol=5e-5)


def test_plan_groups_rows_that_move_the_same_parts():
    chain = sequence("arm_cross", frames=2, seed=0).chain
    S = 2 * chain.n_params + 1
    order, moved = _plan(chain, 10, 8)
    assert order.shape == (moved.shape[0] * 8,) and set(order) == set(range(10 * S))
    dep = chain.dependency_mask()
    for g, rows in enumerate(order.reshape(-1, 8)):
        for r in rows:
            s = r % S
            parts = np.ones(chain.n_parts, bool) if s == 0 else dep[:, (s - 1) // 2]
            np.testing.assert_array_equal(parts, moved[g].astype(bool))


def test_bad_input(device, scene):
    chain, frame, sc = scene
    X = _stack(chain, 1)
    with pytest.raises(TypeError, match="chain: expected a gputrack.models.Chain"):
        pose_residuals(device, "body", X, sc, frame.gray, frame.depth)
    with pytest.raises(ValueError, match=r"params: expected shape \(n=\d+, %d\), got \(\d+, 5\)" % chain.n_params):
        pose_residuals(device, chain, X[:, :5], sc, frame.gray, frame.depth)
    with pytest.raises(ValueError, match="params: expected at least one"):
        pose_residuals(device, chain, X[:0], sc, frame.gray, frame.depth)
    with pytest.raises(ValueError, match="params: expected finite values"):
        bad = X.copy()
        bad[0, 0] = np.nan
        pose_residuals(device, chain, bad, sc, frame.gray, frame.depth)
    with pytest.raises(ValueError, match="out: expected a float32 array of shape"):
        small = np.empty((3, 4), np.float32) if device.backend == "numpy" else device.empty((3, 4), np.float32)
        pose_residuals(device, chain, X, sc, frame.gray, frame.depth, out=small)

"""One particle-filter stage (gputrack.ops.pf.pf_stage) against its composition and the reference.

The composition sample_around -> forward_kinematics -> rgbd_cost -> best_k on the same device is
what pf_stage promises to compute; Taichi and OpenCL run it with a partial evaluation of the parts
no sampled parameter moves (cascade stages), which must not change the scores beyond float rounding.
"""

import dataclasses
import re

import numpy as np
import pytest
from tolerances import assert_matches, tolerance

import gputrack
from gputrack.models.upper_body import pf_sigma
from gputrack.ops.kinematics import forward_kinematics
from gputrack.ops.particles import best_k, sample_around
from gputrack.ops.pf import pf_stage
from gputrack.ops.template import RgbdScene, rgbd_cost
from gputrack.sim import sequence
from gputrack.trackers.body import BodyTracker, BodyTrackerConfig

REF = gputrack.device("numpy")
SEED = 2**40 + 12345


@pytest.fixture(scope="session")  # built once, not again per device (see test_body_tracker.py)
def scene():
    """Frame 1 of a simulated sequence, the RgbdScene of the template at frame 0 (default constants),
    and 10 candidates near the truth."""
    seq = sequence("arm_cross", frames=2, seed=0)
    tracker = BodyTracker(REF, seq.params[0], config=BodyTrackerConfig(lm_iterations=0, samples=200))
    tracker.track(seq[1].gray, seq[1].depth)
    rgb, dep = tracker._templates
    rng = np.random.default_rng(3)
    cand = (seq.params[1][None] + rng.normal(0, 0.01, (10, seq.chain.n_params))).astype(np.float32)
    groups = tracker._groups()
    return seq.chain, seq[1], RgbdScene(rgb, dep, tracker.camera), cand, groups


def _sigma(chain, group):
    return (pf_sigma(chain) * group).astype(np.float32)


def _composed(device, chain, cand, sigma, n, frame, sc, k):
    samples = sample_around(device, cand, sigma, n, SEED, keep_candidates=True)
    tf = forward_kinematics(device, chain, samples)
    cost = rgbd_cost(device, tf, sc, frame.gray, frame.depth)
    return samples, cost, best_k(device, cost.total, k, rows=samples)


@pytest.mark.parametrize("which", ["torso", "right arm", "left arm", "all", "none"])
@pytest.mark.parametrize("n,k", [(1500, 10), (13, 3), (129, 10)])
def test_pf_stage_equals_its_composition(device, scene, which, n, k):
    chain, frame, sc, cand, groups = scene
    group = {"torso": groups[0], "right arm": groups[1], "left arm": groups[2]}.get(which)
    if which == "all":
        group = np.ones(chain.n_params, bool)
    if which == "none":
        group = np.zeros(chain.n_params, bool)
    sigma = _sigma(chain, group)
    c = cand[: min(10, n)]
    got = pf_stage(device, chain, c, sigma, n, SEED, sc, frame.gray, frame.depth, k=k)
    samples, cost, want = _composed(device, chain, c, sigma, n, frame, sc, k)
    # scores: the k lowest of the composition's costs (sums of 256 terms: scale as rgbd_cost's tests)
    assert_matches(device, got.scores, gputrack.to_numpy(want.scores), scale=50)
    idx = gputrack.to_numpy(got.indices)
    total = gputrack.to_numpy(cost.total)
    assert_matches(device, got.scores, total[idx], scale=50)
    np.testing.assert_array_equal(gputrack.to_numpy(got.rows), gputrack.to_numpy(samples)[idx])
    assert got.rows.shape == (k, chain.n_params) and got.indices.shape == (k,)


@pytest.mark.parametrize("which", ["torso", "all"])
def test_pf_stage_with_a_depth_tolerance_equals_its_composition(device, scene, which):
    """depth_tol reaches the fused kernels, in the partial (cascade) and the full evaluation."""
    chain, frame, sc, cand, groups = scene
    sigma = _sigma(chain, groups[0] if which == "torso" else np.ones(chain.n_params, bool))
    tol = RgbdScene(sc.rgb, sc.depth, sc.camera, depth_tol=2.0)
    got = pf_stage(device, chain, cand, sigma, 300, SEED, tol, frame.gray, frame.depth)
    samples, cost, want = _composed(device, chain, cand, sigma, 300, frame, tol, 10)
    assert_matches(device, got.scores, gputrack.to_numpy(want.scores), scale=50)
    plain = pf_stage(device, chain, cand, sigma, 300, SEED, sc, frame.gray, frame.depth)
    assert gputrack.to_numpy(got.scores)[0] < gputrack.to_numpy(plain.scores)[0]


def test_pf_stage_matches_reference(device, scene):
    chain, frame, sc, cand, groups = scene
    for group in groups:
        sigma = _sigma(chain, group)
        got = pf_stage(device, chain, cand, sigma, 1500, SEED, sc, frame.gray, frame.depth)
        want = pf_stage(REF, chain, cand, sigma, 1500, SEED, sc, frame.gray, frame.depth)
        assert_matches(device, got.scores, want.scores, scale=50)
        # the same samples win (the generator is shared; rounding may swap near-ties only)
        same = gputrack.to_numpy(got.indices) == want.indices
        assert same.mean() >= 0.8, (gputrack.to_numpy(got.indices), want.indices)
        rtol, atol = tolerance(device, scale=10)
        np.testing.assert_allclose(gputrack.to_numpy(got.rows)[same], want.rows[same], rtol=rtol, atol=atol)


def test_pf_stage_keeps_the_best_candidate(device, scene):
    """The first sample of each block is its candidate: a stage never returns a worse best score."""
    chain, frame, sc, cand, groups = scene
    base = rgbd_cost(device, forward_kinematics(device, chain, cand), sc, frame.gray, frame.depth)
    got = pf_stage(device, chain, cand, _sigma(chain, groups[1]), 300, SEED, sc, frame.gray, frame.depth)
    rtol, atol = tolerance(device, scale=50)
    assert gputrack.to_numpy(got.scores)[0] <= gputrack.to_numpy(base.total).min() * (1 + rtol) + atol


def whole(message: str) -> str:
    """A ``pytest.raises(match=...)`` pattern that matches ``message`` whole, nothing more or less."""
    return "^" + re.escape(message) + r"\Z"


def test_pf_stage_rejects_bad_input(device, scene):
    chain, frame, sc, cand, groups = scene
    sigma = _sigma(chain, groups[0])
    args = (sc, frame.gray, frame.depth)
    with pytest.raises(TypeError, match=whole("chain: expected a gputrack.models.Chain, got str")):
        pf_stage(device, "upper body", cand, sigma, 100, 1, *args)
    with pytest.raises(ValueError, match=whole("candidates: expected shape (C=10, P=14), got (10, 5)")):
        pf_stage(device, chain, cand[:, :5], sigma, 100, 1, *args)
    negative = -sigma - 1
    with pytest.raises(ValueError, match=whole(f"sigma: expected finite standard deviations >= 0, got {negative}")):
        pf_stage(device, chain, cand, negative, 100, 1, *args)
    with pytest.raises(ValueError, match=whole("sigma: expected a real (P=14,) array, got float32 (3,)")):
        pf_stage(device, chain, cand, sigma[:3], 100, 1, *args)
    if device.backend != "numpy":
        want = "sigma: expected a NumPy array (it decides on the host which parts move), got a DeviceArray"
        with pytest.raises(TypeError, match=whole(want)):
            pf_stage(device, chain, cand, device.asarray(sigma), 100, 1, *args)
    with pytest.raises(ValueError, match=whole("n: expected C=10 <= n and n (P + C + 1) < 2**31, got 5")):
        pf_stage(device, chain, cand, sigma, 5, 1, *args)
    with pytest.raises(ValueError, match=whole("k: expected an integer in [1, n=100], got 0")):
        pf_stage(device, chain, cand, sigma, 100, 1, *args, k=0)
    with pytest.raises(ValueError, match=whole("seed: expected an integer in [0, 2**64), got -1")):
        pf_stage(device, chain, cand, sigma, 100, -1, *args)
    two_parts = dataclasses.replace(chain, parts=chain.parts[:2], n_params=8, param_names=chain.param_names[:8],
                                    rest=chain.rest[:8])  # fmt: skip
    with pytest.raises(ValueError, match=whole("scene.rgb.part: expected part indices in [0, J=2), got 4")):
        pf_stage(device, two_parts, cand[:, :8], sigma[:8], 100, 1, *args)


def test_pf_stage_writes_into_out(device, scene):
    """``out=`` (an earlier result) receives the same k rows, scores and indices as a fresh call;
    a stage's own candidates or a result of other sizes is refused."""
    chain, frame, sc, cand, groups = scene
    sigma = _sigma(chain, groups[1])
    args = (sc, frame.gray, frame.depth)
    fresh = pf_stage(device, chain, cand, sigma, 300, SEED, *args)
    out = pf_stage(device, chain, cand, sigma, 300, SEED + 1, *args)  # other values, same sizes
    got = pf_stage(device, chain, cand, sigma, 300, SEED, *args, out=out)
    for name in ("indices", "scores", "rows"):
        assert getattr(got, name) is getattr(out, name)
        np.testing.assert_array_equal(gputrack.to_numpy(getattr(got, name)), gputrack.to_numpy(getattr(fresh, name)))
    chained = pf_stage(device, chain, fresh.rows, sigma, 300, SEED, *args, out=out)  # rows of another result: fine
    assert chained.rows is out.rows
    with pytest.raises(ValueError, match="out.rows: expected an array other than"):
        pf_stage(device, chain, out.rows, sigma, 300, SEED, *args, out=out)
    with pytest.raises(ValueError, match=r"out.indices: expected a int32 array of shape \(3,\)"):
        pf_stage(device, chain, cand, sigma, 300, SEED, *args, k=3, out=out)
    with pytest.raises(TypeError, match="out: expected a gputrack.BestK"):
        pf_stage(device, chain, cand, sigma, 300, SEED, *args, out=(out.indices, out.scores, out.rows))


@pytest.mark.parametrize("lanes", [1, 4])
def test_opencl_partial_evaluation_with_other_lane_counts(device, scene, lanes, monkeypatch):
    """The OpenCL kernels as a GPU builds them (one hypothesis per work-item) and with 4 lanes:
    a cascade stage's partial evaluation still equals the composition."""
    if device.backend != "opencl":
        pytest.skip("OpenCL's lane count (the other backends fix their own)")
    from gputrack.backends.opencl import template as cl_template

    # forced through the stage's launch parameters (a GPU's own choice is 1 whatever CPU_LANES is)
    default = cl_template.default_params(device)
    monkeypatch.setattr(cl_template, "default_params", lambda dev: {**default, "lanes": lanes})
    used = []
    real = cl_template._kernel
    monkeypatch.setattr(cl_template, "_kernel", lambda dev, name, **defines: used.append(defines["LANES"])
                        or real(dev, name, **defines))  # fmt: skip
    chain, frame, sc, cand, groups = scene
    for group in groups:
        sigma = _sigma(chain, group)
        got = pf_stage(device, chain, cand, sigma, 129, SEED, sc, frame.gray, frame.depth)
        samples, cost, want = _composed(device, chain, cand, sigma, 129, frame, sc, 10)
        assert_matches(device, got.scores, gputrack.to_numpy(want.scores), scale=50)
        idx = gputrack.to_numpy(got.indices)
        assert_matches(device, got.scores, gputrack.to_numpy(cost.total)[idx], scale=50)
    assert lanes in used, used  # the stage ran the variant asked for

"""The landmark residuals of paper 003's bundle adjustment on the device (gputrack.ops.face_bundle):
every device against the NumPy host model, the host model's Jacobian against central differences,
the held plan taking the next solve's frames, which devices use the kernel, bad input. A synthetic
model (no data files needed)."""

import dataclasses

import numpy as np
import pytest
from tolerances import assert_matches

import gputrack
from gputrack.models import Camera
from gputrack.ops.face_bundle import LandmarkFrames, LandmarkModel, LandmarkResiduals, evaluate
from gputrack.trackers.face.bundle import device_model

REF = gputrack.device("numpy")
K, A, S, N = 10, 5, 15, 7
F = 6 + A
P = N * F + S


def scene(seed=0, B=2, prior=True, S=S):
    """A random model, one solve's frames (some landmarks of weight 0) and B parameter vectors of
    heads 500-700 mm in front of the camera."""
    rng = np.random.default_rng(seed)
    model = LandmarkModel(rng.normal(0, 40, (K, 3)), rng.normal(0, 3, (K, 3, A)), rng.normal(0, 1, (K, 3, S, A)),
                          Camera(700.0, 690.0, 320.0, 240.0))  # fmt: skip
    sw = rng.uniform(0.5, 1.5, (N, K))
    sw[rng.random((N, K)) < 0.1] = 0.0
    frames = LandmarkFrames(rng.uniform(100, 500, (N, K, 2)), sw, scale=rng.uniform(0.5, 2.0, N * F + S),
                            prior=rng.uniform(0, 2, S) if prior else None,
                            prior_mean=rng.normal(0, 1, S) if prior else None)  # fmt: skip
    x = np.zeros((B, N * F + S))
    fr = x[:, : N * F].reshape(B, N, F)
    fr[..., :3] = rng.normal(0, 0.4, (B, N, 3))
    fr[0, 0, :3] = [1e-4, -2e-4, 0.0]  # a near-zero rotation: the coefficients' series
    fr[..., 3:6] = rng.normal([0, 0, 600], [30, 30, 60], (B, N, 3))
    fr[..., 6:] = rng.normal(0, 1, (B, N, A))
    x[:, N * F :] = rng.normal(0, 1, (B, S))
    return model, frames, x


def _dt(device):
    return np.float64 if device.fp64 else np.float32


@pytest.mark.parametrize("prior,S", [(True, S), (False, S), (False, 0)])  # S = 0: the generic PCA model's
def test_devices_match_the_host_model(device, prior, S):
    model, frames, x = scene(prior=prior, S=S)
    plan = LandmarkResiduals(device, model, frames)
    frames = plan.frames  # checked
    y = x / frames.scale
    dt = _dt(device)
    Y = device.asarray(y.astype(dt)) if device.backend != "numpy" else y
    R = gputrack.to_numpy(plan.residuals(Y)).copy()
    J = gputrack.to_numpy(plan.jacobian(Y)).copy()
    r_want, J_want = evaluate(model, frames, x)
    J_want = J_want * frames.scale  # the Jacobian with respect to y = x / scale
    assert R.shape == (2, frames.rows) and J.shape == (2, frames.rows, N * F + S) and R.dtype == dt
    # the residuals are px (up to ~1e3), the Jacobian's entries up to ~1e4 (scaled): relative tolerances
    assert_matches(device, R, r_want, dt, scale=np.abs(r_want).max())
    assert_matches(device, J, J_want, dt, scale=np.abs(J_want).max())
    assert np.all(J[J_want == 0] == 0)  # the entries that cannot be non-zero stay 0
    assert frames.rows == 2 * K * N + (S if prior else 0)


def test_host_jacobian_matches_central_differences():
    model, frames, x = scene(seed=3, B=1)
    frames.check(model)
    _, J = evaluate(model, frames, x)
    h = 1e-6 * np.maximum(np.abs(x[0]), 1.0)
    num = np.empty_like(J[0])
    for p in range(P):
        e = np.zeros_like(x)
        e[0, p] = h[p]
        num[:, p] = (evaluate(model, frames, x + e, False)[0][0] - evaluate(model, frames, x - e, False)[0][0]) / (2 * h[p])
    np.testing.assert_allclose(J[0], num, rtol=1e-5, atol=1e-5 * np.abs(num).max())


def test_a_held_plan_takes_the_next_frames(device):
    model, frames, x = scene(seed=5, B=1)
    _, other, _ = scene(seed=6, B=1)
    other = dataclasses.replace(other, scale=np.full(P, 0.7))
    plan = LandmarkResiduals(device, model, frames)
    dt = _dt(device)
    Y = x / 0.7
    Yd = device.asarray(Y.astype(dt)) if device.backend != "numpy" else Y
    plan.residuals(Yd)
    plan.update(other)
    got_r = gputrack.to_numpy(plan.residuals(Yd)).copy()
    got_J = gputrack.to_numpy(plan.jacobian(Yd)).copy()
    fresh = LandmarkResiduals(device, model, other)
    assert_matches(device, got_r, gputrack.to_numpy(fresh.residuals(Yd)), dt)
    assert_matches(device, got_J, gputrack.to_numpy(fresh.jacobian(Yd)), dt)
    with pytest.raises(ValueError, match="with a prior .*, got 7 frames without one"):
        plan.update(dataclasses.replace(other, prior=None, prior_mean=None))


def test_which_devices_use_the_kernel(device):
    if device.backend == "numpy":
        assert not device_model(device)
    elif device.spec == "taichi:vulkan" and device.info.kind != "gpu":
        assert not device_model(device)  # lavapipe: the host model is faster
    else:
        assert device_model(device)


def test_bad_input():
    model, frames, x = scene(B=1)
    cam = Camera(700.0, 690.0, 320.0, 240.0)
    with pytest.raises(ValueError, match=r"L0: expected shape \(K=10, 3, A\)"):
        LandmarkModel(model.mean, model.L0[:5], model.G, cam)
    with pytest.raises(ValueError, match="G: expected shape"):
        LandmarkModel(model.mean, model.L0, model.G[..., :2], cam)
    with pytest.raises(ValueError, match="mean: expected finite"):
        LandmarkModel(np.full((K, 3), np.nan), model.L0, model.G, cam)
    with pytest.raises(TypeError, match="camera: expected a gputrack.models.Camera"):
        LandmarkModel(model.mean, model.L0, model.G, (700, 700, 320, 240))
    with pytest.raises(ValueError, match="min_depth"):
        LandmarkModel(model.mean, model.L0, model.G, cam, min_depth=0.0)
    bad = [
        (dataclasses.replace(frames, target=frames.target[:, :5]), r"target: expected shape \(n >= 1, K=10, 2\)"),
        (dataclasses.replace(frames, sqrt_weights=-frames.sqrt_weights - 1), "sqrt_weights: expected values >= 0"),
        (dataclasses.replace(frames, scale=frames.scale[:-1]), "scale: expected shape"),
        (dataclasses.replace(frames, scale=np.zeros(P)), "scale: expected values > 0"),
        (dataclasses.replace(frames, prior=-np.ones(S)), "prior: expected values >= 0"),
        (dataclasses.replace(frames, target=np.full((N, K, 2), np.inf)), "target: expected finite"),
    ]
    for f, msg in bad:
        with pytest.raises(ValueError, match=msg):
            LandmarkResiduals(REF, model, f)
    plan = LandmarkResiduals(REF, model, frames)
    with pytest.raises(ValueError, match=rf"points: expected shape \(B >= 1, P={P}\)"):
        plan.residuals(x[:, :-1])
    with pytest.raises(TypeError, match="frames: expected LandmarkFrames"):
        LandmarkResiduals(REF, model, {"target": frames.target})
    _, fewer, _ = scene(seed=1, B=1)
    with pytest.raises(ValueError, match="frames: expected 7 frames"):
        plan.update(dataclasses.replace(fewer, target=fewer.target[:3], sqrt_weights=fewer.sqrt_weights[:3],
                                        scale=np.ones(3 * F + S)))  # fmt: skip

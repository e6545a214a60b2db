"""The projection of face hypotheses on the device (gputrack.ops.face_points): every device against the
float64 host model, the pose model's projection, the particle filter's turn test from the facing it
returns, bad input."""

import numpy as np
import pytest

import gputrack
from gputrack.models import Camera
from gputrack.models.pose import facing, project, rodrigues
from gputrack.ops.face_points import project_faces
from gputrack.trackers.face import FaceConfig
from gputrack.trackers.face.pf import FaceParticleFilter, shape_model

REF = gputrack.device("numpy")
CAM = Camera(700.0, 690.0, 319.5, 239.5)
N, K, D = 300, 10, 4


def hypotheses(seed=0):
    rng = np.random.default_rng(seed)
    states = np.concatenate([rng.normal(0, 0.4, (N, 3)), rng.normal([0, 0, 600], [30, 30, 80], (N, 3)),
                             rng.normal(0, 1, (N, D))], axis=1).astype(np.float32)  # fmt: skip
    states[0, :3] = [1e-4, -2e-4, 0.0]  # a near-zero rotation: the coefficients' series
    states[1, :3] = 0.0
    states[2, 3:6] = [0.0, 0.0, -40.0]  # behind the camera: projected far off the image, clipped
    model = shape_model(rng.normal(0, 40, (K, 3)), rng.normal(0, 3, (K, 3, D)))
    return states, model


def test_devices_match_the_host_model(device):
    states, model = hypotheses()
    want_p, want_f = project_faces(REF, states.astype(np.float64), model.astype(np.float64), CAM)
    S, M = (states, model) if device.backend == "numpy" else (device.asarray(states), device.asarray(model))
    points, facing = project_faces(device, S, M, CAM)
    got_p, got_f = gputrack.to_numpy(points), gputrack.to_numpy(facing)
    assert got_p.shape == (N, K, 2) and got_p.dtype == np.float32 and got_f.shape == (N,)
    # float32 pixels of a few hundred: a few 1e-5 relative
    np.testing.assert_allclose(got_p, want_p, rtol=2e-5, atol=2e-3)
    np.testing.assert_allclose(got_f, want_f, atol=2e-6)
    assert np.abs(got_p[2]).max() > 1e4  # behind the camera: far off any image
    out = project_faces(device, S, M, CAM)
    again = project_faces(device, S, M, CAM, out=out)
    assert again[0] is out[0] and again[1] is out[1]
    np.testing.assert_array_equal(gputrack.to_numpy(again[0]), got_p)


def test_host_model_projects_like_the_pose_model():
    states, model = hypotheses(1)
    st = states.astype(np.float64)
    shapes = model[:, :, 0].astype(np.float64) + np.einsum("kcd,nd->nkc", model[:, :, 1:].astype(np.float64), st[:, 6:])
    want = project(CAM, rodrigues(st[:, :3]), st[:, 3:6], shapes)
    points, facing = project_faces(REF, st, model.astype(np.float64), CAM)
    ok = np.arange(N) != 2  # the one behind the camera: clipped here, not in project()
    np.testing.assert_allclose(points[ok], want[ok], rtol=1e-6, atol=1e-3)
    t = st[:, 3:6]
    np.testing.assert_allclose(facing, np.einsum("nc,nc->n", rodrigues(st[:, :3])[:, :, 2], t)
                               / np.linalg.norm(t, axis=1), atol=1e-6)  # fmt: skip


def test_the_turn_test_reads_the_facing():
    cfg = FaceConfig(particles=N, seed=3)
    pf = FaceParticleFilter(CAM, np.zeros(D), np.ones(D), cfg, np.random.default_rng(3))
    states, model = hypotheses(2)
    st = states.astype(np.float64)
    st[:40, :3] = [0.0, np.radians(80.0), 0.0]  # turned 80 deg (> max_turn 75)
    st[:40, 3:6] = [0.0, 0.0, 600.0]
    pf.reset(st[10], K=K)
    scores = np.linspace(0, 9, N)
    _, facing = project_faces(REF, st, model.astype(np.float64), CAM)
    np.testing.assert_array_equal(pf.log_weights(scores, st, facing), pf.log_weights(scores, st))
    assert np.all(pf.log_weights(scores, st, facing)[:40] == -np.inf)


def test_bad_input():
    states, model = hypotheses()
    with pytest.raises(ValueError, match=r"states: expected shape \(N=300, P=10\), got \(300, 9\)"):
        project_faces(REF, states[:, :9], model, CAM)
    with pytest.raises(ValueError, match="shape_model: expected shape"):
        project_faces(REF, states, model[:, :2], CAM)
    with pytest.raises(TypeError, match="camera: expected a gputrack.models.Camera"):
        project_faces(REF, states, model, (700, 700, 320, 240))
    bad = states.copy()
    bad[5, 4] = np.nan
    with pytest.raises(ValueError, match="states"):
        project_faces(REF, bad, model, CAM)
    with pytest.raises(ValueError, match="at least one hypothesis"):
        project_faces(REF, states[:0], model, CAM)
    with pytest.raises(TypeError, match="out"):
        project_faces(REF, states, model, CAM, out=np.zeros((N, K, 2), np.float32))


def test_device_inputs_are_float32(device):
    if device.backend == "numpy":
        pytest.skip("the numpy device takes float64 too (it computes in float64)")
    states, model = hypotheses()
    with pytest.raises(TypeError, match="states: expected dtype float32"):
        project_faces(device, states.astype(np.float64), model, CAM)


def test_facing_is_the_cosine_to_the_ray():
    """models.pose.facing: 1 for a model looking along the ray, cos 40 deg turned by 40 deg about y,
    0 edge-on, and per row for stacks."""
    t = np.array([0.0, 0.0, 600.0])
    turns = np.radians([0.0, 40.0, 90.0])
    R = rodrigues(np.stack([np.zeros(3), turns, np.zeros(3)], axis=1))
    np.testing.assert_allclose(facing(R, np.tile(t, (3, 1))), np.cos(turns), atol=1e-12)
    assert facing(np.eye(3), t) == pytest.approx(1.0)

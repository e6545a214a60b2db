"""Paper 003's face tracker: the particle filter's pieces (eq. 11-13), the re-localisation (eq. 14), every
device against the reference on the start and the first tracked frame, Table 1 on a simulated
sequence (full protocol on the fast local devices), a lost face, a Haar start and bad input."""

import dataclasses
import functools

import numpy as np
import pytest

import gputrack
from gputrack.models import Camera
from gputrack.models.face import FaceModel, PcaFaceModel, load_ict
from gputrack.models.pose import project, rodrigues
from gputrack.trackers.face import FaceConfig, FaceTracker
from gputrack.trackers.face.metrics import pose_errors, shape_error, table1
from gputrack.trackers.face.pf import DETECTION_SPREAD, FaceParticleFilter, project_hypotheses
from gputrack.trackers.face.tracker import detect_faces

REF = gputrack.device("numpy")


@functools.lru_cache(maxsize=1)
def _data():
    from gputrack.sim.face import face_sequence

    ict = load_ict()
    return ict, FaceModel.from_ict(ict), PcaFaceModel.from_ict(ict), face_sequence("expressions", frames=90, ict=ict)


@functools.lru_cache(maxsize=4)
def _frames(n):
    seq = _data()[3]
    return [seq[k] for k in range(n)]


@pytest.fixture(scope="module")
def data():
    try:
        return _data()
    except FileNotFoundError as e:
        pytest.skip(f"the ICT face data is absent (shared/data/ict_face beside the repository, or $GPUTRACK_DATA/ict_face): {e}")


def start_points(frames, noise=1.0, seed=0):
    rng = np.random.default_rng(seed)
    return np.array([f.landmarks2d + rng.normal(0, noise, f.landmarks2d.shape) for f in frames])


# -- the particle filter's pieces (host code) ---------------------------------------------------------------


def test_hypotheses_project_like_the_pose_model():
    rng = np.random.default_rng(0)
    cam = Camera(700, 690, 319.5, 239.5)
    states = np.concatenate([rng.normal(0, 0.3, (50, 3)), rng.normal([0, 0, 600], 20, (50, 3)),
                             rng.normal(0, 1, (50, 4))], axis=1)  # fmt: skip
    mean, basis = rng.normal(0, 40, (10, 3)), rng.normal(0, 3, (10, 3, 4))
    want = project(cam, rodrigues(states[:, :3]), states[:, 3:6], mean + np.einsum("kcd,nd->nkc", basis, states[:, 6:]))
    got = project_hypotheses(cam, states, mean, basis)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-3)


def test_particle_filter_weights_and_estimate():
    cfg = FaceConfig(particles=400, seed=3)
    a_std = np.array([0.0, 0.5, 0.2])  # the first component is fixed (std 0)
    pf = FaceParticleFilter(Camera(700, 700, 320, 240), np.array([0.3, 0.0, 0.1]), a_std, cfg,
                            np.random.default_rng(cfg.seed))  # fmt: skip
    state = np.array([0.0, 0.1, 0.0, 5.0, -3.0, 600.0, 0.9, 0.2, 0.1])
    pf.reset(state, K=10)
    assert pf.estimate[6] == 0.3  # held at its mean
    pf.propose(np.zeros((10, 3)), np.zeros((10, 3, 3)))
    assert np.all(pf.proposed[:, 6] == 0.3)
    np.testing.assert_allclose(pf.proposed.std(axis=0)[:6], pf.noise()[:6], rtol=0.15)
    np.testing.assert_allclose(pf.noise()[7:], cfg.kappa * a_std[1:])  # eq. 12: kappa sigma_a
    scores = np.linspace(-2, 9, 400)
    lw = pf.log_weights(scores, pf.proposed)
    z = (pf.proposed[:, 7:] - [0.0, 0.1]) / a_std[1:]
    np.testing.assert_allclose(lw, -((10 - scores) ** 2) / 2 - 0.5 * (z**2).sum(axis=1))  # eq. 13, sigma = 1
    noise = pf.noise()  # of this frame (the update changes the velocity it adapts to)
    est = pf.update(scores)
    best = int(np.argmax(lw))
    near = np.all(np.abs(pf.states - pf.states[best]) <= cfg.near * noise, axis=1)
    w = np.exp(lw - lw.max())
    np.testing.assert_allclose(est, np.average(pf.states[near], axis=0, weights=w[near]))
    assert est[6] == 0.3  # the held component exactly at its mean, not a weighted mean's rounding of it
    np.testing.assert_allclose(pf.weights.sum(), 1.0)
    assert pf.best_score == scores[best]
    # beyond eq. 13: a face turned away from the camera, or a head outside the depth range, weighs 0
    odd = np.tile(state, (3, 1))
    odd[0, :3] = [0.0, np.radians(80.0), 0.0]  # turned 80 deg (> max_turn 75)
    odd[1, 5], odd[2, 5] = 100.0, 5000.0  # nearer / farther than depth_range
    assert np.all(pf.log_weights(np.full(3, 10.0), odd) == -np.inf)
    assert np.isfinite(pf.log_weights(np.full(1, 10.0), state[None])).all()


def test_a_detection_is_mixed_into_the_next_proposal_only():
    cfg = FaceConfig(particles=2000, seed=1)
    a_std = np.array([0.5, 0.2])
    pf = FaceParticleFilter(Camera(700, 700, 320, 240), np.zeros(2), a_std, cfg, np.random.default_rng(cfg.seed))
    state = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 600.0, 0.0, 0.0])
    pf.reset(state, K=10)
    det = np.array([0.1, -0.2, 0.05, 20.0, -10.0, 650.0, 0.3, 0.1])
    pf.mix(det, 0.25)
    got = pf.sample()
    m = 500  # the last quarter: around the detection, with DETECTION_SPREAD (translation as a fraction of its depth)
    spread = np.concatenate([DETECTION_SPREAD[:3], np.array(DETECTION_SPREAD[3:]) * det[5], cfg.kappa * a_std])
    assert np.all(np.abs(got[-m:].mean(axis=0) - det) <= 0.2 * spread)  # ~4.5 standard errors
    np.testing.assert_allclose(got[-m:].std(axis=0), spread, rtol=0.15)
    noise = pf.noise()  # the rest from the dynamics (eq. 12), at rest here
    np.testing.assert_allclose(got[:-m].std(axis=0), noise, rtol=0.15)
    assert np.abs(got[:-m] - state).max(axis=0)[5] < 6 * noise[5]
    again = pf.sample()  # the next proposal: the dynamics only
    assert np.abs(again - state).max(axis=0)[5] < 6 * noise[5]
    with pytest.raises(ValueError, match=r"state: expected 8 finite values, got \(7,\)"):
        pf.mix(det[:7], 0.25)
    with pytest.raises(ValueError, match=r"share: expected a fraction in \[0, 1\], got 1.5"):
        pf.mix(det, 1.5)
    pf.mix(det, 0.25)
    pf.reset(state, K=10)  # a restart drops a pending detection
    assert np.abs(pf.sample() - state).max(axis=0)[5] < 6 * noise[5]


def test_a_move_to_a_detection_is_a_new_start_not_motion():
    cfg = FaceConfig(particles=200, seed=2)
    pf = FaceParticleFilter(Camera(700, 700, 320, 240), np.zeros(1), np.array([0.5]), cfg, np.random.default_rng(2))
    state = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 600.0, 0.0])
    det = np.array([0.0, 0.3, 0.0, 30.0, 0.0, 620.0, 0.0])
    for best_mixed in (True, False):
        pf.reset(state, K=10)
        pf.mix(det, 0.1)
        pf.propose_states()
        scores = np.zeros(200)
        scores[195 if best_mixed else 5] = 10.0  # the last 20 hypotheses are the detection's
        est = pf.update(scores)
        if best_mixed:
            assert np.abs(est[3] - det[3]) < 10 and np.all(pf.velocity == 0.0)  # no drift by the jump next frame
        else:
            np.testing.assert_allclose(pf.velocity, est - state)  # eq. 12's velocity


def test_a_move_carries_every_hypothesis_and_counts_as_motion():
    cfg = FaceConfig(particles=50, seed=4)
    pf = FaceParticleFilter(Camera(700, 700, 320, 240), np.zeros(1), np.array([0.5]), cfg, np.random.default_rng(4))
    with pytest.raises(RuntimeError, match=r"call reset\(\) before move\(\)"):
        pf.move(np.zeros(7))
    state = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 600.0, 0.0])
    pf.reset(state, K=10)
    pf.propose_states()
    est = pf.update(np.linspace(0.0, 9.0, 50))
    states, velocity = pf.states.copy(), pf.velocity.copy()
    step = np.array([0.01, -0.02, 0.0, 1.5, 0.0, -4.0, 0.0])
    pf.move(est + step)
    np.testing.assert_allclose(pf.states, states + step)
    np.testing.assert_allclose(pf.velocity, velocity + step)  # eq. 12's drift from the moved estimate
    np.testing.assert_allclose(pf.estimate, est + step)
    with pytest.raises(ValueError, match=r"state: expected 7 finite values, got \(6,\)"):
        pf.move(np.zeros(6))


def test_detect_faces_of_given_sizes(data):
    gray = _frames(1)[0].gray
    full = detect_faces(gray)
    assert len(full) == 1
    w = full[0][2]
    for scale in (1.1, 1.2):  # fewer scales searched
        sized = detect_faces(gray, sizes=(w / 1.4, 1.4 * w), scale_factor=scale)
        assert len(sized) == 1
        np.testing.assert_allclose(sized[0], full[0], atol=0.1 * w)
    assert detect_faces(gray, sizes=(2 * w, 4 * w)) == []  # no face that large
    assert detect_faces(gray, sizes=(w / 4, w / 2)) == []  # nor that small


# -- every device against the reference --------------------------------------------------------------------


def _run(device, data, frames, config, n_track):
    _, model, _, seq = data
    trk = FaceTracker(device, model, seq.camera, config)
    ests = trk.start(np.array([f.gray for f in frames[:7]]), start_points(frames[:7]))
    for f in frames[7 : 7 + n_track]:
        ests.append(trk.track(f.gray))
    return trk, ests


def test_devices_match_the_reference(device, data):
    frames = _frames(8)
    cfg = FaceConfig(particles=256)
    _, want = _run(REF, data, frames, cfg, 1)
    _, got = _run(device, data, frames, cfg, 1)
    for w, g in zip(want, got):  # the start (7 bundle-adjusted frames) and the first tracked frame
        np.testing.assert_allclose(g.rvec, w.rvec, atol=2e-4)
        np.testing.assert_allclose(g.translation, w.translation, atol=0.05)
        np.testing.assert_allclose(g.expression, w.expression, atol=2e-3)
        np.testing.assert_allclose(g.identity, w.identity, atol=2e-3)
        np.testing.assert_allclose(g.confidence, w.confidence, atol=1e-4)


def test_table1_on_a_simulated_sequence(device, data):
    """Table 1 on the 'expressions' sequence (a person not among the model's 26, 90 frames): the
    multilinear tracker within bounds set from measurements (taichi:cpu and opencl), and ahead of the
    generic PCA model in pitch and yaw (where it leads in most of face_seeds' runs; in depth this one
    run is 27.7 against 19.7 mm since the templates' views, 26.8 against 29.0 before). The protocol runs on taichi:cpu (the suite's time); every other device
    is pinned to the reference by test_devices_match_the_reference."""
    if device.spec != "taichi:cpu":
        pytest.skip(f"{device.spec}: the 90-frame protocol runs on taichi:cpu; "
                    "test_devices_match_the_reference pins this device to the reference")  # fmt: skip
    _, model, pca, seq = data
    frames = _frames(90)
    from gputrack.demos.face import track_sequence

    class Frames:  # the rendered frames, shared by both runs
        camera, identity = seq.camera, seq.identity

        def __len__(self):
            return len(frames)

        def __getitem__(self, k):
            return frames[k]

    rec = track_sequence(device, Frames(), model, FaceConfig())
    t = table1(rec["errors"])
    assert rec["lost"].sum() == 0
    # the feature points (eq. 14) within a few px of the true landmarks, every frame measured
    assert rec["feature_px"].shape == (90,) and np.isfinite(rec["feature_px"]).all()
    assert 0.1 < rec["feature_px"].mean() < 4.0
    assert t["x"][0] < 3.0 and t["y"][0] < 3.0 and t["z"][0] < 40.0
    assert t["roll"][0] < 2.0 and t["pitch"][0] < 6.0 and t["yaw"][0] < 6.0
    assert np.isfinite(rec["errors"]).all()
    generic = table1(track_sequence(device, Frames(), pca, FaceConfig())["errors"])
    assert t["pitch"][0] < generic["pitch"][0] and t["yaw"][0] < generic["yaw"][0]


def test_the_true_identity_is_the_simulated_persons(data):
    """The floor runs' identity (``true_identity``): the model's coordinates of the simulated person,
    whose shape in the first frames it fits (at the best deformation) far better than the model's
    mean identity does."""
    from gputrack.demos.face import true_identity

    ict, model, _, seq = data
    s = true_identity(ict, seq, model)
    assert s.shape == (model.identity_dims,) and np.isfinite(s).all()

    def misfit(identity, frame):  # RMS mm of the frame's true points from the identity's best deformation
        mean, basis = model.expression_basis(identity)
        B = basis.reshape(-1, basis.shape[-1])
        a = np.linalg.lstsq(B, (frame.shape - mean).ravel(), rcond=None)[0]
        return np.sqrt(((B @ a - (frame.shape - mean).ravel()) ** 2).mean())

    for frame in _frames(3):
        assert misfit(s, frame) < 0.2 * misfit(model.identity_mean, frame)  # 0.29 against 3.46 mm


def test_landmark_floor_is_the_size_the_landmarks_cannot_show(data):
    """The bundle adjustment on perfect feature points of the model's mean face, turning by up to
    30 deg: at its own size the depth comes out right; the same face 10 % larger, whose points are
    those of the mean face 10 % nearer, comes out at the mean size, z 1/1.1 of the truth (the scale
    no landmark shows). The key frames are those of the widest spread of face directions."""
    from types import SimpleNamespace

    from gputrack.demos.face import landmark_floor

    _, model, _, seq = data
    base = model.shape(model.identity_mean, model.expression_mean)
    yaws = np.radians(np.linspace(-30.0, 30.0, 13))
    out = {}
    for scale in (1.0, 1.1):
        frames = []
        for k, yaw in enumerate(yaws):
            rvec = np.array([0.0, yaw, 0.0])
            t = np.array([5.0 * k, -10.0, 600.0 + 10.0 * k])
            frames.append(SimpleNamespace(rvec=rvec, translation=t, visible=np.ones(model.K, bool),
                                          landmarks2d=project(seq.camera, rodrigues(rvec), t, scale * base)))
        out[scale] = landmark_floor(model, frames, seq.camera, FaceConfig())
    assert abs(out[1.0]["relative"]) < 1e-6 and out[1.0]["rms"] < 1e-6
    # the size is what the points cannot show; the rotations they show exactly, at either size
    assert max(out[1.0]["rotation_deg"]) < 1e-4 and max(out[1.1]["rotation_deg"]) < 1e-2
    assert abs(out[1.1]["relative"] - (1 / 1.1 - 1)) < 1e-4 and out[1.1]["rms"] < 1e-3
    np.testing.assert_allclose(out[1.1]["z_mm"], 660 * (1 - 1 / 1.1), rtol=1e-3)  # the frames' mean depth 660 mm
    assert sorted(out[1.0]["keyframes"]) == [0, 1, 2, 9, 10, 11, 12]  # the turns' two ends
    with pytest.raises(ValueError, match="at least n=7"):
        landmark_floor(model, frames[:6], seq.camera, FaceConfig())


def test_a_lost_face_is_reported_and_found_again(device, data):
    if device.spec != "taichi:cpu":
        pytest.skip("runs on taichi:cpu, inside the test run's own taichi:cpu phase")
    dev = device
    frames = _frames(12)
    cfg = FaceConfig(particles=256, redetect_after=2)
    trk, _ = _run(dev, data, frames, cfg, 1)
    blank = np.full_like(frames[0].gray, 90)
    ests = [trk.track(blank) for _ in range(3)]
    assert all(e.lost and e.confidence == 0.0 for e in ests)
    assert all(np.isfinite(e.translation).all() and np.isfinite(e.rvec).all() for e in ests)
    assert np.isnan(ests[0].features).all()
    back = [trk.track(f.gray) for f in frames[9:12]]
    assert not back[-1].lost and back[-1].confidence > 0.4
    err = pose_errors([back[-1].rotation], [back[-1].translation], [frames[11].rotation], [frames[11].translation])
    assert err[0, :2].max() < 10.0  # x, y within 10 mm after the re-detection


def test_the_face_is_searched_for_at_the_size_of_the_estimates_depth(data):
    """The detection proposals' search (``_detected_box``) looks for the box a frontal face at the
    estimate's depth gets: an estimate turned 65 deg away from a face that looks at the camera still
    finds that face's box, though its own points span less than half of it (a search sized by
    their extent would look for boxes too small, and a filter turned away would never come back).
    The proposal drawn from it is frontal and keeps the estimate's depth, which the box's size agrees
    with."""
    _, model, _, seq = data
    frames = _frames(8)
    trk = FaceTracker(REF, model, seq.camera, FaceConfig(particles=64))
    trk.start(np.array([f.gray for f in frames[:7]]), start_points(frames[:7]))
    img = frames[7].gray.astype(np.float32)
    box, _ = trk._detected_box(img, near=True)
    assert box is not None
    turned = trk.pf.estimate.copy()
    turned[1] += np.radians(65.0)
    trk.pf.reset(turned, model.K)
    again, last = trk._detected_box(img, near=True)
    assert again is not None and abs(again[2] - box[2]) < 0.15 * box[2]
    assert 1.4 * np.ptp(last[:, 0]) / 0.49 < box[2]  # beyond the largest box a search by the points' extent takes
    # the turn contradicts the box: hypotheses around the box's frontal pose, at the estimate's depth (the box's
    # size agrees with it)
    trk._propose_detected(img)
    state, share = trk.pf._mix
    assert trk.proposals == 1 and share == trk.config.detect_share
    assert np.degrees(np.linalg.norm(state[:3])) < 5.0 and state[5] == pytest.approx(turned[5])


def test_a_filter_turned_far_is_searched_for_every_frame(data):
    """Detection proposals are made every ``detect_every``-th frame, and every frame while the
    estimate is turned further than ``DETECT_FAR`` from the camera: on the first tracked frame
    (not a 10th), a filter put 60 deg off a face that looks at the camera gets hypotheses around
    the face; put 35 deg off (turned, but not that far) it waits for the 10th frame."""
    from gputrack.trackers.face.tracker import DETECT_FAR, DETECT_TURN

    _, model, _, seq = data
    frames = _frames(8)
    assert DETECT_TURN < 35.0 < DETECT_FAR < 60.0
    made = {}
    for turn in (60.0, 35.0):
        trk = FaceTracker(REF, model, seq.camera, FaceConfig(particles=64, detect_every=10, redetect_after=1000))
        trk.start(np.array([f.gray for f in frames[:7]]), start_points(frames[:7]))
        wrong = trk.pf.estimate.copy()
        wrong[1] += np.radians(turn)
        trk.pf.reset(wrong, model.K)
        assert trk.frame % 10 != 0
        trk.track(frames[7].gray)
        made[turn] = trk.proposals
    assert made == {60.0: 1, 35.0: 0}


def test_a_filter_on_a_wrong_pose_moves_to_the_detected_face(device, data):
    """The filter put on a pose turned 35 deg and moved 15 mm from the face (its NCC still above
    ``lost_score``): with detection proposals every frame (made where the box contradicts the
    estimate) it is back on the face within a few frames; without them it is still off (the control).
    The pose refinement is off in both runs: it too brings such a filter back (2.8 px from the third
    frame on, measured), and this test is the proposals'."""
    if device.spec != "taichi:cpu":
        pytest.skip("runs on taichi:cpu, inside the test run's own taichi:cpu phase")
    _, model, _, seq = data
    frames = _frames(15)
    errors = {}
    for every in (1, 0):
        cfg = FaceConfig(particles=256, detect_every=every, redetect_after=1000, refine_pose=False)
        trk = FaceTracker(device, model, seq.camera, cfg)
        trk.start(np.array([f.gray for f in frames[:7]]), start_points(frames[:7]))
        wrong = trk.pf.estimate.copy()
        wrong[1] += np.radians(35.0)
        wrong[3] += 15.0
        trk.pf.reset(wrong, model.K)
        ests = [trk.track(f.gray) for f in frames[7:15]]
        assert not any(e.lost for e in ests)
        assert (trk.proposals >= 1 and trk.proposals_taken >= 1) if every else trk.proposals == 0
        errors[every] = [np.abs(e.landmarks - f.landmarks2d).mean() for e, f in zip(ests, frames[7:15])]
    back, control = np.mean(errors[1][2:]), np.mean(errors[0][2:])  # px, from the third frame on (1.4 / 5.8 measured)
    assert back < 4.0 and back < 0.7 * control, (errors[1], errors[0])
    assert control > 4.5, errors[0]


def _pose_misfit(camera, shape, points):
    """misfit(rvec, t): the RMS px of the pose's projected ``shape`` from the finite ``points``."""
    ok = np.isfinite(points).all(axis=1)
    return lambda rvec, t: np.sqrt(np.mean((project(camera, rodrigues(rvec), t, shape) - points)[ok] ** 2))


def _assert_least_squares_pose(misfit, rvec, t):
    """No small step of a pose parameter fits better than (rvec, t): a least-squares fit."""
    best = misfit(rvec, t)
    for i in range(6):
        for d in (-1.0, 1.0):
            x = np.concatenate([rvec, t])
            x[i] += d * (1e-3 if i < 3 else 0.2)
            assert misfit(x[:3], x[3:]) > best - 1e-6


def test_the_pose_is_refined_to_the_feature_points(data):
    """``refine_pose`` with ``refine_deformation=0`` (the pose alone): the first tracked frame's filter
    estimate is the same with and without it (same stream), and so are the re-localised points;
    refined, the reported pose fits them (PnP) better than the filter's, and every hypothesis moved
    with it."""
    _, model, _, seq = data
    frames = _frames(8)
    runs = {}
    for refine in (False, True):
        cfg = FaceConfig(particles=128, refine_pose=refine, refine_deformation=0.0,
                         learn_identity=False)  # the shape stays the fitted one  # fmt: skip
        trk = FaceTracker(REF, model, seq.camera, cfg)
        trk.start(np.array([f.gray for f in frames[:7]]), start_points(frames[:7]))
        runs[refine] = (trk, trk.track(frames[7].gray))
    (plain, p), (refined, r) = runs[False], runs[True]
    np.testing.assert_array_equal(r.features, p.features)
    assert np.isfinite(r.features).all()
    shape = refined._shape(r.expression)
    misfit = _pose_misfit(seq.camera, shape, r.features)
    assert misfit(r.rvec, r.translation) < misfit(p.rvec, p.translation) - 0.05  # 1.48 vs 1.68 px measured
    np.testing.assert_allclose(r.landmarks, project(seq.camera, r.rotation, r.translation, shape))
    _assert_least_squares_pose(misfit, r.rvec, r.translation)
    np.testing.assert_array_equal(r.expression, p.expression)  # the pose only
    step = np.concatenate([r.rvec - p.rvec, r.translation - p.translation, np.zeros(len(r.expression))])
    assert np.abs(step).max() > 0
    np.testing.assert_allclose(refined.pf.states - plain.pf.states, np.broadcast_to(step, plain.pf.states.shape),
                               atol=1e-9)  # fmt: skip
    np.testing.assert_allclose(refined.pf.estimate[:3], r.rvec)
    # points that would move the pose beyond the bundle adjustment's box (pose_range) are not trusted
    state = refined.pf.estimate.copy()
    for shift, taken in ((2.0, True), (150.0, False)):  # px, every point: 1.6 mm sideways / about 130 mm (> 30)
        refined.pf.reset(state, model.K)
        refined._host = {"lost": False, "state": state.copy(), "gray": frames[7].gray.astype(np.float32)}
        refined._refine({"features": r.landmarks + [shift, 0.0], "match": np.ones(model.K, np.float32)})
        moved = refined._host["state"][3] - state[3]
        assert (0.2 < moved < 30.0) if taken else moved == 0.0, (shift, moved)
        assert np.array_equal(refined.pf.estimate, refined._host["state"])


def test_the_deformation_is_refined_with_the_pose(data):
    """``refine_deformation`` (default 0.5): the reported pose and deformation are the least-squares fit
    to the re-localised points with the prior around the filter's deformation (no small step of any
    of them does better), and every hypothesis moved by the whole step."""
    _, model, _, seq = data
    frames = _frames(8)
    runs = {}
    for refine in (False, True):
        trk = FaceTracker(REF, model, seq.camera, FaceConfig(particles=128, refine_pose=refine, learn_identity=False))
        trk.start(np.array([f.gray for f in frames[:7]]), start_points(frames[:7]))
        runs[refine] = (trk, trk.track(frames[7].gray))
    (plain, p), (refined, r) = runs[False], runs[True]
    np.testing.assert_array_equal(r.features, p.features)  # the same filter estimate and points before the fit
    sd = 0.5 * model.expression_std
    free = sd > 0  # components the model holds (std 0) stay: tests/test_face_refine.py
    np.testing.assert_array_equal(r.expression[~free], p.expression[~free])
    assert np.abs(r.expression - p.expression)[free].max() > 1e-3

    def objective(x):
        u = project(seq.camera, rodrigues(x[:3]), x[3:6], refined._shape(x[6:]))
        return float(np.sum((u - r.features) ** 2) + np.sum(((x[6:] - p.expression)[free] / sd[free]) ** 2))

    x = np.concatenate([r.rvec, r.translation, r.expression])
    best = objective(x)
    assert best < objective(np.concatenate([p.rvec, p.translation, p.expression]))
    for i in [*range(6), *(6 + np.flatnonzero(free))]:
        for d in (-1.0, 1.0):
            y = x.copy()
            y[i] += d * (1e-3 if i < 3 else 0.2 if i < 6 else 0.02 * sd[i - 6])
            assert objective(y) > best - 1e-6, i
    np.testing.assert_allclose(r.landmarks, project(seq.camera, r.rotation, r.translation, refined._shape(r.expression)))
    step = x - np.concatenate([p.rvec, p.translation, p.expression])
    np.testing.assert_allclose(refined.pf.states - plain.pf.states, np.broadcast_to(step, plain.pf.states.shape),
                               atol=1e-9)  # fmt: skip


def test_points_that_do_not_match_their_templates_are_left_out(data):
    """``min_match`` (default 0.5): a re-localised point whose match with its template is below it is
    NaN in the frame's features and the fit ignores it (moving it changes nothing); where fewer than
    six match, the six that match best are kept; min_match = -1 keeps every point."""
    _, model, _, seq = data
    frames = _frames(8)
    trk = FaceTracker(REF, model, seq.camera, FaceConfig(particles=128, learn_identity=False))
    trk.start(np.array([f.gray for f in frames[:7]]), start_points(frames[:7]))
    est = trk.track(frames[7].gray)
    assert np.isfinite(est.features).all()  # every point of this frame matches
    state, points = trk.pf.estimate.copy(), frames[7].landmarks2d.astype(np.float32)

    def refine(match, pts=points, config=None):
        trk.config = config or FaceConfig(particles=128, learn_identity=False)
        trk.pf.reset(state, model.K)
        trk._host = {"lost": False, "state": state.copy(), "gray": frames[7].gray.astype(np.float32)}
        trk._refine({"features": pts, "match": np.asarray(match, np.float32)})
        return trk._host["features"], trk._host["state"]

    match = np.full(model.K, 0.9)
    match[[0, 4]] = [0.2, 0.49]  # below 0.5
    feats, fitted = refine(match)
    assert np.isnan(feats[[0, 4]]).all() and np.isfinite(np.delete(feats, [0, 4], axis=0)).all()
    moved = points.copy()
    moved[[0, 4]] += 25.0  # the left-out points anywhere: the same fit
    np.testing.assert_array_equal(refine(match, moved)[1], fitted)
    assert not np.allclose(refine(np.ones(model.K), moved)[1], fitted)  # counted, they move it
    few = np.array([0.9, 0.1, 0.9, 0.2, 0.9, 0.3, 0.9, 0.05, 0.9, 0.25])  # five match: the best of the rest too
    feats, _ = refine(few)
    np.testing.assert_array_equal(np.isfinite(feats).all(axis=1), [1, 0, 1, 0, 1, 1, 1, 0, 1, 0])
    feats, _ = refine(match, config=FaceConfig(particles=128, learn_identity=False, min_match=-1.0))
    assert np.isfinite(feats).all()
    with pytest.raises(ValueError, match=r"FaceConfig.min_match: expected a number in \[-1, 1\], got 1.5"):
        FaceConfig(min_match=1.5)


def test_templates_come_from_the_view_nearest_the_estimate(data):
    """``template_views`` (degrees): a tracked frame where at least eight points matched and whose face
    direction is more than this from every kept source's becomes a source of the templates; each
    point's template is cut from the source nearest the estimate's direction where that point
    matched, warped from that source's pose. 0 keeps the first frame's alone."""
    from gputrack.models.pose import rotation_vector
    from gputrack.ops.face_relocate import sample_patches
    from gputrack.trackers.face.templates import template_warp

    _, model, _, seq = data
    frames = _frames(9)
    cfg = FaceConfig(particles=128, learn_identity=False, template_views=10.0)
    trk = FaceTracker(REF, model, seq.camera, cfg)
    trk.start(np.array([f.gray for f in frames[:7]]), start_points(frames[:7]))
    views = trk.views
    assert len(views) == 1
    first_pose, shape = views.sources[0][2], trk._shape(trk.pf.estimate[6:])

    def turned(deg):  # the first source's pose turned by deg about the camera's y axis
        return rotation_vector(rodrigues(np.array([0.0, np.radians(deg), 0.0])) @ rodrigues(first_pose[0])), first_pose[1]

    img, pts = frames[8].gray.astype(np.float32), frames[8].landmarks2d
    unmatched = pts.copy()
    unmatched[[1, 3]] = np.nan
    assert not views.add(img, pts, turned(6.0), shape)  # within 10 deg of the first
    assert not views.add(img, np.where(np.arange(model.K)[:, None] < 3, np.nan, pts), turned(15.0), shape)  # 7 matched
    assert views.add(img + 1.0, unmatched, turned(15.0), shape)
    assert not views.add(img, pts, turned(20.0), shape)  # 5 deg from the second
    np.testing.assert_array_equal(views.choice(turned(12.0)[0]), [1, 0, 1, 0, 1, 1, 1, 1, 1, 1])
    np.testing.assert_array_equal(views.choice(turned(3.0)[0]), np.zeros(model.K))

    # the templates: each point's from its source, warped from that source's pose
    pose = turned(13.0)
    got = views.templates(pose, shape)
    for i in (0, 1):
        image, points, source_pose, source_shape = views.sources[i]
        k = views.choice(pose[0]) == i
        warp = template_warp(seq.camera, source_pose, source_shape[k], pose, shape[k])
        np.testing.assert_array_equal(got[k], sample_patches(image, points[k], cfg.template, warp).astype(np.float32))

    # the picture: a row per source, a cell per point, blank where the point did not match
    from gputrack.trackers.face.pictures import draw_template_sources

    pic = draw_template_sources(views, scale=2)
    side = 2 * cfg.template
    assert pic.shape == (2 * (side + 4) + 4, 140 + model.K * (side + 4), 3) and pic.dtype == np.uint8
    cell = lambda r, k: pic[4 + r * (side + 4) : 4 + r * (side + 4) + side, 140 + k * (side + 4) :][:, :side]
    assert (cell(1, 1) == 40).all() and (cell(1, 3) == 40).all() and (cell(1, 2) != 40).any()

    # tracking: a frame matched everywhere and turned from the first adds a source (here any turn counts)
    trk = FaceTracker(REF, model, seq.camera, dataclasses.replace(cfg, template_views=1e-6))
    trk.start(np.array([f.gray for f in frames[:7]]), start_points(frames[:7]))
    est = trk.track(frames[7].gray)
    assert np.isfinite(est.features).all() and len(trk.views) == trk.template_sources == 2
    np.testing.assert_array_equal(trk.views.sources[1][1], est.features)
    trk = FaceTracker(REF, model, seq.camera, dataclasses.replace(cfg, template_views=0.0))
    trk.start(np.array([f.gray for f in frames[:7]]), start_points(frames[:7]))
    trk.track(frames[7].gray)
    assert len(trk.views) == 1
    with pytest.raises(ValueError, match=r"FaceConfig.template_views"):
        FaceConfig(template_views=-1.0)


def test_feature_points_given_replace_eq14s(data):
    """``track(gray, features=)``: points from elsewhere (here the true landmarks) are the frame's
    feature points, the pose is fitted to them, and eq. 14 still gives the next frame's patches; NaN
    points are unknown; bad points are a clear error."""
    _, model, _, seq = data
    frames = _frames(9)
    runs = {}
    for given in (False, True):
        trk = FaceTracker(REF, model, seq.camera, FaceConfig(particles=128, learn_identity=False))  # the shape stays
        trk.start(np.array([f.gray for f in frames[:7]]), start_points(frames[:7]))
        truth = frames[7].landmarks2d.copy()
        truth[3] = np.nan  # unknown
        runs[given] = (trk, trk.track(frames[7].gray, features=truth if given else None))
    (plain, p), (trk, g) = runs[False], runs[True]
    np.testing.assert_array_equal(g.features, truth)
    assert not np.isnan(p.features).any()
    ok = np.isfinite(truth).all(axis=1)
    # the pose is fitted to the points given (the known ones): no small step of it fits them better, and it
    # projects nearer them than the pose fitted to eq. 14's points
    _assert_least_squares_pose(_pose_misfit(seq.camera, trk._shape(g.expression), truth), g.rvec, g.translation)
    assert np.abs(g.landmarks - truth)[ok].mean() < np.abs(p.landmarks - truth)[ok].mean()
    # eq. 14 ran all the same: the previous patches are the same in both
    def previous(t):
        x = t.scheduler.buffers["previous"]
        return x.numpy() if hasattr(x, "numpy") else np.asarray(x)

    np.testing.assert_array_equal(previous(trk), previous(plain))
    with pytest.raises(ValueError, match=r"features: expected shape \(10, 2\), got \(9, 2\)"):
        trk.track(frames[8].gray, features=truth[:9])
    with pytest.raises(ValueError, match="features: expected finite values or NaN"):
        trk.track(frames[8].gray, features=np.full((10, 2), np.inf))


def test_start_from_a_haar_face_box(device, data):
    if device.spec != "taichi:cpu":
        pytest.skip("runs on taichi:cpu, inside the test run's own taichi:cpu phase")
    dev = device
    _, model, _, seq = data
    frames = _frames(10)
    trk = FaceTracker(dev, model, seq.camera, FaceConfig(particles=256))
    ests = trk.start(np.array([f.gray for f in frames[:7]]))
    for f in frames[7:10]:
        ests.append(trk.track(f.gray))
    err = np.abs(ests[-1].landmarks - frames[9].landmarks2d)
    assert np.median(err) < 6.0  # px
    assert shape_error(model, ests[-1].identity, ests[-1].expression, frames[9].shape) < 8.0


def test_the_start_anchors_the_templates_to_all_start_frames(data):
    """A detector's error in the first frame would stay in the templates; anchored, the start's points
    (the templates' and every start frame's) carry only the mean error of the 7 frames."""
    _, model, _, seq = data
    frames = _frames(7)
    gray = np.array([f.gray for f in frames])
    truth = np.array([f.landmarks2d for f in frames])
    noisy = start_points(frames, noise=1.0, seed=3)
    noisy[3, 2] = np.nan  # unknown in one frame: stays unknown
    ests = FaceTracker(REF, model, seq.camera, FaceConfig(particles=64)).start(gray, noisy)
    got = np.array([e.features for e in ests])
    assert np.isnan(got[3, 2]).all() and np.isfinite(np.delete(got.reshape(-1, 2), 3 * 10 + 2, axis=0)).all()
    before, after = np.hypot(*(noisy - truth).transpose(2, 0, 1)), np.hypot(*(got - truth).transpose(2, 0, 1))
    assert np.nanmean(after[0]) < 0.6 * np.nanmean(before[0])  # the templates' points
    assert np.nanmean(after) < 0.6 * np.nanmean(before)
    plain = FaceTracker(REF, model, seq.camera, FaceConfig(particles=64, anchor_templates=False)).start(gray, noisy)
    np.testing.assert_array_equal(np.array([e.features for e in plain]), noisy)
    # the first frame's points only: the others are followed from them, the first frame's stay as given
    first = FaceTracker(REF, model, seq.camera, FaceConfig(particles=64)).start(gray, noisy[0])
    np.testing.assert_array_equal(first[0].features, noisy[0])


def test_bad_input(data):
    dev = REF
    _, model, _, seq = data
    frames = _frames(8)
    gray = np.array([f.gray for f in frames[:7]])
    trk = FaceTracker(dev, model, seq.camera, FaceConfig(particles=64))
    with pytest.raises(RuntimeError, match="call start"):
        trk.track(frames[7].gray)
    with pytest.raises(ValueError, match=r"frames: expected the first n=7 frames \(FaceConfig.keyframes\), got 6"):
        trk.start(gray[:6], start_points(frames[:6]))
    with pytest.raises(ValueError, match=r"landmarks: expected shape \(n=7, K=10, 2\), got \(7, 9, 2\)"):
        trk.start(gray, start_points(frames[:7])[:, :9])
    lm = start_points(frames[:7])
    lm[0, 3] = np.nan
    with pytest.raises(ValueError, match="every point of the first frame"):
        trk.start(gray, lm)
    with pytest.raises(ValueError, match="expected a face"):
        trk.start(np.zeros_like(gray))
    trk.start(gray, start_points(frames[:7]))
    with pytest.raises(ValueError, match=r"gray: expected a frame of the started size \(480, 640\), got \(240, 320\)"):
        trk.track(frames[7].gray[::2, ::2])
    with pytest.raises(ValueError, match="gray: expected finite pixel values"):
        trk.track(np.full((480, 640), np.nan, np.float32))
    with pytest.raises(ValueError, match="gray: expected a"):
        trk.track(frames[7].gray.astype(complex))
    with pytest.raises(TypeError, match="model: expected a FaceModel or PcaFaceModel, got str"):
        FaceTracker(dev, "model", seq.camera)
    with pytest.raises(ValueError, match="FaceConfig.particles: expected an int >= 1, got 0"):
        FaceConfig(particles=0)
    with pytest.raises(ValueError, match=r"FaceConfig.pose_range: expected \(radians, mm\) > 0"):
        dataclasses.replace(FaceConfig(), pose_range=(0.1,))
    with pytest.raises(ValueError, match="FaceConfig.relocate_contrast: expected a finite number >= 0, got -1"):
        FaceConfig(relocate_contrast=-1.0)
    with pytest.raises(ValueError, match=r"FaceConfig.relocate_shading: expected relocate_contrast > 0 .*, got "
                                         "relocate_contrast 0"):  # fmt: skip
        FaceConfig(relocate_shading=True, relocate_contrast=0.0)
    with pytest.raises(TypeError, match="FaceConfig.refine_pose: expected a bool, got 'no'"):
        FaceConfig(refine_pose="no")
    with pytest.raises(ValueError, match=r"FaceConfig.refine_deformation: expected a finite number >= 0, got -0.5"):
        FaceConfig(refine_deformation=-0.5)
    with pytest.raises(TypeError, match="FaceConfig.warp_templates: expected a bool, got 1"):
        FaceConfig(warp_templates=1)
    with pytest.raises(ValueError, match="FaceConfig.detect_every: expected an int >= 0, got -1"):
        FaceConfig(detect_every=-1)
    with pytest.raises(ValueError, match=r"FaceConfig.detect_share: expected a fraction in \[0, 1\], got 1.5"):
        FaceConfig(detect_share=1.5)
    # a flat (occluded) frame: reported lost, the pose stays finite
    est = trk.track(np.full((480, 640), 128, np.uint8))
    assert est.lost and est.confidence == 0.0 and np.isfinite(est.translation).all()


# -- the command line ---------------------------------------------------------------------------------------


def test_track_command_on_an_image_folder(device, tmp_path, data):
    if device.spec != "taichi:cpu":
        pytest.skip("runs on taichi:cpu, inside the test run's own taichi:cpu phase")
    import json

    import cv2

    from gputrack.cli import main

    _, _, _, seq = data
    frames = _frames(11)
    for k, f in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"{k:03d}.png"), f.gray)
    cam = seq.camera
    (tmp_path / "cam.json").write_text(json.dumps({"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}))
    (tmp_path / "first.json").write_text(json.dumps({"landmarks": start_points(frames[:1])[0].tolist()}))
    out = tmp_path / "poses.jsonl"
    assert main(["track", "face", "--video", str(tmp_path / "*.png"), "--camera", str(tmp_path / "cam.json"),
                 "--landmarks", str(tmp_path / "first.json"), "--device", "taichi:cpu", "--out", str(out),
                 "--save", str(tmp_path / "pics")]) == 0  # fmt: skip
    lines = [json.loads(s) for s in out.read_text().splitlines()]
    assert len(lines) == 12 and lines[-1]["frames"] == 11 and len(lines[-1]["identity"]) == 15
    # the command's lines are the library's estimates: FaceTracker on the same frames and start points
    _, model, _, _ = data
    trk = FaceTracker(device, model, cam, FaceConfig())
    want = trk.start(np.array([f.gray for f in frames[:7]]), start_points(frames[:1])[0])
    want += [trk.track(f.gray) for f in frames[7:]]
    for line, w in zip(lines[:11], want):
        np.testing.assert_allclose(line["rotation"], w.rotation, atol=1e-9)
        np.testing.assert_allclose(line["translation"], w.translation, atol=1e-6)
        np.testing.assert_allclose(line["landmarks"], w.landmarks, atol=1e-6)
    last = lines[10]
    err = pose_errors([np.array(last["rotation"])], [np.array(last["translation"])], [frames[10].rotation],
                      [frames[10].translation])  # fmt: skip
    # a start from one frame's points (1 px noise, followed into the other six by Lucas-Kanade) leaves the
    # pitch a few degrees off for this person: at this frame 6.0-9.6 deg, the largest angle's error, over
    # the filter's seeds 0-7 (measured with and without FaceConfig.warp_templates)
    assert err[0, :2].max() < 5.0 and err[0, 3:].max() < 12.0 and not last["lost"]
    assert (tmp_path / "pics" / "frame_00010.png").exists()


def test_track_command_reports_bad_input(tmp_path, capsys):
    import json

    from gputrack.cli import main

    assert main(["track", "face", "--video", str(tmp_path / "none*.png")]) == 1
    assert "expected a video, a directory of images or a glob pattern, found nothing" in capsys.readouterr().err
    (tmp_path / "lm.json").write_text(json.dumps({"landmarks": [[1, 2]] * 9}))
    assert main(["track", "face", "--video", str(tmp_path), "--landmarks", str(tmp_path / "lm.json")]) == 1
    assert 'expected "landmarks" of shape (10, 2) or (n, 10, 2), got (9, 2)' in capsys.readouterr().err
    (tmp_path / "m.npz").write_bytes(b"junk")
    assert main(["track", "face", "--video", str(tmp_path), "--model", str(tmp_path / "m.npz")]) == 1
    assert "expected an .npz face model, could not read it" in capsys.readouterr().err


def test_demo_command(device, tmp_path, capsys, data):
    if device.spec != "taichi:cpu":
        pytest.skip("runs on taichi:cpu, inside the test run's own taichi:cpu phase")
    import json

    from gputrack.cli import main

    assert main(["demo", "face", "--device", "taichi:cpu", "--frames", "9", "--sequence", "depth",
                 "--save", str(tmp_path), "--json", str(tmp_path / "r.json")]) == 0  # fmt: skip
    text = capsys.readouterr().out
    assert "Table 1: errors against the truth (sequence depth" in text and "true identity (floor)" in text
    rep = json.loads((tmp_path / "r.json").read_text())
    assert set(rep["table1"]) == {"multilinear", "generic PCA", "true identity (floor)"}
    assert all(np.isfinite(v[0]) for t in rep["table1"].values() for v in t.values())
    assert "detect" in [s["name"] for s in rep["stages"]] and "; detection proposals " in text  # timed and counted
    assert set(rep["detection_proposals"]) == set(rep["table1"])
    assert set(rep["template_sources"]) == set(rep["table1"]) and min(rep["template_sources"].values()) >= 1
    assert "; template sources " in text
    assert (tmp_path / "errors.png").exists() and (tmp_path / "frame_0008.png").exists()
    assert (tmp_path / "template_sources.png").exists()


def test_benchmark_cases_run_and_match_the_reference(device, data):
    """perf/bench_face.py's cases at a small size on taichi:cpu: the frame tracks, the NCC scores equal
    the reference's, the bundle step and its scipy peer reach about the same cost."""
    import argparse

    from tolerances import assert_matches

    from gputrack.benchmarks import face as bench

    if device.spec != "taichi:cpu":
        pytest.skip("runs on taichi:cpu, inside the test run's own taichi:cpu phase")
    dev = device
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args(["--frames", "9", "--particles", "64"])
    frame, score, bundle = bench.cases(dev, args)
    est = frame.run()
    assert np.isfinite(est.translation).all() and not est.lost
    assert_matches(dev, score.run(), score.reference(), scale=10.0 * 10)
    s = bundle.run()
    assert s.shape == (15,) and np.isfinite(s).all()
    peer = bundle.peers["scipy least_squares (trf, 5 iterations)"]()
    assert np.isfinite(peer.cost)

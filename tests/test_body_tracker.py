"""Paper 000's upper-body tracker end to end on every backend, and its rigid case on real RGB-D data."""

import functools

import numpy as np
import pytest
from conftest import FULL_PROTOCOL

import gputrack
from gputrack.models import rigid
from gputrack.models.chain import joint_transform
from gputrack.shared_data import shared_data
from gputrack.sim import sequence, shoulders_off
from gputrack.trackers.body import BodyTracker, BodyTrackerConfig
from gputrack.trackers.body.metrics import arm_axis_errors, shoulder_camera_errors, shoulder_errors
from gputrack.trackers.body.template import frame_template

ICL = shared_data("icl_nuim_rgbd")
FRAMES = 7


def track(device, seq, **config):
    tracker = BodyTracker(device, seq.params[0], config=BodyTrackerConfig(**config))
    estimates = [tracker.track(f.gray, f.depth) for f in list(seq)[1:]]
    return tracker, estimates


# session scope: the device fixture is session-scoped and parametrised, so pytest runs the tests
# device by device and would build a module-scoped fixture again for every device
@pytest.fixture(scope="session")
def arm_cross():
    seq = sequence("arm_cross", frames=FRAMES, seed=0)
    return seq, list(seq)


def test_pf_then_lm_track_the_arms(device, arm_cross):
    """The paper's filter (each frame starts where the last ended: predict=False) within the issue's
    bounds, and the default (the constant-velocity start added) as close with the LM."""
    seq, _ = arm_cross
    _, pf = track(device, seq, lm_iterations=0, predict=False)
    _, both = track(device, seq, lm_iterations=10, predict=False)
    _, default = track(device, seq, lm_iterations=10)
    err_pf, err_lm, err_default = (
        arm_axis_errors(seq.chain, np.array([e.params for e in run]), seq.params[1:]).mean(axis=0)
        for run in (pf, both, default)
    )
    # issue bounds: PF 3 stages <= 1.0 deg per part; PF + LM 10 lower than PF alone
    assert (err_pf <= 1.0).all(), err_pf
    assert err_lm.mean() < err_pf.mean(), (err_lm, err_pf)
    assert (err_lm <= 0.5).all(), err_lm
    assert (err_default <= 0.5).all(), err_default
    assert all(e.confidence == 1.0 and np.isfinite(e.params).all() for e in pf + both + default)


def test_steady_state_frame_moves_only_frame_and_poses(device, arm_cross):
    seq, frames = arm_cross
    cfg = BodyTrackerConfig(lm_iterations=3, template_every=1000, samples=300)
    tracker = BodyTracker(device, seq.params[0], config=cfg)
    tracker.track(frames[1].gray, frames[1].depth)  # builds and uploads the template
    tracker.track(frames[2].gray, frames[2].depth)
    frame = tracker.scheduler.frames[-1]
    if device.backend == "numpy":
        assert (frame.h2d, frame.d2h) == (0, 0)
        return
    image_bytes = frames[2].gray.nbytes + frames[2].depth.nbytes
    poses = cfg.candidates * seq.chain.n_params * 4  # the C candidate poses, float32
    # the scheduler's inputs: the two images and the C start candidates, into last frame's arrays
    assert frame.stages["upload inputs"][1:] == (image_bytes + poses, 0)
    assert frame.stages["template"][1:] == (0, 0)  # not due: nothing rendered, nothing moved
    assert all(frame.stages[n][1:] == (0, 0) for n in frame.stages if n.startswith("PF stage")), frame.stages
    assert frame.stages["download outputs"][1:] == (0, 0)  # the LM's estimate is on the host already
    # the LM downloads the PF's candidates (its declared host read) and exchanges the points it
    # evaluates and their costs per iteration
    assert frame.stages["LM"][2] >= poses
    assert frame.h2d <= image_bytes + 2 * poses, frame.stages
    assert frame.d2h <= 2 * poses * 2, frame.stages


def test_template_every_frame_moves_only_a_few_counts(device, arm_cross):
    """The template made on the device each frame: the host sends the part transforms (and a new
    quota plan when the quotas change) and reads the per-part counts; the points stay there."""
    seq, frames = arm_cross
    cfg = BodyTrackerConfig(lm_iterations=0, template_every=1, samples=300)
    tracker = BodyTracker(device, seq.params[0], config=cfg)
    for f in frames[1:4]:
        tracker.track(f.gray, f.depth)
    frame = tracker.scheduler.frames[-1]
    if device.backend == "numpy":
        assert (frame.h2d, frame.d2h) == (0, 0)
        return
    J = seq.chain.n_parts
    h2d, d2h = frame.stages["template"][1:]
    assert d2h == J * 10 * 4  # the per-part counts (10 columns: gputrack.backends.reference.model_template.STATS), int32
    assert h2d <= 4096, h2d  # transforms and box table; plan and part index only when new
    assert all(frame.stages[n][1:] == (0, 0) for n in frame.stages if n.startswith("PF stage")), frame.stages


def test_a_cost_jump_is_tracked_again_with_wider_sigmas(device, arm_cross):
    """A frame whose cost jumps (here: every candidate's right elbow 60 deg off, as after a lost
    arm) runs the recovery pass once, and the frame keeps the lower cost of the two passes; frames
    without a jump never run it. (Whether the pass finds the arm again depends on how far off it
    is: perf/soak_body.py measures how often arms are lost over long runs.)"""
    seq, frames = arm_cross
    out = {}
    for ratio in (0.0, 2.0):
        cfg = BodyTrackerConfig(lm_iterations=3, samples=500, recover_ratio=ratio)
        tracker = BodyTracker(device, seq.params[0], config=cfg)
        for f in frames[1:4]:
            tracker.track(f.gray, f.depth)
        assert tracker.recoveries == 0
        tracker.candidates[:, 11] += np.radians(60.0)  # right elbow (ph_RL)
        est = tracker.track(frames[4].gray, frames[4].depth)
        out[ratio] = (est, tracker.recoveries, tracker.recovered, tracker._costs)
    (plain, n0, _, costs), (rec, n1, kept, _) = out[0.0], out[2.0]
    assert plain.cost > 2.0 * np.median(list(costs)[:-1])  # the jump
    assert (n0, n1) == (0, 1) and kept in (0, 1)
    assert rec.cost <= plain.cost
    assert (rec.cost < plain.cost) == (kept == 1)


def test_the_start_moves_the_better_half_by_the_last_motion(arm_cross):
    """predict (the default): a frame starts from the C candidates, the better half of them also moved
    by the last frame's change of the estimate (constant velocity); predict=False starts where the
    last frame ended (the paper). A host rule: one device shows it."""
    seq, frames = arm_cross
    device = gputrack.device("numpy")
    for predict in (False, True):
        cfg = BodyTrackerConfig(lm_iterations=0, samples=200, predict=predict)
        tracker = BodyTracker(device, seq.params[0], config=cfg)
        np.testing.assert_array_equal(tracker._start(), tracker.candidates.astype(np.float32))  # no motion yet
        before = tracker.params.copy()
        tracker.track(frames[1].gray, frames[1].depth)
        motion, cand = tracker.params - before, tracker.candidates
        assert np.abs(motion).max() > 0
        start = tracker._start()
        C, h = cfg.candidates, cfg.candidates // 2
        assert start.shape == (C, seq.chain.n_params) and start.dtype == np.float32
        np.testing.assert_array_equal(start[: C - h], cand[: C - h].astype(np.float32))
        moved = cand[:h] + motion if predict else cand[C - h :]
        np.testing.assert_array_equal(start[C - h :], moved.astype(np.float32))
        tracker.track(np.full_like(frames[2].gray, 0.5), np.zeros_like(frames[2].depth))  # kept: no motion
        np.testing.assert_array_equal(tracker._start(), tracker.candidates.astype(np.float32))
    # the shoulder positions (the 20-parameter chain) are the body's build: the filter does not sample
    # them and the start does not move them
    seq = sequence("shoulder_spread", frames=3, seed=0, shoulders=True)
    tracker = BodyTracker(device, shoulders_off(seq.params[0], 0), config=BodyTrackerConfig(
        lm_iterations=3, samples=200, shoulders=True))  # fmt: skip
    before = tracker.params.copy()
    tracker.track(seq[1].gray, seq[1].depth)
    motion, cand, start = tracker.params - before, tracker.candidates, tracker._start()
    assert np.abs(motion[14:]).max() > 0  # the LM moved them
    np.testing.assert_array_equal(start[5:, 14:], cand[:5, 14:].astype(np.float32))
    np.testing.assert_array_equal(start[5:, :14], (cand[:5, :14] + motion[:14]).astype(np.float32))


SHOULDER_TRIALS = 3
SHOULDER_STEP = 2  # every other frame of the 30 fps sequence (15 fps, for time): 39 frames to the arms lowered


@pytest.fixture(scope="session")
def shoulder_trials():
    """Table 7's protocol, per trial: a seeded shoulder_spread sequence (arms spread beside the
    torso, then lowered about the shoulders) and its first pose with each shoulder 30 mm off."""
    trials = []
    for seed in range(SHOULDER_TRIALS):
        seq = sequence("shoulder_spread", frames=80, seed=seed, shoulders=True)
        frames = [seq[i] for i in range(SHOULDER_STEP, len(seq), SHOULDER_STEP)]
        trials.append((seq.chain, shoulders_off(seq.params[0], seed), frames))
    return trials


def test_shoulders_estimated_from_30mm_off(device, shoulder_trials):
    # Table 7: PF 1 stage + LM 50, tracked until the arms are lowered; t_RS, t_LS (torso
    # coordinates) of the last frame against the truth. The depth is rounded to 5 mm steps, so a
    # reading means "within 2.5 mm" (depth_tol). N' = 256 depth points: with 128 the static
    # torso's turn about its vertical axis is pinned to about +-0.4 deg only, which moves t_S
    # along torso z by the turn times the 195 mm lever (1-2.6 mm)
    if device.spec != FULL_PROTOCOL[0]:  # the suite's time: the full protocol on one device
        pytest.skip(f"the full Table 7 protocol runs on {FULL_PROTOCOL[0]} (`gputrack demo body --shoulders` runs "
                    f"it anywhere); {device.spec} runs test_shoulders_short_run")  # fmt: skip
    cfg = BodyTrackerConfig(shoulders=True, stages=1, lm_iterations=50, depth_tol=2.5, n_depth=256)
    errors, joints = [], []
    for chain, start, frames in shoulder_trials:
        tracker = BodyTracker(device, start, config=cfg)
        for f in frames:
            est = tracker.track(f.gray, f.depth)
        assert est.confidence == 1.0 and np.isfinite(est.params).all()
        errors.append(shoulder_errors(est.params, frames[-1].params)[0])
        joints.append(shoulder_camera_errors(chain, est.params, frames[-1].params)[0])
    errors, joints = np.array(errors), np.array(joints)
    # issue bound: within 1 mm per axis, as the paper's mean over trials (0.16-0.31 mm over 30).
    # Measured here: per trial 0.0-1.0 mm on every backend (means per axis 0.11-0.47); over 8
    # seeds at 30 fps (`gputrack demo body`, README) up to 1.6 mm in one trial
    assert (errors.mean(axis=0) <= 1.0).all(), errors
    assert (errors <= 2.0).all(), errors
    # the shoulder joints where the camera sees them (the full pose's error included); measured
    # 0.0-0.8 mm per value on taichi:cpu and opencl
    assert (joints.mean(axis=0) <= 1.0).all() and (joints <= 2.0).all(), joints
    assert (joints[:, [2, 5]] <= 1.5).all(), joints


def test_shoulders_short_run(device, shoulder_trials):
    """The Table 7 code path on every device: the first trial's first 3 frames (of 39). The shoulders
    start 30 mm off (9.7-22 mm per axis at that frame); measured after 3 frames: 0.01-1.9 mm per axis,
    means 0.37-0.59 mm on numpy, taichi:cpu, opencl and taichi:vulkan."""
    cfg = BodyTrackerConfig(shoulders=True, stages=1, lm_iterations=50, depth_tol=2.5, n_depth=256)
    chain, start, frames = shoulder_trials[0]
    tracker = BodyTracker(device, start, config=cfg)
    for f in frames[:3]:
        est = tracker.track(f.gray, f.depth)
    assert est.confidence == 1.0 and np.isfinite(est.params).all()
    before = shoulder_errors(start, frames[2].params)[0]
    after = shoulder_errors(est.params, frames[2].params)[0]
    assert before.max() > 9.0, before  # the protocol's start really is off
    assert (after <= 2.5).all() and after.mean() <= 1.0, (after, before)


def test_the_callers_frames_are_left_as_they_are(device, arm_cross):
    seq, frames = arm_cross
    tracker = BodyTracker(device, seq.params[0], config=BodyTrackerConfig(lm_iterations=1, samples=100))
    copies = [(f.gray.copy(), f.depth.copy()) for f in frames[1:4]]
    for f in frames[1:4]:  # each frame goes into the tracker's own device arrays, not the last frame's
        tracker.track(f.gray, f.depth)
    for f, (gray, depth) in zip(frames[1:4], copies):
        np.testing.assert_array_equal(f.gray, gray)
        np.testing.assert_array_equal(f.depth, depth)


def test_bad_frames_keep_the_last_pose(device, arm_cross):
    seq, frames = arm_cross
    tracker = BodyTracker(device, seq.params[0], config=BodyTrackerConfig(lm_iterations=2, samples=200))
    gray, depth = frames[1].gray, frames[1].depth
    with pytest.raises(ValueError, match=r"gray: expected shape \(480, 640\), got \(240, 320\)"):
        tracker.track(gray[::2, ::2], depth)
    with pytest.raises(TypeError, match="depth: expected float32, got float64"):
        tracker.track(gray, depth.astype(np.float64))
    est = tracker.track(gray, np.zeros_like(depth))
    assert est.confidence == 0.0 and "no valid depth" in est.message
    np.testing.assert_array_equal(est.params, seq.params[0])
    # a pose that puts the person out of view: no template can be made, the pose is kept
    lost = BodyTracker(device, seq.params[0] + np.r_[0, 0, 0, 20000.0, 0, 0, np.zeros(8)],
                       config=BodyTrackerConfig(lm_iterations=0, samples=100))  # fmt: skip
    est = lost.track(gray, depth)
    assert est.confidence == 0.0 and np.isfinite(est.params).all()
    with pytest.raises(ValueError, match="initial_params: expected shape"):
        BodyTracker(device, np.zeros(3))
    with pytest.raises(ValueError, match="initial_params: expected finite"):
        BodyTracker(device, np.full(14, np.nan))


def test_frames_and_templates_are_checked_on_every_device(device, arm_cross):
    """NaN/inf gray frames are refused on every device as on numpy (on the host copy, before the
    upload; taichi:cpu, opencl and vulkan took them); templates that are not SparseTemplates are a
    TypeError naming what was expected; a frame whose cost is not finite keeps the last pose with
    confidence 0 whatever computed it."""
    seq, frames = arm_cross
    tracker = BodyTracker(device, seq.params[0], config=BodyTrackerConfig(lm_iterations=0, samples=100))
    gray, depth = frames[1].gray, frames[1].depth
    for value in (np.nan, np.inf, -np.inf):
        bad = gray.copy()
        bad[5, 7] = value
        with pytest.raises(ValueError, match=rf"^gray: expected finite values, got {value} at index \(5, 7\)\Z"):
            tracker.track(bad, depth)
    with pytest.raises(ValueError, match=r"^gray: expected finite values, got nan at index \(0, 0\)\Z"):
        tracker.track(np.full_like(gray, np.nan), depth)
    want = r"^templates: expected None or a pair \(RGB, depth\) of gputrack.SparseTemplate, got tuple of str, str\Z"
    with pytest.raises(TypeError, match=want):
        tracker.track(gray, depth, templates=("a", "b"))
    with pytest.raises(TypeError, match=r"got str\Z"):
        tracker.track(gray, depth, templates="ab")
    assert tracker.frame_index == 0  # nothing ran
    start = tracker.params.copy()
    tracker.scheduler.run = lambda **inputs: {"estimate": tracker.candidates.copy(), "cost": float("inf")}
    est = tracker.track(gray, depth)
    assert est.confidence == 0.0 and "no finite cost" in est.message
    np.testing.assert_array_equal(est.params, start)


def _icl_frames():
    if not ICL.is_dir():
        pytest.skip(f"real data not found at {ICL}")
    cv2 = pytest.importorskip("cv2")
    frames = []
    for i in range(5):
        bgr = cv2.imread(str(ICL / "color" / f"{i:05d}.jpg"))
        gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(np.float32) / 255.0
        depth = cv2.imread(str(ICL / "depth" / f"{i:05d}.png"), cv2.IMREAD_UNCHANGED).astype(np.float32)  # mm
        frames.append((gray, depth))
    rows = [line.split() for line in (ICL / "trajectory.log").read_text().splitlines() if line.strip()]
    poses = [np.array([[float(v) for v in rows[5 * k + r]] for r in range(1, 5)]) for k in range(len(rows) // 5)]
    return frames, poses


ICL_CAMERA = gputrack.Camera(525.0, 525.0, 319.5, 239.5)  # camera_primesense.json


@functools.lru_cache(maxsize=1)
def _icl_templates() -> tuple:
    """The (RGB, depth) templates of frames 0-3 as host arrays (xyz, part, value): ``frame_template``
    runs on the host, ~8 s a frame, the same for every device; a worker computes them once."""
    frames, _ = _icl_frames()
    return tuple(tuple((t.xyz, t.part, t.value) for t in frame_template(*frames[i], ICL_CAMERA)) for i in range(4))


def test_icl_nuim_camera_motion(device):
    """Rigid case of the same tracker: template from frame i, PF + LM to frame i+1, vs trajectory.log."""
    frames, poses = _icl_frames()
    camera = ICL_CAMERA
    chain = rigid()
    deg = np.pi / 180
    sigma = np.array([1 * deg, 1 * deg, 1 * deg, 10.0, 10.0, 10.0])
    # ICL-NUIM depth carries simulated sensor noise of 1-2 % (20-50 mm at 2.5 m): c' = 50 mm, lambda = 0.5
    cfg = BodyTrackerConfig(lm_iterations=10, c_depth=50.0, lam=0.5)
    errors = []
    for i in range(4):
        tracker = BodyTracker(device, np.zeros(6), camera=camera, chain=chain, sigma=sigma, config=cfg)
        templates = tuple(gputrack.SparseTemplate(*arrays) for arrays in _icl_templates()[i])
        est = tracker.track(*frames[i + 1], templates=templates)
        T = np.eye(4)
        T[:3] = joint_transform(chain.parts[0], est.params[None])[0]
        truth = np.linalg.inv(poses[i + 1]) @ poses[i]  # camera i -> camera i+1
        truth[:3, 3] *= 1000.0  # m -> mm
        t_err = np.linalg.norm(T[:3, 3] - truth[:3, 3])
        R = T[:3, :3].T @ truth[:3, :3]
        r_err = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
        errors.append((t_err, r_err, np.linalg.norm(truth[:3, 3])))
    errors = np.array(errors)
    # the camera moves ~24 mm a frame; tracked to within 10 mm and 0.5 deg
    assert (errors[:, 0] <= 10.0).all() and (errors[:, 1] <= 0.5).all(), errors
    assert errors[:, 0].mean() < 0.5 * errors[:, 2].mean(), errors

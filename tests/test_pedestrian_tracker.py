"""Paper 002's pedestrian tracker: the rules (eq. 1-6), the accuracy protocol on the simulator
(taichi:cpu / opencl in full), every device against the numpy reference, and bad input."""

import dataclasses
import warnings

import numpy as np
import pytest

import gputrack
from gputrack.benchmarks.pedestrians import crowd_depth, crowd_positions
from gputrack.models import Camera
from gputrack.ops import floor_background
from gputrack.sim.pedestrians import pedestrian_sequence
from gputrack.trackers.pedestrians import PedestrianConfig, PedestrianTracker, plane_background
from gputrack.trackers.pedestrians import rules
from gputrack.trackers.pedestrians.metrics import detection_metrics, identification_metrics

#: the one device that runs the long protocols (the suite's time budget); the others are pinned to numpy
PROTOCOL_DEVICE = "taichi:cpu"
SMALL = Camera(160 / (2 * np.tan(np.radians(29.5))), 120 / (2 * np.tan(np.radians(23.0))), 79.5, 59.5)


# -- the rules ---------------------------------------------------------------------------------------
def test_cost_is_eq_3_and_rejects_far_or_different_pairs():
    cost, ok = rules.cost_matrix([[0, 0, 2000], [0, 0, 4000]], [0.05, 0.05], [[300, 0, 2400], [0, 0, 4000]],
                                 [0.08, 0.5], alpha=0.8, max_distance=900, max_volume_change=0.15)  # fmt: skip
    assert cost[0, 0] == pytest.approx(0.8 * 0.5 + 0.2 * 0.03)  # d = 0.5 m, |dV| = 0.03 m^3
    assert ok[0, 0] and not ok[0, 1]  # 2 m away
    assert not ok[1, 1]  # same place, volume 0.45 m^3 apart
    assert rules.assign(cost, ok) == [(0, 0)]


def test_gated_assignment_leaves_far_pairs_unmade():
    """Track 0 is near segment 0 (0.05), track 1 only reaches segment 0 (0.48), track 0 reaches
    segment 1 (0.62). As many pairs as possible: the two far pairs (1.10); with leaving one
    unassigned at 0.375: the near pair and two left over (0.80)."""
    cost = np.array([[0.05, 0.62], [0.48, rules._REJECTED]])
    ok = cost < 1.0
    assert sorted(rules.assign(cost, ok)) == [(0, 1), (1, 0)]
    assert rules.assign(cost, ok, 0.375) == [(0, 0)]
    assert sorted(rules.assign(cost, ok, 0.6)) == [(0, 1), (1, 0)]  # leaving is dear: 1.25 > 1.10
    assert rules.assign(np.zeros((0, 3)), np.zeros((0, 3), bool), 0.375) == []


def test_occlusion_gain_eq_4_to_6():
    # V_abs = 0.02 / 0.05 = 0.4, V_rel = 0.02 / 0.08 = 0.25: O = 0.2 * 0.4 + 0.8 * 0.25 = 0.28
    assert rules.occlusion_gain(0.02, 0.08, v_thr=0.05, beta=0.2) == pytest.approx(0.28)
    assert rules.occlusion_gain(0.08, 0.08, v_thr=0.05, beta=0.2) == 1.0  # whole: the plain filter
    assert rules.occlusion_gain(0.2, 0.08, v_thr=0.05, beta=0.2) == 1.0  # larger than before: clipped
    assert rules.occlusion_gain(0.06, np.nan, v_thr=0.05, beta=0.2) == 1.0  # no history


def test_plane_background_is_the_level_floor():
    got = plane_background(SMALL, (0, 2, 0, -2000), (120, 160))  # any scale of the normal
    want = floor_background(SMALL, 1000.0, (120, 160))
    np.testing.assert_allclose(got, want, rtol=1e-6)


@pytest.mark.parametrize("bad", [{"alpha": 1.5}, {"beta": -0.1}, {"n_points": 0}, {"eps": 0.0},
                                 {"max_missed": 0}, {"ground_plane": (0, 0, 0, -1)}, {"p0": (1.0,)},
                                 {"min_width": -1.0}, {"view_margin": float("nan")}, {"faint_points": -1},
                                 {"faint_radius": 0.0}, {"split_gap": float("inf")}, {"merge_volume": 0.0},
                                 {"weak_points": -1}, {"weak_points": 2.5}])  # fmt: skip
def test_config_rejects_bad_values(bad):
    with pytest.raises(ValueError, match="expected"):
        PedestrianConfig(**bad)


# -- simulated sequences ----------------------------------------------------------------------------
def _run(device, seq, frames, configs):
    """Track ``frames`` frames of ``seq`` with one tracker per config, in lockstep (one render)."""
    trks = [PedestrianTracker(device, camera=seq.camera, config=c) for c in configs]
    bg = seq.background(30)
    recs = [{"ti": [], "tp": [], "hi": [], "hp": [], "seg": [], "frames": []} for _ in configs]
    for t in trks:
        t.learn_background(bg)
    for k in range(frames):
        f = seq[k]
        for t, r in zip(trks, recs):
            fr = t.track(f.depth)
            r["frames"].append(fr)
            r["ti"].append(f.ids)
            r["tp"].append(f.position)
            r["hi"].append(np.array([p.id for p in fr.pedestrians], np.int64))
            r["hp"].append(np.array([p.position for p in fr.pedestrians]).reshape(-1, 3))
            r["seg"].append(np.array([[s.lo[0], s.hi[0], s.lo[2], s.hi[2]] for s in fr.segments]).reshape(-1, 4))
    return recs


def test_accuracy_protocol_on_the_simulator(device):
    """Paper 002 sec. 5 on a 200-frame, 640 x 480 simulated sequence (seed 0, 8 people, up to 5 in
    view): detection and identification near the paper's figures (measured: detection P 99.4 %,
    R 94.4 %; identification P 100 %, R 93.9 %), and the split/merge reasoning with the occlusion
    gain far above plain Kalman + Hungarian on identification precision (50.8 %)."""
    if device.spec != PROTOCOL_DEVICE:
        pytest.skip(f"the protocol runs on {PROTOCOL_DEVICE}; every device is pinned to numpy below")
    seq = pedestrian_sequence(np.random.default_rng(0), frames=200, people=8, max_in_view=5, scale=0.5)
    full, plain = _run(device, seq, 200, [PedestrianConfig(),
                                           PedestrianConfig(occlusion_gain=False, split_merge=False)])  # fmt: skip
    det = detection_metrics(full["tp"], full["seg"])
    ident = identification_metrics(full["ti"], full["tp"], full["hi"], full["hp"])
    base = identification_metrics(plain["ti"], plain["tp"], plain["hi"], plain["hp"])
    assert det.precision >= 0.98 and det.recall >= 0.9 and det.f >= 0.94
    assert ident.precision >= 0.9 and ident.recall >= 0.9
    assert ident.precision > base.precision + 0.2
    ids = set().union(*[set(h.tolist()) for h in full["hi"]])
    people = set().union(*[set(t.tolist()) for t in full["ti"]])
    assert len(ids) <= 2 * len(people)  # no flood of short-lived tracks


def test_every_device_matches_the_numpy_reference(device):
    """10 frames at 320 x 240: the same segments (depth_points' subsets and DBSCAN's labels are the
    same on every backend) and the same tracks, positions within float32 rounding."""
    seq = pedestrian_sequence(np.random.default_rng(3), frames=40, people=4, max_in_view=3, scale=0.25)
    start = next(k for k in range(40) if seq[k].in_view >= 1)
    ref = gputrack.device("numpy")
    got_trk, ref_trk = (PedestrianTracker(d, camera=seq.camera) for d in (device, ref))
    bg = seq.background(30)
    got_trk.learn_background(bg)
    ref_trk.learn_background(bg)
    seen = 0
    for k in range(start, start + 10):
        f = seq[k].depth
        a, b = got_trk.track(f), ref_trk.track(f)
        assert len(a.segments) == len(b.segments)
        for s, t in zip(a.segments, b.segments):
            np.testing.assert_allclose(s.position, t.position, atol=1e-3)
            assert s.n_points == t.n_points
        assert [(p.id, p.status) for p in a.pedestrians] == [(p.id, p.status) for p in b.pedestrians]
        for p, q in zip(a.pedestrians, b.pedestrians):
            np.testing.assert_allclose(p.position, q.position, atol=0.5)
            np.testing.assert_allclose(p.velocity, q.velocity, atol=0.5)
        seen += len(a.pedestrians)
    assert seen > 0


# -- bad input ---------------------------------------------------------------------------------------
def _tracker(device, **kw):
    trk = PedestrianTracker(device, camera=SMALL, config=PedestrianConfig(**kw))
    bg = crowd_depth(SMALL, (120, 160), np.zeros((0, 2)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trk.learn_background(np.stack([bg] * 3))
    return trk


def test_bad_frames_are_clear_errors(device):
    trk = _tracker(device)
    with pytest.raises(ValueError, match="expected a frame of the background's shape"):
        trk.track(np.zeros((60, 80), np.uint16))
    with pytest.raises(TypeError, match="expected a depth frame of dtype uint16 or float32"):
        trk.track(np.zeros((120, 160), np.float64))
    with pytest.raises(ValueError, match="finite"):
        trk.track(np.full((120, 160), np.inf, np.float32))
    fresh = PedestrianTracker(device, camera=SMALL)
    with pytest.raises(ValueError, match="learn_background"):
        fresh.track(np.zeros((120, 160), np.uint16))
    with pytest.raises(TypeError, match="camera"):
        PedestrianTracker(device, camera=(1, 2, 3, 4))


def test_background_checks(device):
    trk = PedestrianTracker(device, camera=SMALL)
    with pytest.warns(UserWarning, match="fewer than the paper's 30"):
        trk.learn_background(np.full((5, 120, 160), 3000, np.uint16))
    with pytest.raises(ValueError, match="background's shape"):  # background of another size
        trk.track(np.zeros((240, 320), np.uint16))
    with pytest.raises(ValueError, match="every pixel missing"):
        trk.learn_background(np.zeros((30, 120, 160), np.uint16))
    with pytest.raises(ValueError, match="at most 64"):
        trk.learn_background(np.zeros((65, 4, 4), np.uint16))
    with pytest.raises(TypeError, match="uint16 or float32"):
        trk.learn_background(np.zeros((30, 4, 4), np.int32))


def test_missing_readings_and_nan_depths(device):
    """A frame with no readings (0) or NaN depths has no segments; tracks are then missed and end
    after 2 frames; states stay finite."""
    trk = _tracker(device)
    person = crowd_depth(SMALL, (120, 160), [[0.0, 2500.0]])
    assert [len(trk.track(person).pedestrians) for _ in range(3)] == [1, 1, 1]
    fr = trk.track(np.zeros((120, 160), np.uint16))
    assert fr.segments == [] and [p.status for p in fr.pedestrians] == ["missed"]
    nan = person.astype(np.float32)
    nan[:] = np.nan
    fr = trk.track(nan)
    assert fr.segments == [] and fr.pedestrians == [] and fr.ended == [0]
    half = person.astype(np.float32)
    half[:, ::2] = np.nan  # every other column missing: still the person
    fr = trk.track(half)
    assert len(fr.segments) == 1 and [p.id for p in fr.pedestrians] == [1]  # a new id, never 0 again
    assert all(np.isfinite(p.position).all() and np.isfinite(p.velocity).all() for p in fr.pedestrians)


def test_a_pedestrian_who_walks_out_of_the_view_ends_at_once(device):
    """Walking right 300 mm a frame at 2.5 m, then gone: predicted beyond the image's right side
    (1.41 m at that depth), the pedestrian has left and ends in that frame (``leave_view``);
    without the rule it is output as missed for max_missed - 1 frames. Gone in the middle of the
    view it is missed either way. A host rule: numpy only (every device is pinned to numpy above)."""
    if device.spec != "numpy":
        pytest.skip("a host rule of the tracker; the devices are pinned to numpy by the test above")
    walk = [crowd_depth(SMALL, (120, 160), [[x, 2500.0]]) for x in np.arange(-1200.0, 1201.0, 300.0)]
    empty = crowd_depth(SMALL, (120, 160), np.zeros((0, 2)))
    got = {}
    for rule in (True, False):
        trk = _tracker(device, leave_view=rule)
        assert [len(trk.track(f).pedestrians) for f in walk] == [1] * len(walk)
        fr = trk.track(empty)
        got[rule] = (fr.ended, [p.status for p in fr.pedestrians])
        trk = _tracker(device, leave_view=rule)
        for f in walk[:4]:
            trk.track(f)
        assert [p.status for p in trk.track(empty).pedestrians] == ["missed"]
    assert got[True] == ([0], []) and got[False] == ([], ["missed"])


def test_a_person_standing_still_keeps_one_id(device):
    """Two minutes at 5 fps of one person standing still: one id, velocity ~0, finite state."""
    trk = _tracker(device)
    person = crowd_depth(SMALL, (120, 160), [[300.0, 3000.0]])
    for _ in range(600 if device.spec == PROTOCOL_DEVICE else 12):
        fr = trk.track(person)
    assert [p.id for p in fr.pedestrians] == [0] and fr.pedestrians[0].status == "tracked"
    assert np.abs(fr.pedestrians[0].velocity).max() < 1.0
    assert np.isfinite(fr.pedestrians[0].position).all()


def test_a_crowd_of_50(device):
    """50 people in view of a 320 x 240 camera stand as a wall (97 % of the image): 1024 points
    cannot separate them (documented: one or a few segments), but nothing breaks: ids unique,
    states finite; when everyone has left every track ends. Four people apart grow a table of one
    slot to four pedestrians."""
    cam = Camera(SMALL.fx * 2, SMALL.fy * 2, 159.5, 119.5)
    trk = PedestrianTracker(device, camera=cam, config=PedestrianConfig(capacity=1))
    empty = crowd_depth(cam, (240, 320), np.zeros((0, 2)))
    trk.learn_background(np.stack([empty] * 30))
    apart = [[-1200.0, 3000.0], [-400.0, 3000.0], [400.0, 3000.0], [1200.0, 3000.0]]
    for _ in range(2):
        fr = trk.track(crowd_depth(cam, (240, 320), apart))
    assert [p.id for p in fr.pedestrians] == [0, 1, 2, 3] and trk.capacity >= 4
    xz = crowd_positions(50)
    ended, started = [0, 1, 2, 3], [0, 1, 2, 3]
    for k in range(4):
        fr = trk.track(crowd_depth(cam, (240, 320), xz + [[50.0 * k, 0.0]]))
        ids = [p.id for p in fr.pedestrians]
        assert len(ids) == len(set(ids)) and len(ids) >= 1 and 1 <= len(fr.segments) <= 5
        assert all(np.isfinite(p.position).all() and np.isfinite(p.velocity).all() for p in fr.pedestrians)
        started += fr.started
        ended += [e for e in fr.ended if e > 3]
    for _ in range(3):
        fr = trk.track(empty)
        ended += [e for e in fr.ended if e > 3]
    assert fr.pedestrians == [] and sorted(ended) == sorted(set(started))
    assert len(started) == len(set(started))  # an id is never given twice


def test_switches_turn_the_rules_off(device):
    """split_merge=False: a person cut in two by a pole-like occluder becomes two pedestrians;
    with the reasoning on, the second part is a split of the first (one pedestrian)."""
    base = crowd_depth(SMALL, (120, 160), [[0.0, 3000.0]])
    cut = base.copy()
    c = int(round(SMALL.cx))
    cut[:, c - 2:c + 3] = 1200  # a narrow post in front splits the body into two segments
    bg = crowd_depth(SMALL, (120, 160), np.zeros((0, 2)))
    bg[:, c - 2:c + 3] = 1200
    out = {}
    for name, cfg in (("on", PedestrianConfig(eps=60.0)), ("off", PedestrianConfig(eps=60.0, split_merge=False))):
        trk = PedestrianTracker(device, camera=SMALL, config=cfg)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            trk.learn_background(np.stack([bg] * 3))
        for _ in range(3):
            trk.track(np.where(np.arange(160) < c + 3, base, bg).astype(np.uint16))  # the left part only
        fr = trk.track(cut)
        out[name] = (len(fr.segments), sorted(p.status for p in fr.pedestrians))
    assert out["on"][0] == 2 and out["on"][1] == ["split"]
    assert out["off"][0] == 2 and len(out["off"][1]) == 2


def _boards(people):
    """A SMALL-camera frame of boards [(x, z, height, width)] mm."""
    d = crowd_depth(SMALL, (120, 160), np.zeros((0, 2)))
    for x, z, h, w in people:
        d = np.minimum(d, crowd_depth(SMALL, (120, 160), [[x, z]], height=h, width=w))
    return d


def test_a_split_needs_an_occluder(device):
    """A short person appears 200 mm beside a tall one (inside its extent, under half its volume):
    with the background seen through the gap it is a pedestrian of its own (``split_occluder``);
    without the rule, or with a nearer person standing in the gap, it is a split part of the tall
    one. When that occluder walks off, the part seen apart becomes a pedestrian with a new id.
    A host rule: numpy only."""
    if device.spec != "numpy":
        pytest.skip("a host rule of the tracker; the devices are pinned to numpy by the test above")
    tall, short, post = (-250, 3000, 1700, 450), (250, 3000, 1350, 300), (0, 1500, 1700, 150)

    def run(frames, **kw):
        trk = PedestrianTracker(device, camera=SMALL, config=PedestrianConfig(**kw))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            trk.learn_background(np.stack([_boards([])] * 3))
        return [trk.track(_boards(people)) for people in frames]

    alone, beside = [[tall]] * 3, [[tall, short]] * 2
    for rule, want in ((True, [(0, "tracked"), (1, "tracked")]), (False, [(0, "split")])):
        fr = run(alone + beside, split_occluder=rule)[-1]
        assert len(fr.segments) == 2 and [(p.id, p.status) for p in fr.pedestrians] == want
    frames = run(alone + [[tall, short, post]] * 3 + beside)
    assert [(p.id, p.status) for p in frames[5].pedestrians] == [(0, "split"), (1, "tracked")]  # 1: the post
    assert frames[6].started == [2]  # the occluder gone: the part seen apart is someone else
    assert [(p.id, p.status) for p in frames[-1].pedestrians] == [(0, "tracked"), (2, "tracked")]


def test_a_pedestrian_seen_whole_after_a_merge_can_split(device):
    """Two boards side by side (ids 0, 1) merge into one segment, then part again; in that frame a
    post in front of the tall one (1) hides the gap to a short board at its side. The short board is
    a split part of 1, as it would be of any tracked pedestrian: the merge of the frame before does
    not count (the status read is this frame's). A host rule: numpy only."""
    if device.spec != "numpy":
        pytest.skip("a host rule of the tracker; the devices are pinned to numpy by the test above")
    tall, post = (-250, 3000, 1700, 450), (-256, 1500, 1700, 150)
    frames = [[tall, (400, 3000, 1700, 450)]] * 3 + [[tall, (150, 3000, 1700, 450)]]
    frames += [[tall, (650, 3000, 1700, 450), (-700, 3000, 1350, 300), post]] * 2
    trk = PedestrianTracker(device, camera=SMALL, config=PedestrianConfig())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trk.learn_background(np.stack([_boards([])] * 3))
    out = [trk.track(_boards(people)) for people in frames]
    assert [(p.id, p.status) for p in out[3].pedestrians] == [(0, "merged"), (1, "merged")]
    for fr in out[4:]:
        assert len(fr.segments) == 4
        assert [p.id for p in fr.pedestrians] == [0, 1, 2] and fr.pedestrians[1].status == "split"
    assert out[4].started == [2] and out[5].started == []  # 2: the post


def test_a_part_seen_apart_becomes_one_new_pedestrian(device):
    """A tall board split by a post into its own part and a short board beside it (two child
    tracks: one on the pedestrian's own segment, one on the short board). When the post leaves, the
    short part seen apart becomes pedestrian 2; the child on the pedestrian's own segment is the
    pedestrian itself and starts nothing: id 0 stays on the tall board. A host rule: numpy only."""
    if device.spec != "numpy":
        pytest.skip("a host rule of the tracker; the devices are pinned to numpy by the test above")
    tall, short, post = (-300, 3000, 1800, 450), (200, 3000, 1300, 250), (-50, 1500, 1700, 150)
    frames = [[tall]] * 3 + [[tall, short, post]] * 3 + [[tall, short]] * 2
    trk = PedestrianTracker(device, camera=SMALL, config=PedestrianConfig())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trk.learn_background(np.stack([_boards([])] * 3))
    out = [trk.track(_boards(people)) for people in frames]
    assert [p.status for p in out[5].pedestrians] == ["split", "tracked"]  # 1: the post
    assert out[6].started == [2] and out[7].started == []
    (a, b) = out[7].pedestrians
    assert (a.id, b.id) == (0, 2) and abs(a.position[0] - -300) < 100 and abs(b.position[0] - 200) < 100


def test_a_faint_pedestrian_keeps_its_id(device):
    """A pedestrian walking 100 mm a frame at 3 m turns into a 40 mm sliver (its points make a
    cluster narrower than min_width: no segment): observed from those points ("faint") it keeps
    its id and follows them; with faint_points=0 it is missed, then deleted. A host rule: numpy only."""
    if device.spec != "numpy":
        pytest.skip("a host rule of the tracker; the devices are pinned to numpy by the test above")
    near = (900, 2000, 1700, 450)  # enough foreground for the 1024 points
    frames = [[(-600 + 100 * k, 3000, 1700, 450 if k < 3 else 40), near] for k in range(6)]
    out = {}
    for fp in (3, 0):
        trk = PedestrianTracker(device, camera=SMALL, config=PedestrianConfig(faint_points=fp))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            trk.learn_background(np.stack([_boards([])] * 3))
        out[fp] = [trk.track(_boards(people)) for people in frames]
    assert all(len(fr.segments) == 1 for fr in out[3][3:])  # the sliver is no segment
    assert [[(p.id, p.status) for p in fr.pedestrians] for fr in out[3][3:]] == [[(0, "tracked"), (1, "faint")]] * 3
    np.testing.assert_allclose(out[3][-1].pedestrians[1].position[[0, 2]], [-100, 3000], atol=120)
    assert [[(p.id, p.status) for p in fr.pedestrians] for fr in out[0][3:]] == [
        [(0, "tracked"), (1, "missed")], [(0, "tracked")], [(0, "tracked")]]  # fmt: skip


def test_weak_segments_observe_but_start_nothing(device):
    """With min_segment_points 40 and weak_points 10, a far board 1100 mm high gives a weak segment
    (16-17 of the points are above the sensor), 1700 mm high a segment (80-95). A pedestrian seen
    first on the tall board, then on the short one, is observed from its weak segment ("tracked",
    the segment reported); the same short board appearing on its own starts nothing and is not
    reported (its points are loose). With weak_points=0 the short board is no segment: the
    pedestrian is faint. A host rule: numpy only."""
    if device.spec != "numpy":
        pytest.skip("a host rule of the tracker; the devices are pinned to numpy by the test above")
    near = (900, 2000, 1700, 450)  # enough foreground for the 1024 points
    shrinks = [[(-600, 3500, 1700, 300), near]] * 3 + [[(-600, 3500, 1100, 300), near]] * 3
    appears = [[near]] * 3 + [[(-600, 3500, 1100, 300), near]] * 3

    def run(frames, weak):
        trk = PedestrianTracker(device, camera=SMALL, config=PedestrianConfig(min_segment_points=40,
                                                                              weak_points=weak))  # fmt: skip
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            trk.learn_background(np.stack([_boards([])] * 3))
        return [trk.track(_boards(people)) for people in frames]

    out = run(shrinks, 10)
    assert [[(p.id, p.status) for p in fr.pedestrians] for fr in out[3:]] == [[(0, "tracked"), (1, "tracked")]] * 3
    for fr in out[3:]:
        assert len(fr.segments) == 2 and 10 <= min(s.n_points for s in fr.segments) < 40
        assert sorted(np.unique(fr.labels[fr.labels >= 0])) == [0, 1]
    np.testing.assert_allclose(out[-1].pedestrians[1].position[[0, 2]], [-600, 3500], atol=150)
    out = run(appears, 10)
    for fr in out[3:]:
        assert [(p.id, p.status) for p in fr.pedestrians] == [(0, "tracked")] and fr.started == []
        assert len(fr.segments) == 1 and fr.segments[0].n_points >= 40
        far = fr.points[:, 0] < 0  # the short board's points: loose
        assert far.sum() >= 10 and (fr.labels[far] == -1).all() and (fr.labels[~far] == 0).all()
    out = run(shrinks, 0)
    assert all(len(fr.segments) == 1 for fr in out[3:])
    assert [[(p.id, p.status) for p in fr.pedestrians] for fr in out[3:]] == [[(0, "tracked"), (1, "faint")]] * 3


def test_drop_labels_renumbers_the_rest():
    lab = np.array([0, 1, -1, 2, 1, 3])
    np.testing.assert_array_equal(rules.drop_labels(lab, [False, True, False, False]), [0, -1, -1, 1, -1, 2])
    np.testing.assert_array_equal(rules.drop_labels(lab, [False] * 4), lab)
    np.testing.assert_array_equal(rules.drop_labels(np.zeros(0, np.int64), [True]), np.zeros(0))


def test_a_merge_ends_when_one_is_seen_again_alone(device):
    """B walks in beside A (one segment: merged), then is gone while A stays. Once A is seen whole
    again the merge ends; A's segment holds one person's volume, so B does not merge again: it is
    hidden behind A for a few frames, then ends, and A is "tracked" throughout. A host rule: numpy only."""
    if device.spec != "numpy":
        pytest.skip("a host rule of the tracker; the devices are pinned to numpy by the test above")
    a = (0, 2500, 1700, 450)
    frames = [[a, (x, 2600, 1700, 450)] for x in (900, 700, 500, 350, 250, 250, 250)] + [[a]] * 12
    trk = PedestrianTracker(device, camera=SMALL, config=PedestrianConfig())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trk.learn_background(np.stack([_boards([])] * 3))
    out = [trk.track(_boards(people)) for people in frames]
    assert [p.status for p in out[2].pedestrians] == ["merged", "merged"]  # one segment, two people
    assert all(fr.pedestrians[0].id == 0 and fr.pedestrians[0].status == "tracked" for fr in out[9:])
    assert any(1 in fr.ended for fr in out[7:]) and [p.id for p in out[-1].pedestrians] == [0]


def test_a_split_part_is_weighed_against_the_size_now(device):
    """A person first seen as a 100 mm sliver, then whole with a small piece behind its edge (a
    bag): the piece is under half of the whole person's volume, so it is a split part of that
    pedestrian, not a new one (the sliver's volume alone would make it "too big"). Numpy only."""
    if device.spec != "numpy":
        pytest.skip("a host rule of the tracker; the devices are pinned to numpy by the test above")
    near = (-1200, 2000, 1700, 450)  # enough foreground for the 1024 points
    whole = [near, (0, 3000, 1700, 450), (350, 3250, 1400, 250)]
    trk = PedestrianTracker(device, camera=SMALL, config=PedestrianConfig())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trk.learn_background(np.stack([_boards([])] * 3))
    out = [trk.track(_boards(people)) for people in [[near], [near, (0, 3000, 1700, 100)], whole, whole]]
    assert len(out[-1].segments) == 3
    assert [(p.id, p.status) for p in out[-1].pedestrians] == [(0, "tracked"), (1, "split")]


def test_seen_apart_reads_the_gap():
    """rules.seen_apart: the background between two segments (True); a nearer reading or missing
    readings there, or a gap under min_gap (False)."""
    from gputrack.trackers.pedestrians.front import Segment

    def seg(x0, x1, z):
        lo, hi = np.array([x0, -600.0, z - 100]), np.array([x1, -50.0, z + 100])
        return Segment((lo + hi) / 2, 0.05, 50, lo, hi)

    a, b = seg(-475.0, -25.0, 3000.0), seg(100.0, 400.0, 3000.0)
    bg = _boards([])
    kw = {"min_gap": 50.0, "beyond": 100.0}
    assert rules.seen_apart(bg, SMALL, a, b, **kw) and rules.seen_apart(bg, SMALL, b, a, **kw)
    assert not rules.seen_apart(_boards([(40, 1500, 1700, 150)]), SMALL, a, b, **kw)  # an occluder
    assert not rules.seen_apart(np.zeros_like(bg), SMALL, a, b, **kw)  # no readings (sunlight)
    assert not rules.seen_apart(bg, SMALL, a, b, min_gap=200.0, beyond=100.0)  # 125 mm apart
    assert not rules.seen_apart(bg, SMALL, a, seg(-300.0, 100.0, 3500.0), **kw)  # one behind the other


def test_config_replace_keeps_validation():
    with pytest.raises(ValueError):
        dataclasses.replace(PedestrianConfig(), containment_margin=-1.0)

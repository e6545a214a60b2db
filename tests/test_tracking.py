"""gputrack.tracking: the composition of roles, the end-to-end tracker against an independent
per-track loop (filterpy + scipy), and bad input. Every test body runs on every device."""

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from scipy.optimize import linear_sum_assignment
from scipy.stats import chi2

from gputrack.ops.kalman import constant_velocity
from gputrack.sim.scenes import cv_scene
from gputrack.tracking import (
    AnyDeleter,
    Assignment,
    Associator,
    CostGater,
    CovarianceDeleter,
    Deleter,
    GNNAssociator,
    Gated,
    Gater,
    Initiator,
    KalmanPredictor,
    KalmanUpdater,
    MahalanobisGater,
    MissDeleter,
    MofNInitiator,
    MultiTargetTracker,
    Predictor,
    StereoUpdater,
    TrackStatus,
    TrackTable,
    TrackTableFull,
    Updater,
)

# the scene and the tracker's parameters, shared by the tracker and the reference loop
DIM, DT, Q_ACC, R_STD = 2, 1.0, 0.05, 0.3
GATE_P, M_OF_N, MAX_MISSES, VEL_VAR = 0.999, (2, 3), 2, 1.0


def _scene(seed=5, frames=45):
    # a crowd: 30 targets in a 20 x 20 area, so that gates overlap and some association problems
    # have several tracks and several detections; births, deaths, misses and clutter
    return cv_scene(np.random.default_rng(seed), frames=frames, targets=30, dim=DIM, dt=DT, q=Q_ACC, r=R_STD,
                    p_detect=0.85, clutter=3.0, birth_rate=0.4, death_prob=0.03, extent=20.0, speed=0.5)  # fmt: skip


def _tracker(device, **kw):
    return MultiTargetTracker.constant_velocity(
        device, dim=DIM, dt=DT, q=Q_ACC, R=R_STD**2, gate_probability=GATE_P, m_of_n=M_OF_N,
        max_misses=MAX_MISSES, velocity_var=VEL_VAR, **kw,
    )  # fmt: skip


# -- the independent reference: one filterpy KalmanFilter per track, scipy on the whole frame ----
class _RefTrack:
    def __init__(self, tid, z, F, Q, H, R):
        kf = KalmanFilter(dim_x=2 * DIM, dim_z=DIM)
        kf.F, kf.Q, kf.H, kf.R = F, Q, H, R
        kf.x = np.zeros(2 * DIM)
        kf.x[0::2] = z
        kf.P = np.diag([R_STD**2, VEL_VAR] * DIM)
        self.id, self.kf, self.status, self.hits, self.misses, self.age = tid, kf, 1, 1, 0, 1


def _reference(frames):
    """Textbook multi-target tracking written plainly: the same rules as the tracker's roles."""
    F, Q = constant_velocity(DIM, DT, Q_ACC, dtype=np.float64)
    H = np.zeros((DIM, 2 * DIM))
    H[np.arange(DIM), 2 * np.arange(DIM)] = 1
    R = R_STD**2 * np.eye(DIM)
    thr = float(np.float32(chi2.ppf(GATE_P, DIM)))  # the tracker compares float32 distances
    M, N = M_OF_N
    tracks, next_id, history = [], 0, []
    for z in frames:
        z = z.astype(np.float64)
        for t in tracks:
            t.kf.predict()
        T, D = len(tracks), len(z)
        cost = np.full((T, D + T), np.inf)
        for i, t in enumerate(tracks):
            S = H @ t.kf.P @ H.T + R
            for d in range(D):
                r = z[d] - H @ t.kf.x
                d2 = r @ np.linalg.solve(S, r)
                if d2 < thr:
                    cost[i, d] = d2
            cost[i, D + i] = thr  # missed detection
        taken = {}
        if T:
            rows, cols = linear_sum_assignment(cost)
            taken = {int(r): int(c) for r, c in zip(rows, cols) if c < D}
        for i, t in enumerate(tracks):
            t.age += 1
            if i in taken:
                t.kf.update(z[taken[i]])
                t.hits += 1
                t.misses = 0
            else:
                t.misses += 1
        keep = []
        for t in tracks:
            if t.status == 1 and t.hits >= M:
                t.status = 2
            if t.status == 1 and t.hits + N - t.age < M:
                continue  # rejected (M of N no longer possible)
            if t.status == 2 and t.misses > MAX_MISSES:
                continue
            keep.append(t)
        used = set(taken.values())
        for d in range(D):
            if d not in used:
                keep.append(_RefTrack(next_id, z[d], F, Q, H, R))
                next_id += 1
        tracks = keep
        history.append({t.id: (t.kf.x.copy(), t.status, t.hits, t.misses, t.age) for t in tracks})
    return history


def test_tracker_matches_a_per_track_filterpy_loop(device):
    scene = _scene()
    frames = [f.detections for f in scene]
    want = _reference(frames)
    tracker = _tracker(device, capacity=4)  # starts small: the table grows several times on the device
    general = 0
    for k, z in enumerate(frames):
        tracker.step(z)
        general += tracker.associator.last_components[1]
        got = tracker.tracks()
        ref = want[k]
        assert sorted(ref) == got.ids.tolist(), f"frame {k}: track ids differ"
        x_ref = np.array([ref[i][0] for i in got.ids]).reshape(-1, 2 * DIM)
        # float32 against float64: positions up to ~30 (float32 spacing ~2e-6), measured worst 7e-6
        np.testing.assert_allclose(got.x, x_ref, rtol=1e-5, atol=5e-5, err_msg=f"frame {k}")
        for name, col in (("status", 1), ("hits", 2), ("misses", 3), ("age", 4)):
            assert getattr(got, name).tolist() == [ref[i][col] for i in got.ids], f"frame {k}: {name} differ"
    assert tracker.table.capacity > 4
    assert general > 0, "the scene should hold association problems with several tracks and detections"
    confirmed = tracker.tracks(confirmed_only=True)
    assert len(confirmed) >= 0.8 * len(scene[-1].target_ids) and (confirmed.status == TrackStatus.CONFIRMED).all()


def test_tracker_follows_the_truth(device):
    # the confirmed tracks sit on the true targets: each alive, often detected target has a
    # confirmed track within 1 m (R std 0.3 m), and no two tracks follow the same target
    scene = _scene(seed=9, frames=30)
    tracker = _tracker(device)
    for f in scene:
        tracker.step(f.detections)
    last = scene[-1]
    tr = tracker.tracks(confirmed_only=True)
    dist = np.linalg.norm(tr.x[:, None, 0::2] - last.states[None, :, 0::2], axis=2)
    nearest = dist.min(axis=0)
    assert np.mean(nearest < 1.0) >= 0.9, f"only {np.mean(nearest < 1.0):.2f} of the targets have a track"
    owner = dist.argmin(axis=1)[dist.min(axis=1) < 1.0]
    assert len(np.unique(owner)) == len(owner), "two confirmed tracks on one target"


# -- the composition with stub roles ----------------------------------------------------------------
class _Log(list):
    pass


class _StubPredictor(Predictor):
    def __init__(self, log):
        self.log = log

    def predict(self, table):
        self.log.append(("predict", table))


class _StubGater(Gater):
    """Gates slot 0 with detection 1 (cost 0.5) when slot 0 is occupied; its device buffer is x."""

    buffers = ("stub_x",)

    def __init__(self, log):
        self.log = log

    def launch(self, table, z):
        self.log.append(("gate", table, z.copy()))
        return {"stub_x": table.x}

    def collect(self, table, z, host):
        self.log.append(("collect", host["stub_x"]))
        occ = table.status[0] != TrackStatus.FREE and len(z) > 1
        rows = np.array([0] if occ else [], np.int64)
        cols = np.array([1] if occ else [], np.int64)
        self.gated = Gated(rows, cols, np.array([0.5] if occ else []), None, table.capacity, len(z), 9.0)
        return self.gated


class _StubAssociator(Associator):
    def __init__(self, log):
        self.log = log

    def associate(self, gated):
        self.log.append(("associate", gated))
        self.assignment = Assignment.from_pairs(gated.rows, gated.cols, gated.n_slots, gated.n_detections)
        return self.assignment


class _StubUpdater(Updater):
    def __init__(self, log):
        self.log = log

    def update(self, table, z, assignment, gain_scale=None):
        self.log.append(("update", table, z.copy(), assignment, gain_scale))


class _StubInitiator(Initiator):
    """Starts one confirmed track per unassigned detection at x = [z0, 0, z1, 0]."""

    def __init__(self, log):
        self.log = log

    def review(self, table):
        self.log.append(("review", table.hits.copy()))
        return np.zeros(0, np.int64), np.zeros(0, np.int64)

    def initiate(self, table, z, assignment):
        self.log.append(("initiate", z.copy(), assignment))
        dets = np.flatnonzero(assignment.det_track < 0)
        x0 = np.zeros((len(dets), 4))
        x0[:, 0::2] = z[dets]
        slots, ids = table.add(x0, np.tile(np.eye(4), (len(dets), 1, 1)), TrackStatus.CONFIRMED)
        return slots, ids, dets, 0


class _StubDeleter(Deleter):
    """Deletes every track that missed twice."""

    def __init__(self, log):
        self.log = log

    def delete(self, table, assignment, gated):
        self.log.append(("delete", assignment, gated))
        return np.flatnonzero((table.status != 0) & (table.misses >= 2))


def test_composition_calls_each_role_with_its_data(device):
    log = _Log()
    roles = dict(predictor=_StubPredictor(log), gater=_StubGater(log), associator=_StubAssociator(log),
                 updater=_StubUpdater(log), initiator=_StubInitiator(log), deleter=_StubDeleter(log))  # fmt: skip
    table = TrackTable(device, 4, capacity=2)
    tracker = MultiTargetTracker(device, m=2, table=table, **roles)
    z0 = np.array([[1.0, 2.0], [3.0, 4.0]], np.float32)
    f0 = tracker.step(z0, gain_scale=[1.0, 0.5])
    names = [e[0] for e in log]
    assert names == ["predict", "gate", "collect", "associate", "update", "review", "delete", "initiate"]
    assert log[0][1] is table and log[1][1] is table
    np.testing.assert_array_equal(log[1][2], z0)
    assert isinstance(log[2][1], np.ndarray) and log[2][1].shape == (2, 4)  # the gate's buffer, on the host
    assert log[3][1] is roles["gater"].gated  # the associator gets the gater's pairs
    assert log[4][3] is roles["associator"].assignment  # the updater gets the assignment
    np.testing.assert_array_equal(log[4][4], [1.0, 0.5])
    assert log[6][1] is roles["associator"].assignment and log[6][2] is roles["gater"].gated
    stages = [s.name for s in tracker.scheduler.stages]
    assert stages == ["predict", "gate", "assign", "update", "start/end"]
    assert f0.started.tolist() == [0, 1] and f0.det_ids.tolist() == [0, 1]
    t = tracker.tracks()
    np.testing.assert_allclose(t.x, [[1, 0, 2, 0], [3, 0, 4, 0]])  # written by the stub initiator
    # frame 2: the stub gater pairs slot 0 with detection 1, so detection 0 starts track 2
    log.clear()
    f1 = tracker.step(np.array([[5.0, 5.0], [1.1, 2.1]], np.float32))
    assert f1.det_ids.tolist() == [2, 0] and f1.started.tolist() == [2]
    np.testing.assert_array_equal(log[4][3].track_det[:2], [1, -1])
    assert tracker.table.capacity == 4  # grew from 2 for the third track
    # frames 3, 4 without detections: the stub deleter ends each track at its second miss
    # (track 1 missed in frame 2 already)
    f2 = tracker.step(np.zeros((0, 2), np.float32))
    f3 = tracker.step(np.zeros((0, 2), np.float32))
    assert f2.deleted.tolist() == [1] and sorted(f3.deleted.tolist()) == [0, 2] and len(tracker.tracks()) == 0


def test_roles_are_replaceable(device):
    # the same scene through another gater (a Euclidean cost matrix of the caller's) and deleter:
    # the tracker calls them every frame with its table and the frame's detections, and tracks
    calls = []

    def euclid(table, z):
        calls.append((table, z))
        x = table.x.numpy() if hasattr(table.x, "buffer") else table.x
        return np.linalg.norm(x[:, None, 0::2] - z[None, :, :], axis=2)

    base = _tracker(device)
    tracker = MultiTargetTracker(device, m=2, predictor=base.predictor, gater=CostGater(euclid, 2.0),
                                 associator=GNNAssociator(), updater=base.updater, initiator=base.initiator,
                                 deleter=AnyDeleter(MissDeleter(1)))  # fmt: skip
    scene = _scene(seed=3, frames=12)
    seen = []
    for f in scene:
        fr = tracker.step(f.detections)
        seen += fr.started.tolist()
    assert [len(z) for _, z in calls] == [len(f.detections) for f in scene]
    assert all(t is tracker.table for t, _ in calls)
    assert seen == list(range(len(seen)))
    assert (tracker.tracks().misses <= 1).all()  # MissDeleter(1) for confirmed, M of N for tentative tracks
    assert len(tracker.tracks(confirmed_only=True)) >= 0.8 * len(scene[-1].target_ids)


def test_role_types_are_checked(device):
    base = _tracker(device)
    with pytest.raises(TypeError, match="gater: expected a gputrack.tracking.Gater"):
        MultiTargetTracker(device, m=2, predictor=base.predictor, gater=object(), associator=base.associator,
                           updater=base.updater, initiator=base.initiator, deleter=base.deleter)  # fmt: skip


# -- the roles on their own -------------------------------------------------------------------------
def _crowd_gated(rng, T, D, p):
    rows, cols = np.nonzero(rng.random((T, D)) < p)
    return Gated(rows, cols, rng.uniform(0, 9, rows.size), None, T, D, 9.0)


def test_gnn_matches_one_dense_assignment():
    # the component-wise solution costs what one dense 2-D assignment of the whole frame costs
    rng = np.random.default_rng(0)
    for T, D, p in ((50, 60, 0.03), (200, 180, 0.01), (40, 40, 0.2), (1, 5, 1.0), (5, 1, 1.0)):
        g = _crowd_gated(rng, T, D, p)
        a = GNNAssociator().associate(g)
        big = np.full((T, D + T), np.inf)
        big[g.rows, g.cols] = g.cost
        big[np.arange(T), D + np.arange(T)] = g.threshold
        r, c = linear_sum_assignment(big)
        want = big[r, c].sum()
        slots, dets = a.pairs
        cost = dict(zip(zip(g.rows.tolist(), g.cols.tolist()), g.cost.tolist()))
        got = sum(cost[(s, d)] for s, d in zip(slots.tolist(), dets.tolist())) + g.threshold * (T - len(slots))
        assert got == pytest.approx(want, rel=1e-12), (T, D, p)
        assert len(np.unique(dets)) == len(dets)
        assert (a.det_track[dets] == slots).all()


def test_gnn_components():
    # two 1-to-1 pairs, a track with two candidates, and a 2 x 2 conflict (solved by scipy)
    rows = np.array([0, 1, 2, 2, 3, 3, 4, 4])
    cols = np.array([0, 1, 2, 3, 4, 5, 4, 5])
    cost = np.array([1.0, 2.0, 3.0, 1.0, 1.0, 2.0, 1.5, 5.0])
    assoc = GNNAssociator()
    a = assoc.associate(Gated(rows, cols, cost, None, 6, 6, 9.0))
    assert a.track_det.tolist() == [0, 1, 3, 5, 4, -1]  # 3 -> 5, 4 -> 4: 2 + 1.5 < 1 + 5
    assert assoc.last_components == (3, 1)
    # a pair that costs as much as a miss is not worth taking
    a = GNNAssociator(miss_cost=1.0).associate(Gated(rows, cols, cost, None, 6, 6, 9.0))
    assert a.track_det.tolist() == [-1, -1, -1, -1, -1, -1]


def test_mofn_confirms_and_rejects(device):
    H = np.array([[1.0, 0.0]])
    init = MofNInitiator(H, np.eye(1), m_of_n=(2, 3))
    table = TrackTable(device, 2, capacity=4)
    table.add(np.zeros((3, 2)), np.tile(np.eye(2), (3, 1, 1)))
    for detected in ([1, 0, 0, 0], [0, 0, 0, 0]):  # slot 0: hit; slots 1, 2: two misses
        table.record(np.array(detected, bool))
        confirm, reject = init.review(table)
        table.confirm(confirm)
        table.remove(reject)
    assert table.status.tolist() == [TrackStatus.CONFIRMED, 0, 0, 0]
    x0, P0 = init.start_state(np.array([[4.0]]))
    np.testing.assert_allclose(x0, [[4.0, 0.0]])
    np.testing.assert_allclose(P0, [[1.0, 0.0], [0.0, 1.0]])


def test_deleters(device):
    table = TrackTable(device, 2, capacity=4)
    table.add(np.zeros((3, 2)), np.tile(np.eye(2), (3, 1, 1)), TrackStatus.CONFIRMED)
    table.record(np.array([0, 1, 0, 0], bool))
    table.record(np.array([0, 1, 0, 0], bool))
    a = Assignment.from_pairs([1], [0], 4, 1)
    g = Gated(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.array([1.0, 50.0, 50.0, np.nan]), 4, 1, 9)
    assert MissDeleter(1).delete(table, a, g).tolist() == [0, 2]
    assert CovarianceDeleter(10.0).delete(table, a, g).tolist() == [2]  # slot 1 was detected
    assert AnyDeleter(MissDeleter(1), CovarianceDeleter(10.0)).delete(table, a, g).tolist() == [0, 2]
    with pytest.raises(ValueError, match="reports trace"):
        CovarianceDeleter(10.0).delete(table, a, Gated(g.rows, g.cols, g.cost, None, 4, 1, 9))


def test_covariance_deleter_in_the_tracker(device):
    # a confirmed track that is never seen again grows until trace(H P H^T) passes max_trace
    # (trace(H P H^T) of this track: 0.84 after one miss, 2.4 after two; the miss count ends it
    # after three)
    tracker = _tracker(device, max_trace=2.0)
    tracker.step(np.array([[1.0, 1.0]], np.float32))
    tracker.step(np.array([[1.0, 1.0]], np.float32))
    assert tracker.tracks(confirmed_only=True).ids.tolist() == [0]
    deleted_at = None
    for k in range(10):
        if 0 in tracker.step(np.zeros((0, 2), np.float32)).deleted:
            deleted_at = k
            break
    assert deleted_at == 1, "deleted by covariance growth at its second miss, before the miss count"


# -- the table ----------------------------------------------------------------------------------
def test_table_grows_on_the_device_and_keeps_rows(device):
    table = TrackTable(device, 4, capacity=2, max_capacity=16)
    rng = np.random.default_rng(1)
    x = rng.standard_normal((11, 4))
    P = np.tile(np.eye(4), (11, 1, 1)) * rng.uniform(1, 2, (11, 1, 1))
    for k in range(0, 11, 3):
        table.add(x[k : k + 3], P[k : k + 3])
    assert table.capacity == 16 and len(table) == 11
    t = table.tracks(covariance=True)
    assert t.ids.tolist() == list(range(11))
    np.testing.assert_allclose(t.x, x, rtol=1e-6)
    np.testing.assert_allclose(t.P, P, rtol=1e-6)
    table.remove(t.slots[[2, 5]])
    slots, ids = table.add(x[:2], P[:2])  # reuses the freed slots, new ids
    assert sorted(slots.tolist()) == sorted(t.slots[[2, 5]].tolist()) and ids.tolist() == [11, 12]


# -- bad input --------------------------------------------------------------------------------------
def test_detections_with_nan_are_rejected_and_change_nothing(device):
    tracker = _tracker(device)
    tracker.step(np.array([[1.0, 1.0], [5.0, 5.0]], np.float32))
    before = tracker.tracks()
    with pytest.raises(ValueError, match=r"detections: expected finite values, got nan at index \(1, 0\)"):
        tracker.step(np.array([[1.0, 1.0], [np.nan, 5.0]], np.float32))
    after = tracker.tracks()
    assert after.ids.tolist() == before.ids.tolist() and after.age.tolist() == before.age.tolist()
    np.testing.assert_array_equal(after.x, before.x)
    tracker.step(np.array([[1.0, 1.0], [5.0, 5.0]], np.float32))
    assert tracker.tracks(confirmed_only=True).ids.tolist() == [0, 1]


def test_empty_frame(device):
    tracker = _tracker(device)
    tracker.step(np.array([[1.0, 1.0]], np.float32))
    for empty in (np.zeros((0, 2), np.float32), [], np.zeros((0,))):
        f = tracker.step(empty)
        assert f.det_ids.shape == (0,) and f.started.size == 0
    assert tracker.tracks().ids.tolist() == []  # the tentative track missed: M of N failed
    f = tracker.step(np.zeros((0, 2)))  # an empty table and an empty frame
    assert len(tracker.tracks()) == 0 and f.deleted.size == 0


def test_table_at_capacity(device):
    # the table is strict; the tracker's initiator starts what fits, counts the rest, never reuses ids
    table = TrackTable(device, 2, capacity=2, max_capacity=4)
    table.add(np.zeros((3, 2)), np.tile(np.eye(2), (3, 1, 1)))
    with pytest.raises(TrackTableFull, match="2 new tracks asked for, 1 fit"):
        table.add(np.zeros((2, 2)), np.tile(np.eye(2), (2, 1, 1)))
    assert len(table) == 3 and table.next_id == 3
    tracker = _tracker(device, capacity=2, max_capacity=3)
    z = np.array([[1.0, 1.0], [5.0, 5.0], [9.0, 9.0], [13.0, 13.0], [17.0, 17.0]], np.float32)
    f = tracker.step(z)
    assert f.dropped == 2 and f.started.tolist() == [0, 1, 2] and f.det_ids.tolist() == [0, 1, 2, -1, -1]
    f = tracker.step(z)  # the three tracks take their detections, two births dropped again
    assert f.dropped == 2 and f.det_ids.tolist() == [0, 1, 2, -1, -1]
    assert tracker.tracks().ids.tolist() == [0, 1, 2] and tracker.initiator.dropped == 4
    far = np.array([[60.0, 60.0], [90.0, 90.0]], np.float32)
    for _ in range(MAX_MISSES):  # the old tracks miss; the new detections wait for room
        f = tracker.step(far)
        assert f.dropped == 2 and f.started.size == 0
    f = tracker.step(far)  # the old tracks end at their third miss, which makes room
    assert f.deleted.tolist() == [0, 1, 2] and f.started.tolist() == [3, 4], "no id was spent on a dropped birth"


def test_no_feasible_assignment(device):
    # every pair gated out: every track misses, every detection starts a track, nothing crashes
    tracker = _tracker(device)
    tracker.step(np.array([[1.0, 1.0], [5.0, 5.0]], np.float32))
    f = tracker.step(np.array([[50.0, 50.0], [90.0, 90.0]], np.float32))
    assert f.started.tolist() == [2, 3] and f.det_ids.tolist() == [2, 3]
    assert tracker.tracks().misses.tolist() == [1, 1, 0, 0]
    inf_cost = CostGater(lambda table, z: np.full((table.capacity, len(z)), np.inf), 1.0)
    g = inf_cost.gate(tracker.table, np.ones((3, 2), np.float32))
    a = GNNAssociator().associate(g)
    assert g.rows.size == 0 and (a.track_det == -1).all() and (a.det_track == -1).all()


def test_wrong_shapes_and_dtypes(device):
    tracker = _tracker(device)
    with pytest.raises(ValueError, match=r"detections: expected shape \(D, m=2\), got \(3, 3\)"):
        tracker.step(np.zeros((3, 3), np.float32))
    with pytest.raises(ValueError, match=r"detections: expected shape \(D, m=2\), got \(4,\)"):
        tracker.step(np.zeros(4, np.float32))
    with pytest.raises(TypeError, match="detections: expected real values, got dtype str"):
        tracker.step(np.array([["a", "b"]]))
    with pytest.raises(ValueError, match=r"gain_scale: expected shape \(1,\)"):
        tracker.step(np.zeros((1, 2)), gain_scale=[1.0, 1.0])
    with pytest.raises(ValueError, match="gain_scale: expected finite values >= 0"):
        tracker.step(np.zeros((1, 2)), gain_scale=[-1.0])
    if device.backend != "numpy":
        with pytest.raises(TypeError, match="detections: expected host"):
            tracker.step(device.asarray(np.zeros((1, 2), np.float32)))
    with pytest.raises(ValueError, match=r"cost: expected a \(C=1024, D=1\) matrix"):
        CostGater(lambda t, z: np.zeros((3, 3)), 1.0).gate(tracker.table, np.zeros((1, 2), np.float32))
    with pytest.raises(ValueError, match=r"x0: expected shape \(k, 4\)"):
        tracker.table.add(np.zeros((1, 3)), np.zeros((1, 3, 3)))
    with pytest.raises(ValueError, match="x0: expected finite values"):
        tracker.table.add(np.full((1, 4), np.nan), np.tile(np.eye(4), (1, 1, 1)))
    with pytest.raises(ValueError, match="max_pairs: expected a positive integer"):
        MahalanobisGater(np.eye(2, 4), np.eye(2), max_pairs=0)
    with pytest.raises(ValueError, match=r"R: expected shape \(2, 2\)"):
        KalmanUpdater(np.eye(2, 4), np.eye(3))
    with pytest.raises(ValueError, match=r"m_of_n: expected integers 1 <= M <= N"):
        MofNInitiator(np.eye(2, 4), np.eye(2), m_of_n=(3, 2))
    with pytest.raises(ValueError, match="Q: expected shape"):
        KalmanPredictor(np.eye(4), np.eye(3))
    assert len(tracker.tracks()) == 0 and tracker.table.next_id == 0  # nothing was started by bad input


def test_gate_overflow_raises_max_pairs(device):
    # 12 detections inside one track's gate with max_pairs 8: gated again with room for all
    tracker = _tracker(device)
    tracker.gater.max_pairs = 8
    tracker.step(np.array([[0.0, 0.0]], np.float32))
    z = np.stack([np.linspace(-0.3, 0.3, 12), np.zeros(12)], 1).astype(np.float32)
    gated = tracker.gater.gate(tracker.table, z)
    assert tracker.gater.max_pairs == 16 and sorted(gated.cols.tolist()) == list(range(12))


def test_steady_state_frame_moves_only_its_inputs_and_outputs(device):
    # through the scheduler: per stage, the bytes a frame moves. Steady state (no track starts
    # or ends): the sorted detections up (padded to 16 rows), the gated pairs down (count, det,
    # d2 of every slot, K = 4), one detection row per slot up; nothing else.
    C, K, m = 16, 4, 2
    tracker = _tracker(device, capacity=C)
    z = np.array([[1.0, 1.0], [9.0, 9.0], [20.0, 4.0]], np.float32)
    first = [tracker.step(z) for _ in range(3)]
    assert [len(f.started) for f in first] == [3, 0, 0] and len(tracker.tracks(confirmed_only=True)) == 3
    frame = tracker.scheduler.last_frame.stages
    moves = device.backend != "numpy"  # the numpy device moves nothing
    want = {"predict": (0, 0), "gate": (16 * m * 4, 0), "assign": (0, C * (1 + 2 * K) * 4),
            "update": (C * m * 4, 0), "start/end": (0, 0)}  # fmt: skip
    got = {name: (h2d, d2h) for name, (_, h2d, d2h) in frame.items()}
    assert got == {k: (v[0] * moves, v[1] * moves) for k, v in want.items()}
    # a frame that starts a track also uploads its slot index and state (16-row buffers), and
    # the next frame's gate the occupied-slot flags (C bytes)
    tracker.step(np.concatenate([z, [[40.0, 40.0]]]).astype(np.float32))
    started = tracker.scheduler.last_frame.stages["start/end"]
    assert started[1:] == ((16 * 4 + 16 * 4 * 4) * moves, 0)
    tracker.step(np.concatenate([z, [[40.0, 40.0]]]).astype(np.float32))
    assert tracker.scheduler.last_frame.stages["gate"][1:] == ((16 * m * 4 + C) * moves, 0)


def _table_with(device, x, P):
    table = TrackTable(device, x.shape[1], capacity=len(x) + 2)
    table.add(x, P, TrackStatus.CONFIRMED)
    return table


def test_kalman_updater_is_kf_update_of_the_assigned_slots(device):
    # gain_scale is per detection and follows it to its slot; unassigned slots keep their state
    from gputrack.backends.reference.kalman import kf_update as ref_update

    rng = np.random.default_rng(2)
    x = rng.normal(0, 3, (5, 4)).astype(np.float32)
    P = np.tile(np.diag([0.5, 1.0, 0.5, 1.0]).astype(np.float32), (5, 1, 1))
    H = np.zeros((2, 4), np.float32)
    H[0, 0] = H[1, 2] = 1
    R = (0.1 * np.eye(2)).astype(np.float32)
    table = _table_with(device, x, P)
    z = rng.normal(0, 3, (3, 2)).astype(np.float32)
    a = Assignment.from_pairs([4, 0, 2], [0, 2, 1], table.capacity, 3)
    KalmanUpdater(H, R).update(table, z, a, gain_scale=np.array([0.5, 1.0, 0.0]))
    rows = np.full((table.capacity, 2), np.nan, np.float32)
    rows[[4, 0, 2]] = z[[0, 2, 1]]
    gain = np.ones(table.capacity, np.float32)
    gain[[4, 0, 2]] = [0.5, 0.0, 1.0]
    t = table.tracks(covariance=True)
    pad_x = np.zeros((table.capacity, 4), np.float32)
    pad_x[:5] = x
    pad_P = np.tile(np.eye(4, dtype=np.float32), (table.capacity, 1, 1))
    pad_P[:5] = P
    wx, wP, _ = ref_update(None, pad_x, pad_P, rows, H, R, None, gain)
    np.testing.assert_allclose(t.x, wx[:5], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(t.P, wP[:5], rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(t.x[[1, 3]], x[[1, 3]])  # not assigned
    np.testing.assert_array_equal(t.x[0], x[0])  # gain 0: unchanged


def test_stereo_updater_is_ekf_update_stereo_of_the_assigned_slots(device):
    from gputrack.backends.reference.kalman import ekf_update_stereo as ref_stereo

    rng = np.random.default_rng(3)
    x = np.zeros((4, 6), np.float32)
    x[:, 0::2] = rng.uniform([-1, -1, 3], [1, 1, 8], (4, 3))
    P = np.tile((0.05 * np.eye(6)).astype(np.float32), (4, 1, 1))
    R = np.diag([1.0, 1.0, 0.2]).astype(np.float32)
    f, b = 500.0, 0.12
    table = _table_with(device, x, P)
    z = np.stack([f * x[:, 0] / x[:, 4], f * x[:, 2] / x[:, 4], f * b / x[:, 4]], 1).astype(np.float32) + 0.7
    a = Assignment.from_pairs([1, 3], [1, 3], table.capacity, 4)
    StereoUpdater(R, f=f, b=b).update(table, z, a)
    rows = np.full((4, 3), np.nan, np.float32)
    rows[[1, 3]] = z[[1, 3]]
    wx, wP, _ = ref_stereo(None, x, P, rows, R, f, b)
    t = table.tracks(covariance=True)
    np.testing.assert_allclose(t.x, wx, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(t.P, wP, rtol=1e-5, atol=1e-5)
    assert not np.allclose(t.x[[1, 3]], x[[1, 3]])

"""The group tracker of paper 001 at the observation level (points with velocities): crossing,
merging, splitting and ending groups, every device against the reference, and bad input."""

import numpy as np
import pytest

import gputrack
from conftest import full_protocol
from gputrack.models import StereoCamera
from gputrack.trackers.groups import GroupConfig, GroupTracker

CAM = StereoCamera(f=513.5, cx=320.0, cy=240.0, b=120.0)


def _frame(rng, people, per=20):
    """Points on each person (centre (3,), velocity (3,)): (y, lam, person index)."""
    y, lam, pid = [], [], []
    for k, (c, v) in enumerate(people):
        y.append(np.asarray(c) + rng.normal(0, [150, 300, 120], (per, 3)))
        lam.append(np.asarray(v) + rng.normal(0, 2.0, (per, 3)))
        pid += [k] * per
    return np.concatenate(y).astype(np.float32), np.concatenate(lam).astype(np.float32), np.array(pid)


def _crossing(k):
    """Group 0 (2 people) walks right, group 1 (3 people) left, 1.2 m behind: they cross at k = 100."""
    a, b = np.array([-2500 + 25.0 * k, 1000, 7000]), np.array([2500 - 25.0 * k, 1000, 8200])
    people = [(a, (25, 0, 0)), (a + (0, 0, 600), (25, 0, 0)),
              (b, (-25, 0, 0)), (b + (0, 0, 600), (-25, 0, 0)), (b + (500, 0, 300), (-25, 0, 0))]  # fmt: skip
    return people, np.array([0, 0, 1, 1, 1])


def _purity(labels, truth):
    """Share of labelled points whose group is the majority group of their true group."""
    ok = 0
    for g in np.unique(truth):
        lab = labels[truth == g]
        lab = lab[lab >= 0]
        if len(lab):
            ok += np.count_nonzero(lab == np.bincount(lab).argmax())
    return ok / max(np.count_nonzero(labels >= 0), 1)


def test_crossing_groups_stay_apart(device):
    frames = 200 if full_protocol(device) else 40
    rng = np.random.default_rng(1)
    trk = GroupTracker(device, camera=CAM)
    owners, purity = [], []
    for k in range(frames):
        people, group = _crossing(k)
        y, lam, pid = _frame(rng, people)
        fr = trk.update_points(y, lam)
        truth = group[pid]
        assert len(fr.groups) == 2 and not fr.merged and not fr.split
        owners.append([np.bincount(fr.labels[truth == g][fr.labels[truth == g] >= 0]).argmax() for g in (0, 1)])
        purity.append(_purity(fr.labels, truth))
    assert (np.array(owners) == owners[0]).all()  # no id switch
    assert np.mean(purity) >= 0.99
    g = {G.id: G for G in fr.groups}[owners[-1][0]]
    want = np.mean([p[0] for p in _crossing(frames - 1)[0][:2]], axis=0)
    assert np.linalg.norm(g.position - want) < 150  # the group's mean, mm
    np.testing.assert_allclose(g.velocity, [25, 0, 0], atol=3)


def test_groups_that_walk_together_merge():
    rng = np.random.default_rng(2)
    trk = GroupTracker(gputrack.device("numpy"), camera=CAM)
    merged_at = None
    for k in range(160):
        t = min(k, 60)
        a = np.array([-2000 + 30.0 * t, 1000, 7000 + 10.0 * t])  # converge until k = 60 ...
        b = np.array([2000 - 30.0 * t, 1000, 7000 + 10.0 * t])
        va, vb = ((30, 0, 10), (-30, 0, 10)) if k < 60 else ((0, 0, 10), (0, 0, 10))
        if k >= 60:  # ... then walk on side by side
            a, b = a + (0, 0, 10.0 * (k - 60)), b + (0, 0, 10.0 * (k - 60))
        y, lam, _ = _frame(rng, [(a, va), (a + (400, 0, 0), va), (b, vb), (b + (-400, 0, 300), vb)])
        fr = trk.update_points(y, lam)
        if fr.merged:
            assert merged_at is None
            merged_at = k
    assert merged_at is not None and 60 <= merged_at <= 60 + 48
    assert len(fr.groups) == 1 and fr.groups[0].n_points == len(y) and (fr.labels == fr.groups[0].id).all()


def test_a_group_whose_people_walk_apart_splits_and_an_empty_group_ends():
    rng = np.random.default_rng(3)
    cfg = GroupConfig(max_missed=10)
    trk = GroupTracker(gputrack.device("numpy"), camera=CAM, config=cfg)
    splits, ended = [], []
    for k in range(120):
        s = max(k - 20, 0) * 25.0  # together for 20 frames, then apart at 50 mm/frame relative
        v = 25.0 if k >= 20 else 0.0
        people = [((-300 - s, 1000, 7000), (-v, 0, 0)), ((-300 - s, 1000, 7600), (-v, 0, 0)),
                  ((300 + s, 1000, 7000), (v, 0, 0)), ((300 + s, 1000, 7600), (v, 0, 0))]  # fmt: skip
        y, lam, pid = _frame(rng, people)
        if k >= 100:
            y, lam = y[:0], lam[:0]  # everyone gone: both groups end after max_missed frames
        fr = trk.update_points(y, lam)
        splits += fr.split
        ended += fr.ended
        if k == 99:
            assert len(fr.groups) == 2
            sides = [set(fr.labels[(pid < 2) & (fr.labels >= 0)]), set(fr.labels[(pid >= 2) & (fr.labels >= 0)])]
            assert len(sides[0]) == len(sides[1]) == 1 and sides[0] != sides[1]
            assert np.mean(fr.labels >= 0) >= 0.95  # a few points fall outside every gate (eq. 8)
    assert len(splits) == 1 and splits[0][1] == 0  # group 0 split once, into itself and group 1
    assert sorted(ended) == [0, 1] and fr.groups == []
    y, lam, _ = _frame(rng, [((0, 1000, 7000), (0, 0, 0))])
    assert [G.id for G in trk.update_points(y, lam).groups] == [2]  # ids are never reused


def test_every_device_agrees_with_the_reference(device):
    """A short crossing run on the device and on numpy: the same labels, states within float32."""
    runs = []
    for dev in (gputrack.device("numpy"), device):
        rng = np.random.default_rng(4)
        trk = GroupTracker(dev, camera=CAM)
        out = []
        for k in range(0, 60, 3):
            y, lam, _ = _frame(rng, _crossing(k)[0])
            fr = trk.update_points(y, lam)
            out.append((fr.labels, [(G.id, G.position, G.velocity, G.covariance, G.n_points) for G in fr.groups]))
        runs.append(out)
    for (la, ga), (lb, gb) in zip(*runs):
        np.testing.assert_array_equal(lb, la)
        assert [g[0] for g in gb] == [g[0] for g in ga] and [g[4] for g in gb] == [g[4] for g in ga]
        for a, b in zip(ga, gb):
            np.testing.assert_allclose(b[1], a[1], rtol=1e-4, atol=0.05)
            np.testing.assert_allclose(b[2], a[2], rtol=1e-4, atol=0.01)
            np.testing.assert_allclose(b[3], a[3], rtol=1e-3, atol=1e-3 * np.abs(a[3]).max())


def test_bad_input_and_degenerate_frames(device):
    trk = GroupTracker(device, camera=CAM)
    y = np.zeros((4, 3), np.float32)
    with pytest.raises(ValueError, match=r"xyz: expected shape \(N, 3\), got \(4, 2\)"):
        trk.update_points(y[:, :2], y)
    with pytest.raises(ValueError, match=r"velocity: expected shape \(N=4, 3\), got \(3, 3\)"):
        trk.update_points(y, y[:3])
    with pytest.raises(ValueError, match=r"xyz: expected finite values or NaN rows \(no point\), got inf"):
        trk.update_points(np.full((4, 3), np.inf), y)
    with pytest.raises(TypeError, match="xyz: expected real values, got dtype complex128"):
        trk.update_points(y.astype(complex), y)
    with pytest.raises(TypeError, match="camera: expected a gputrack.models.StereoCamera"):
        GroupTracker(device, camera=(513.5, 120.0))
    with pytest.raises(ValueError, match="GroupConfig.gamma: expected a positive finite number"):
        GroupConfig(gamma=0)
    rng = np.random.default_rng(5)
    y, lam, _ = _frame(rng, [((0, 1000, 7000), (10, 0, 0))])
    trk.update_points(y, lam)
    # a frame without points, then one of NaN points only: the group is predicted, never NaN
    for pts in (np.zeros((0, 3)), np.full((30, 3), np.nan)):
        fr = trk.update_points(pts, pts)
        assert len(fr.labels) == len(pts) and (fr.labels == -1).all()
        assert len(fr.groups) == 1 and np.isfinite(fr.groups[0].position).all() and fr.groups[0].n_points == 0
    # points behind the camera: assigned to nothing, the state stays finite
    fr = trk.update_points(np.array([[0, 0, -5000.0]] * 10), np.zeros((10, 3)))
    assert all(np.isfinite(G.covariance).all() for G in fr.groups)

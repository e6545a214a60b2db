"""Paper 001's group metrics on hand-made cases with known answers, and on the simulator's truth
(host code: one run, no device)."""

import sys

import numpy as np
import pytest

from gputrack.trackers.groups.metrics import (
    FrameRecord,
    clear_mot,
    contingency,
    evaluate,
    id_switches,
    match,
    merge_latency,
    purity,
)

# five people: 0, 1 in true group 0; 2, 3, 4 in true group 1; two points on each
PIDS = np.repeat(np.arange(5), 2)
GROUP = np.array([0, 0, 1, 1, 1])
TRUE_IDS = np.array([0, 1])
TRUE_MEANS = np.array([[-500.0, 0.0, 6000.0], [500.0, 0.0, 7000.0]])


def record(labels, person_group=GROUP, reported_ids=(0, 1), reported_means=None, true_ids=TRUE_IDS,
           true_means=TRUE_MEANS, pids=PIDS):  # fmt: skip
    reported_ids = np.asarray(reported_ids, np.int64)
    if reported_means is None:
        reported_means = np.zeros((len(reported_ids), 3))
    return FrameRecord(np.asarray(labels), pids, person_group, reported_ids, reported_means, true_ids, true_means)


def test_contingency_and_purity_by_hand():
    labels = np.array([0, 0, 0, 1, 1, 1, 1, 1, -1, -1])  # person 1 split, person 4 unassigned
    gi, ri, c = contingency(labels, PIDS, GROUP)
    assert gi.tolist() == [0, 1] and ri.tolist() == [0, 1] and c.tolist() == [[3, 1], [0, 4]]
    assert purity(labels, PIDS, GROUP) == pytest.approx(7 / 8)
    assert match(labels, PIDS, GROUP) == {0: 0, 1: 1}
    # both true groups in one reported group: one-to-one matching gives it to the larger one
    one = np.zeros(10, np.int64)
    assert match(one, PIDS, GROUP) == {1: 0}
    assert purity(one, PIDS, GROUP) == pytest.approx(6 / 10)
    # clutter points (person -1) and unassigned points are not counted; a dict map works too
    labels = np.array([5, 5, 9, 9, 9, 9, 9, 9, 5, 5])
    pids = np.array([0, 1, 2, 3, 4, -1, 2, 3, -1, -1])
    assert purity(labels, pids, {0: 0, 1: 0, 2: 1, 3: 1, 4: 1}) == 1.0
    assert match(labels, pids, {0: 0, 1: 0, 2: 1, 3: 1, 4: 1}) == {0: 5, 1: 9}
    assert np.isnan(purity(np.full(10, -1), PIDS, GROUP))


def test_perfect_tracking():
    labels = GROUP[PIDS]
    recs = [record(labels, reported_means=TRUE_MEANS + [[k, 0, 0], [0, 0, 0]]) for k in range(6)]
    m = evaluate(recs)
    assert (m.purity == 1.0).all() and m.mean_purity == 1.0
    assert m.total_switches == 0 and m.switches == {0: 0, 1: 0}
    assert m.error[:, 0] == pytest.approx(np.arange(6.0)) and (m.error[:, 1] == 0).all()
    assert m.mean_error == pytest.approx(np.arange(6.0).sum() / 12)
    assert m.mot["mota"] == 1.0 and m.mot["idf1"] == 1.0 and m.mot["num_switches"] == 0
    assert m.mot["motp"] == pytest.approx(np.arange(6.0).sum() / 12)
    assert m.merge_latency is None


def test_a_relabelled_group_is_one_switch_and_a_swap_two():
    labels = GROUP[PIDS]
    relabel = [record(labels) for _ in range(3)] + [record(np.where(labels == 0, 7, labels), reported_ids=(7, 1))
                                                    for _ in range(3)]  # fmt: skip
    m = evaluate(relabel, mot=False)
    assert m.switches == {0: 1, 1: 0} and m.total_switches == 1 and (m.purity == 1).all() and m.mot is None
    swap = [record(labels) for _ in range(3)] + [record(1 - labels) for _ in range(3)]
    assert evaluate(swap, mot=False).switches == {0: 1, 1: 1}
    # an unmatched frame in between is skipped, not a switch
    gap = [record(labels), record(np.full(10, -1)), record(labels)]
    assert evaluate(gap, mot=False).total_switches == 0
    assert id_switches([{0: 1}, {0: 2}, {}, {0: 2}, {0: 1}]) == {0: 2}


def merge_records(tracker_merges_at, merge_frame=5, n=12):
    """True groups 0 and 1 become group 2 at ``merge_frame``; the tracker's two groups (ids 10, 11)
    become one (id 10) at ``tracker_merges_at`` (None: never)."""
    recs = []
    for k in range(n):
        pg = GROUP if k < merge_frame else np.full(5, 2)
        merged = tracker_merges_at is not None and k >= tracker_merges_at
        labels = np.where(GROUP[PIDS] == 0, 10, 10 if merged else 11)
        rep = (10,) if merged else (10, 11)
        tid = np.array([0, 1]) if k < merge_frame else np.array([2])
        tm = TRUE_MEANS if k < merge_frame else TRUE_MEANS.mean(0, keepdims=True)
        recs.append(record(labels, pg, rep, None, tid, tm))
    return recs


def test_merge_latency():
    assert merge_latency(merge_records(8), 5, 2) == 3
    assert merge_latency(merge_records(5), 5, 2) == 0
    assert merge_latency(merge_records(3), 5, 2) == -2  # merged two frames before the truth
    assert merge_latency(merge_records(None), 5, 2) is None
    assert evaluate(merge_records(9), merge_frame=5, merged_group=2, mot=False).merge_latency == 4
    # min_share: 4 of the 5 people (8 of 10 points) in one group is "one group" at 0.8, not at 0.9
    recs = merge_records(None)
    for k in range(7, 12):
        lab = recs[k].labels.copy()
        lab[np.isin(PIDS, [2, 3])] = 10
        recs[k] = record(lab, np.full(5, 2), (10, 11), None, np.array([2]), TRUE_MEANS[:1])
    assert merge_latency(recs, 5, 2, min_share=0.8) == 2 and merge_latency(recs, 5, 2, min_share=0.9) is None
    with pytest.raises(ValueError, match="merged_group"):
        merge_latency(recs, 5, 7)
    with pytest.raises(ValueError, match="merge_frame"):
        merge_latency(recs, 12, 2)


def test_clear_mot_on_a_tiny_known_case():
    """One true group at the origin; reports 100 mm off, 300 mm off, 700 mm off (> max_dist: a miss
    and a false positive), then a new id on the spot (a switch)."""
    o = np.zeros((1, 3))
    recs = [record(np.zeros(0, np.int64), np.zeros(0, np.int64), (h,), [[dx, 0.0, 0.0]], [0], o, np.zeros(0, np.int64))
            for h, dx in ((5, 100.0), (5, 300.0), (5, 700.0), (6, 0.0))]  # fmt: skip
    m = clear_mot(recs, max_dist=500.0)
    assert m["num_misses"] == 1 and m["num_false_positives"] == 1
    assert m["num_switches"] == 1 and m["num_matches"] == 2  # motmetrics: a switch is not a match
    assert m["mota"] == pytest.approx(1 - 3 / 4)
    assert m["motp"] == pytest.approx(400.0 / 3)
    assert m["idf1"] == pytest.approx(2 * 2 / (2 * 2 + 2 + 2))  # IDTP 2 (id 5), IDFP 2, IDFN 2
    assert clear_mot(recs, max_dist=1000.0)["num_misses"] == 0


def test_clear_mot_needs_motmetrics(monkeypatch):
    monkeypatch.setitem(sys.modules, "motmetrics", None)
    with pytest.raises(ImportError, match="pip install"):
        clear_mot([record(GROUP[PIDS])])


def test_bad_input():
    with pytest.raises(ValueError, match="one per point"):
        record(np.zeros(3, np.int64))
    with pytest.raises(ValueError, match="distinct"):
        record(GROUP[PIDS], reported_ids=(1, 1))
    with pytest.raises(ValueError, match=r"shape \(2, 3\)"):
        record(GROUP[PIDS], reported_means=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="integer"):
        record(np.zeros(10))
    with pytest.raises(ValueError, match="finite"):
        record(GROUP[PIDS], true_means=np.full((2, 3), np.nan))
    with pytest.raises(TypeError, match="FrameRecord"):
        evaluate([{"labels": []}])
    with pytest.raises(ValueError, match="max_dist"):
        clear_mot([record(GROUP[PIDS])], max_dist=-1.0)


def test_an_oracle_on_simulated_observations():
    """Labels = the true groups of the simulator's observation points, reported means = the means
    of each group's points: purity 1, no switches, every group found (the means of the visible
    surface points lie 0.2-0.5 m from the true means), the merge seen at once."""
    from gputrack.sim.groups import scene

    sc = scene("merging", np.random.default_rng(0), scale=0.25, supersample=1, empty_frames=0)
    k0 = sc.merge_frame
    recs = []
    rng = np.random.default_rng(1)
    for k in range(k0 - 8, k0 + 8):
        xyz, _, pid = sc.observations(k, rng)
        t = sc.truth(k)
        labels = t.group[pid]
        ids = np.unique(labels)
        means = np.array([xyz[labels == g].mean(axis=0) for g in ids])
        recs.append(FrameRecord(labels, pid, t.group, ids, means, t.group_ids, t.group_mean))
    m = evaluate(recs, merge_frame=8, merged_group=sc.merged_group)
    assert (m.purity == 1.0).all() and m.total_switches == 0 and m.merge_latency == 0
    assert m.mot["mota"] == 1.0 and m.mot["idf1"] == 1.0
    assert 100.0 < m.mean_error < 600.0  # see the metrics module: max_dist


def test_pictures():
    from gputrack.trackers.groups.pictures import colour, draw_groups, group_ellipses, plot_trajectories

    rng = np.random.default_rng(0)
    uv = np.concatenate([rng.normal([80, 60], [4, 15], (40, 2)), rng.normal([200, 100], [10, 5], (30, 2))])
    labels = np.repeat([3, 4], [40, 30])
    labels[0] = -1
    ell = group_ellipses(uv, labels)
    assert sorted(ell) == [3, 4]
    assert ell[4][0] == pytest.approx(uv[40:].mean(0)) and ell[4][1] == pytest.approx(np.cov(uv[40:].T))
    img = np.full((160, 320), 90, np.uint8)
    out = draw_groups(img, uv, labels, radius=1)
    assert out.shape == (160, 320, 3) and out.dtype == np.uint8 and (img == 90).all()
    u, v = np.rint(uv[45]).astype(int)
    assert tuple(out[v, u]) == colour(4) and colour(3) != colour(4) and colour(-1) == (160, 160, 160)
    # the ellipse: group 4's 2-sigma ellipse is wide (sigma 10 px in u) and flat (5 px in v)
    cu, cv = np.rint(ell[4][0]).astype(int)
    row = np.flatnonzero((out[cv] == colour(4)).all(axis=1))
    col = np.flatnonzero((out[:, cu] == colour(4)).all(axis=1))
    assert 14 < (row.max() - row.min()) / 2 < 26 and 6 < (col.max() - col.min()) / 2 < 14
    with pytest.raises(ValueError, match="uint8"):
        draw_groups(img.astype(float), uv, labels)
    with pytest.raises(ValueError, match="labels"):
        draw_groups(img, uv, labels[:-1])

    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    t = np.linspace(0, 1, 20)[:, None]
    tracks = {3: np.hstack([t * 3000, 0 * t, 6000 + 0 * t]), 4: np.hstack([-t * 3000, 0 * t, 7500 + 0 * t])}
    tracks[4][:5] = np.nan  # not reported at first
    fig = plot_trajectories(tracks, truth={0: tracks[3] + 30}, title="crossing")
    ax = fig.axes[0]
    assert len(ax.lines) == 3 and ax.get_xlabel() == "x (mm)"
    assert sorted(tx.get_text() for tx in ax.texts) == ["3", "4"]
    with pytest.raises(ValueError, match=r"\(T, 3\)"):
        plot_trajectories({1: np.zeros((4, 2))})
    import matplotlib.pyplot as plt

    plt.close("all")

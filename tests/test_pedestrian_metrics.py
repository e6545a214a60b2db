"""Paper 002's metrics (sec. 5) on hand-made cases with known answers (host code, no device)."""

import numpy as np
import pytest

from gputrack.trackers.pedestrians.metrics import (
    clear_mot,
    detection_metrics,
    format_tables,
    identification_metrics,
    match_frame,
    segment_box,
    segments_cover,
)


def walk(x0, z, frames, step=200.0, y=-250.0):
    """(frames, 3) positions walking along +x at depth z."""
    x = x0 + step * np.arange(frames)
    return np.stack([x, np.full(frames, y), np.full(frames, z)], axis=1)


def scene(tracks, frames):
    """Per-frame truth lists from {person id: (first frame, positions (n, 3))}."""
    ids, pos = [], []
    for f in range(frames):
        i = [k for k, (f0, p) in tracks.items() if f0 <= f < f0 + len(p)]
        ids.append(np.array(i, dtype=np.int64))
        pos.append(np.array([tracks[k][1][f - tracks[k][0]] for k in i]).reshape(-1, 3))
    return ids, pos


def boxes(positions, half=150.0, front=200.0):
    """A segment per person: the front of the body, 0.3 m wide, 0.1 m deep, 100-200 mm before its axis."""
    p = np.asarray(positions).reshape(-1, 3)
    return np.stack([p[:, 0] - half, p[:, 0] + half, p[:, 2] - front, p[:, 2] - front + 100], axis=1)


A, B = walk(-1000, 2000, 10), walk(1000, 3500, 10, step=-200)


def test_perfect_tracking_scores_one_everywhere():
    ids, pos = scene({1: (0, A), 2: (3, B[:6]), 3: (5, walk(0, 4500, 5))}, 10)
    hyp = [i + 100 for i in ids]  # the tracker's own ids
    det = detection_metrics(pos, [boxes(p) for p in pos])
    assert (det.precision, det.recall, det.f) == (1.0, 1.0, 1.0)
    assert (det.frame_precision == 1).all() and (det.frame_f == 1).all()
    ident = identification_metrics(ids, pos, hyp, pos)
    assert (ident.precision, ident.recall) == (1.0, 1.0)
    assert ident.per_id[101] == (10, 1, 10, 3) and ident.per_person[2] == (6, 102, 6, 3)
    assert ident.precision_rows == {3: (3, 1.0)} and ident.recall_rows == {3: (3, 1.0)}
    mot = clear_mot(ids, pos, hyp, pos)
    assert mot["mota"] == 1.0 and mot["motp"] == 0.0 and mot["idf1"] == 1.0 and mot["num_switches"] == 0
    assert mot["num_objects"] == sum(len(i) for i in ids)


def test_a_missed_person_lowers_recall_only():
    ids, pos = scene({1: (0, A), 2: (0, B)}, 10)
    det = detection_metrics(pos, [boxes(p[:1]) for p in pos])  # only person 1 is segmented
    assert det.precision == 1.0 and det.recall == 0.5 and det.f == pytest.approx(2 / 3)
    np.testing.assert_array_equal(det.detected, 1)
    np.testing.assert_array_equal(det.people, 2)
    ident = identification_metrics(ids, pos, [i[:1] for i in ids], [p[:1] for p in pos])
    assert ident.precision == 1.0 and ident.recall == 0.5  # person 2: no frame on any id
    assert ident.per_person[2] == (10, -1, 0, 2)
    mot = clear_mot(ids, pos, [i[:1] for i in ids], [p[:1] for p in pos])
    assert mot["mota"] == 0.5 and mot["num_misses"] == 10


def test_two_people_in_one_segment_are_both_detected():
    p = np.array([[0.0, -300.0, 2000.0], [400.0, -300.0, 2100.0]])  # walking side by side
    merged = segment_box(np.array([[-150, -500, 1850], [550, -200, 1950], [200, -100, 1900.0]]))
    np.testing.assert_array_equal(merged, [-150, 550, 1850, 1950])
    assert segments_cover(merged[None], p).tolist() == [[True, True]]
    det = detection_metrics([p], [merged[None]])
    assert (det.precision, det.recall) == (1.0, 1.0) and det.detected.tolist() == [2]
    split = np.array([[-150, -50, 1850, 1900], [-40, 60, 1850, 1900.0]])  # person 1 split in two
    det = detection_metrics([p], [split])
    assert det.precision == 1.0 and det.recall == 0.5
    far = np.array([[2000, 2200, 4000, 4100.0]])  # a segment on nobody
    det = detection_metrics([p], [np.concatenate([merged[None], far])])
    assert det.precision == 0.5 and det.recall == 1.0


def test_segment_margin():
    p = np.array([[0.0, 0.0, 2000.0]])
    box = np.array([[-100.0, 100.0, 1700.0, 1749.0]])  # 251 mm in front of the body's axis
    assert not segments_cover(box, p).any()
    assert segments_cover(box, p, margin=251.0).all()
    assert segments_cover(box + [0, 0, 1, 1], p).all()


def test_empty_frames_count_as_perfect_and_false_segments_as_errors():
    det = detection_metrics([np.zeros((0, 3)), np.zeros((0, 3))], [np.zeros((0, 4)), boxes([[0, 0, 2000]])])
    assert det.frame_precision.tolist() == [1.0, 0.0] and det.frame_recall.tolist() == [1.0, 1.0]
    assert det.frame_f.tolist() == [1.0, 0.0]
    assert det.precision == 0.0 and det.recall == 1.0 and det.f == 0.0


def test_an_id_switch_lowers_identification_by_the_right_amount():
    ids, pos = scene({1: (0, A), 2: (0, B)}, 10)
    # the tracker swaps its ids after frame 5: id 7 on person 1 for 6 frames, then on person 2 for 4
    hyp = [np.array([7, 8]) if f < 6 else np.array([8, 7]) for f in range(10)]
    ident = identification_metrics(ids, pos, hyp, pos)
    assert ident.id_precisions == {7: 0.6, 8: 0.6}
    assert ident.id_recalls == {1: 0.6, 2: 0.6}
    assert ident.per_id[7] == (10, 1, 6, 2) and ident.per_id[8] == (10, 2, 6, 2)
    mot = clear_mot(ids, pos, hyp, pos)
    assert mot["num_switches"] == 2 and mot["mota"] == pytest.approx(1 - 2 / 20)
    # one person's track broken in two (a new id after 7 frames): precision stays 1, recall 0.7
    ids1, pos1 = scene({1: (0, A)}, 10)
    broken = [np.array([3 if f < 7 else 4]) for f in range(10)]
    ident = identification_metrics(ids1, pos1, broken, pos1)
    assert ident.precision == 1.0 and ident.recall == pytest.approx(0.7)


def test_recall_over_the_detected_frames():
    """Person 1 is segmented in frames 0-7 (tracked as 5 in 0-5, as 6 in 6-7) and missed in 8-9
    (no track); person 2 is never segmented, tracked by nobody. Over every frame in view: recall
    (6/10 + 0) / 2; over the detected frames person 1 has 6/8 and person 2 is left out."""
    ids, pos = scene({1: (0, A), 2: (0, B)}, 10)
    segs = [boxes(p[:1]) if f < 8 else np.zeros((0, 4)) for f, p in enumerate(pos)]
    hyp = [np.array([5 if f < 6 else 6]) if f < 8 else np.zeros(0, np.int64) for f in range(10)]
    hp = [p[:1] if f < 8 else np.zeros((0, 3)) for f, p in enumerate(pos)]
    ident = identification_metrics(ids, pos, hyp, hp, segments=segs)
    assert ident.recall == pytest.approx((0.6 + 0.0) / 2)
    assert ident.per_detected == {1: (8, 5, 6, 2)} and ident.recall_detected == pytest.approx(0.75)
    assert ident.recall_detected_rows == {2: (1, pytest.approx(0.75))}
    assert ident.per_person == identification_metrics(ids, pos, hyp, hp).per_person  # unchanged by segments
    table = format_tables(None, ident).splitlines()
    t4 = table[table.index(next(s for s in table if s.startswith("Table 4"))):]
    assert "detected frames" in t4[0] and t4[-1].split() == ["total", "2", "30.0", "1", "75.0"]
    with pytest.raises(ValueError, match="segments="):
        _ = identification_metrics(ids, pos, hyp, hp).recall_detected
    with pytest.raises(ValueError, match="one entry per frame"):
        identification_metrics(ids, pos, hyp, hp, segments=segs[:3])


def test_breakdown_by_people_in_view():
    # person 1 alone (frames 0-9); then people 2, 3 (frames 10-19) joined by 4 (frames 15-19)
    ids, pos = scene({1: (0, A), 2: (10, walk(-1000, 2000, 10)), 3: (10, walk(-1000, 3000, 10)),
                      4: (15, walk(0, 4000, 5))}, 20)  # fmt: skip
    hyp = [i.copy() for i in ids]
    for f in range(17, 20):  # the tracker gives person 4 the id 3 and person 3 the id 4 for 3 frames
        hyp[f] = np.array([2, 4, 3])
    ident = identification_metrics(ids, pos, hyp, pos)
    assert ident.precision_rows == {1: (1, 1.0), 3: (3, pytest.approx((1 + 7 / 10 + 3 / 5) / 3))}
    assert ident.recall_rows == {1: (1, 1.0), 3: (3, pytest.approx((1 + 7 / 10 + 3 / 5) / 3))}
    # the rows follow the given counts of people in view when passed
    ident2 = identification_metrics(ids, pos, hyp, pos, in_view=np.full(20, 5))
    assert set(ident2.precision_rows) == {5}
    table = format_tables(detection_metrics(pos, [boxes(p) for p in pos]), ident)
    lines = table.splitlines()
    assert "Table 2" in lines[0] and "100.0 %" in lines[1]
    t3 = lines[lines.index(next(s for s in lines if s.startswith("Table 3"))) + 2 :][:6]
    assert t3[0].split() == ["1", "1", "100.0"] and t3[1].split() == ["2", "0", "-"]
    assert t3[2].split() == ["3", "3", f"{100 * (1 + 0.7 + 0.6) / 3:.1f}"] and t3[5].split()[0] == "total"
    assert t3[5].split()[1:] == ["4", f"{100 * ident.precision:.1f}"]
    assert "Table 4" in table


def test_matching_is_one_to_one_within_the_gate():
    truth = np.array([[0.0, 0, 2000], [300.0, 0, 2000]])
    hyp = np.array([[150.0, 0, 2000], [2000.0, 0, 2000]])
    assert match_frame([1, 2], truth, [5, 6], hyp) == [(1, 5)]  # one track for two people: one match
    assert match_frame([1], truth[:1], [5], [[0.0, 900, 2501]]) == []  # 501 mm away in the ground plane
    assert match_frame([1], truth[:1], [5], [[0.0, 900, 2499]]) == [(1, 5)]  # y is ignored
    assert match_frame([1, 2], truth, [5, 6], [[290.0, 0, 2000], [10.0, 0, 2000]]) == [(1, 6), (2, 5)]


def test_clear_mot_distances():
    ids, pos = scene({1: (0, A)}, 10)
    up = [p + [0.0, 300.0, 0.0] for p in pos]  # a track 300 mm lower than the truth
    assert clear_mot(ids, pos, ids, up)["motp"] == pytest.approx(300.0)
    assert clear_mot(ids, pos, ids, up, plane=True)["motp"] == pytest.approx(0.0)
    far = [p + [600.0, 0.0, 0.0] for p in pos]
    mot = clear_mot(ids, pos, ids, far)
    assert mot["num_matches"] == 0 and mot["num_false_positives"] == 10 and mot["mota"] == -1.0
    assert clear_mot(ids, pos, ids, far, max_distance=700.0)["motp"] == pytest.approx(600.0)


def test_bad_input():
    p = [np.zeros((1, 3))]
    with pytest.raises(ValueError, match="one entry per frame"):
        identification_metrics([np.array([1])], p, [], [])
    with pytest.raises(ValueError, match="unique"):
        identification_metrics([np.array([1])], p, [np.array([2, 2])], [np.zeros((2, 3))])
    with pytest.raises(ValueError, match="finite"):
        detection_metrics([np.full((1, 3), np.nan)], [np.zeros((0, 4))])
    with pytest.raises(ValueError, match="x_min <= x_max"):
        detection_metrics(p, [np.array([[1.0, 0.0, 0.0, 1.0]])])
    with pytest.raises(ValueError, match=r"\(N, 4\)"):
        detection_metrics(p, [np.zeros((1, 3))])
    with pytest.raises(ValueError, match="same length"):
        identification_metrics([np.array([1, 2])], p, [np.array([1])], p)
    with pytest.raises(TypeError, match="one entry per frame"):
        detection_metrics(np.zeros((2, 1, 3)), [np.zeros((0, 4))] * 2)
    with pytest.raises(ValueError, match="max_distance"):
        clear_mot([np.array([1])], p, [np.array([1])], p, max_distance=0.0)


# -- pictures ----------------------------------------------------------------------------------------------
def test_depth_picture():
    from gputrack.trackers.pedestrians.pictures import depth_picture

    d = np.zeros((60, 80), np.uint16)
    d[:, :40] = 1000
    d[:, 40:] = 4500
    d[:5] = 0  # no reading
    d[5:8] = 6000  # beyond the range
    img = depth_picture(d, boxes=[[20, 40, 10, 30]], ids=[7])
    assert img.shape == (60, 80, 3) and img.dtype == np.uint8
    assert (img[:8] == 0).all()
    assert img[50, 5, 2] > img[50, 5, 0] and img[50, 75, 0] > img[50, 75, 2]  # BGR: near red, far blue
    assert (img[30, 10] == 255).all() and (img[20, 20] == 255).all()  # the box's outline
    with pytest.raises(ValueError, match="one per box"):
        depth_picture(d, boxes=[[0, 1, 0, 1]], ids=[1, 2])


def test_top_view():
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gputrack.trackers.pedestrians.pictures import top_view

    ax = top_view([3, 4], [[0, -300, 2000], [500, -300, 3000]], [[-150, 150, 1800, 1900], [350, 650, 2800, 2900]],
                  history={3: walk(-1000, 2000, 6)}, truth_positions=[[0, -300, 2000]], title="frame 0")  # fmt: skip
    assert len(ax.patches) == 2 and [t.get_text() for t in ax.texts] == ["3", "4"]
    assert ax.get_title() == "frame 0"
    plt.close(ax.figure)

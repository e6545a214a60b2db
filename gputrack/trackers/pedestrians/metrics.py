"""Paper 002's accuracy measures (sec. 5), pure NumPy, independent of the tracker's classes.

Inputs are per-frame lists (one entry per frame, F frames), in camera coordinates (mm; x right,
y down, z forward); the *ground plane* is (x, z):

- truth: ``truth_ids[f]`` (K,) int person ids and ``truth_positions[f]`` (K, 3) their positions
  (the simulator's chest-height centre or the floor point below it: only x and z are used, except
  by :func:`clear_mot` with ``plane=False``);
- segments (detection, sec. 5.1): ``segments[f]`` (M, 4) ground-plane boxes
  [x_min, x_max, z_min, z_max] of the frame's segments (:func:`segment_box` makes one from a
  segment's points);
- tracks (identification, sec. 5.2): ``hyp_ids[f]`` (M,) int tracker ids, unique within a frame,
  and ``hyp_positions[f]`` (M, 3) their positions.

Detection (sec. 5.1, Table 2). Person k is *covered* by segment j when its ground-plane point lies in
the segment's box grown by ``margin`` on every side (default 250 mm: a depth camera sees the front
of a body only, so a segment's box lies some 100-250 mm in front of the body's centre axis). A
person is detected when some segment covers it, so two people inside one segment are both detected
(the paper's rule); a segment is correct when it covers some person (a person split into two
segments gives two correct segments). Per frame and pooled over the sequence (sums of counts):
precision = correct segments / segments, recall = detected people / people,
F = 2 P R / (P + R). A ratio with nothing to count (no segments, no people) is 1: nothing was
got wrong; F of P = R = 0 is 0.

Identification (sec. 5.2, Tables 3-4). Each frame, tracks are matched one-to-one to people by the
assignment of least total ground-plane distance among the pairs within ``max_distance`` (default
500 mm; scipy's ``linear_sum_assignment``). Per tracker id: its frames = the frames it is output in;
its majority person = the person it is matched to most often (ties: the smaller person id); its
precision = frames matched to the majority person / its frames (0 when never matched).
Identification precision = the mean over ids. Per person: its frames = the frames it is in the
truth; its majority id likewise; its recall = frames matched to the majority id / its frames;
identification recall = the mean over people. Both are broken down by the largest number of people
in view (default: the truth's count per frame) over the id's or the person's frames: Table 3's and
Table 4's rows 1, 2, ... (row 0: ids output only in frames with nobody in view).

Recall over the detected frames (given the segments): the same rule with a person's frames the
frames in which a segment covers it (detection's sense; people never covered are left out: they
are Table 2's misses). The paper's wording ("the frames in which the pedestrian appears") leaves
open which frames count; its figures (detection recall 89.5 %, identification recall 94.6 %) fit
this reading better, since over every frame in view a person's identification recall can hardly
exceed its detection recall. Both are reported.

CLEAR MOT (MOTA, MOTP in mm) and IDF1: :func:`clear_mot`, via ``motmetrics`` (the ``test`` extra),
imported when called.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = [
    "DEFAULT_MARGIN",
    "DEFAULT_MAX_DISTANCE",
    "Detection",
    "Identification",
    "clear_mot",
    "detection_metrics",
    "format_tables",
    "identification_metrics",
    "match_frame",
    "segment_box",
    "segments_cover",
]

#: mm a segment's ground-plane box is grown by when testing whether it covers a person
DEFAULT_MARGIN = 250.0
#: mm, the largest ground-plane distance of a matched track and person
DEFAULT_MAX_DISTANCE = 500.0


# -- input checks ---------------------------------------------------------------------------------------
def _array(a, name, cols, kind="f"):
    x = np.asarray(a)
    if x.size == 0 and x.ndim <= 1 and cols is not None:
        x = x.reshape(0, cols)
    if kind == "i":
        if x.dtype.kind not in "iu" or x.ndim != 1:
            raise ValueError(f"{name}: expected a 1-D integer array, got {x.dtype.name} {x.shape}")
        return x.astype(np.int64)
    if x.dtype.kind not in "iuf" or x.ndim != 2 or x.shape[1] != cols:
        raise ValueError(f"{name}: expected a real (N, {cols}) array, got {x.dtype.name} {x.shape}")
    x = x.astype(np.float64)
    if not np.isfinite(x).all():
        raise ValueError(f"{name}: expected finite values, got non-finite entries")
    return x


def _frames(name, seq):
    if isinstance(seq, np.ndarray) or not hasattr(seq, "__len__"):
        raise TypeError(f"{name}: expected a list with one entry per frame, got {type(seq).__name__}")
    return len(seq)


def _same_length(**lists):
    n = {k: _frames(k, v) for k, v in lists.items()}
    if len(set(n.values())) > 1:
        raise ValueError(f"expected one entry per frame in each list, got lengths {n}")
    return next(iter(n.values()))


def _ids_positions(ids, pos, f, what):
    i = _array(ids, f"{what}_ids[{f}]", None, "i")
    p = _array(pos, f"{what}_positions[{f}]", 3)
    if len(i) != len(p):
        raise ValueError(
            f"{what}_ids[{f}] and {what}_positions[{f}]: expected the same length, got {len(i)} and {len(p)}"
        )
    if len(np.unique(i)) != len(i):
        raise ValueError(f"{what}_ids[{f}]: expected unique ids within a frame, got {i.tolist()}")
    return i, p


def _ratio(num, den):
    """num / den elementwise, 1 where den = 0 (nothing to get wrong)."""
    num = np.asarray(num, dtype=np.float64)
    den = np.asarray(den, dtype=np.float64)
    return np.where(den > 0, num / np.maximum(den, 1), 1.0)


def _f_score(p, r):
    p, r = np.asarray(p, dtype=np.float64), np.asarray(r, dtype=np.float64)
    return np.where(p + r > 0, 2 * p * r / np.where(p + r > 0, p + r, 1.0), 0.0)


# -- detection (sec. 5.1) ---------------------------------------------------------------------------------
def segment_box(points) -> np.ndarray:
    """(4,) ground-plane box [x_min, x_max, z_min, z_max] of a segment's points (N, 3) or (N, 2)
    (x, z) (N >= 1)."""
    p = np.asarray(points)
    if p.dtype.kind not in "iuf" or p.ndim != 2 or p.shape[1] not in (2, 3) or len(p) == 0:
        raise ValueError(f"points: expected a real (N, 3) or (N, 2) array with N >= 1, got {p.dtype.name} {p.shape}")
    xz = p[:, [0, 2]] if p.shape[1] == 3 else p
    xz = xz.astype(np.float64)
    if not np.isfinite(xz).all():
        raise ValueError("points: expected finite values, got non-finite entries")
    return np.array([xz[:, 0].min(), xz[:, 0].max(), xz[:, 1].min(), xz[:, 1].max()])


def segments_cover(boxes, positions, margin: float = DEFAULT_MARGIN) -> np.ndarray:
    """(M, K) bool: segment j covers person k (its ground-plane point (x, z) inside box j grown by
    ``margin``). boxes (M, 4) [x_min, x_max, z_min, z_max]; positions (K, 3)."""
    b = _array(boxes, "boxes", 4)
    p = _array(positions, "positions", 3)
    if (b[:, 1] < b[:, 0]).any() or (b[:, 3] < b[:, 2]).any():
        raise ValueError("boxes: expected x_min <= x_max and z_min <= z_max in every row")
    if not (np.isfinite(margin) and margin >= 0):
        raise ValueError(f"margin: expected a finite number >= 0, got {margin!r}")
    x, z = p[None, :, 0], p[None, :, 2]
    return ((x >= b[:, None, 0] - margin) & (x <= b[:, None, 1] + margin)
            & (z >= b[:, None, 2] - margin) & (z <= b[:, None, 3] + margin))  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Detection:
    """Detection counts per frame (F,) int64 and the sequence's pooled precision, recall, F (Table 2).

    ``correct``: segments covering a person; ``segments``; ``detected``: people covered by a
    segment; ``people``. ``frame_precision``/``frame_recall``/``frame_f`` (F,) per frame.
    """

    correct: np.ndarray
    segments: np.ndarray
    detected: np.ndarray
    people: np.ndarray

    @property
    def precision(self) -> float:
        return float(_ratio(self.correct.sum(), self.segments.sum()))

    @property
    def recall(self) -> float:
        return float(_ratio(self.detected.sum(), self.people.sum()))

    @property
    def f(self) -> float:
        return float(_f_score(self.precision, self.recall))

    @property
    def frame_precision(self) -> np.ndarray:
        return _ratio(self.correct, self.segments)

    @property
    def frame_recall(self) -> np.ndarray:
        return _ratio(self.detected, self.people)

    @property
    def frame_f(self) -> np.ndarray:
        return _f_score(self.frame_precision, self.frame_recall)


def detection_metrics(truth_positions, segments, margin: float = DEFAULT_MARGIN) -> Detection:
    """Per-frame detection counts (sec. 5.1; see the module docstring).

    truth_positions: per frame (K, 3); segments: per frame (M, 4) ground-plane boxes.
    """
    n = _same_length(truth_positions=truth_positions, segments=segments)
    out = np.zeros((4, n), dtype=np.int64)
    for f in range(n):
        cov = segments_cover(segments[f], truth_positions[f], margin)
        out[:, f] = (cov.any(axis=1).sum(), cov.shape[0], cov.any(axis=0).sum(), cov.shape[1])
    return Detection(*out)


# -- identification (sec. 5.2) -----------------------------------------------------------------------------
def match_frame(truth_ids, truth_positions, hyp_ids, hyp_positions,
                max_distance: float = DEFAULT_MAX_DISTANCE) -> list[tuple[int, int]]:  # fmt: skip
    """One frame's one-to-one matching of tracks to people: [(person id, track id)], the pairs of
    least total ground-plane distance among those within ``max_distance``."""
    ti, tp = _ids_positions(truth_ids, truth_positions, "?", "truth")
    hi, hp = _ids_positions(hyp_ids, hyp_positions, "?", "hyp")
    if not (np.isfinite(max_distance) and max_distance > 0):
        raise ValueError(f"max_distance: expected a finite number > 0, got {max_distance!r}")
    return _match(ti, tp, hi, hp, max_distance)


def _match(ti, tp, hi, hp, max_distance):
    if len(ti) == 0 or len(hi) == 0:
        return []
    from scipy.optimize import linear_sum_assignment

    d = np.hypot(tp[:, None, 0] - hp[None, :, 0], tp[:, None, 2] - hp[None, :, 2])
    ok = d <= max_distance
    if not ok.any():
        return []
    cost = np.where(ok, d, max_distance * (len(ti) + len(hi) + 1))  # a forbidden pair never beats a gap
    rows, cols = linear_sum_assignment(cost)
    return [(int(ti[r]), int(hi[c])) for r, c in zip(rows, cols) if ok[r, c]]


@dataclasses.dataclass(frozen=True)
class Identification:
    """Trajectory identification (Tables 3-4).

    ``per_id``: {track id: (frames, majority person or -1, frames on it, largest people in view)};
    ``per_person``: {person id: (frames, majority track id or -1, frames on it, largest in view)};
    ``per_detected``: the same over the frames in which a segment covers the person (None: no
    segments given; people never covered are left out).
    """

    per_id: dict
    per_person: dict
    per_detected: dict | None = None

    @property
    def id_precisions(self) -> dict:
        """{track id: share of its frames on its majority person}."""
        return {k: v[2] / v[0] for k, v in self.per_id.items()}

    @property
    def id_recalls(self) -> dict:
        """{person id: share of its frames on its majority track id}."""
        return {k: v[2] / v[0] for k, v in self.per_person.items()}

    @property
    def detected_recalls(self) -> dict:
        """{person id: share of its detected frames on its majority track id} (needs the segments)."""
        if self.per_detected is None:
            raise ValueError("identification: expected segments= to identification_metrics for the detected frames")
        return {k: v[2] / v[0] for k, v in self.per_detected.items()}

    @property
    def precision(self) -> float:
        """Mean over track ids (1.0 when there is none)."""
        v = list(self.id_precisions.values())
        return float(np.mean(v)) if v else 1.0

    @property
    def recall(self) -> float:
        """Mean over people (1.0 when there is none)."""
        v = list(self.id_recalls.values())
        return float(np.mean(v)) if v else 1.0

    @property
    def recall_detected(self) -> float:
        """Mean over the people ever detected of their recall over the detected frames."""
        v = list(self.detected_recalls.values())
        return float(np.mean(v)) if v else 1.0

    @staticmethod
    def _rows(table, values) -> dict:
        rows: dict = {}
        for k, v in table.items():
            rows.setdefault(v[3], []).append(values[k])
        return {n: (len(v), float(np.mean(v))) for n, v in sorted(rows.items())}

    @property
    def precision_rows(self) -> dict:
        """Table 3: {largest people in view: (number of ids, mean precision)}."""
        return self._rows(self.per_id, self.id_precisions)

    @property
    def recall_rows(self) -> dict:
        """Table 4: {largest people in view: (number of people, mean recall)}."""
        return self._rows(self.per_person, self.id_recalls)

    @property
    def recall_detected_rows(self) -> dict:
        """Table 4 over the detected frames: {largest people in view: (people, mean recall)}."""
        return self._rows(self.per_detected, self.detected_recalls)


def _majority(counter: dict) -> tuple[int, int]:
    if not counter:
        return -1, 0
    best = min(counter, key=lambda k: (-counter[k], k))
    return best, counter[best]


def identification_metrics(truth_ids, truth_positions, hyp_ids, hyp_positions, *,
                           max_distance: float = DEFAULT_MAX_DISTANCE, in_view=None, segments=None,
                           margin: float = DEFAULT_MARGIN) -> Identification:  # fmt: skip
    """Trajectory-identification precision and recall (sec. 5.2; see the module docstring).

    in_view: optional (F,) people in view per frame for the breakdown (default: len(truth_ids[f]));
    segments: optional per frame (M, 4) ground-plane boxes (as :func:`detection_metrics`) for the
    recall over the detected frames (a person covered by a box grown by ``margin``).
    """
    lists = {"truth_ids": truth_ids, "truth_positions": truth_positions, "hyp_ids": hyp_ids,
             "hyp_positions": hyp_positions}  # fmt: skip
    if segments is not None:
        lists["segments"] = segments
    n = _same_length(**lists)
    if not (np.isfinite(max_distance) and max_distance > 0):
        raise ValueError(f"max_distance: expected a finite number > 0, got {max_distance!r}")
    if in_view is not None:
        iv = np.asarray(in_view)
        if iv.dtype.kind not in "iu" or iv.shape != (n,) or (iv < 0).any():
            raise ValueError(f"in_view: expected ({n},) integers >= 0, got {iv.dtype.name} {iv.shape}")
    ids_frames: dict = {}
    person_frames: dict = {}
    id_on: dict = {}
    person_on: dict = {}
    id_max: dict = {}
    person_max: dict = {}
    det_frames: dict = {}
    det_on: dict = {}
    det_max: dict = {}
    for f in range(n):
        ti, tp = _ids_positions(truth_ids[f], truth_positions[f], f, "truth")
        hi, hp = _ids_positions(hyp_ids[f], hyp_positions[f], f, "hyp")
        crowd = int(iv[f]) if in_view is not None else len(ti)
        covered = set() if segments is None else set(ti[segments_cover(segments[f], tp, margin).any(axis=0)].tolist())
        for k in covered:
            det_frames[k] = det_frames.get(k, 0) + 1
            det_max[k] = max(det_max.get(k, 0), crowd)
        for k in hi.tolist():
            ids_frames[k] = ids_frames.get(k, 0) + 1
            id_max[k] = max(id_max.get(k, 0), crowd)
        for k in ti.tolist():
            person_frames[k] = person_frames.get(k, 0) + 1
            person_max[k] = max(person_max.get(k, 0), crowd)
        for p, h in _match(ti, tp, hi, hp, max_distance):
            c = id_on.setdefault(h, {})
            c[p] = c.get(p, 0) + 1
            c = person_on.setdefault(p, {})
            c[h] = c.get(h, 0) + 1
            if p in covered:
                c = det_on.setdefault(p, {})
                c[h] = c.get(h, 0) + 1
    per_id = {k: (m, *_majority(id_on.get(k, {})), id_max[k]) for k, m in sorted(ids_frames.items())}
    per_person = {k: (m, *_majority(person_on.get(k, {})), person_max[k]) for k, m in sorted(person_frames.items())}
    per_detected = None if segments is None else {
        k: (m, *_majority(det_on.get(k, {})), det_max[k]) for k, m in sorted(det_frames.items())}  # fmt: skip
    return Identification(per_id, per_person, per_detected)


# -- CLEAR MOT and IDF1 (motmetrics) ----------------------------------------------------------------------
def clear_mot(truth_ids, truth_positions, hyp_ids, hyp_positions, *, max_distance: float = DEFAULT_MAX_DISTANCE,
              plane: bool = False) -> dict:  # fmt: skip
    """CLEAR MOT and identity measures via ``motmetrics`` with Euclidean distances in mm (3D, or
    the ground plane (x, z) with ``plane=True``); pairs farther than ``max_distance`` never match.

    Returns {"mota", "motp" (mm, mean distance of the matches), "idf1", "idp", "idr",
    "num_switches", "num_misses", "num_false_positives", "num_matches", "num_objects"}.
    Raises ImportError when motmetrics is missing (it is in the ``test`` extra).
    """
    try:
        import motmetrics as mm
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("clear_mot needs motmetrics: pip install motmetrics (or gputrack[test])") from e
    n = _same_length(truth_ids=truth_ids, truth_positions=truth_positions, hyp_ids=hyp_ids,
                     hyp_positions=hyp_positions)  # fmt: skip
    if not (np.isfinite(max_distance) and max_distance > 0):
        raise ValueError(f"max_distance: expected a finite number > 0, got {max_distance!r}")
    cols = [0, 2] if plane else [0, 1, 2]
    acc = mm.MOTAccumulator(auto_id=True)
    for f in range(n):
        ti, tp = _ids_positions(truth_ids[f], truth_positions[f], f, "truth")
        hi, hp = _ids_positions(hyp_ids[f], hyp_positions[f], f, "hyp")
        d = np.linalg.norm(tp[:, None, cols] - hp[None, :, cols], axis=-1) if len(ti) and len(hi) else \
            np.empty((len(ti), len(hi)))  # fmt: skip
        d = np.where(d <= max_distance, d, np.nan)
        acc.update(ti.tolist(), hi.tolist(), d)
    names = ["mota", "motp", "idf1", "idp", "idr", "num_switches", "num_misses", "num_false_positives",
             "num_matches", "num_objects"]  # fmt: skip
    s = mm.metrics.create().compute(acc, metrics=names, name="seq")
    return {k: (int(s[k].iloc[0]) if k.startswith("num_") else float(s[k].iloc[0])) for k in names}


# -- tables ---------------------------------------------------------------------------------------------
def format_tables(detection: Detection | None = None, identification: Identification | None = None,
                  mot: dict | None = None, rows: int = 5) -> str:  # fmt: skip
    """Text in the layout of paper 002's Tables 2-4 (and a CLEAR MOT line if ``mot`` is given).

    Tables 3-4 list rows 1..``rows`` people in view (and any other row present, e.g. 0), an empty
    row shown as "-", then the total (the mean over all ids / people).
    """
    out = []
    if detection is not None:
        out += ["Table 2  pedestrian detection per frame",
                f"  precision  {100 * detection.precision:5.1f} %",
                f"  recall     {100 * detection.recall:5.1f} %",
                f"  F          {100 * detection.f:5.1f} %"]  # fmt: skip
    if identification is not None:
        ident = identification
        cols = [[("Table 3  trajectory-identification precision", "ids", ident.precision_rows, ident.precision,
                  len(ident.per_id))],
                [("Table 4  trajectory-identification recall", "people", ident.recall_rows, ident.recall,
                  len(ident.per_person))]]  # fmt: skip
        if ident.per_detected is not None:  # over the detected frames, beside
            cols[1].append(("right: over the detected frames", "people", ident.recall_detected_rows,
                            ident.recall_detected, len(ident.per_detected)))  # fmt: skip
        for group in cols:
            if out:
                out.append("")
            out.append(group[0][0] + ("" if len(group) == 1 else "   (left: every frame in view; "
                                      + "; ".join(t for t, *_ in group[1:]) + ")"))
            out.append("  people in view" + "".join(f"  {what:>6}  mean (%)" for _, what, *_ in group))
            for n in sorted(set(range(1, rows + 1)).union(*[set(g[2]) for g in group])):
                line = f"  {n:>14}"
                for _, _, table, _, _ in group:
                    c, m = table.get(n, (0, None))
                    line += f"  {c:>6}  " + ("       -" if m is None else f"{100 * m:8.1f}")
                out.append(line)
            out.append(f"  {'total':>14}" + "".join(f"  {count:>6}  {100 * total:8.1f}"
                                                     for _, _, _, total, count in group))  # fmt: skip
    if mot is not None:
        if out:
            out.append("")
        out.append(f"CLEAR MOT  MOTA {100 * mot['mota']:.1f} %  MOTP {mot['motp']:.0f} mm  IDF1 "
                   f"{100 * mot['idf1']:.1f} %  ID switches {mot['num_switches']}")  # fmt: skip
    return "\n".join(out)

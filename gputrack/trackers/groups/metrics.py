"""Paper 001's qualitative results as numbers: group purity, id switches, merge latency, the error
of the groups' 3D means, and CLEAR MOT / IDF1 of the group means.

Plain arrays in, no tracker classes: per frame a :class:`FrameRecord` with

- ``labels`` (N,) int: each observation point's reported group id (-1: not assigned);
- ``person_ids`` (N,) int: each point's true person (-1: a point on no person, e.g. clutter);
- ``person_group``: the true group of each person this frame (a dict {person: group}, or an
  array indexed by person id, -1 for none): after a merge its members share one group;
- ``reported_ids`` (R,) and ``reported_means`` (R, 3): the groups the tracker reports, their 3D
  means (mm);
- ``true_ids`` (G,) and ``true_means`` (G, 3): the true groups present and their means (mm).

Definitions (frame k):

- contingency C[g, r]: the number of *labelled* points (label r >= 0, on a person of true group
  g); points with label -1 or on no person are not counted;
- matching: the one-to-one pairing of true and reported groups maximising the matched points
  sum_g C[g, M(g)] (Hungarian; pairs with C = 0 are not matched). Each true group is matched to
  the reported group most of its points go to, unless two true groups have their majority in
  the same reported group: then only the one with more points there keeps it;
- purity = sum_g C[g, M(g)] / sum C: the share of labelled points whose reported group is their
  true group's match (NaN without labelled points). 1 iff every reported group holds the points
  of one true group and no true group is split;
- id switches: per true group, the matched reported id changing from one frame where the group
  is matched to the next such frame (frames where it is unmatched are skipped);
- merge latency: for the merged true group (its members at the merge frame, set S), "one group
  reported" holds at frame k when one reported id holds at least ``min_share`` of the labelled
  points of S. Latency = the first frame >= merge frame where it holds, minus the merge frame;
  when it already holds at the merge frame, minus the number of frames before it over which it
  held without a break (negative: merged early). None when it never holds;
- mean error: for each matched pair, || reported mean - true mean || (mm);
- CLEAR MOT (MOTA, MOTP) and IDF1 of the group means (motmetrics): objects = true groups,
  hypotheses = reported groups, distance = 3D Euclidean (mm), pairs farther than ``max_dist``
  cannot match; MOTP is the mean distance of the matches (mm). The default ``max_dist`` is 1 m:
  a group's mean of visible surface points lies 0.2-0.5 m from the mean of its members' centres
  in the simulated scenes (the points are on the surfaces facing the camera, and occluded members
  give fewer of them), so a correct tracker's means are that far from the truth.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = [
    "FrameRecord",
    "GroupMetrics",
    "clear_mot",
    "contingency",
    "evaluate",
    "id_switches",
    "match",
    "merge_latency",
    "purity",
]


def _ints(a, name, n=None) -> np.ndarray:
    x = np.asarray(a)
    if x.size == 0:
        x = x.astype(np.int64).reshape(0)
    if x.ndim != 1 or x.dtype.kind not in "iu":
        raise ValueError(f"{name}: expected a 1-D integer array, got {x.dtype.name} {x.shape}")
    if n is not None and len(x) != n:
        raise ValueError(f"{name}: expected {n} entries (one per point), got {len(x)}")
    return x.astype(np.int64)


def _means(a, name, n) -> np.ndarray:
    x = np.asarray(a, dtype=np.float64) if np.asarray(a).size else np.zeros((0, 3))
    if x.shape != (n, 3):
        raise ValueError(f"{name}: expected shape ({n}, 3) (one 3D mean per id), got {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError(f"{name}: expected finite values, got {x[~np.isfinite(x)][0]}")
    return x


def _group_of(person_group, person_ids) -> np.ndarray:
    """The true group of each point (-1 for no person or a person without a group)."""
    out = np.full(len(person_ids), -1, np.int64)
    if isinstance(person_group, dict):
        for i, p in enumerate(person_ids):
            out[i] = int(person_group.get(int(p), -1)) if p >= 0 else -1
        return out
    table = _ints(person_group, "person_group")
    ok = (person_ids >= 0) & (person_ids < len(table))
    out[ok] = table[person_ids[ok]]
    return out


@dataclasses.dataclass(frozen=True)
class FrameRecord:
    """One frame's tracker output and truth (see the module); arrays are checked and converted."""

    labels: np.ndarray
    person_ids: np.ndarray
    person_group: object
    reported_ids: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    reported_means: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    true_ids: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    true_means: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))

    def __post_init__(self):
        labels = _ints(self.labels, "labels")
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "person_ids", _ints(self.person_ids, "person_ids", len(labels)))
        if not isinstance(self.person_group, dict):
            object.__setattr__(self, "person_group", _ints(self.person_group, "person_group"))
        for ids, means in (("reported_ids", "reported_means"), ("true_ids", "true_means")):
            i = _ints(getattr(self, ids), ids)
            if len(np.unique(i)) != len(i):
                raise ValueError(f"{ids}: expected distinct ids, got {i.tolist()}")
            object.__setattr__(self, ids, i)
            object.__setattr__(self, means, _means(getattr(self, means), means, len(i)))


def contingency(labels, person_ids, person_group):
    """(true_ids (G,), reported_ids (R,), C (G, R) int64): labelled points per true x reported group."""
    labels = _ints(labels, "labels")
    person_ids = _ints(person_ids, "person_ids", len(labels))
    g = _group_of(person_group, person_ids)
    ok = (labels >= 0) & (g >= 0)
    gi, gk = np.unique(g[ok], return_inverse=True)
    ri, rk = np.unique(labels[ok], return_inverse=True)
    c = np.zeros((len(gi), len(ri)), np.int64)
    np.add.at(c, (gk, rk), 1)
    return gi, ri, c


def match(labels, person_ids, person_group) -> dict:
    """{true group: matched reported id}: the one-to-one matching of most points (see the module)."""
    from scipy.optimize import linear_sum_assignment

    gi, ri, c = contingency(labels, person_ids, person_group)
    if c.size == 0:
        return {}
    rows, cols = linear_sum_assignment(-c)
    return {int(gi[a]): int(ri[b]) for a, b in zip(rows, cols) if c[a, b] > 0}


def purity(labels, person_ids, person_group) -> float:
    """Share of labelled points whose reported group is their true group's match (NaN if none)."""
    gi, ri, c = contingency(labels, person_ids, person_group)
    total = c.sum()
    if total == 0:
        return float("nan")
    m = match(labels, person_ids, person_group)
    col = {int(r): j for j, r in enumerate(ri)}
    row = {int(g): i for i, g in enumerate(gi)}
    return float(sum(c[row[g], col[r]] for g, r in m.items()) / total)


def id_switches(matches) -> dict:
    """{true group: number of switches} over a sequence of per-frame matches ({true: reported})."""
    last, out = {}, {}
    for m in matches:
        for g, r in m.items():
            out.setdefault(g, 0)
            if g in last and last[g] != r:
                out[g] += 1
            last[g] = r
    return out


def _one_group(rec: FrameRecord, members: np.ndarray, min_share: float) -> bool:
    on = np.isin(rec.person_ids, members) & (rec.labels >= 0)
    if not on.any():
        return False
    _, counts = np.unique(rec.labels[on], return_counts=True)
    return counts.max() >= min_share * on.sum()


def merge_latency(records, merge_frame: int, merged_group: int, min_share: float = 0.9):
    """Frames from the true merge until one group is reported for the merged group (see the
    module): an int (negative: merged before the truth), or None if it never happens."""
    if isinstance(merge_frame, bool) or not isinstance(merge_frame, (int, np.integer)) \
            or not 0 <= merge_frame < len(records):  # fmt: skip
        raise ValueError(f"merge_frame: expected a frame index in [0, {len(records)}), got {merge_frame!r}")
    if not 0.5 < min_share <= 1.0:
        raise ValueError(f"min_share: expected a number in (0.5, 1], got {min_share!r}")
    pg = records[merge_frame].person_group
    if isinstance(pg, dict):
        members = np.array([p for p, g in pg.items() if g == merged_group], np.int64)
    else:
        members = np.flatnonzero(np.asarray(pg) == merged_group)
    if len(members) == 0:
        raise ValueError(f"merged_group: expected a true group present at frame {merge_frame}, got {merged_group}")
    for k in range(merge_frame, len(records)):
        if _one_group(records[k], members, min_share):
            if k > merge_frame:
                return k - merge_frame
            j = merge_frame
            while j > 0 and _one_group(records[j - 1], members, min_share):
                j -= 1
            return j - merge_frame
    return None


def clear_mot(records, max_dist: float = 1000.0) -> dict:
    """CLEAR MOT and IDF1 of the group means with motmetrics (see the module): dict of ``mota``,
    ``motp`` (mm), ``idf1``, ``num_switches``, ``num_false_positives``, ``num_misses``,
    ``num_matches`` (motmetrics' counts: a switch is a correspondence but not a match, so the
    correspondences are ``num_matches + num_switches``, over which MOTP averages)."""
    try:
        import motmetrics as mm
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "the CLEAR MOT and IDF1 figures need motmetrics: pip install 'gputrack[test]' (or pip install motmetrics)"
        ) from e
    if not (np.isfinite(max_dist) and max_dist > 0):
        raise ValueError(f"max_dist: expected a positive distance (mm), got {max_dist!r}")
    acc = mm.MOTAccumulator(auto_id=True)
    for rec in records:
        d = np.linalg.norm(rec.true_means[:, None, :] - rec.reported_means[None, :, :], axis=-1)
        d[d > max_dist] = np.nan
        acc.update(rec.true_ids.tolist(), rec.reported_ids.tolist(), d)
    names = ["mota", "motp", "idf1", "num_switches", "num_false_positives", "num_misses", "num_matches"]
    s = mm.metrics.create().compute(acc, metrics=names, name="groups")
    return {n: (float(s[n].iloc[0]) if n in ("mota", "motp", "idf1") else int(s[n].iloc[0])) for n in names}


@dataclasses.dataclass(frozen=True)
class GroupMetrics:
    """:func:`evaluate`'s figures: ``purity`` (F,) per frame (NaN: no labelled points) and its
    mean over the frames that have one; ``matches`` per frame {true: reported}; ``switches``
    {true group: id switches} and their ``total_switches``; ``true_ids`` (G,) every true group of
    the sequence and ``error`` (F, G) the error of each matched group's mean (mm, NaN where
    unmatched) with ``mean_error`` over all matched pairs; ``merge_latency`` (frames, or None);
    ``mot`` the :func:`clear_mot` dict (None when not asked for)."""

    purity: np.ndarray
    mean_purity: float
    matches: list
    switches: dict
    total_switches: int
    true_ids: np.ndarray
    error: np.ndarray
    mean_error: float
    merge_latency: object
    mot: object


def evaluate(records, *, merge_frame=None, merged_group=None, min_share=0.9, max_dist=1000.0, mot=True):
    """All the figures of a tracked sequence (``records``: one :class:`FrameRecord` per frame)."""
    records = list(records)
    if not all(isinstance(r, FrameRecord) for r in records):
        bad = next(type(r).__name__ for r in records if not isinstance(r, FrameRecord))
        raise TypeError(f"records: expected FrameRecord items, got {bad}")
    pur = np.array([purity(r.labels, r.person_ids, r.person_group) for r in records])
    matches = [match(r.labels, r.person_ids, r.person_group) for r in records]
    sw = id_switches(matches)
    ids = np.unique(np.concatenate([r.true_ids for r in records] + [np.zeros(0, np.int64)]))
    col = {int(g): j for j, g in enumerate(ids)}
    err = np.full((len(records), len(ids)), np.nan)
    for k, (r, m) in enumerate(zip(records, matches)):
        tpos = {int(g): i for i, g in enumerate(r.true_ids)}
        rpos = {int(h): i for i, h in enumerate(r.reported_ids)}
        for g, h in m.items():
            if g in tpos and h in rpos and g in col:
                err[k, col[g]] = np.linalg.norm(r.reported_means[rpos[h]] - r.true_means[tpos[g]])
    lat = None
    if merge_frame is not None:
        if merged_group is None:
            raise ValueError("merged_group: expected the merged true group's id with merge_frame, got None")
        lat = merge_latency(records, merge_frame, merged_group, min_share)
    finite = pur[np.isfinite(pur)]
    errs = err[np.isfinite(err)]
    return GroupMetrics(
        purity=pur,
        mean_purity=float(finite.mean()) if len(finite) else float("nan"),
        matches=matches,
        switches=sw,
        total_switches=int(sum(sw.values())),
        true_ids=ids,
        error=err,
        mean_error=float(errs.mean()) if len(errs) else float("nan"),
        merge_latency=lat,
        mot=clear_mot(records, max_dist) if mot else None,
    )

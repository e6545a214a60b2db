"""The associator role: one detection per track at most, chosen from the gated pairs (host).

:class:`GNNAssociator` is global nearest neighbour: among the gated pairs it picks a one-to-one
matching that minimises

    sum over matched pairs of cost  +  miss_cost x (number of gated tracks left unmatched)

(``miss_cost`` defaults to the gate's threshold, so that any gated pair is cheaper than a miss).
This is Stone Soup's ``GNNWith2DAssignment`` over a ``DistanceHypothesiser`` whose
``missed_distance`` is ``miss_cost``, gated by a ``DistanceGater``: each track's row of the 2-D
assignment matrix holds its gated detections and its own "missed" column.

It never solves one dense T x D problem. The gated pairs form a sparse bipartite graph; its
connected components (``scipy.sparse.csgraph.connected_components``) are independent problems:

- a component with one track or one detection (a 1-to-1 pair, a track with several candidate
  detections, a detection claimed by several tracks) is solved by its cheapest pair, for all
  such components at once (vectorised: one lexsort);
- every other component is solved by ``scipy.optimize.linear_sum_assignment`` on its own
  r x (c + r) matrix (its c detections and r "missed" columns), one call per component.

Everything runs on the host (the gated pairs are small); no greedy or device path is used.
Ties between equal costs go to the lower slot, then the lower detection (in the vectorised
case) or as SciPy resolves them.
"""

from __future__ import annotations

import abc
import dataclasses

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from .gater import Gated

__all__ = ["Assignment", "Associator", "GNNAssociator"]


@dataclasses.dataclass(frozen=True)
class Assignment:
    """The association of one frame: ``track_det`` (C,) int64, the detection each slot takes
    (-1: none); ``det_track`` (D,) int64, the slot each detection goes to (-1: none)."""

    track_det: np.ndarray
    det_track: np.ndarray

    @property
    def pairs(self) -> tuple:
        """(slots, detections) of the matched pairs, ascending slot."""
        slots = np.flatnonzero(self.track_det >= 0)
        return slots, self.track_det[slots]

    @classmethod
    def from_pairs(cls, slots, dets, n_slots: int, n_detections: int) -> "Assignment":
        track_det = np.full(n_slots, -1, np.int64)
        det_track = np.full(n_detections, -1, np.int64)
        track_det[slots] = dets
        det_track[dets] = slots
        return cls(track_det, det_track)


class Associator(abc.ABC):
    """Chooses at most one detection per track (and one track per detection) from gated pairs."""

    @abc.abstractmethod
    def associate(self, gated: Gated) -> Assignment:
        """The assignment of one frame from its gated pairs."""


class GNNAssociator(Associator):
    """Global nearest neighbour by 2-D assignment on the connected components (see the module)."""

    def __init__(self, miss_cost: float | None = None):
        if miss_cost is not None and not np.isfinite(float(miss_cost)):
            raise ValueError(f"miss_cost: expected a finite number or None (the gate's threshold), got {miss_cost!r}")
        self.miss_cost = None if miss_cost is None else float(miss_cost)
        self.last_components = (0, 0)  # (solved by the vectorised path, solved by linear_sum_assignment)

    def associate(self, gated: Gated) -> Assignment:
        C, D = gated.n_slots, gated.n_detections
        miss = gated.threshold if self.miss_cost is None else self.miss_cost
        worth = gated.cost < miss  # a pair costing at least a miss is never better than the miss
        rows, cols, cost = gated.rows[worth], gated.cols[worth], gated.cost[worth]
        self.last_components = (0, 0)
        if rows.size == 0:
            return Assignment.from_pairs([], [], C, D)
        tracks, ri = np.unique(rows, return_inverse=True)  # graph nodes: tracks 0..nr-1, detections nr..
        dets, ci = np.unique(cols, return_inverse=True)
        nr, nc = len(tracks), len(dets)
        # A component has one track iff each detection of that track has no other track, and one
        # detection iff each track of that detection has no other detection: found from the
        # degrees, without a graph search.
        deg_t, deg_d = np.bincount(ri, minlength=nr), np.bincount(ci, minlength=nc)
        solo_t = np.zeros(nr, bool)  # track whose detections are all its own
        solo_t[ri] = True
        solo_t[ri[deg_d[ci] > 1]] = False
        solo_d = np.zeros(nc, bool)  # detection whose tracks are all its own
        solo_d[ci] = True
        solo_d[ci[deg_t[ri] > 1]] = False
        one_track, one_det = solo_t[ri], solo_d[ci]
        star = one_track | one_det
        # those components: the cheapest pair of each, all at once
        e = np.flatnonzero(star)
        key = np.where(one_track[e], ri[e], nr + ci[e])  # the component's single track or detection
        e = e[np.lexsort((cols[e], rows[e], cost[e], key))]
        key = np.where(one_track[e], ri[e], nr + ci[e])
        first = e[np.r_[True, key[1:] != key[:-1]]] if e.size else e
        slots, chosen = [rows[first]], [cols[first]]
        general = self._general(np.flatnonzero(~star), rows, cols, cost, miss, slots, chosen)
        self.last_components = (len(first), general)
        return Assignment.from_pairs(np.concatenate(slots), np.concatenate(chosen), C, D)

    @staticmethod
    def _general(g, rows, cols, cost, miss, slots, chosen) -> int:
        """Components with several tracks and several detections (edges g): their connected
        components, then one linear_sum_assignment per component on r x (c + r); components of
        one shape are laid out together. Appends the matched pairs; returns the component count."""
        if g.size == 0:
            return 0
        tracks, ri = np.unique(rows[g], return_inverse=True)
        dets, ci = np.unique(cols[g], return_inverse=True)
        nr, nc = len(tracks), len(dets)
        order = np.argsort(ri, kind="stable")  # edges track -> detection, as CSR rows of the track nodes
        indptr = np.zeros(nr + nc + 1, np.int32)
        indptr[1 : nr + 1] = np.cumsum(np.bincount(ri, minlength=nr))
        indptr[nr + 1 :] = indptr[nr]
        graph = csr_matrix((np.ones(g.size, np.int8), (nr + ci[order]).astype(np.int32), indptr),
                           shape=(nr + nc, nr + nc))  # fmt: skip
        ncomp, label = connected_components(graph, directed=True, connection="weak")
        tnodes = np.argsort(label[:nr], kind="stable")  # track nodes grouped by component
        dnodes = np.argsort(label[nr:], kind="stable")
        tcount = np.bincount(label[:nr], minlength=ncomp)
        dcount = np.bincount(label[nr:], minlength=ncomp)
        tstart = np.r_[0, np.cumsum(tcount)]
        dstart = np.r_[0, np.cumsum(dcount)]
        tlocal = np.empty(nr, np.int64)
        tlocal[tnodes] = np.arange(nr) - tstart[label[:nr][tnodes]]
        dlocal = np.empty(nc, np.int64)
        dlocal[dnodes] = np.arange(nc) - dstart[label[nr:][dnodes]]
        comp = label[ri]
        shape_key = tcount * (nc + 1) + dcount  # components of one (r, c) are solved from one array
        for key in np.unique(shape_key):
            comps = np.flatnonzero(shape_key == key)
            r, c = int(tcount[comps[0]]), int(dcount[comps[0]])
            where = np.full(ncomp, -1, np.int64)
            where[comps] = np.arange(len(comps))
            edges = np.flatnonzero(where[comp] >= 0)
            M = np.full((len(comps), r, c + r), np.inf)
            M[where[comp[edges]], tlocal[ri[edges]], dlocal[ci[edges]]] = cost[g[edges]]
            M[:, np.arange(r), c + np.arange(r)] = miss  # the "missed" column of each track
            for j, k in enumerate(comps):
                a, b = linear_sum_assignment(M[j])
                hit = b < c
                slots.append(tracks[tnodes[tstart[k] + a[hit]]])
                chosen.append(dets[dnodes[dstart[k] + b[hit]]])
        return int(ncomp)

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
Ties between equal costs go to the pair the gater lists first (in the vectorised case) or as
SciPy resolves them.
"""

from __future__ import annotations

import abc
import dataclasses

import numpy as np

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
        # A component has one track iff each detection of that track has no other track, and one
        # detection iff each track of that detection has no other detection: found from the
        # degrees, without a graph search.
        deg_t, deg_d = np.bincount(rows, minlength=C), np.bincount(cols, minlength=D)
        shared_t = np.zeros(C, bool)  # track with a detection that another track also gates
        shared_t[rows[deg_d[cols] > 1]] = True
        shared_d = np.zeros(D, bool)  # detection that a track with other detections also gates
        shared_d[cols[deg_t[rows] > 1]] = True
        one_track, one_det = ~shared_t[rows], ~shared_d[cols]
        star = one_track | one_det
        # those components: the cheapest pair of each, all at once (a lone pair is its own)
        e = np.flatnonzero(star)
        key = np.where(one_track[e], rows[e], C + cols[e])  # the component's single track or detection
        lone = np.bincount(key, minlength=C + D)[key] == 1
        many = e[~lone]
        many = many[np.argsort(cost[many], kind="stable")]
        kmany = np.where(one_track[many], rows[many], C + cols[many])
        many = many[np.argsort(kmany, kind="stable")]
        kmany = np.sort(kmany, kind="stable")
        first = np.concatenate([e[lone], many[np.r_[True, kmany[1:] != kmany[:-1]]] if many.size else many])
        slots, chosen = [rows[first]], [cols[first]]
        general = self._general(np.flatnonzero(~star), rows, cols, cost, miss, slots, chosen)
        self.last_components = (len(first), general)
        return Assignment.from_pairs(np.concatenate(slots), np.concatenate(chosen), C, D)

    @staticmethod
    def _general(g, rows, cols, cost, miss, slots, chosen) -> int:
        """Components with several tracks and several detections (edges g): their connected
        components, then one linear_sum_assignment per component on r x (c + r); the components
        of one shape (r, c) are laid out in one (G, r, c + r) array and their results gathered
        at once. Appends the matched pairs; returns the component count."""
        if g.size == 0:
            return 0
        # imported here, on the first frame that needs them: at module level they cost ~0.5 s of
        # every `import gputrack`
        from scipy.optimize import linear_sum_assignment
        from scipy.sparse import csr_matrix
        from scipy.sparse.csgraph import connected_components

        tracks, ri = _compact(rows[g])
        dets, ci = _compact(cols[g])
        nr, nc = len(tracks), len(dets)
        # the bipartite graph with each edge in both directions, as a CSR matrix built directly:
        # its strongly connected components are the connected components (and SciPy finds them
        # without the transposed copy it makes for weak or undirected ones)
        N = nr + nc
        u = np.concatenate([ri, nr + ci])
        v = np.concatenate([nr + ci, ri])
        order = np.argsort(u, kind="stable")
        indptr = np.zeros(N + 1, np.int32)
        np.cumsum(np.bincount(u, minlength=N), out=indptr[1:])
        graph = csr_matrix((np.ones(2 * g.size), v[order].astype(np.int32), indptr), shape=(N, N))
        ncomp, label = connected_components(graph, directed=True, connection="strong")
        tnodes = np.argsort(label[:nr], kind="stable")  # track nodes grouped by component
        dnodes = np.argsort(label[nr:], kind="stable")
        tcount = np.bincount(label[:nr], minlength=ncomp)
        dcount = np.bincount(label[nr:], minlength=ncomp)
        tstart = np.cumsum(tcount) - tcount
        dstart = np.cumsum(dcount) - dcount
        tlocal = np.empty(nr, np.int64)
        tlocal[tnodes] = np.arange(nr) - tstart[label[:nr][tnodes]]
        dlocal = np.empty(nc, np.int64)
        dlocal[dnodes] = np.arange(nc) - dstart[label[nr:][dnodes]]
        comp = label[ri]
        shape_key = tcount * (nc + 1) + dcount
        corder = np.argsort(shape_key, kind="stable")  # components grouped by shape (r, c)
        cpos = np.empty(ncomp, np.int64)  # position of a component within its group
        keys, gstart = np.unique(shape_key[corder], return_index=True)
        gsize = np.diff(np.r_[gstart, ncomp])
        cpos[corder] = np.arange(ncomp) - np.repeat(gstart, gsize)
        eorder = np.argsort(shape_key[comp], kind="stable")  # edges grouped likewise
        ebounds = np.searchsorted(shape_key[comp][eorder], keys)
        ebounds = np.r_[ebounds, len(eorder)]
        for j, key in enumerate(keys):
            comps = corder[gstart[j] : gstart[j] + gsize[j]]
            r, c = int(tcount[comps[0]]), int(dcount[comps[0]])
            edges = eorder[ebounds[j] : ebounds[j + 1]]
            M = np.full((len(comps), r, c + r), np.inf)
            M[cpos[comp[edges]], tlocal[ri[edges]], dlocal[ci[edges]]] = cost[g[edges]]
            M[:, np.arange(r), c + np.arange(r)] = miss  # the "missed" column of each track
            b = np.array([linear_sum_assignment(m)[1] for m in M])  # (G, r): rows come back in order
            hit = b < c
            slots.append(tracks[tnodes[(tstart[comps][:, None] + np.arange(r))[hit]]])
            chosen.append(dets[dnodes[(dstart[comps][:, None] + b)[hit]]])
        return int(ncomp)


def _compact(v: np.ndarray):
    """(the distinct values of v ascending, v's index into them): np.unique(return_inverse=True)
    for small non-negative integers, without its sort."""
    present = np.zeros(int(v.max()) + 1, bool)
    present[v] = True
    return np.flatnonzero(present), (np.cumsum(present) - 1)[v]

"""The gater role: which (track, detection) pairs may be associated, and at what cost.

A gater returns a :class:`Gated`: the sparse gated cost graph of one frame on the host, edges
``rows`` (slots) x ``cols`` (detections) with their ``cost``. Two gaters:

- :class:`MahalanobisGater`: squared Mahalanobis distances of every track to every detection on
  the device (paper 001 eq. 8) with :func:`gputrack.ops.gating.gate_pairs`, gated by a
  chi-square quantile; only the gated pairs come back to the host.
- :class:`CostGater`: a cost matrix of the caller's choice (a function of the table and the
  detections), gated by a threshold.
"""

from __future__ import annotations

import abc
import dataclasses

import numpy as np

from ..device import DeviceArray
from ..ops.gating import gate_pairs
from ._checks import observation_model
from ._staging import Staging
from .table import TrackStatus, TrackTable

__all__ = ["CostGater", "Gated", "Gater", "MahalanobisGater"]


@dataclasses.dataclass(frozen=True)
class Gated:
    """The gated pairs of one frame (host arrays), E edges.

    - ``rows`` (E,) int64: slots of the table; ``cols`` (E,) int64: detection indices;
    - ``cost`` (E,) float64: the pair's cost (smaller is better), below ``threshold``;
    - ``trace`` (C,) or None: trace(H P H^T) of each slot's predicted covariance (its position
      variance in measurement space), where the gater computes it (read by
      :class:`gputrack.tracking.CovarianceDeleter`);
    - ``n_slots`` C, ``n_detections`` D, ``threshold``: the gate.
    """

    rows: np.ndarray
    cols: np.ndarray
    cost: np.ndarray
    trace: np.ndarray | None
    n_slots: int
    n_detections: int
    threshold: float


class Gater(abc.ABC):
    """Gates the tracks of a table against the detections of a frame, in two halves that map
    onto the tracker's stages: :meth:`launch` (device work, no wait) returns the device buffers
    named in :attr:`buffers`; :meth:`collect` turns those buffers, downloaded, into a
    :class:`Gated` on the host. :meth:`gate` runs both."""

    #: names of the device buffers :meth:`launch` returns (declared by the tracker's gate stage)
    buffers: tuple = ()

    @abc.abstractmethod
    def launch(self, table: TrackTable, z: np.ndarray) -> dict:
        """Start gating z (D,m) host detections (finite); returns {name: device array}."""

    @abc.abstractmethod
    def collect(self, table: TrackTable, z: np.ndarray, host: dict) -> Gated:
        """The gated pairs (only occupied slots) from launch's buffers downloaded to the host."""

    def gate(self, table: TrackTable, z: np.ndarray) -> Gated:
        """:meth:`launch` then :meth:`collect` (downloading the buffers)."""
        return self.collect(table, z, {k: _host(v) for k, v in self.launch(table, z).items()})


def _host(a) -> np.ndarray:
    return a.numpy() if isinstance(a, DeviceArray) else np.asarray(a)


class MahalanobisGater(Gater):
    """Mahalanobis gating on the device: pair (t, d) is gated when
    d2 = (z_d - H x_t)^T S_t^-1 (z_d - H x_t) < threshold, S_t = H P_t H^T + R (paper 001 eq. 8).

    H (m,n), R (m,m) host matrices. ``threshold`` defaults to the chi-square quantile of
    ``probability`` with m degrees of freedom (a true detection falls inside its track's gate
    with that probability).

    :meth:`launch`: one launch per frame. The detections are sorted by their first coordinate
    on the host (so that the kernel sweeps only a strip per track, exact; see
    :mod:`gputrack.ops.gating`) and uploaded into a reused buffer; the buffers are, per slot,
    the count of gated detections, the first ``max_pairs`` of them and their distances
    (``gate_count`` (C,), ``gate_det`` and ``gate_d2`` (C, max_pairs)), and with ``trace=True``
    trace(H P H^T) (``gate_trace`` (C,), for :class:`gputrack.tracking.CovarianceDeleter`;
    otherwise :class:`Gated` ``trace`` is None). :meth:`collect`: the pairs, with detection
    indices in the caller's order. A frame in which some track gates more than ``max_pairs``
    detections is gated again by :meth:`collect` (a second launch and download in that frame
    only) with ``max_pairs`` raised to the next power of two above the largest count (kept for
    later frames), so no pair is lost.
    """

    def __init__(self, H, R, *, threshold: float | None = None, probability: float = 0.999, max_pairs: int = 4,
                 trace: bool = False):  # fmt: skip
        H, R = observation_model(H, R)
        if threshold is None:
            if not 0.0 < probability < 1.0:
                raise ValueError(f"probability: expected a value in (0, 1), got {probability!r}")
            from scipy.stats import chi2  # here, not at import: scipy.stats costs ~0.5 s to import

            threshold = float(chi2.ppf(probability, H.shape[0]))
        threshold = float(threshold)
        if not (np.isfinite(threshold) and threshold > 0):
            raise ValueError(f"threshold: expected a positive finite number, got {threshold!r}")
        if isinstance(max_pairs, bool) or not isinstance(max_pairs, (int, np.integer)) or max_pairs < 1:
            raise ValueError(f"max_pairs: expected a positive integer, got {max_pairs!r}")
        self.H, self.R, self.threshold, self.max_pairs = H, R, threshold, int(max_pairs)
        self.trace = bool(trace)
        self._staging: dict = {}
        self._outs: dict = {}
        self._matrices: dict = {}  # (device, dtype) -> H, R uploaded once

    @property
    def m(self) -> int:
        return self.H.shape[0]

    def _outputs(self, table, K):
        """The gate's output arrays, reused while the capacity and K stay the same."""
        dev, C = table.device, table.capacity
        key = (dev, table.dtype)
        found = self._outs.get(key)
        if found is None or found[1].shape != (C, K):
            found = self._outs[key] = (dev.empty((C,), np.int32), dev.empty((C, K), np.int32),
                                       dev.empty((C, K), table.dtype), dev.empty((C,), table.dtype))  # fmt: skip
        return found

    @property
    def buffers(self) -> tuple:
        return ("gate_count", "gate_det", "gate_d2") + (("gate_trace",) if self.trace else ())

    def launch(self, table: TrackTable, z: np.ndarray) -> dict:
        if table.n != self.H.shape[1]:
            raise ValueError(f"table: expected state size n={self.H.shape[1]} (H's columns), got n={table.n}")
        g = self._launch(table, z, self.max_pairs)
        names = self.buffers
        return dict(zip(names, (g.count, g.det, g.d2, g.trace)[: len(names)]))

    def _launch(self, table, z, K):
        dev = table.device
        st = self._staging.get(dev)
        if st is None:
            st = self._staging[dev] = Staging(dev)
        D = len(z)
        self._order = order = np.argsort(z[:, 0], kind="stable")
        zd, _ = st.put_rows("z", z[order].astype(table.dtype, copy=False))
        self._zd = zd
        HR = self._matrices.get((dev, table.dtype))
        if HR is None:
            HR = self._matrices[(dev, table.dtype)] = (dev.asarray(self.H.astype(table.dtype)),
                                                        dev.asarray(self.R.astype(table.dtype)))  # fmt: skip
        H, R = HR
        return gate_pairs(dev, table.x, table.P, H, R, zd, self.threshold, active=table.sync_active(), sorted_z=True,
                          n_z=D, out=self._outputs(table, K))  # fmt: skip

    def collect(self, table: TrackTable, z: np.ndarray, host: dict) -> Gated:
        count, det, d2 = host["gate_count"], host["gate_det"], host["gate_d2"]
        trace = host["gate_trace"] if self.trace else None
        D = len(z)
        most = int(count.max(initial=0))
        if most > det.shape[1]:  # some track gates more than K detections: gate again with room for all
            self.max_pairs = 1 << (most - 1).bit_length()
            g = self._launch(table, z, self.max_pairs)
            count, det, d2 = _host(g.count), _host(g.det), _host(g.d2)
        order = self._order
        rows = np.flatnonzero(count)  # slot of each pair, and its column k < count
        n = count[rows]
        rows = np.repeat(rows, n)
        k = np.arange(len(rows)) - np.repeat(np.cumsum(n) - n, n)
        return Gated(rows.astype(np.int64), order[det[rows, k]].astype(np.int64), d2[rows, k].astype(np.float64),
                     trace, table.capacity, D, self.threshold)  # fmt: skip


class CostGater(Gater):
    """A cost matrix of the caller's choice: ``cost(table, z)`` (called by :meth:`launch`)
    returns a (C, D) array of pair costs, smaller is better: NumPy, or a DeviceArray of the
    table's device (the tracker's assign stage downloads it). A pair of an occupied slot is
    gated when its cost is finite and < ``threshold``. Reports no ``trace`` (a covariance
    deleter needs :class:`MahalanobisGater`)."""

    def __init__(self, cost, threshold: float):
        if not callable(cost):
            raise TypeError(f"cost: expected a function (table, z) -> (C, D) array, got {type(cost).__name__}")
        threshold = float(threshold)
        if not np.isfinite(threshold):
            raise ValueError(f"threshold: expected a finite number, got {threshold!r}")
        self.cost, self.threshold = cost, threshold

    buffers = ("cost",)

    def launch(self, table: TrackTable, z: np.ndarray) -> dict:
        return {"cost": self.cost(table, z)}

    def collect(self, table: TrackTable, z: np.ndarray, host: dict) -> Gated:
        C, D = table.capacity, len(z)
        c = np.asarray(host["cost"])
        if c.shape != (C, D):
            raise ValueError(f"cost: expected a (C={C}, D={D}) matrix (slots x detections), got shape {c.shape}")
        if c.dtype.kind not in "iuf":
            raise TypeError(f"cost: expected a real matrix, got dtype {c.dtype.name}")
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(c) & (c < self.threshold) & (table.status != TrackStatus.FREE)[:, None]
        rows, cols = np.nonzero(ok)
        return Gated(rows.astype(np.int64), cols.astype(np.int64), c[rows, cols].astype(np.float64), None, C, D,
                     self.threshold)  # fmt: skip

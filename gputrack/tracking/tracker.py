"""A multi-target tracker as a short composition of the roles, all tracks in one TrackTable.

One frame (:meth:`MultiTargetTracker.step`) is five stages of a :class:`gputrack.scheduler.Scheduler`,
each a role call that works on all tracks at once:

===========  =====================================================  ====================  ======
stage        what                                                   buffers               where
===========  =====================================================  ====================  ======
predict      every slot, one launch (Predictor)                     x, P -> x, P          device
gate         tracks x detections, one launch (Gater.launch); the    x, P, active ->       device
             detections are uploaded sorted                         the gater's buffers
assign       the gated pairs (Gater.collect) and one detection per  host read of the      host
             track (Associator)                                     gater's buffers
update       every assigned slot, one launch (Updater)              x, P -> x, P          device
start/end    lifecycle bookkeeping on the host mirror, M-of-N       -> x, P, active       host,
             confirmation, deletions (Deleter), new tracks written                        one
             into free slots (Initiator)                                                  scatter
                                                                                          per array
===========  =====================================================  ====================  ======

Only the assign stage waits for the device (its host read). As in Stone Soup's
``MultiTargetTracker`` (associate, update, delete, initiate), but no Python object per track:
states stay on the device; the host holds the lifecycle mirror of the table (ids, status, hits,
misses, age), computed from the assignment it already has. The detections are host data (the
stages sort, gather and initiate from them); the stage that needs them on the device uploads
them (gate: sorted, into a reused buffer; update: one row per slot). ``tracker.scheduler``
reports each stage's time and bytes (``profile=True`` times the device work of each stage).

Per steady-state frame the host uploads the sorted detections (D m values, padded), the
occupied-slot flags when they changed (C bytes), one detection row per slot (C m) and the new
tracks (index, x0), and downloads the gate's pairs (C (1 + 2 K) values). States come to the
host only through :meth:`MultiTargetTracker.tracks`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..device import Device, DeviceArray
from ..scheduler import Scheduler, Stage
from .associator import Associator, GNNAssociator
from .deleter import AnyDeleter, CovarianceDeleter, Deleter, MissDeleter
from .gater import Gater, MahalanobisGater
from .initiator import Initiator, MofNInitiator
from .predictor import KalmanPredictor, Predictor
from .table import TrackStatus, TrackTable, Tracks
from .updater import KalmanUpdater, Updater

__all__ = ["MultiTargetTracker", "TrackingFrame"]


@dataclasses.dataclass(frozen=True)
class TrackingFrame:
    """What one :meth:`MultiTargetTracker.step` did (host arrays).

    - ``det_ids`` (D,) int64: the id of the track each detection updated or started (-1: none,
      i.e. a birth dropped because the table was full); a track may have ended in the same frame;
    - ``started``, ``confirmed``, ``deleted`` (k,) int64: ids started, confirmed, ended;
    - ``dropped``: detections that could not start a track (table at ``max_capacity``).
    """

    det_ids: np.ndarray
    started: np.ndarray
    confirmed: np.ndarray
    deleted: np.ndarray
    dropped: int


class MultiTargetTracker:
    """Predictor, gater, associator, updater, initiator and deleter composed over one TrackTable.

    Every role is replaceable (any object of the role's base class). ``table``: the TrackTable
    to use (default: a new one for the predictor's state size with ``capacity``,
    ``max_capacity`` and ``dtype``). :meth:`constant_velocity` builds the usual configuration.
    """

    def __init__(self, device: Device, *, predictor: Predictor, gater: Gater, associator: Associator,
                 updater: Updater, initiator: Initiator, deleter: Deleter, m: int, table: TrackTable | None = None,
                 capacity: int = 1024, max_capacity: int = 1 << 20, dtype=np.float32,
                 profile: bool = False):  # fmt: skip
        for name, role, base in (("predictor", predictor, Predictor), ("gater", gater, Gater),
                                 ("associator", associator, Associator), ("updater", updater, Updater),
                                 ("initiator", initiator, Initiator), ("deleter", deleter, Deleter)):  # fmt: skip
            if not isinstance(role, base):
                raise TypeError(f"{name}: expected a gputrack.tracking.{base.__name__}, got {type(role).__name__}")
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 1:
            raise ValueError(f"m: expected the detection size, a positive integer, got {m!r}")
        if table is None:
            n = getattr(predictor, "n", None)
            if n is None:
                raise ValueError("table: expected a TrackTable when the predictor does not say its state size (n)")
            table = TrackTable(device, n, capacity=capacity, max_capacity=max_capacity, dtype=dtype)
        elif table.device is not device:
            raise ValueError(f"table: expected a TrackTable on {device.spec}, got one on {table.device.spec}")
        self.device, self.table, self.m = device, table, int(m)
        self.predictor, self.gater, self.associator = predictor, gater, associator
        self.updater, self.initiator, self.deleter = updater, initiator, deleter
        gate = tuple(gater.buffers)
        self.scheduler = Scheduler(device, [
            Stage("predict", self._predict, reads=("x", "P"), writes=("x", "P")),
            Stage("gate", self._gate, reads=("x", "P", "active"), writes=gate),
            Stage("assign", self._assign, host_reads=gate, writes=("gated", "assignment")),
            Stage("update", self._update, reads=("x", "P", "assignment"), writes=("x", "P")),
            Stage("start/end", self._start_end, reads=("gated", "assignment"), writes=("x", "P", "active")),
        ], state=("x", "P", "active"), profile=profile)  # fmt: skip
        self._bind(self.scheduler.buffers, "x", "P", "active")
        self._frame = None

    @classmethod
    def constant_velocity(cls, device: Device, *, dim: int = 2, dt: float = 1.0, q=1.0, R=1.0,
                          gate_probability: float = 0.999, m_of_n=(2, 3), max_misses: int = 3,
                          max_trace: float | None = None, velocity_var: float = 1.0,
                          **kw) -> "MultiTargetTracker":  # fmt: skip
        """Constant-velocity tracks (state [x xdot y ydot ...], ``dim`` axes, acceleration
        variance ``q``) from position detections with noise covariance ``R`` (a variance or a
        (dim, dim) matrix): Kalman predictor and updater, Mahalanobis gate at
        ``gate_probability``, GNN association, M-of-N start, deletion after more than
        ``max_misses`` misses (and, with ``max_trace``, on covariance growth). ``kw``:
        capacity, max_capacity, dtype, profile."""
        predictor = KalmanPredictor.constant_velocity(dim, dt, q)
        H = np.zeros((dim, 2 * dim))
        H[np.arange(dim), 2 * np.arange(dim)] = 1.0
        R = np.asarray(R, dtype=np.float64)
        R = R * np.eye(dim) if R.ndim == 0 else R
        deleter = MissDeleter(max_misses)
        if max_trace is not None:
            deleter = AnyDeleter(deleter, CovarianceDeleter(max_trace))
        gater = MahalanobisGater(H, R, probability=gate_probability, trace=max_trace is not None)
        return cls(device, predictor=predictor, gater=gater,
                   associator=GNNAssociator(), updater=KalmanUpdater(H, R),
                   initiator=MofNInitiator(H, R, m_of_n=m_of_n, velocity_var=velocity_var), deleter=deleter, m=dim,
                   **kw)  # fmt: skip

    # -- one frame -----------------------------------------------------------------------------
    def step(self, detections, *, gain_scale=None) -> TrackingFrame:
        """Track one frame of detections (D, m) (host, finite; D = 0 is a frame without any).
        ``gain_scale`` (D,) >= 0 scales each detection's Kalman gain (paper 002), or None."""
        self._frame = self._inputs(detections, gain_scale)  # (z, gain): host data the stages read
        try:
            self.scheduler.run()
            return self._result
        finally:
            self._frame = None

    def _bind(self, b, *names) -> None:
        """The table's arrays (new ones after a growth) as the scheduler's buffers."""
        for name in names:
            b[name] = getattr(self.table, name)

    def _predict(self, b) -> None:
        self.predictor.predict(self.table)
        self._bind(b, "x", "P")

    def _gate(self, b) -> None:
        for name, array in self.gater.launch(self.table, self._frame[0]).items():
            b[name] = array

    def _assign(self, b) -> None:
        gated = self.gater.collect(self.table, self._frame[0], {n: b[n] for n in self.gater.buffers})
        b["gated"] = gated
        b["assignment"] = self.associator.associate(gated)

    def _update(self, b) -> None:
        z, gain = self._frame
        self.updater.update(self.table, z, b["assignment"], gain)
        self._bind(b, "x", "P")

    def _start_end(self, b) -> None:
        z, assignment, table = self._frame[0], b["assignment"], self.table
        table.record(assignment.track_det >= 0)
        confirm, reject = self.initiator.review(table)
        confirmed = table.confirm(confirm)
        det_ids = np.where(assignment.det_track >= 0, table.ids[np.maximum(assignment.det_track, 0)], -1)
        ended = np.zeros(table.capacity, bool)
        ended[reject] = True
        ended[self.deleter.delete(table, assignment, b["gated"])] = True
        deleted = table.remove(np.flatnonzero(ended))
        _, started, dets, dropped = self.initiator.initiate(table, z, assignment)
        det_ids[dets] = started
        self._bind(b, "x", "P", "active")
        self._result = TrackingFrame(det_ids, started, confirmed, deleted, int(dropped))

    def _inputs(self, detections, gain_scale):
        if isinstance(detections, DeviceArray):
            raise TypeError("detections: expected host (NumPy) detections (D, m), got a DeviceArray")
        z = np.asarray(detections)
        if z.dtype.kind not in "iuf":
            raise TypeError(f"detections: expected real values, got dtype {z.dtype.name}")
        if z.size == 0 and z.ndim <= 2:
            z = z.reshape(0, self.m)
        if z.ndim != 2 or z.shape[1] != self.m:
            raise ValueError(f"detections: expected shape (D, m={self.m}), got {z.shape}")
        if not np.isfinite(z).all():
            bad = np.argwhere(~np.isfinite(z))[0]
            raise ValueError(f"detections: expected finite values, got {z[tuple(bad)]} at index "
                             f"{tuple(int(i) for i in bad)} (drop or fill such rows first)")  # fmt: skip
        z = z.astype(self.table.dtype, copy=False)
        if gain_scale is None:
            return z, None
        g = np.asarray(gain_scale, dtype=np.float64)
        if g.shape != (len(z),):
            raise ValueError(f"gain_scale: expected shape ({len(z)},) (one per detection), got {g.shape}")
        if not (np.isfinite(g).all() and (g >= 0).all()):
            raise ValueError("gain_scale: expected finite values >= 0")
        return z, g

    # -- reading -------------------------------------------------------------------------------
    def tracks(self, *, covariance: bool = False, confirmed_only: bool = False) -> Tracks:
        """The tracks, downloaded (see :meth:`TrackTable.tracks`)."""
        return self.table.tracks(covariance=covariance, status=TrackStatus.CONFIRMED if confirmed_only else None)

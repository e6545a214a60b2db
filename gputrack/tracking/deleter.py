"""The deleter role: which tracks end (host, from the lifecycle mirror and the gate's output).

- :class:`MissDeleter`: a confirmed track ends after more than ``max_misses`` consecutive frames
  without a detection (Stone Soup's ``UpdateTimeStepsDeleter``).
- :class:`CovarianceDeleter`: a confirmed track that was not detected this frame ends when the
  trace of its predicted position covariance, trace(H P H^T), exceeds ``max_trace`` (Stone
  Soup's ``CovarianceBasedDeleter`` with ``mapping`` = the measured components; a track that
  was not updated has its prediction as its posterior). The trace comes from the gate
  (:class:`gputrack.tracking.MahalanobisGater` reports it with the pairs), so no covariance is
  downloaded for this.
- :class:`AnyDeleter`: the union of several deleters.

Tentative tracks are confirmed or rejected by the initiator (M of N); deleters look at confirmed
tracks only.
"""

from __future__ import annotations

import abc

import numpy as np

from .associator import Assignment
from .gater import Gated
from .table import TrackStatus, TrackTable

__all__ = ["AnyDeleter", "CovarianceDeleter", "Deleter", "MissDeleter"]


class Deleter(abc.ABC):
    """Chooses the confirmed tracks that end after a frame."""

    @abc.abstractmethod
    def delete(self, table: TrackTable, assignment: Assignment, gated: Gated) -> np.ndarray:
        """Slots (ascending int64) to delete, after the frame's bookkeeping (table.record)."""


class MissDeleter(Deleter):
    """Delete a confirmed track after more than ``max_misses`` consecutive misses."""

    def __init__(self, max_misses: int = 3):
        if isinstance(max_misses, bool) or not isinstance(max_misses, (int, np.integer)) or max_misses < 0:
            raise ValueError(f"max_misses: expected an integer >= 0, got {max_misses!r}")
        self.max_misses = int(max_misses)

    def delete(self, table, assignment, gated) -> np.ndarray:
        return np.flatnonzero((table.status == TrackStatus.CONFIRMED) & (table.misses > self.max_misses))


class CovarianceDeleter(Deleter):
    """Delete an undetected confirmed track whose trace(H P H^T) exceeds ``max_trace``."""

    def __init__(self, max_trace: float):
        max_trace = float(max_trace)
        if not (np.isfinite(max_trace) and max_trace > 0):
            raise ValueError(f"max_trace: expected a positive finite number, got {max_trace!r}")
        self.max_trace = max_trace

    def delete(self, table, assignment, gated) -> np.ndarray:
        if gated.trace is None:
            raise ValueError("CovarianceDeleter: expected a gater that reports trace(H P H^T) "
                             "(MahalanobisGater(..., trace=True)), got gated pairs without it")  # fmt: skip
        with np.errstate(invalid="ignore"):
            grown = ~(gated.trace <= self.max_trace)  # NaN counts as grown
        return np.flatnonzero((table.status == TrackStatus.CONFIRMED) & (assignment.track_det < 0) & grown)


class AnyDeleter(Deleter):
    """Delete what any of ``deleters`` deletes."""

    def __init__(self, *deleters: Deleter):
        for d in deleters:
            if not isinstance(d, Deleter):
                raise TypeError(f"deleters: expected Deleter objects, got {type(d).__name__}")
        self.deleters = deleters

    def delete(self, table, assignment, gated) -> np.ndarray:
        found = [d.delete(table, assignment, gated) for d in self.deleters]
        return np.unique(np.concatenate(found)).astype(np.int64) if found else np.zeros(0, np.int64)

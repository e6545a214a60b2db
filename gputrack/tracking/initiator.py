"""The initiator role: tracks started from unassigned detections, and M-of-N confirmation.

:class:`MofNInitiator`:

- start: every detection not assigned to a track starts a TENTATIVE track (in detection order,
  so ids follow it), with the state of Stone Soup's ``SimpleMeasurementInitiator``: the prior
  state and covariance with the measured components replaced by H^+ z and H^+ R H^+T (H^+ the
  pseudo-inverse of H; for a position H, the position is the detection, the velocity the
  prior's);
- confirm: a tentative track with at least M hits within its first N frames (the detection that
  started it counts) becomes CONFIRMED;
- reject: a tentative track that can no longer reach M hits in N frames (hits + N - age < M) is
  returned for deletion.

Full table: the tracks that do not fit in the table's ``max_capacity`` are not started (the
unassigned detections with the lowest indices get the room); they are counted in
:attr:`MofNInitiator.dropped` and in the tracker's frame result, and logged once at WARNING.
Existing tracks are never dropped, and no id is used for a track that was not started.
"""

from __future__ import annotations

import abc
import logging

import numpy as np

from .associator import Assignment
from .table import TrackStatus, TrackTable

__all__ = ["Initiator", "MofNInitiator"]

log = logging.getLogger("gputrack")


class Initiator(abc.ABC):
    """Starts tracks from the detections no track took, and confirms or rejects tentative ones."""

    @abc.abstractmethod
    def review(self, table: TrackTable) -> tuple:
        """After a frame's bookkeeping: (slots to confirm, tentative slots to delete)."""

    @abc.abstractmethod
    def initiate(self, table: TrackTable, z: np.ndarray, assignment: Assignment) -> tuple:
        """Start tracks from the unassigned detections; returns (slots, ids, detections they came
        from, how many could not be started)."""


class MofNInitiator(Initiator):
    """M-of-N confirmation (see the module). H (m,n), R (m,m); ``prior_x`` (n,) and ``prior_P``
    (n,n) the prior of the unmeasured components (default zero velocity with variance
    ``velocity_var`` on every component that H does not measure)."""

    def __init__(self, H, R, *, m_of_n=(2, 3), prior_x=None, prior_P=None, velocity_var: float = 1.0):
        H = np.asarray(H, dtype=np.float64)
        R = np.asarray(R, dtype=np.float64)
        if H.ndim != 2 or R.shape != (H.shape[0], H.shape[0]):
            raise ValueError(f"H, R: expected (m, n) and (m, m) matrices, got {H.shape} and {R.shape}")
        M, N = m_of_n
        if not (isinstance(M, (int, np.integer)) and isinstance(N, (int, np.integer)) and 1 <= M <= N):
            raise ValueError(f"m_of_n: expected integers 1 <= M <= N, got {m_of_n!r}")
        n = H.shape[1]
        prior_x = np.zeros(n) if prior_x is None else np.asarray(prior_x, dtype=np.float64)
        prior_P = velocity_var * np.eye(n) if prior_P is None else np.asarray(prior_P, dtype=np.float64)
        if prior_x.shape != (n,) or prior_P.shape != (n, n):
            raise ValueError(f"prior_x, prior_P: expected shapes ({n},) and ({n}, {n}), got {prior_x.shape}, "
                             f"{prior_P.shape}")  # fmt: skip
        mapped = np.flatnonzero(np.abs(H).sum(axis=0) > 0)  # the measured state components
        self.pinv = np.linalg.pinv(H)
        self.x_base = prior_x.copy()
        self.x_base[mapped] = 0.0
        self.P_base = prior_P.copy()
        self.P_base[mapped, :] = 0.0
        self.P_base[:, mapped] = 0.0
        self.P_base += self.pinv @ R @ self.pinv.T  # the measured components' covariance
        self.M, self.N = int(M), int(N)
        self.dropped = 0  # detections that could not start a track (table full), since construction

    def start_state(self, z: np.ndarray):
        """x0 (k,n) of tracks started from detections z (k,m), and their covariance P0 (n,n),
        the same for all."""
        x0 = self.x_base[None, :] + z.astype(np.float64) @ self.pinv.T
        return x0, self.P_base

    def review(self, table: TrackTable) -> tuple:
        tentative = table.status == TrackStatus.TENTATIVE
        confirm = np.flatnonzero(tentative & (table.hits >= self.M))
        reject = np.flatnonzero(tentative & (table.hits < self.M) & (table.hits + self.N - table.age < self.M))
        return confirm, reject

    def initiate(self, table: TrackTable, z: np.ndarray, assignment: Assignment) -> tuple:
        free = np.flatnonzero(assignment.det_track < 0)
        room = table.room()
        dropped = max(len(free) - room, 0)
        if dropped:
            if self.dropped == 0:
                log.warning("track table full (max_capacity %d): %d new tracks not started; later drops are only "
                            "counted", table.max_capacity, dropped)  # fmt: skip
            self.dropped += dropped
            free = free[:room]
        x0, P0 = self.start_state(z[free])
        slots, ids = table.add(x0, P0, TrackStatus.TENTATIVE)
        return slots, ids, free, dropped

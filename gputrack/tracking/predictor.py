"""The predictor role: every slot of a track table predicted in one launch."""

from __future__ import annotations

import abc

import numpy as np

from ..ops.kalman import constant_velocity, kf_predict, shared_matrix
from .table import TrackTable

__all__ = ["KalmanPredictor", "Predictor"]


class Predictor(abc.ABC):
    """Moves every track of a table to the next frame, in place on the device."""

    @abc.abstractmethod
    def predict(self, table: TrackTable) -> None:
        """Predict x (C,n) and P (C,n,n) of ``table`` in place."""


class KalmanPredictor(Predictor):
    """x' = F x, P' = F P F^T + Q for all C slots in one :func:`gputrack.ops.kf_predict` launch
    (paper 001 eq. 2-3). F, Q (n,n) host matrices, uploaded once per device (with their zero
    pattern, so the kernels skip the zeros of a constant-velocity F and Q)."""

    def __init__(self, F, Q):
        F = np.asarray(F, dtype=np.float64)
        Q = np.asarray(Q, dtype=np.float64)
        if F.ndim != 2 or F.shape[0] != F.shape[1]:
            raise ValueError(f"F: expected a square (n, n) matrix, got shape {F.shape}")
        if Q.shape != F.shape:
            raise ValueError(f"Q: expected shape {F.shape} (F's), got {Q.shape}")
        for name, a in (("F", F), ("Q", Q)):
            if not np.isfinite(a).all():
                raise ValueError(f"{name}: expected finite values")
        self.F, self.Q = F, Q
        self._shared: dict = {}

    @classmethod
    def constant_velocity(cls, dim: int = 2, dt: float = 1.0, q=1.0) -> "KalmanPredictor":
        """The constant-velocity model of :func:`gputrack.ops.constant_velocity` (state order
        [x xdot y ydot ...], ``q`` the acceleration variance)."""
        F, Q = constant_velocity(dim, dt, q, dtype=np.float64)
        return cls(F, Q)

    @property
    def n(self) -> int:
        return self.F.shape[0]

    def _matrices(self, table):
        key = (table.device, table.dtype)
        found = self._shared.get(key)
        if found is None:
            found = self._shared[key] = (shared_matrix(table.device, self.F, table.dtype),
                                         shared_matrix(table.device, self.Q, table.dtype))  # fmt: skip
        return found

    def predict(self, table: TrackTable) -> None:
        if table.n != self.n:
            raise ValueError(f"table: expected state size n={self.n} (F's), got n={table.n}")
        F, Q = self._matrices(table)
        kf_predict(table.device, table.x, table.P, F, Q, out=(table.x, table.P))

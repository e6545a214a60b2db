"""The updater role: every slot that took a detection updated in one launch.

The detections are gathered per slot on the host (the assignment is there) into a (C, m) array
and uploaded; a slot without a detection gets a row of NaN, which :func:`gputrack.ops.kf_update`
treats as a missing observation (the track keeps its prediction, status SKIPPED). That row of
NaN is the update's mask: one upload instead of two. ``gain_scale`` (per detection, >= 0;
paper 002 eq. 4-6: trust occluded, shrunken segments less) is mapped to the slots the same way.
"""

from __future__ import annotations

import abc

import numpy as np

from ..ops.kalman import ekf_update_stereo, kf_update, shared_matrix
from ._checks import observation_model
from ._staging import Staging
from .associator import Assignment
from .table import TrackTable

__all__ = ["KalmanUpdater", "StereoUpdater", "Updater"]


class Updater(abc.ABC):
    """Updates the tracks of a table with their assigned detections, in place on the device."""

    @abc.abstractmethod
    def update(self, table: TrackTable, z: np.ndarray, assignment: Assignment, gain_scale=None) -> None:
        """z (D,m) host detections; ``assignment.track_det`` (C,) names each slot's detection
        (-1: none); gain_scale (D,) or None."""


class _SlotRows(Updater):
    """Shared part: per-slot observation rows (NaN = none) and gain, uploaded into reused arrays."""

    def __init__(self):
        self._staging: dict = {}
        self._status: dict = {}

    def _inputs(self, table, z, assignment, gain_scale):
        dev = table.device
        st = self._staging.get(dev)
        if st is None:
            st = self._staging[dev] = Staging(dev)
        C = table.capacity
        if assignment.track_det.shape != (C,):
            raise ValueError(f"assignment: expected track_det of shape ({C},) (the table's slots), got "
                             f"{assignment.track_det.shape}")  # fmt: skip
        slots = np.flatnonzero(assignment.track_det >= 0)
        rows = np.full((C, z.shape[1]), np.nan, table.dtype)  # NaN row: no detection (kf_update: SKIPPED)
        rows[slots] = z[assignment.track_det[slots]]
        gain = None
        if gain_scale is not None:
            g = np.ones(C, table.dtype)
            g[slots] = gain_scale[assignment.track_det[slots]]
            gain = st.put("gain", g)
        status = self._status.get(dev)
        if status is None or status.shape != (C,):
            status = self._status[dev] = dev.empty((C,), np.uint8)
        return st, st.put("z", rows), gain, status


class KalmanUpdater(_SlotRows):
    """Linear Kalman update (:func:`gputrack.ops.kf_update`, Joseph form): H (m,n), R (m,m)."""

    def __init__(self, H, R):
        super().__init__()
        H, R = observation_model(H, R)
        self.H, self.R = H, R
        self._shared: dict = {}

    def update(self, table, z, assignment, gain_scale=None) -> None:
        st, zd, gain, status = self._inputs(table, z, assignment, gain_scale)
        key = (table.device, table.dtype)
        shared = self._shared.get(key)
        if shared is None:
            shared = self._shared[key] = (shared_matrix(table.device, self.H, table.dtype),
                                          shared_matrix(table.device, self.R, table.dtype))  # fmt: skip
        kf_update(table.device, table.x, table.P, zd, *shared, gain_scale=gain, out=(table.x, table.P, status))


class StereoUpdater(_SlotRows):
    """Stereo EKF update (:func:`gputrack.ops.ekf_update_stereo`, paper 001 eq. 4-6): state
    [x xdot y ydot z zdot], detections [u v d] (pixels, disparity), R (3,3), focal length ``f``
    (pixels), baseline ``b``, principal point (cx, cy). Gate such detections with a gater of the
    caller's choice (e.g. :class:`gputrack.tracking.CostGater`, or Mahalanobis gating of
    triangulated positions): :class:`gputrack.tracking.MahalanobisGater` is linear."""

    def __init__(self, R, *, f: float, b: float, cx: float = 0.0, cy: float = 0.0):
        super().__init__()
        R = np.asarray(R, dtype=np.float64)
        if R.shape != (3, 3):
            raise ValueError(f"R: expected shape (3, 3), got {R.shape}")
        self.R, self.f, self.b, self.cx, self.cy = R, float(f), float(b), float(cx), float(cy)
        self._shared: dict = {}

    def update(self, table, z, assignment, gain_scale=None) -> None:
        st, zd, gain, status = self._inputs(table, z, assignment, gain_scale)
        key = (table.device, table.dtype)
        R = self._shared.get(key)
        if R is None:
            R = self._shared[key] = shared_matrix(table.device, self.R, table.dtype)
        ekf_update_stereo(table.device, table.x, table.P, zd, R, f=self.f, b=self.b, cx=self.cx, cy=self.cy,
                          gain_scale=gain, out=(table.x, table.P, status))  # fmt: skip

"""Multi-target tracking from batched roles: all tracks of a tracker in one device-resident table.

    import gputrack
    from gputrack.tracking import MultiTargetTracker

    dev = gputrack.device("taichi:cpu")
    tracker = MultiTargetTracker.constant_velocity(dev, dim=2, dt=1 / 30, q=1.0, R=0.01)
    for z in frames:                       # z (D, 2) detections of one frame (NumPy)
        frame = tracker.step(z)            # frame.det_ids, .started, .confirmed, .deleted
    tracks = tracker.tracks()              # ids, status, x (downloaded), hits, misses, age

The roles (Stone Soup's, on a :class:`TrackTable` instead of one object per track), each a base
class and a default implementation:

- :class:`Predictor` / :class:`KalmanPredictor`: every slot predicted in one launch;
- :class:`Gater` / :class:`MahalanobisGater` (device gating, only gated pairs come back) or
  :class:`CostGater` (a cost matrix of the caller's choice);
- :class:`Associator` / :class:`GNNAssociator`: 2-D assignment per connected component;
- :class:`Updater` / :class:`KalmanUpdater` (or :class:`StereoUpdater`): one launch;
- :class:`Initiator` / :class:`MofNInitiator`: tracks from unassigned detections, M-of-N;
- :class:`Deleter` / :class:`MissDeleter`, :class:`CovarianceDeleter`, :class:`AnyDeleter`;
- :class:`MultiTargetTracker`: their composition, one frame in five stages.
"""

from .associator import Assignment, Associator, GNNAssociator
from .deleter import AnyDeleter, CovarianceDeleter, Deleter, MissDeleter
from .gater import CostGater, Gated, Gater, MahalanobisGater
from .initiator import Initiator, MofNInitiator
from .predictor import KalmanPredictor, Predictor
from .table import TrackStatus, TrackTable, TrackTableFull, Tracks
from .tracker import MultiTargetTracker, TrackingFrame
from .updater import KalmanUpdater, StereoUpdater, Updater

__all__ = [
    "AnyDeleter",
    "Assignment",
    "Associator",
    "CostGater",
    "CovarianceDeleter",
    "Deleter",
    "GNNAssociator",
    "Gated",
    "Gater",
    "Initiator",
    "KalmanPredictor",
    "KalmanUpdater",
    "MahalanobisGater",
    "MissDeleter",
    "MofNInitiator",
    "MultiTargetTracker",
    "Predictor",
    "StereoUpdater",
    "TrackStatus",
    "TrackTable",
    "TrackTableFull",
    "TrackingFrame",
    "Tracks",
    "Updater",
]

"""Paper 002's pedestrian tracker: depth frames -> segments -> one Kalman filter per pedestrian."""

from .front import DepthFrontEnd, Segment, plane_background
from .tracker import Pedestrian, PedestrianConfig, PedestrianFrame, PedestrianTracker

__all__ = ["DepthFrontEnd", "Pedestrian", "PedestrianConfig", "PedestrianFrame", "PedestrianTracker", "Segment",
           "plane_background"]

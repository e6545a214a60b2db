"""Paper 001: stereo group tracking (subtraction stereo, KLT, one EKF per group)."""

from .tracker import Group, GroupConfig, GroupFrame, GroupTracker

__all__ = ["Group", "GroupConfig", "GroupFrame", "GroupTracker"]

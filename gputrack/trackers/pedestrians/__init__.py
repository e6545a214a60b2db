"""Paper 002's pedestrian tracker from incomplete 3D point clouds: :mod:`.metrics` (sec. 5)."""

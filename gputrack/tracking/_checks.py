"""Input checks shared by the tracking roles."""

from __future__ import annotations

import numpy as np


def observation_model(H, R) -> tuple[np.ndarray, np.ndarray]:
    """``H`` (m, n) and ``R`` (m, m) as float64 arrays of finite values, or a ValueError saying which."""
    H = np.asarray(H, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    if H.ndim != 2:
        raise ValueError(f"H: expected an (m, n) matrix, got shape {H.shape}")
    if R.shape != (H.shape[0], H.shape[0]):
        raise ValueError(f"R: expected shape ({H.shape[0]}, {H.shape[0]}), got {R.shape}")
    if not (np.isfinite(H).all() and np.isfinite(R).all()):
        raise ValueError("H, R: expected finite values")
    return H, R

"""The papers' accuracy measures.

Paper 000 (Tables 5-6): the angle between the estimated and the true main (x) axis of each upper
and lower arm, in degrees; Table 7: the shoulder-position error per axis, in millimetres.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ARM_PARTS", "arm_axis_errors", "axis_angle", "mean_arm_errors", "shoulder_errors"]

#: Table 5/6 columns: right upper arm, left upper arm, right forearm, left forearm (upper_body() part indices)
ARM_PARTS = {"right_upper_arm": 1, "left_upper_arm": 2, "right_forearm": 3, "left_forearm": 4}


def axis_angle(estimated, true, axis: int = 0) -> np.ndarray:
    """Angle (degrees) between the ``axis`` columns of rotations in transforms (..., 3, 3 or 4).

    Computed as atan2(|a x b|, a . b), accurate for small angles (arccos of a dot product near 1 is not).
    """
    a = np.asarray(estimated, dtype=np.float64)[..., :3, axis]
    b = np.asarray(true, dtype=np.float64)[..., :3, axis]
    if a.shape != b.shape:
        raise ValueError(f"estimated and true: expected the same shape, got {a.shape} and {b.shape}")
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = (a * b).sum(axis=-1)
    return np.degrees(np.arctan2(cross, dot))


def _poses(chain, params, name):
    from .backends.reference.kinematics import forward_kinematics

    p = np.asarray(params, dtype=np.float64)
    if p.ndim == 1:
        p = p[None]
    if p.ndim != 2 or p.shape[1] != chain.n_params:
        raise ValueError(f"{name}: expected shape (B, {chain.n_params}) or ({chain.n_params},), got {np.shape(params)}")
    if not np.isfinite(p).all():
        raise ValueError(f"{name}: expected finite values, got non-finite entries")
    return forward_kinematics(None, chain, p)


def arm_axis_errors(chain, estimated, true, parts=tuple(ARM_PARTS.values())) -> np.ndarray:
    """(B, len(parts)) degrees: angle between estimated and true x axis of each part (Tables 5-6).

    ``estimated`` and ``true`` are parameter vectors (B, P) or (P,) of ``chain``; the axes are
    compared in camera coordinates (so a torso error shows in the arms' errors, as in the paper).
    """
    est = _poses(chain, estimated, "estimated")
    tru = _poses(chain, true, "true")
    if est.shape != tru.shape:
        raise ValueError(
            f"estimated and true: expected the same number of poses, got {est.shape[0]} and {tru.shape[0]}"
        )
    idx = list(parts)
    return axis_angle(est[:, idx], tru[:, idx])


def mean_arm_errors(chain, estimated, true) -> dict:
    """Mean arm-axis error (degrees) per arm part over a sequence, in Table 5/6 column order."""
    err = arm_axis_errors(chain, estimated, true)
    return {name: float(err[:, k].mean()) for k, name in enumerate(ARM_PARTS)}


def shoulder_errors(estimated, true) -> np.ndarray:
    """(B, 6) absolute error (mm) of t_RS, t_LS (parameters 14-19 of the 20-parameter chain; Table 7)."""
    est = np.atleast_2d(np.asarray(estimated, dtype=np.float64))
    tru = np.atleast_2d(np.asarray(true, dtype=np.float64))
    if est.shape[-1] != 20 or tru.shape[-1] != 20:
        raise ValueError(f"estimated and true: expected 20-parameter vectors, got {est.shape} and {tru.shape}")
    return np.abs(est[:, 14:20] - tru[:, 14:20])

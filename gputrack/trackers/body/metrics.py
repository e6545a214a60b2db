"""The papers' accuracy measures.

Paper 000 (Tables 5-6): the angle between the estimated and the true main (x) axis of each upper
and lower arm, in degrees; Table 7: the shoulder-position error per axis, in millimetres.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ARM_PARTS", "arm_axis_errors", "axis_angle", "mean_arm_errors", "shoulder_camera_errors", "shoulder_errors"]

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
    p = np.asarray(params, dtype=np.float64)
    if p.ndim == 1:
        p = p[None]
    if p.ndim != 2 or p.shape[1] != chain.n_params:
        raise ValueError(f"{name}: expected shape (B, {chain.n_params}) or ({chain.n_params},), got {np.shape(params)}")
    if not np.isfinite(p).all():
        raise ValueError(f"{name}: expected finite values, got non-finite entries")
    return chain.transforms(p)


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


def shoulder_camera_errors(chain, estimated, true) -> np.ndarray:
    """(B, 6) absolute error (mm) of the right and left shoulder joints' positions in camera coordinates.

    The joints are the origins of the upper arms (``right_upper_arm``, ``left_upper_arm``) under
    the full pose, so an error of the torso's pose shows here as it does in the image, whereas
    :func:`shoulder_errors` compares t_RS, t_LS in torso coordinates: a torso turned by an angle
    a about its vertical axis (the parts' depth is along the camera's viewing direction there)
    with the shoulders kept where they are seen moves t_RS and t_LS along torso z by about
    -+ a * 195 mm (3.4 mm per degree), in opposite directions on the two sides.
    """
    est = _poses(chain, estimated, "estimated")
    tru = _poses(chain, true, "true")
    if est.shape != tru.shape:
        raise ValueError(
            f"estimated and true: expected the same number of poses, got {est.shape[0]} and {tru.shape[0]}"
        )
    idx = [chain.index("right_upper_arm"), chain.index("left_upper_arm")]
    return np.abs(est[:, idx, :, 3] - tru[:, idx, :, 3]).reshape(len(est), 6)

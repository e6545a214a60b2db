"""The face tracker's figures in paper 003's terms (Table 1, Fig. 7).

- :func:`pose_errors`: per frame the absolute errors of x, y, z (mm, the model origin's position in
  the camera frame) and of roll, pitch, yaw (deg; roll about the camera's z axis, yaw about y, pitch
  about x, :func:`gputrack.models.pose.euler_from_rotation`) against the truth;
- :func:`table1`: their mean and standard deviation (Table 1), :func:`format_table1` side by side for
  several models (the paper: the multilinear model against the generic PCA model);
- :func:`error_parts` (beyond the paper): how much of a run's errors is one offset held through
  the run, how much changes slowly with the motion and how much from frame to frame;
- :func:`rotation_sources` (beyond the paper): the rotation errors the feature points alone leave
  (with the true shape) and those the estimated shape alone leaves (with the true points);
- :func:`shape_error`: the RMS distance (mm) of the K estimated model-frame points from the true ones
  (Fig. 7's bottom graph: the facial shape error in the model coordinate system), per frame: how the
  identity converges.
"""

from __future__ import annotations

import numpy as np

from ...models.pose import euler_from_rotation, fit_pose, rodrigues, rotation_vector

__all__ = ["COLUMNS", "PAPER_TABLE1", "error_parts", "format_table1", "pose_errors", "rotation_sources", "shape_error",
           "table1"]

#: Table 1's columns
COLUMNS = ("x", "y", "z", "roll", "pitch", "yaw")


def pose_errors(rotations, translations, true_rotations, true_translations, *, signed: bool = False) -> np.ndarray:
    """(F, 6) absolute errors per frame: x, y, z (mm), roll, pitch, yaw (deg); ``signed``: the
    estimate minus the truth instead (angles wrapped into [-180, 180)).

    rotations (F, 3, 3) and translations (F, 3) estimated (model -> camera), the true ones alike.
    Frames where the estimate is NaN (lost without a pose) give NaN rows."""
    R, t = np.asarray(rotations, np.float64), np.asarray(translations, np.float64)
    Rt, tt = np.asarray(true_rotations, np.float64), np.asarray(true_translations, np.float64)
    if R.shape[1:] != (3, 3) or Rt.shape != R.shape or t.shape != (len(R), 3) or tt.shape != t.shape:
        raise ValueError(f"expected rotations (F, 3, 3) and translations (F, 3) alike for estimate and truth, got "
                         f"{R.shape}, {t.shape}, {Rt.shape}, {tt.shape}")  # fmt: skip
    d_ang = euler_from_rotation(R) - euler_from_rotation(Rt)
    d_ang = (d_ang + np.pi) % (2 * np.pi) - np.pi
    err = np.column_stack([t - tt, np.degrees(d_ang)])
    return err if signed else np.abs(err)


def error_parts(signed_errors, window: int = 9) -> dict:
    """How one run's signed errors (F, C) (:func:`pose_errors` with ``signed=True``, in frame order;
    NaN rows left out) are made: {"offset": (C,) the absolute value of their mean, held through the
    run; "slow": (C,) the mean distance of their moving average over ``window`` frames (centred, the
    ends held) from that mean, what changes with the motion; "jitter": (C,) the mean distance of the
    errors from that moving average, what changes from frame to frame}. The three add up to at least
    the mean absolute error. Where the offset and the slow part are most of it, smoothing the
    estimate over time cannot help; a better model of the face or better feature points can."""
    from scipy.ndimage import uniform_filter1d

    e = np.asarray(signed_errors, np.float64)
    if e.ndim != 2:
        raise ValueError(f"signed_errors: expected (F, C), got shape {e.shape}")
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1:
        raise ValueError(f"window: expected an int >= 1, got {window!r}")
    e = e[np.isfinite(e).all(axis=1)]
    if not len(e):
        return {k: np.full(e.shape[1], np.nan) for k in ("offset", "slow", "jitter")}
    mean = e.mean(axis=0)
    smooth = uniform_filter1d(e, int(window), axis=0, mode="nearest")
    return {"offset": np.abs(mean), "slow": np.abs(smooth - mean).mean(axis=0), "jitter": np.abs(e - smooth).mean(axis=0)}


def rotation_sources(camera, features, shapes, true_points, true_shapes, true_rotations, true_translations) -> dict:
    """Where a run's rotation errors come from: the feature points or the estimated shape.

    Per frame two poses are fitted (:func:`gputrack.models.pose.fit_pose`, from the true pose):
    the true shape to the tracked feature points, and the estimated shape to the true points. The
    first pose's error is what the feature points alone leave; the second's what the shape (the
    identity and the deformation) alone leaves. features, true_points (F, K, 2) px (NaN: unknown or
    hidden); shapes, true_shapes (F, K, 3) mm in the model frame; true_rotations (F, 3, 3),
    true_translations (F, 3). Returns {"points": (F, 3), "shape": (F, 3)}: absolute roll, pitch and
    yaw errors (deg), NaN rows where fewer than 6 points are known."""
    F = len(true_rotations)
    arrays = {"features": (features, (F, None, 2)), "shapes": (shapes, (F, None, 3)),
              "true_points": (true_points, (F, None, 2)), "true_shapes": (true_shapes, (F, None, 3)),
              "true_rotations": (true_rotations, (F, 3, 3)), "true_translations": (true_translations, (F, 3))}  # fmt: skip
    a = {}
    for name, (v, shape) in arrays.items():
        v = np.asarray(v, np.float64)
        if v.ndim != len(shape) or any(w is not None and g != w for g, w in zip(v.shape, shape)):
            want = "(" + ", ".join("K" if w is None else str(w) for w in shape) + ")"
            raise ValueError(f"{name}: expected shape {want}, got {v.shape}")
        a[name] = v
    ks = {a[name].shape[1] for name in ("features", "shapes", "true_points", "true_shapes")}
    if len(ks) > 1:
        raise ValueError(f"features, shapes, true_points, true_shapes: expected the same K points, got K = {sorted(ks)}")
    out = {"points": np.full((F, 3), np.nan), "shape": np.full((F, 3), np.nan)}
    for f in range(F):
        R, t = a["true_rotations"][f], a["true_translations"][f]
        guess = (rotation_vector(R), t)
        pairs = (("points", a["true_shapes"][f], a["features"][f]), ("shape", a["shapes"][f], a["true_points"][f]))
        for key, X, m in pairs:
            fit = fit_pose(camera, X, m, guess)
            if fit is not None:
                out[key][f] = np.abs(pose_errors(rodrigues(fit[0])[None], fit[1][None], R[None], t[None])[0, 3:])
    return out


def table1(errors) -> dict:
    """{column: (mean, std)} of (F, 6) :func:`pose_errors`, NaN rows left out."""
    e = np.asarray(errors, np.float64)
    e = e[np.isfinite(e).all(axis=1)]
    return {c: (float(e[:, i].mean()) if len(e) else np.nan, float(e[:, i].std()) if len(e) else np.nan)
            for i, c in enumerate(COLUMNS)}  # fmt: skip


def format_table1(rows: dict, paper: dict | None = None) -> str:
    """Table 1 layout: one block per model name of ``rows`` ({name: table1(...)}), mean and std."""
    head = "                              x [mm]   y [mm]   z [mm]   roll [deg] pitch [deg] yaw [deg]"
    lines = [head]
    for name, t in rows.items():
        for k, label in ((0, "mean"), (1, "std")):
            vals = "".join(f"{t[c][k]:9.2f}" if i < 3 else f"{t[c][k]:12.2f}" for i, c in enumerate(COLUMNS))
            lines.append(f"{name[:24]:<24} {label:<4}{vals}")
    if paper:
        for name, vals in paper.items():
            lines.append(f"{name[:24]:<24} mean" + "".join(
                f"{v:9.2f}" if i < 3 else f"{v:12.2f}" for i, v in enumerate(vals)))  # fmt: skip
    return "\n".join(lines)


def shape_error(model, identity, expression, true_shape) -> float:
    """RMS distance (mm) of ``model.shape(identity, expression)`` (K, 3) from ``true_shape`` (K, 3),
    both in the model frame, after removing their mean offset (the pose takes a common shift)."""
    est = model.shape(identity, expression)
    true = np.asarray(true_shape, np.float64)
    d = (est - est.mean(axis=0)) - (true - true.mean(axis=0))
    return float(np.sqrt((d * d).sum(axis=1).mean()))

#: Table 1 of the paper (means; Core 2 Duo, real sequences against a two-camera reference)
PAPER_TABLE1 = {
    "paper: multilinear": (3.26, 4.37, 20.18, 0.41, 3.12, 2.33),
    "paper: generic PCA": (6.14, 4.71, 51.32, 0.34, 6.54, 3.34),
}

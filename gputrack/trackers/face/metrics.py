"""The face tracker's figures in paper 003's terms (Table 1, Fig. 7).

- :func:`pose_errors`: per frame the absolute errors of x, y, z (mm, the model origin's position in
  the camera frame) and of roll, pitch, yaw (deg; roll about the camera's z axis, yaw about y, pitch
  about x, :func:`gputrack.models.pose.euler_from_rotation`) against the truth;
- :func:`table1`: their mean and standard deviation (Table 1), :func:`format_table1` side by side for
  several models (the paper: the multilinear model against the generic PCA model);
- :func:`shape_error`: the RMS distance (mm) of the K estimated model-frame points from the true ones
  (Fig. 7's bottom graph: the facial shape error in the model coordinate system), per frame: how the
  identity converges.
"""

from __future__ import annotations

import numpy as np

from ...models.pose import euler_from_rotation

__all__ = ["COLUMNS", "PAPER_TABLE1", "format_table1", "pose_errors", "shape_error", "table1"]

#: Table 1's columns
COLUMNS = ("x", "y", "z", "roll", "pitch", "yaw")


def pose_errors(rotations, translations, true_rotations, true_translations) -> np.ndarray:
    """(F, 6) absolute errors per frame: x, y, z (mm), roll, pitch, yaw (deg).

    rotations (F, 3, 3) and translations (F, 3) estimated (model -> camera), the true ones alike.
    Frames where the estimate is NaN (lost without a pose) give NaN rows."""
    R, t = np.asarray(rotations, np.float64), np.asarray(translations, np.float64)
    Rt, tt = np.asarray(true_rotations, np.float64), np.asarray(true_translations, np.float64)
    if R.shape[1:] != (3, 3) or Rt.shape != R.shape or t.shape != (len(R), 3) or tt.shape != t.shape:
        raise ValueError(f"expected rotations (F, 3, 3) and translations (F, 3) alike for estimate and truth, got "
                         f"{R.shape}, {t.shape}, {Rt.shape}, {tt.shape}")  # fmt: skip
    d_ang = euler_from_rotation(R) - euler_from_rotation(Rt)
    d_ang = (d_ang + np.pi) % (2 * np.pi) - np.pi
    return np.column_stack([np.abs(t - tt), np.degrees(np.abs(d_ang))])


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

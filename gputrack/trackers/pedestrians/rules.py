"""Host-side rules of the pedestrian tracker (paper 002 sec. 4.3): the assignment cost (eq. 1-3),
the assignment with rejection, containment tests and the occlusion-adaptive gain (eq. 4-6).

They work on the few tracks and segments of a frame (tens), in NumPy and SciPy.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["assign", "behind", "cost_matrix", "inside", "occlusion_gain"]

#: cost of a rejected pair in the assignment: above any feasible pair's cost
_REJECTED = 1e6


def cost_matrix(track_pos, track_vol, seg_pos, seg_vol, *, alpha: float, max_distance: float,
                max_volume_change: float) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(cost (T, M), feasible (T, M) bool) of tracks i and segments j.

    Eq. 1: d_ij = || p_j - p_i || (xyz, metres); eq. 2: V_ij = | V_j - V_i | (m^3); eq. 3:
    c_ij = alpha d_ij + (1 - alpha) V_ij. A pair is feasible when d_ij <= max_distance (mm) and
    V_ij <= max_volume_change (m^3) (sec. 4.3: pairs whose position or volume differ too much are
    rejected); an infeasible pair's cost is a large constant, so the assignment first maximises the
    number of feasible pairs, then minimises their cost.
    """
    tp = np.asarray(track_pos, np.float64).reshape(-1, 3)
    sp = np.asarray(seg_pos, np.float64).reshape(-1, 3)
    d = np.linalg.norm(tp[:, None, :] - sp[None, :, :], axis=-1) / 1000.0  # eq. 1 (m)
    dv = np.abs(np.asarray(seg_vol, np.float64)[None, :] - np.asarray(track_vol, np.float64)[:, None])  # eq. 2
    c = alpha * d + (1.0 - alpha) * dv  # eq. 3
    ok = (d * 1000.0 <= max_distance) & (dv <= max_volume_change) & np.isfinite(c)
    return np.where(ok, c, _REJECTED), ok


def assign(cost, feasible) -> list[tuple[int, int]]:
    """The assignment of least total cost (scipy's ``linear_sum_assignment``; with unequal counts
    the smaller side is assigned in full), infeasible pairs dropped: [(i, j)]."""
    if cost.size == 0:
        return []
    r, c = linear_sum_assignment(cost)
    return [(int(i), int(j)) for i, j in zip(r, c) if feasible[i, j]]


def inside(point, lo, hi, margin: float) -> bool:
    """Is ``point`` (3,) inside the box [lo, hi] grown by ``margin`` in the ground plane (x, z)?"""
    return bool(lo[0] - margin <= point[0] <= hi[0] + margin and lo[2] - margin <= point[2] <= hi[2] + margin)


def behind(point, lo, hi, margin: float) -> bool:
    """Is ``point`` (3,) in the shadow of the box [lo, hi] seen from the camera: farther than its
    front (z > lo_z) and within its bearings x / z in the ground plane, widened by ``margin`` at
    the point's depth?"""
    z = point[2]
    if not z > lo[2] or lo[2] <= 0:
        return False
    b = point[0] / z
    bearings = (lo[0] / lo[2], hi[0] / lo[2], lo[0] / hi[2], hi[0] / hi[2])
    w = margin / z
    return bool(min(bearings) - w <= b <= max(bearings) + w)


def occlusion_gain(v_det: float, v_max: float, *, v_thr: float, beta: float) -> float:
    """Eq. 4-6: O_ocl = beta V_abs + (1 - beta) V_rel with V_abs = V_det / V_thr (1 when V_det >=
    V_thr) and V_rel = V_det / V_max (V_max: the largest volume observed in the last frames; no
    history: V_rel = 1). Returned as the Kalman gain scale, clipped to [0, 1]: a shrunken segment
    (strong occlusion) is trusted less, a full one as the plain filter (the paper's wording of the
    direction is inverted in places; this is its intent)."""
    v_abs = v_det / v_thr if v_det < v_thr else 1.0  # eq. 4
    v_rel = v_det / v_max if v_max > 0 and np.isfinite(v_max) else 1.0  # eq. 5
    o = beta * v_abs + (1.0 - beta) * v_rel  # eq. 6
    return float(min(max(o, 0.0), 1.0))

"""Host-side rules of the pedestrian tracker (paper 002 sec. 4.3): the assignment cost (eq. 1-3),
the assignment with rejection, containment and occlusion tests and the occlusion-adaptive gain
(eq. 4-6).

They work on the few tracks and segments of a frame (tens), in NumPy and SciPy.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["assign", "bearings", "behind", "cost_matrix", "drop_labels", "gap_bearings", "inside",
           "nearest_in_bearing", "occlusion_gain", "seen_apart"]

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


def assign(cost, feasible, unassigned: float | None = None) -> list[tuple[int, int]]:
    """The assignment of least total cost, infeasible pairs dropped: [(i, j)] (scipy's
    ``linear_sum_assignment``).

    ``unassigned`` None: as many feasible pairs as possible, then the least cost (with unequal
    counts the smaller side is assigned in full). A cost u: leaving a track or a segment without a
    partner costs u each, so a pair is made only where it lowers the total: two far pairs that take
    each other's near partners (c = 0.48 + 0.62) lose to one near pair and two left over (c + 2u).
    """
    if cost.size == 0:
        return []
    cost = np.where(feasible, cost, _REJECTED)
    if unassigned is None:
        r, c = linear_sum_assignment(cost)
    else:
        T, M = cost.shape
        big = np.full((T + M, M + T), _REJECTED)
        big[:T, :M] = cost
        big[np.arange(T), M + np.arange(T)] = unassigned
        big[T + np.arange(M), np.arange(M)] = unassigned
        big[T:, M:] = 0.0
        r, c = linear_sum_assignment(big)
        keep = (r < T) & (c < M)
        r, c = r[keep], c[keep]
    return [(int(i), int(j)) for i, j in zip(r, c) if feasible[i, j]]


def drop_labels(labels, dropped) -> np.ndarray:
    """Points' segment indices (N,) (-1: none) after the segments marked in ``dropped`` (M,) bool
    are removed: theirs become -1, the others are renumbered in order."""
    keep = ~np.asarray(dropped, bool)
    new = np.where(keep, np.cumsum(keep) - 1, -1)
    lab = np.asarray(labels, np.int64)
    return np.where(lab >= 0, new[np.maximum(lab, 0)], -1)


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
    b0, b1 = bearings(lo, hi)
    w = margin / z
    return bool(b0 - w <= point[0] / z <= b1 + w)


def bearings(lo, hi) -> tuple[float, float]:
    """The bearings x / z (smallest, largest) under which the camera sees the ground-plane box
    [lo, hi] (z > 0)."""
    b = (lo[0] / lo[2], hi[0] / lo[2], lo[0] / hi[2], hi[0] / hi[2])
    return min(b), max(b)


def gap_bearings(a, b) -> tuple[float, float]:
    """(g0, g1): the bearings between segments a and b (``lo``/``hi`` boxes); g1 <= g0 where their
    bearings overlap (one in front of the other)."""
    (a0, a1), (b0, b1) = bearings(a.lo, a.hi), bearings(b.lo, b.hi)
    return (a1, b0) if a0 <= b0 else (b1, a0)


def seen_apart(depth, camera, a, b, *, min_gap: float, beyond: float) -> bool:
    """Does the camera see past segments a and b through the gap between them, i.e. are they two
    bodies, not one split by occlusion? ``depth`` (H, W) the frame (0 or NaN: no reading), in the
    unit of the segments (``camera.depth_scale`` applied when it has one).

    True when the gap between their bearings is wider than ``min_gap`` at the nearer one's depth
    and more than half of its pixels in the rows of the two (their heights projected at the
    nearer depth) read farther than the farther segment's back by ``beyond``: nothing stands
    between them. A nearer reading there (an occluder, moving or static) or a missing one (sunlight,
    no return) keeps them possibly one body."""
    g0, g1 = gap_bearings(a, b)
    near = min(a.lo[2], b.lo[2])
    if not (g1 - g0) * near > min_gap:
        return False
    H, W = depth.shape
    c0 = max(math.ceil(camera.cx + camera.fx * g0), 0)
    c1 = min(math.floor(camera.cx + camera.fx * g1) + 1, W)
    top, bottom = min(a.lo[1], b.lo[1]), max(a.hi[1], b.hi[1])
    r0 = max(math.floor(camera.cy + camera.fy * top / near), 0)
    r1 = min(math.ceil(camera.cy + camera.fy * bottom / near) + 1, H)
    if c1 <= c0 or r1 <= r0:
        return False
    d = depth[r0:r1, c0:c1].astype(np.float64) * getattr(camera, "depth_scale", 1.0)
    far = max(a.hi[2], b.hi[2]) + beyond
    with np.errstate(invalid="ignore"):
        past = np.count_nonzero(d > far)  # NaN and 0 (no reading) are not past
    return bool(past > 0.5 * d.size)


def nearest_in_bearing(seg, parts):
    """The segment of ``parts`` (non-empty) with the smallest gap in bearing to ``seg``."""

    def gap(p):
        g0, g1 = gap_bearings(seg, p)
        return g1 - g0

    return min(parts, key=gap)


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

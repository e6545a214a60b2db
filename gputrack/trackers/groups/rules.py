"""The host-side rules of the group tracker (paper 001 sec. 3.4-3.5): when regions overlap, how
groups merge (eq. 13-15), when a group splits, and the moments of a set of points.

These work on the few groups of a frame (T <= ~100), in NumPy; the per-point work (gating all
points against all groups, eq. 8-11, and the groups' moments, eq. 7), the EKF update and the
merge pre-test run on the device (:func:`gputrack.ops.point_groups.group_frame`).
"""

from __future__ import annotations

import numpy as np

POS = np.array([0, 2, 4])  # eq. 1: x = [x xdot y ydot z zdot]
VEL = np.array([1, 3, 5])
_S = np.linspace(0.0, 1.0, 129)[1:-1]  # the interior of (0, 1) searched by ellipsoids_overlap


def ellipsoids_overlap(a, A, b, B, gamma: float) -> np.ndarray:
    """Do the regions {y : (y - a)^T A^-1 (y - a) <= gamma} and the same for (b, B) intersect?

    a, b (k, d) centres; A, B (k, d, d) positive-definite shapes; returns (k,) bool. Exact test
    (the ellipsoids meet iff max over s in (0, 1) of (b - a)^T (A / (1 - s) + B / s)^-1 (b - a)
    <= gamma, Gilitschenski and Hanebeck 2012): with A = L L^T and L^-1 B L^-T = V diag(l) V^T,
    e = V^T L^-1 (b - a), the function is sum_k e_k^2 s (1 - s) / (s + l_k (1 - s)), maximised
    over a grid of 127 values of s (two spheres of radii r1, r2: |b - a| <= r1 + r2).
    """
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if len(a) == 0:
        return np.zeros(0, bool)
    L = np.linalg.cholesky(np.asarray(A, np.float64))
    Li = np.linalg.inv(L)
    C = Li @ np.asarray(B, np.float64) @ np.swapaxes(Li, 1, 2)
    lam, V = np.linalg.eigh((C + np.swapaxes(C, 1, 2)) / 2)
    e = np.einsum("kji,kj->ki", V, np.einsum("kij,kj->ki", Li, b - a))
    s = _S[None, :, None]
    f = (e[:, None, :] ** 2 * s * (1 - s) / (s + np.maximum(lam, 0)[:, None, :] * (1 - s))).sum(-1)
    return f.max(axis=1) <= gamma


def overlapping_pairs(x, Sigma, gamma: float) -> np.ndarray:
    """Pairs (i, j), i < j, of groups whose search regions intersect in position and in velocity
    (eq. 13): regions {y : (y - mean)^T Sigma_block^-1 (y - mean) <= gamma} of the position and
    the velocity blocks of each group's spread Sigma. x (T, 6), Sigma (T, 6, 6). (k, 2) int."""
    T = len(x)
    if T < 2:
        return np.zeros((0, 2), np.int64)
    i, j = np.triu_indices(T, 1)
    keep = np.ones(len(i), bool)
    for idx in (POS, VEL):
        c = x[:, idx]
        S = Sigma[:, idx][:, :, idx]
        r = np.sqrt(gamma * np.linalg.eigvalsh(S)[:, -1])  # bounding spheres first: most pairs end here
        near = keep & (np.linalg.norm(c[i] - c[j], axis=1) <= r[i] + r[j])
        keep[:] = False
        keep[near] = ellipsoids_overlap(c[i[near]], S[i[near]], c[j[near]], S[j[near]], gamma)
    return np.stack([i[keep], j[keep]], 1)


def merge_states(weights, x, Sigma):
    """Eq. 14-15: the count-weighted state and covariance of groups merged into one.

    weights (k,) = the groups' point counts N_i; x (k, 6); Sigma (k, 6, 6) (the spreads, or the
    Kalman covariances: the same rule). x_m = sum w_i x_i, Sigma_m = sum w_i (Sigma_i +
    (x_i - x_m)(x_i - x_m)^T), w_i = N_i / sum N (equal weights when every N_i is 0)."""
    w = np.asarray(weights, np.float64)
    w = np.full(len(w), 1.0 / len(w)) if w.sum() <= 0 else w / w.sum()
    xm = w @ x  # eq. 14
    d = x - xm
    Sm = np.einsum("k,kij->ij", w, Sigma + d[:, :, None] * d[:, None, :])  # eq. 15
    return xm, (Sm + Sm.T) / 2


def moments(points, velocities):
    """The mean state (6,) in state order and the population covariance (6, 6) of k >= 1 points."""
    q = np.empty((len(points), 6))
    q[:, POS], q[:, VEL] = points, velocities
    m = q.mean(0)
    d = q - m
    return m, d.T @ d / len(q)


def may_exceed(S, c: float) -> np.ndarray:
    """(k,) bool: may the largest eigenvalue of each symmetric 3x3 ``S`` (k, 3, 3) reach ``c``?
    False where c I - S is positive definite (Sylvester: its three leading minors are positive),
    i.e. every eigenvalue is below c, and where S is not finite; a cheap exact filter before an
    eigendecomposition."""
    S = np.asarray(S, np.float64)
    a, b, f = c - S[:, 0, 0], c - S[:, 1, 1], c - S[:, 2, 2]
    d, e, g = S[:, 0, 1], S[:, 0, 2], S[:, 1, 2]  # the off-diagonal entries of c I - S, negated
    m2 = a * b - d * d
    m3 = a * (b * f - g * g) - d * (d * f + g * e) - e * (d * g + b * e)
    return ~((a > 0) & (m2 > 0) & (m3 > 0)) & np.isfinite(S).all((1, 2))

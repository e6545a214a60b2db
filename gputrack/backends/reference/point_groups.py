"""NumPy reference of :mod:`gputrack.ops.point_groups`: every point against every group, then the
moments of each group's points (paper 001 eq. 7-11)."""

from __future__ import annotations

import numpy as np

POS = np.array([0, 2, 4])  # eq. 1: x = [x xdot y ydot z zdot]
VEL = np.array([1, 3, 5])


def _block_factors(S, ok):
    """Inverse Cholesky factors W (T,3,3) with W S W^T = I, log det S (T,), and whether S is
    positive definite (a pivot <= 0 is not)."""
    T = S.shape[0]
    W = np.zeros((T, 3, 3))
    logdet = np.zeros(T)
    pd = np.zeros(T, bool)
    for j in np.flatnonzero(ok):
        try:
            L = np.linalg.cholesky(S[j])
        except np.linalg.LinAlgError:
            continue
        W[j] = np.linalg.inv(L)
        logdet[j] = 2.0 * np.log(np.diag(L)).sum()
        pd[j] = True
    return W, logdet, pd


def assign_points(device, points, velocities, means, spreads, active, gamma, N, out):
    labels, counts, mean, cov = out
    y = np.asarray(points[:N], np.float64)
    lam = np.asarray(velocities[:N], np.float64)
    xi = np.asarray(means, np.float64)
    S = np.asarray(spreads, np.float64)
    S = (S + np.swapaxes(S, 1, 2)) / 2.0
    on = np.ones(len(xi), bool) if active is None else np.asarray(active) != 0
    Wp, ldp, pdp = _block_factors(S[:, POS][:, :, POS], on)
    Wv, ldv, pdv = _block_factors(S[:, VEL][:, :, VEL], on)
    valid = np.isfinite(y).all(1) & np.isfinite(lam).all(1)
    ep = Wp @ (y.T[None] - xi[:, POS, None])  # (T, 3, N): whitened y_i - xi_j
    d2p = (ep * ep).sum(1).T  # (N, T) eq. 8: (y_i - xi_j)^T Sigma^-1 (y_i - xi_j)
    ev = Wv @ (lam.T[None] - xi[:, VEL, None])
    d2v = (ev * ev).sum(1).T
    gated = valid[:, None] & (on & pdp)[None, :] & (d2p < gamma)  # eq. 8
    # eq. 9-11: log m_total = log m_p + log m_v = -(d2p + log det P_xi + d2v + log det P_v) / 2 + const
    # (k_p, k_v and the normal densities' 2 pi factors are common to every group: the argmax drops them)
    score = -(d2p + ldp[None, :]) - np.where(pdv[None, :], d2v + ldv[None, :], 0.0)
    score = np.where(gated, score, -np.inf)
    best = np.argmax(score, axis=1)  # the first maximum: ties go to the lowest slot
    lab = np.where(gated.any(1), best, -1)
    labels[:N] = lab
    labels[N:] = -1
    T = len(xi)
    q = np.concatenate([y, lam], axis=1)[:, [0, 3, 1, 4, 2, 5]]  # each point in state order
    order = np.argsort(lab, kind="stable")
    bounds = np.searchsorted(lab[order], np.arange(T + 1))
    for j in range(T):
        pts = q[order[bounds[j]:bounds[j + 1]]]
        n = len(pts)
        counts[j] = n
        m = pts.mean(0) if n else xi[j]
        mean[j] = m
        d = pts - m
        cov[j] = d.T @ d / n if n else 0.0  # eq. 7: cov(C_y), the spread of the group's points (population)
    return out

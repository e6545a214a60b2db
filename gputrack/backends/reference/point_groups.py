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
    ep = np.einsum("tab,ntb->nta", Wp, y[:, None, :] - xi[None, :, POS])  # whitened y_i - xi_j
    d2p = (ep * ep).sum(-1)  # eq. 8: (y_i - xi_j)^T Sigma^-1 (y_i - xi_j)
    ev = np.einsum("tab,ntb->nta", Wv, lam[:, None, :] - xi[None, :, VEL])
    d2v = (ev * ev).sum(-1)
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
    for j in range(T):
        q = np.concatenate([y[lab == j], lam[lab == j]], axis=1)  # (n, [pos vel])
        n = len(q)
        counts[j] = n
        state = np.empty(6)
        state[POS], state[VEL] = (q[:, :3].mean(0), q[:, 3:].mean(0)) if n else (xi[j, POS], xi[j, VEL])
        mean[j] = state
        c = np.zeros((6, 6))
        if n:
            d = np.empty((n, 6))
            d[:, POS], d[:, VEL] = q[:, :3] - state[POS], q[:, 3:] - state[VEL]
            c = d.T @ d / n  # eq. 7: cov(C_y), the spread of the group's points (population)
        cov[j] = c
    return out

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


def _bound(S):
    """An upper bound of the largest eigenvalue of each symmetric (k, 3, 3): the smaller of the
    trace and the largest absolute row sum (Gershgorin)."""
    tr = np.trace(S, axis1=1, axis2=2)
    rows = np.abs(S).sum(2).max(1)
    return np.minimum(tr, rows)


def group_frame(device, table, points, velocities, constants, n, labels):
    """gputrack.ops.point_groups.group_frame: the readable version, through the reference's own
    kf_predict, assign_points and ekf_update_stereo."""
    from .kalman import ekf_update_stereo, kf_predict

    c = np.asarray(constants, np.float32)
    F, Q, R = c[0:36].reshape(6, 6), c[36:72].reshape(6, 6), np.diag(c[72:75])
    f, b, cx, cy, gamma, alpha, min_pts, fp, fv, offset, mgamma = (float(v) for v in c[75:86])
    tab = table
    T = tab.shape[0]
    x = tab[:, 0:6].copy()
    P = tab[:, 6:42].reshape(T, 6, 6).copy()
    Sig = tab[:, 42:78].reshape(T, 6, 6).copy()
    active = tab[:, 78] > 0.5
    x, P = kf_predict(None, x, P, F, Q)  # eq. 2-3
    floor = np.zeros((6, 6), np.float32)
    floor[POS, POS], floor[VEL, VEL] = np.float32(fp), np.float32(fv)
    y = np.array(points, np.float32)
    lam = np.ascontiguousarray(velocities, np.float32)
    if offset > 0:  # each point moved along its viewing ray, from the surface to the body's axis
        r = np.sqrt(y[:, 0] * y[:, 0] + y[:, 1] * y[:, 1] + y[:, 2] * y[:, 2])
        with np.errstate(invalid="ignore", divide="ignore"):
            y = y * (np.float32(1) + np.float32(offset) / np.where(r > 0, r, np.float32(np.nan)))[:, None]
    cnt = np.zeros(T, np.int32)
    mean = np.zeros((T, 6), np.float32)
    cov = np.zeros((T, 6, 6), np.float32)
    assign_points(device, y, lam, x, Sig + floor, active.astype(np.uint8), np.float32(gamma), n,
                  (labels, cnt, mean, cov))  # fmt: skip  # eq. 8-11, eq. 7's cov(C_y)
    seen = active & (cnt >= min_pts) & (mean[:, 4] > 0)
    a = np.float32(alpha)
    Sig = np.where(seen[:, None, None], a * Sig + (np.float32(1) - a) * cov, Sig)  # eq. 7
    Sig = (Sig + np.swapaxes(Sig, 1, 2)) * np.float32(0.5)
    z = np.full((T, 3), np.nan, np.float32)  # NaN row: predicted only
    m = mean[seen]
    z[seen] = np.stack([f * m[:, 0] / m[:, 4] + cx, f * m[:, 2] / m[:, 4] + cy, f * b / m[:, 4]], 1)  # eq. 6
    x, P, _ = ekf_update_stereo(None, x, P, z, R, f, b, cx, cy)  # eq. 4-6
    # the merge pre-test (eq. 13): bounding spheres of the regions in position and in velocity
    G = Sig + floor
    centre = x.astype(np.float64)
    many = cnt >= min_pts
    centre[np.ix_(many, VEL)] = mean[np.ix_(many, VEL)]
    rp = np.sqrt(np.float64(mgamma) * _bound(G[:, POS][:, :, POS].astype(np.float64)))
    rv = np.sqrt(np.float64(mgamma) * _bound(G[:, VEL][:, :, VEL].astype(np.float64)))
    dp = np.linalg.norm(centre[:, None, POS] - centre[None, :, POS], axis=2)
    dv = np.linalg.norm(centre[:, None, VEL] - centre[None, :, VEL], axis=2)
    near = (dp <= rp[:, None] + rp[None, :]) & (dv <= rv[:, None] + rv[None, :]) & active[:, None] & active[None, :]
    near = np.triu(near, 1)
    tab[:, 0:6] = x
    tab[:, 6:42] = P.reshape(T, 36)
    tab[:, 42:78] = Sig.reshape(T, 36)
    tab[:, 79] = cnt
    tab[:, 80:86] = mean
    tab[:, 86] = seen
    tab[:, 87] = near.sum(1)
    tab[:, 88:92] = -1
    for i in np.flatnonzero(near.any(1)):
        js = np.flatnonzero(near[i])[:4]
        tab[i, 88:88 + len(js)] = js
    return table, labels

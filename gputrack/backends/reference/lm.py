"""NumPy reference of the batched Levenberg-Marquardt (paper 000 eq. 22-24; paper 003 eq. 8-9).

The solver state is the packed layout of :class:`gputrack.ops.lm.Layout`, read through named
NumPy views so that the math below reads like the paper. Every device backend implements the same
steps in the same order (``solver_update``) in one launch.
"""

from __future__ import annotations

import numpy as np

from ...abi import LMLayout as LAY
from ...abi import LMReason, LMStatus

# status / reason codes (gputrack/abi.py)
RUNNING, CONVERGED, MAX_ITER, FAILED = LMStatus.RUNNING, LMStatus.CONVERGED, LMStatus.MAX_ITER, LMStatus.FAILED
R_FTOL, R_XTOL, R_GTOL, R_MAXIT = LMReason.FTOL, LMReason.XTOL, LMReason.GTOL, LMReason.MAX_ITER
R_NONFINITE, R_NOTPD, R_DAMPING = LMReason.NONFINITE, LMReason.NOT_PD, LMReason.DAMPING

MAX_CHOL_TRIES = 40


def normal_equations(device, J, r, out=None):
    JtJ = np.einsum("bmi,bmj->bij", J, J)  # eq. 22: J^T J
    Jtr = np.einsum("bmi,bm->bi", J, r)  # eq. 22: J^T r
    if out is not None:
        out[0][...] = JtJ
        out[1][...] = Jtr
        return out
    return JtJ, Jtr


def cholesky(A):
    """Lower Cholesky factor of one symmetric matrix (lower triangle read), or None if not PD."""
    P = A.shape[0]
    L = np.zeros_like(A)
    for j in range(P):
        s = A[j, j] - L[j, :j] @ L[j, :j]
        if not (s > 0) or not np.isfinite(s):
            return None
        L[j, j] = np.sqrt(s)
        L[j + 1 :, j] = (A[j + 1 :, j] - L[j + 1 :, :j] @ L[j, :j]) / L[j, j]
    return L


def chol_solve(L, b):
    """Solve L L^T x = b by forward and back substitution."""
    P = L.shape[0]
    y = np.zeros_like(b)
    for i in range(P):
        y[i] = (b[i] - L[i, :i] @ y[:i]) / L[i, i]
    x = np.zeros_like(b)
    for i in range(P - 1, -1, -1):
        x[i] = (y[i] - L[i + 1 :, i] @ x[i + 1 :]) / L[i, i]
    return x


def lm_step(device, JtJ, Jtr, damping, out=None):
    B, P = Jtr.shape
    delta, ok = out if out is not None else (np.empty_like(Jtr), np.empty(B, np.int32))
    delta[...] = 0
    ok[...] = 0
    eye = np.eye(P, dtype=JtJ.dtype)
    for b in range(B):
        L = cholesky(JtJ[b] + damping[b] * eye)  # eq. 22: J^T J + C I
        if L is not None:
            delta[b] = chol_solve(L, Jtr[b])  # eq. 22: (J^T J + C I)^-1 J^T r, by Cholesky
            ok[b] = 1
    return delta, ok


def lm_solve(device, J, r, damping, out=None):
    JtJ, Jtr = normal_equations(device, J, r)
    return lm_step(device, JtJ, Jtr, damping, out)


# ------------------------------------------------------------------------------------------------
# solver


class State:
    """Arrays of one solve (see gputrack.ops.lm.Layout); W is set by ``solver_workspace``."""

    def __init__(self, device, lay, S, I, Out):
        self.device, self.lay, self.S, self.I, self.Out = device, lay, S, I, Out
        self.W = None


def solver_state(device, lay, S, I, Out):
    return State(device, lay, S, I, Out)


def solver_workspace(state, lay, W):
    state.lay, state.W = lay, W


def solver_init(state, X0, K, X):
    """S and I from the start points X0 and the constants K; the first points to evaluate into X."""
    lay, S, I = state.lay, state.S, state.I
    B, P = lay.B, lay.P
    dt = S.dtype
    S[:] = 0
    I[:] = 0
    I[LAY.IG_B], I[LAY.IG_HAS_MASK], I[LAY.IG_P] = B, int(lay.has_mask), P
    kb = lay.kblock(K)
    x0 = np.asarray(X0).astype(dt)
    lay.vec(S, lay.x)[:] = x0
    lay.vec(S, lay.xt)[:] = x0
    lay.vec(S, lay.lo)[:] = kb[:, LAY.K_LO * P : (LAY.K_LO + 1) * P]
    lay.vec(S, lay.hi)[:] = kb[:, LAY.K_HI * P : (LAY.K_HI + 1) * P]
    lay.vec(S, lay.h)[:] = K[lay.kh : lay.kh + P]
    lay.sc(S, lay.C)[:] = kb[:, LAY.K_NVEC * P]
    lay.sc(S, lay.nu)[:] = 2.0
    n_const = lay.NGLOB + (lay.M * P if lay.has_mask else 0)
    S[lay.glob : lay.glob + n_const] = K[lay.kglob : lay.kglob + n_const]
    rel = S[lay.glob + LAY.G_REL]
    SX = X.shape[0] // B
    for b in range(B):
        _points(lay, S, X, b, x0[b], SX, rel)


def solver_active(state) -> int:
    return int(np.count_nonzero(state.lay.iblock(state.I)[:, LAY.I_STATUS] == RUNNING))


def solver_result(state):
    return state.Out.copy()


def _finite(a):
    return np.isfinite(a).all()


def solver_update(state, R, X, *, first, final, jac=None):
    """One iteration for every running problem: accept/reject the evaluated trial, update the
    damping, normal equations at the accepted point, damped Cholesky step, next points into X.

    R: residuals of the last call, (B * SR, M) with SR = 2P + 1 (trial point and its perturbed
    copies, eq. 24) or SR = 1 (trial point only; then ``jac`` (B, M, P) is its Jacobian or the
    call was the last one). X: (B * SX, P) receives the next points (SX = 2P + 1 or 1).
    """
    lay, S, I, W = state.lay, state.S, state.I, state.W
    B, P, M = lay.B, lay.P, lay.M
    dt = S.dtype
    R = np.asarray(R)
    SR, SX = R.shape[0] // B, X.shape[0] // B
    x, xt, g, den = lay.vec(S, lay.x), lay.vec(S, lay.xt), lay.vec(S, lay.g), lay.vec(S, lay.den)
    lo, hi = lay.vec(S, lay.lo), lay.vec(S, lay.hi)
    A = lay.wmat(W, lay.A, P, P)
    Jt = lay.wmat(W, lay.Jt, P, M)
    F, C, nu, pred, Ft, snorm = (lay.sc(S, o) for o in (lay.F, lay.C, lay.nu, lay.pred, lay.Ft, lay.snorm))
    glob = S[lay.glob : lay.glob + lay.NGLOB]
    ftol, xtol, gtol = glob[[LAY.G_FTOL, LAY.G_XTOL, LAY.G_GTOL]]
    rel, ctiny, cmax = glob[[LAY.G_REL, LAY.G_CTINY, LAY.G_CMAX]]
    mask = lay.maskview(S) if I[LAY.IG_HAS_MASK] else np.ones((M, P), dt)
    ib = lay.iblock(I)
    status, iters, accepted, reason = ib[:, LAY.I_STATUS], ib[:, LAY.I_ITER], ib[:, LAY.I_ACCEPTED], ib[:, LAY.I_REASON]
    fin = ib[:, LAY.I_FIN :]
    Rb = R.reshape(B, SR, M).astype(dt)
    rt = Rb[:, 0]  # residuals at the trial points
    have_J = not final
    accepted[:] = 0

    for b in np.flatnonzero(status == RUNNING):
        # Jacobian at the trial point: eq. 24 central differences over the stored points, or given
        if have_J:
            if jac is not None:
                Jb = np.asarray(jac[b], dtype=dt)
                ok_J = _finite(Jb)
                Jt[b] = Jb.T
            else:
                # (P, M): r(x + eps e_n) - r(x - eps e_n), only where the Jacobian mask is set
                diff = np.where(mask.T != 0, Rb[b, 1::2] - Rb[b, 2::2], 0)
                ok_J = _finite(diff)
                safe = np.where(den[b] != 0, den[b], 1)
                Jt[b] = np.where(den[b][:, None] != 0, diff / safe[:, None], 0)  # eq. 24
            fin[b] = ok_J
        else:
            ok_J = True
        # acceptance of the trial (its cost Ft = sum r^2, eq. 20-21)
        Ft[b] = rt[b] @ rt[b]
        if not (_finite(rt[b]) and ok_J and np.isfinite(Ft[b])):
            status[b], reason[b] = FAILED, R_NONFINITE
            if first:
                F[b] = np.inf  # no finite cost at x0
            continue
        if first:
            acc = True
        else:
            iters[b] += 1
            dF = F[b] - Ft[b]
            acc = dF > 0
            if acc:
                rho = dF / pred[b] if pred[b] > 0 else 1.0
                C[b] *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)  # Nielsen: lower C near the optimum
                nu[b] = 2.0
            else:
                C[b] *= nu[b]  # rejected: raise this problem's C only
                nu[b] *= 2.0
                if np.linalg.norm(xt[b] - x[b]) <= xtol * (xtol + np.linalg.norm(x[b])):
                    status[b], reason[b] = CONVERGED, R_XTOL  # no step this small improves the cost
                elif C[b] > cmax * (1.0 + np.max(np.diag(A[b]))):
                    status[b], reason[b] = FAILED, R_DAMPING
                    continue
        if acc:
            accepted[b] = 1
            snorm[b] = np.linalg.norm(xt[b] - x[b])
            F_old = F[b]
            x[b], F[b] = xt[b], Ft[b]
            if not first:
                if F_old - F[b] <= ftol * F_old:
                    status[b], reason[b] = CONVERGED, R_FTOL
                elif snorm[b] <= xtol * (xtol + np.linalg.norm(x[b])):
                    status[b], reason[b] = CONVERGED, R_XTOL
            if have_J:
                A[b] = Jt[b] @ Jt[b].T  # eq. 22: J^T J
                g[b] = Jt[b] @ rt[b]  # eq. 22: J^T r
                if status[b] == RUNNING:
                    # projected gradient: drop components pushing against an active bound (the
                    # step is x - delta, so g > 0 moves down, g < 0 moves up)
                    gp = np.where(((x[b] >= hi[b]) & (g[b] < 0)) | ((x[b] <= lo[b]) & (g[b] > 0)), 0, g[b])
                    if np.max(np.abs(gp)) <= gtol:
                        status[b], reason[b] = CONVERGED, R_GTOL
        if final and status[b] == RUNNING:
            status[b], reason[b] = MAX_ITER, R_MAXIT

    if final:
        _export(state)
        return
    eye = np.eye(P, dtype=dt)
    for b in range(B):
        if status[b] == RUNNING:
            # parameters held at a bound by the gradient (the step is x - delta) stay there: their
            # rows and columns of the system become the identity, their right-hand side 0
            act = ((x[b] >= hi[b]) & (g[b] < 0)) | ((x[b] <= lo[b]) & (g[b] > 0))
            Ab = np.where(act[:, None] | act[None, :], 0, A[b]) + np.diag(act.astype(dt))
            gb = np.where(act, 0, g[b])
            # damped Cholesky (eq. 22); a failure raises C tenfold and tries again
            dmax = 1.0 + np.max(np.diag(A[b]))
            L = cholesky(Ab + C[b] * eye)
            tries = 0
            while L is None and tries <= MAX_CHOL_TRIES and C[b] <= cmax * dmax:
                C[b] = max(10.0 * C[b], ctiny * dmax)
                L = cholesky(Ab + C[b] * eye)
                tries += 1
            if L is None:
                status[b], reason[b] = FAILED, R_NOTPD
            else:
                delta = chol_solve(L, gb)
                xt[b] = np.clip(x[b] - delta, lo[b], hi[b])  # eq. 22, projected into the box (paper 003 eq. 8-9)
                s = x[b] - xt[b]
                pred[b] = 2.0 * (s @ g[b]) - s @ (A[b] @ s)  # predicted reduction of the model ||r - J s||^2
        # next points: the trial and its perturbed copies (eq. 24), or the accepted x when stopped
        _points(lay, S, X, b, xt[b] if status[b] == RUNNING else x[b], SX, rel)
    _export(state)


def _points(lay, S, X, b, p, SX, rel):
    """Rows b*SX .. of X: the point p and, when SX > 1, its perturbed copies (eq. 24); their
    denominators (over the stored, possibly rounded, points) into den[b]."""
    dt = S.dtype
    P = lay.P
    lo, hi, h, den = (lay.vec(S, o)[b] for o in (lay.lo, lay.hi, lay.h, lay.den))
    p = p.copy()
    rows = X[b * SX : (b + 1) * SX]
    rows[:] = p
    if SX > 1:
        xp, xm = _perturbed(p, lo, hi, h, rel)
        for n in range(P):
            rows[1 + 2 * n, n] = xp[n]
            rows[2 + 2 * n, n] = xm[n]
            den[n] = dt.type(rows[1 + 2 * n, n]) - dt.type(rows[2 + 2 * n, n])
    else:
        den[:] = 0


def _export(state):
    """Out (B, P + 5): x, F, C, status, iterations, reason."""
    lay, S, Out = state.lay, state.S, state.Out
    P = lay.P
    ib = lay.iblock(state.I)
    Out[:, :P] = lay.vec(S, lay.x)
    Out[:, P + LAY.O_F] = lay.sc(S, lay.F)
    Out[:, P + LAY.O_C] = lay.sc(S, lay.C)
    Out[:, P + LAY.O_STATUS] = ib[:, LAY.I_STATUS]
    Out[:, P + LAY.O_ITER] = ib[:, LAY.I_ITER]
    Out[:, P + LAY.O_REASON] = ib[:, LAY.I_REASON]


def _perturbed(p, lo, hi, h, rel):
    eps = np.where(h > 0, h, rel * np.maximum(np.abs(p), 1))
    return np.minimum(p + eps, hi), np.maximum(p - eps, lo)

"""NumPy reference of the batched Levenberg-Marquardt (paper 000 eq. 22-24; paper 003 eq. 8-9).

The solver state is the packed layout of :class:`gputrack.ops.lm.Layout`, read through named
NumPy views so that the math below reads like the paper. Every device backend implements the same
steps in the same order (``solver_update``) in one launch.
"""

from __future__ import annotations

import numpy as np

from ...abi import LMLayout as LAY
from ...abi import LMReason, LMScale, LMStatus

# status / reason codes (gputrack/abi.py)
RUNNING, CONVERGED, MAX_ITER, FAILED = LMStatus.RUNNING, LMStatus.CONVERGED, LMStatus.MAX_ITER, LMStatus.FAILED
R_FTOL, R_XTOL, R_GTOL, R_MAXIT = LMReason.FTOL, LMReason.XTOL, LMReason.GTOL, LMReason.MAX_ITER
R_NONFINITE, R_NOTPD, R_DAMPING = LMReason.NONFINITE, LMReason.NOT_PD, LMReason.DAMPING

MAX_CHOL_TRIES = 40
#: the global slot of S (and K) holding the damping's scaling (gputrack/abi.py LMLayout.G_SCALE): 0 =
#: C I (paper 000 eq. 22), 1 = C diag(J^T J) (Marquardt), 2 = C D with D the running maximum of
#: diag(J^T J) over the iterations (MINPACK's scaling); every backend reads it
G_SCALE = LAY.G_SCALE
SCALE_IDENTITY, SCALE_MARQUARDT, SCALE_MINPACK = (int(m) for m in LMScale)  # gputrack.abi


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


def reads_host(device) -> bool:
    """The solver's callables may hand NumPy arrays straight to this backend (always)."""
    return True


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

    R: residuals of the last call, (B * SR, M) with SR = 2P + 1 (trial point and its copies moved
    by +-eps, central differences, eq. 24), SR = P + 1 (the point and its copies moved by +eps,
    forward differences) or SR = 1 (trial point only; then ``jac`` (B, M, P) is its Jacobian or the
    call was the last one). X: (B * SX, P) receives the next points (SX = 2P + 1, P + 1 or 1).
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
    D = lay.wmat(W, lay.D, 1, P)[:, 0]  # the damping's scale of the last step (scaled modes)
    F, C, nu, pred, Ft, snorm = (lay.sc(S, o) for o in (lay.F, lay.C, lay.nu, lay.pred, lay.Ft, lay.snorm))
    glob = S[lay.glob : lay.glob + lay.NGLOB]
    ftol, xtol, gtol = glob[[LAY.G_FTOL, LAY.G_XTOL, LAY.G_GTOL]]
    rel, ctiny, cmax = glob[[LAY.G_REL, LAY.G_CTINY, LAY.G_CMAX]]
    scale = int(glob[G_SCALE])
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
                # (P, M): r(x + eps e_n) - r(x - eps e_n) (central) or r(x + eps e_n) - r(x) (forward),
                # only where the Jacobian mask is set
                minus = Rb[b, 2::2] if SR == 2 * P + 1 else Rb[b, :1]
                diff = np.where(mask.T != 0, Rb[b, 1 : 2 * P + 1 : 2 if SR == 2 * P + 1 else 1] - minus, 0)
                ok_J = _finite(diff)
                safe = np.where(den[b] != 0, den[b], 1)
                Jt[b] = np.where(den[b][:, None] != 0, diff / safe[:, None], 0)  # eq. 24
            fin[b] = ok_J
        else:
            ok_J = True
        # the norms of the xtol test: plain, or weighted by the last step's damping scale D (as
        # MINPACK's ||D x||; scale-invariant)
        w = D[b] if (scale != SCALE_IDENTITY and not first) else None
        # acceptance of the trial (its cost Ft = sum r^2, eq. 20-21)
        with np.errstate(over="ignore", invalid="ignore"):  # a far trial may overflow: rejected below
            Ft[b] = rt[b] @ rt[b]
        ok = _finite(rt[b]) and ok_J and np.isfinite(Ft[b])
        if first and not ok:
            status[b], reason[b] = FAILED, R_NONFINITE
            F[b] = np.inf  # no finite cost at x0
            continue
        if first:
            acc = True
        else:
            iters[b] += 1
            dF = F[b] - Ft[b]
            acc = ok and dF > 0  # a trial with non-finite residuals or Jacobian is rejected (as MINPACK)
            if acc:
                rho = dF / pred[b] if pred[b] > 0 else 1.0
                C[b] *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)  # Nielsen: lower C near the optimum
                nu[b] = 2.0
            else:
                C[b] *= nu[b]  # rejected: raise this problem's C only
                nu[b] *= 2.0
                if _norm(xt[b] - x[b], w) <= xtol * (xtol + _norm(x[b], w)):
                    status[b], reason[b] = CONVERGED, R_XTOL  # no step this small improves the cost
                elif C[b] > cmax * _cref(A[b], scale):
                    status[b], reason[b] = FAILED, R_DAMPING
                    continue
        if acc:
            accepted[b] = 1
            snorm[b] = _norm(xt[b] - x[b], w)
            F_old = F[b]
            x[b], F[b] = xt[b], Ft[b]
            if not first:
                if F_old - F[b] <= ftol * F_old:
                    status[b], reason[b] = CONVERGED, R_FTOL
                elif snorm[b] <= xtol * (xtol + _norm(x[b], w)):
                    status[b], reason[b] = CONVERGED, R_XTOL
            if have_J:
                A[b] = Jt[b] @ Jt[b].T  # eq. 22: J^T J
                g[b] = Jt[b] @ rt[b]  # eq. 22: J^T r
                if status[b] == RUNNING:
                    # projected gradient: drop components pushing against an active bound (the
                    # step is x - delta, so g > 0 moves down, g < 0 moves up)
                    gp = np.where(((x[b] >= hi[b]) & (g[b] < 0)) | ((x[b] <= lo[b]) & (g[b] > 0)), 0, g[b])
                    if scale != SCALE_IDENTITY:
                        # scaled modes: MINPACK's measure, the cosine of the angle between r and
                        # each column of J, |J_n^T r| / (||J_n|| ||r||) (0 for a zero column)
                        nrm = np.sqrt(np.diag(A[b]) * F[b])
                        gp = np.where(nrm > 0, gp / np.where(nrm > 0, nrm, 1), 0)
                    if np.max(np.abs(gp)) <= gtol:
                        status[b], reason[b] = CONVERGED, R_GTOL
        if final and status[b] == RUNNING:
            status[b], reason[b] = MAX_ITER, R_MAXIT

    if final:
        _export(state)
        return
    for b in range(B):
        if status[b] == RUNNING:
            # parameters held at a bound by the gradient (the step is x - delta) stay there: their
            # rows and columns of the system become the identity, their right-hand side 0
            act = ((x[b] >= hi[b]) & (g[b] < 0)) | ((x[b] <= lo[b]) & (g[b] > 0))
            Ab = np.where(act[:, None] | act[None, :], 0, A[b]) + np.diag(act.astype(dt))
            gb = np.where(act, 0, g[b])
            # the damping's scale: 1 (C I, eq. 22), diag(J^T J) (Marquardt), or its running maximum
            # over the iterations (MINPACK); a zero column gets 1
            dA = np.diag(A[b])
            if scale == SCALE_IDENTITY:
                D[b] = 1.0
            else:
                d = np.maximum(D[b], dA) if (scale == SCALE_MINPACK and iters[b] > 0) else dA
                D[b] = np.where(d > 0, d, 1.0)
            damp = np.where(act, 1.0, D[b])  # held parameters: a unit row, + C
            # damped Cholesky (eq. 22); a failure raises C tenfold and tries again
            cref = _cref(A[b], scale)
            L = cholesky(Ab + C[b] * np.diag(damp))
            tries = 0
            while L is None and tries <= MAX_CHOL_TRIES and C[b] <= cmax * cref:
                C[b] = max(10.0 * C[b], ctiny * cref)
                L = cholesky(Ab + C[b] * np.diag(damp))
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


def _norm(v, w=None):
    """||v||, or with weights w sqrt(sum w v^2)."""
    return np.sqrt(v @ v) if w is None else np.sqrt((w * v) @ v)


def _cref(A, scale):
    """What the damping's limits are relative to: 1 + max diag(J^T J) for C I, 1 when scaled."""
    return 1.0 + np.max(np.diag(A)) if scale == SCALE_IDENTITY else 1.0


def _points(lay, S, X, b, p, SX, rel):
    """Rows b*SX .. of X: the point p and, when SX > 1, its perturbed copies (eq. 24); their
    denominators (over the stored, possibly rounded, points) into den[b]."""
    dt = S.dtype
    P = lay.P
    lo, hi, h, den = (lay.vec(S, o)[b] for o in (lay.lo, lay.hi, lay.h, lay.den))
    p = p.copy()
    rows = X[b * SX : (b + 1) * SX]
    rows[:] = p
    if SX == 2 * P + 1:  # central differences (eq. 24)
        xp, xm = _perturbed(p, lo, hi, h, rel)
        for n in range(P):
            rows[1 + 2 * n, n] = xp[n]
            rows[2 + 2 * n, n] = xm[n]
            den[n] = dt.type(rows[1 + 2 * n, n]) - dt.type(rows[2 + 2 * n, n])
    elif SX > 1:  # forward differences: +eps, or -eps where +eps would leave the box
        eps = _eps(p, h, rel)
        for n in range(P):
            up = p[n] + eps[n]
            rows[1 + n, n] = up if up <= hi[n] else max(p[n] - eps[n], lo[n])
            den[n] = dt.type(rows[1 + n, n]) - dt.type(rows[0, n])
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


def _eps(p, h, rel):
    """The steps: h where given, else rel |p| (rel where p = 0, as MINPACK's fdjac2)."""
    a = np.abs(p)
    return np.where(h > 0, h, rel * np.where(a > 0, a, 1))


def _perturbed(p, lo, hi, h, rel):
    eps = _eps(p, h, rel)
    return np.minimum(p + eps, hi), np.maximum(p - eps, lo)

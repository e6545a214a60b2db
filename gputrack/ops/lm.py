"""Batched small-matrix Levenberg-Marquardt (paper 000 eq. 20-24 and Alg. 2; paper 003 eq. 6-10).

B independent nonlinear least-squares problems with P parameters and M residuals each are
solved together: the residuals of every problem are evaluated in one batched call of the user's
residual function, and the normal equations, the damped Cholesky solve, the acceptance test,
the damping update and the next points to evaluate are computed for every problem in ONE
device launch per iteration.

Ops (one launch each):

- :func:`normal_equations` ``(J (B,M,P), r (B,M)) -> (J^T J (B,P,P), J^T r (B,P))``.
- :func:`lm_step` ``(JtJ, Jtr, damping (B,)) -> (delta (B,P), ok (B,) int32)``: solves
  ``(J^T J + C I) delta = J^T r`` by Cholesky; a problem whose damped matrix is not positive
  definite gets ``ok = 0`` and ``delta = 0`` (never NaN).
- :func:`lm_solve` ``(J, r, damping) -> (delta, ok)``: the two above fused in one launch.

Sign convention (eq. 22): the new point is ``x - delta``.

Solver: :class:`LeastSquaresSolver` (settings checked once, device buffers kept from solve to
solve, damping C I or scale-invariant C diag(J^T J) / MINPACK's running maximum per solver), see
its docstring for the algorithm, the residual-function protocol, bounds, sparsity, precision and
the bad-input policy; :func:`least_squares` is its one-shot form.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import inspect
import logging
import operator
import weakref
from typing import ClassVar

import numpy as np

from ..abi import LMLayout, LMReason, LMScale, LMStatus
from ..device import Device, DeviceArray, as_host_array, foreign_array_error, per_device_cache
from ..profiler import Profiler
from . import backend_module
from ._args import arg, check_device, check_shapes, compact, match_shape, out_arrays, real_array, shape_of

log = logging.getLogger("gputrack")

__all__ = [
    "REASONS",
    "LMStatus",
    "DAMPING_SCALES",
    "LeastSquaresResult",
    "LeastSquaresSolver",
    "least_squares",
    "lm_solve",
    "lm_step",
    "normal_equations",
]

#: relative finite-difference step (of |x|; of 1 where x = 0, as MINPACK's fdjac2) used when
#: ``step=None``, by ``diff`` and precision: cbrt(machine eps) for central differences, sqrt(machine
#: eps) for forward ones, the usual optima (scipy and MINPACK use the same).
DEFAULT_REL_STEP = {
    "central": {"float64": float(np.finfo(np.float64).eps ** (1 / 3)),
                "float32": float(np.finfo(np.float32).eps ** (1 / 3))},
    "forward": {"float64": float(np.finfo(np.float64).eps ** 0.5),
                "float32": float(np.finfo(np.float32).eps ** 0.5)},
}  # fmt: skip
#: residual rows per problem of a finite-difference call, by ``diff``: the point and its copies moved
#: by +eps_n and -eps_n (central, eq. 24), or by +eps_n only (forward). Every backend tells the two
#: apart by the number of rows (2P + 1 > P + 1 > 1 for P >= 1).
DIFF_ROWS = {"central": lambda P: 2 * P + 1, "forward": lambda P: P + 1}

#: a start point within this many units in the last place (of the solver's dtype) of a bound starts
#: on it (:func:`_onto_bounds`)
BOUND_ULPS = 4
#: smallest damping tried after a failed Cholesky, relative to 1 + max diag(J^T J).
_CTINY = {"float64": 1e-12, "float32": 1e-6}
#: damping above which a problem fails (no acceptable step), relative to 1 + max diag(J^T J).
_CMAX = {"float64": 1e16, "float32": 1e10}


Status = LMStatus  # short name inside this module (LMStatus and LMReason: gputrack/abi.py)

#: why a problem stopped (``LeastSquaresResult.reason`` holds these codes; ``REASONS`` the words).
REASONS = {
    LMReason.RUNNING: "running",
    LMReason.FTOL: "ftol: relative cost reduction below ftol",
    LMReason.XTOL: "xtol: relative step below xtol",
    LMReason.GTOL: "gtol: projected gradient below gtol",
    LMReason.MAX_ITER: "max_iter reached",
    LMReason.NONFINITE: "non-finite residuals or Jacobian",
    LMReason.NOT_PD: "damped normal matrix not positive definite at the largest damping",
    LMReason.DAMPING: "no acceptable step: damping overflow",
}


@dataclasses.dataclass
class LeastSquaresResult:
    """Result of :func:`least_squares` (NumPy arrays, downloaded once at the end).

    x (B,P), cost (B,) = sum of squared residuals at x, iterations (B,) = steps tried by each
    problem, status (B,) int8 codes of :class:`LMStatus`, reason (B,) int8 codes of ``REASONS``,
    damping (B,) the final C, nfev = calls of the residual function, njev = calls of the
    Jacobian callable, npoints = points evaluated in all, dtype = the precision the solver ran in,
    x0_clipped (B,) bool = x0 was outside the bounds and was clipped into them.
    """

    x: np.ndarray
    cost: np.ndarray
    iterations: np.ndarray
    status: np.ndarray
    reason: np.ndarray
    damping: np.ndarray
    nfev: int
    njev: int
    npoints: int
    dtype: np.dtype
    x0_clipped: np.ndarray

    @property
    def success(self) -> np.ndarray:
        return self.status == Status.CONVERGED

    def statuses(self) -> list[LMStatus]:
        return [LMStatus(int(s)) for s in self.status]

    def messages(self) -> list[str]:
        return [REASONS[int(r)] for r in self.reason]


# ------------------------------------------------------------------------------------------------
# layout of the packed solver state (shared by every backend; see Layout)


class Layout:
    """Offsets of the solver's arrays for B problems of P parameters and M residuals (from the
    slots of :class:`gputrack.abi.LMLayout`, which every backend's kernels read).

    A solve moves only what carries information. Up: X0 and K (K only when it differs from the
    last K uploaded into the same pooled buffer, see :meth:`_Pool.upload_cached`: a solve with
    the settings of the previous one, e.g. a tracker's next frame, uploads X0 only). Down: Out at
    the end, and with ``early_stop`` the int block I after each iteration. S, W and I live only
    on the device: ``solver_init`` fills S and I from X0 and K in one launch (and writes the first
    points to evaluate), W is written by the iterations before it is read.

    K (float, solver dtype; uploaded, ``k_size()`` values): per problem b a block of
    ``KB = 2P + 1`` values at ``b*KB``: lo[P], hi[P] bounds (clamped to the dtype's finite range),
    c0 initial damping; then h[P] absolute steps (0: relative); then 8 globals ftol, xtol, gtol,
    rel (relative step), ctiny, cmax, scale (the damping's scaling: 0 C I, 1 Marquardt, 2 MINPACK;
    ``G_SCALE`` of the backends), spare; then the Jacobian mask M*P (1.0 where
    computed) when ``has_mask``.

    X0 (B, P) start points (uploaded): float32 when every value is exactly a float32 (a
    tracker's float32 poses), else the solver dtype.

    S (float; device only, ``s_size()`` values): per problem b a block of ``SB = 7P + 8`` values
    at ``b*SB``: x[P] accepted point, xt[P] trial point, g[P] = J^T r at x, den[P]
    finite-difference denominators of the pending points, lo[P], hi[P], h[P] (copied from K),
    then 8 scalars F (cost at x), C (damping), nu (damping growth), pred (predicted reduction of
    the trial), Ft (trial cost), snorm, spare, spare. After the B blocks the 8 globals (copied
    from K); then the mask M*P when ``has_mask``.

    W (float; device only, ``w_size()`` values, allocated once M is known): per problem b a
    block of ``WB = 2 P^2 + P M + P`` values at ``b*WB``: A[P*P] = J^T J at x (both triangles),
    L[P*P] Cholesky factor, Jt[P*M] = J^T at the last evaluated point (rows of J^T contiguous),
    D[P] the damping's scale of the last step (1 for C I; diag(J^T J) or its running maximum).

    I (int32; device only, downloaded whole by each ``early_stop`` check, ``i_size()`` values):
    8 globals [spare, B, has_mask, P, spare...], then per problem ``IB = 4 + P`` values: status,
    iterations, accepted, reason, fin[P] (finite flags of the perturbed rows). The kernels take
    M from the residual array, not from I (I is written before the first call fixes M).

    Out (B, OB = P + 5) (float; downloaded once at the end): x[P], F, C, status, iterations,
    reason of each problem (the codes are small integers, exact in float32); every update
    launch rewrites it, so it is current whenever the loop stops.

    Bytes per solve on a device: up ``X0.nbytes`` + (``k_size() * itemsize`` unless cached)
    (+ with a mask and a residual function taking ``rows``, its two uint8 row masks, (B (2P + 1),
    M) and (B, M), unless cached the same way);
    down ``B * OB * itemsize`` + ``i_size() * 4`` per ``early_stop`` check. Independent of M
    without a mask.
    """

    NSCAL = LMLayout.NSCAL
    NGLOB = LMLayout.NGLOB

    def __init__(self, B: int, P: int, M: int = 0, has_mask: bool = False):
        L = LMLayout
        self.B, self.P, self.M, self.has_mask = B, P, M, bool(has_mask)
        self.x, self.xt, self.g, self.den = L.S_X * P, L.S_XT * P, L.S_G * P, L.S_DEN * P
        self.lo, self.hi, self.h = L.S_LO * P, L.S_HI * P, L.S_H * P
        self.scal = L.S_NVEC * P
        self.F, self.C, self.nu, self.pred, self.Ft, self.snorm = (
            self.scal + i for i in (L.SC_F, L.SC_C, L.SC_NU, L.SC_PRED, L.SC_FT, L.SC_SNORM)
        )
        self.SB = self.scal + self.NSCAL
        self.glob = B * self.SB
        self.mask = self.glob + self.NGLOB
        # W
        self.A, self.L, self.Jt = L.W_A * P * P, L.W_L * P * P, L.W_NSQ * P * P
        self.D = self.Jt + P * M
        self.WB = L.W_NSQ * P * P + P * M + P
        # K
        self.KB = L.K_NVEC * P + 1
        self.kh = B * self.KB
        self.kglob = self.kh + P
        self.kmask = self.kglob + self.NGLOB
        # I, Out
        self.IB = L.I_NFIX + P
        self.ib = L.NIGLOB  # first per-problem int block
        self.OB = P + L.O_N

    def s_size(self) -> int:
        return self.mask + (self.M * self.P if self.has_mask else 0)

    def w_size(self) -> int:
        return self.B * self.WB

    def k_size(self) -> int:
        return self.kmask + (self.M * self.P if self.has_mask else 0)

    def i_size(self) -> int:
        return self.ib + self.B * self.IB

    # NumPy views (used by the reference backend and to pack / unpack on the host)
    def block(self, S: np.ndarray) -> np.ndarray:
        return S[: self.glob].reshape(self.B, self.SB)

    def vec(self, S, off, n=None):
        return self.block(S)[:, off : off + (self.P if n is None else n)]

    def sc(self, S, off):
        return self.block(S)[:, off]

    def wmat(self, W, off, rows, cols):
        return W.reshape(self.B, self.WB)[:, off : off + rows * cols].reshape(self.B, rows, cols)

    def iblock(self, I: np.ndarray) -> np.ndarray:
        return I[self.ib : self.ib + self.B * self.IB].reshape(self.B, self.IB)

    def maskview(self, S):
        return S[self.mask : self.mask + self.M * self.P].reshape(self.M, self.P)

    def kblock(self, K):
        return K[: self.kh].reshape(self.B, self.KB)


# ------------------------------------------------------------------------------------------------
# ops


def _float_dtypes(device):
    return (np.float32, np.float64) if device.fp64 else (np.float32,)


def _arg(device, x, name, spec, dims, dtype):
    """``arg``, with a shortcut for an array already on ``device`` whose dtype is one of ``dtype``
    and whose shape matches ``spec`` (the common case in a loop: ``arg`` takes ~4 us a call on
    taichi:cpu, this ~1 us). Anything else, errors included, goes through ``arg``."""
    if isinstance(x, DeviceArray) and x.device is device and x.dtype in dtype and len(x.shape) == len(spec):
        bound = dict(dims)
        for got, want in zip(x.shape, spec):
            if bound.setdefault(want, got) != got:
                break
        else:
            dims.update(bound)
            return x
    return arg(device, x, name, spec, dims, dtype=dtype)


def normal_equations(device: Device, J, r, *, out=None):
    """J^T J and J^T r for every problem (one launch).

    J: (B, M, P) float32 or float64 (float64 only on a device with fp64); r: (B, M), same dtype.
    Returns (JtJ (B, P, P) symmetric, Jtr (B, P)) on the device, in J's dtype. ``out``: a
    (JtJ, Jtr) pair of arrays on the device to write into (saves the allocations, ~0.2 ms each
    for Taichi ndarrays, in a loop).
    """
    device = check_device(device)
    check_shapes({}, (J, "J", ("B", "M", "P")), (r, "r", ("B", "M")))  # before any value is read
    dims: dict = {}
    J = _arg(device, J, "J", ("B", "M", "P"), dims, _float_dtypes(device))
    r = _arg(device, r, "r", ("B", "M"), dims, (J.dtype,))
    _nonempty(dims, "J")
    out = out_arrays(
        device, out, (("JtJ", (dims["B"], dims["P"], dims["P"]), J.dtype), ("Jtr", (dims["B"], dims["P"]), J.dtype))
    )
    return backend_module(device, "lm").normal_equations(device, J, r, out)


def lm_step(device: Device, JtJ, Jtr, damping, *, out=None):
    """Solve (J^T J + C I) delta = J^T r per problem by Cholesky (eq. 22; new point = x - delta).

    JtJ: (B, P, P) symmetric (the lower triangle is read); Jtr: (B, P); damping: (B,) C >= 0, all
    in one float dtype. Returns (delta (B, P), ok (B,) int32): ok = 0 flags a problem whose damped
    matrix is not positive definite; its delta is 0, never NaN. ``out``: a (delta, ok) pair of
    arrays on the device to write into.
    """
    device = check_device(device)
    _shapes_first(damping, (JtJ, "JtJ", ("B", "P", "P")), (Jtr, "Jtr", ("B", "P")))
    dims: dict = {}
    JtJ = _arg(device, JtJ, "JtJ", ("B", "P", "P"), dims, _float_dtypes(device))
    Jtr = _arg(device, Jtr, "Jtr", ("B", "P"), dims, (JtJ.dtype,))
    damping = _damping_arg(device, damping, dims, JtJ.dtype)
    _nonempty(dims, "JtJ")
    out = out_arrays(device, out, (("delta", (dims["B"], dims["P"]), JtJ.dtype), ("ok", (dims["B"],), np.int32)))
    return backend_module(device, "lm").lm_step(device, JtJ, Jtr, damping, out)


def lm_solve(device: Device, J, r, damping, *, out=None):
    """normal_equations + lm_step fused in one launch: (J (B,M,P), r (B,M), damping (B,)) -> (delta, ok).

    ``out``: a (delta (B, P), ok (B,) int32) pair of arrays on the device to write into.
    """
    device = check_device(device)
    _shapes_first(damping, (J, "J", ("B", "M", "P")), (r, "r", ("B", "M")))
    dims: dict = {}
    J = _arg(device, J, "J", ("B", "M", "P"), dims, _float_dtypes(device))
    r = _arg(device, r, "r", ("B", "M"), dims, (J.dtype,))
    damping = _damping_arg(device, damping, dims, J.dtype)
    _nonempty(dims, "J")
    out = out_arrays(device, out, (("delta", (dims["B"], dims["P"]), J.dtype), ("ok", (dims["B"],), np.int32)))
    return backend_module(device, "lm").lm_solve(device, J, r, damping, out)


def _nonempty(dims, name):
    for k, v in dims.items():
        if v == 0:
            raise ValueError(f"{name}: expected a non-empty {k} dimension, got {k}=0")


def _shapes_first(damping, *args):
    """The shapes of the arrays ``args`` ((x, name, spec) each) and of ``damping`` (a number or
    (B,)), checked before any value is read or converted."""
    dims: dict = {}
    check_shapes(dims, *args)
    if not isinstance(damping, DeviceArray) and shape_of(damping, "damping") == ():
        return
    check_shapes(dims, (damping, "damping", ("B",)))


def _shape_in(value, name, shapes, want):
    """Check that ``value`` has one of ``shapes`` (without converting it), else ValueError."""
    shape = shape_of(value, name)
    if shape not in shapes:
        raise ValueError(f"{name}: expected {want}, got shape {shape}")


def _damping_arg(device, damping, dims, dtype):
    if not isinstance(damping, DeviceArray):
        shape = shape_of(damping, "damping")
        if shape != ():
            match_shape("damping", shape, ("B",), dims)
        d = real_array(damping, "damping").astype(np.float64)
        if d.ndim == 0:
            d = np.full(dims["B"], float(d))
        if d.ndim == 1 and d.shape[0] == dims["B"] and np.isfinite(d).all() and (d < 0).any():
            raise ValueError(f"damping: expected values >= 0, got {d.min()}")
        damping = d.astype(dtype)
    return _arg(device, damping, "damping", ("B",), dims, (np.dtype(dtype),))


# ------------------------------------------------------------------------------------------------
# solver


def _rows_protocol(fn) -> bool:
    """True when ``fn`` accepts a ``rows`` keyword (the sparse evaluation protocol)."""
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False
    p = params.get("rows")
    return p is not None and p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)


def _onto_bounds(x, lo, hi, dtype):
    """``x`` (float64) with every value within BOUND_ULPS units in the last place of ``dtype`` of a
    finite bound moved onto that bound. The kernels hold a parameter at a bound by an exact
    comparison (x >= hi with the gradient pushing up, x <= lo with it pushing down): a start one
    rounding inside a bound (a previous solution scaled back, a running mean clipped) would be a
    free parameter, and its step, clipped back into the box, changes the whole step (a face
    bundle's key-frame depths moved 7.4 instead of 2.8 mm for an identity component 1 ulp inside
    its bound)."""
    tol = BOUND_ULPS * float(np.finfo(dtype).eps)
    with np.errstate(invalid="ignore"):
        on_hi = np.isfinite(hi) & (x >= hi - tol * np.abs(hi))
        on_lo = np.isfinite(lo) & (x <= lo + tol * np.abs(lo))
    return np.where(on_hi, hi, np.where(on_lo, lo, x))


def _bounds(value, name, B, P, dtype, default):
    if value is None:
        return np.full((B, P), default, dtype=np.float64)
    v = real_array(value, name).astype(np.float64, copy=False)
    if v.ndim == 0:
        v = np.full((B, P), float(v))
    elif v.shape == (P,):
        v = np.broadcast_to(v, (B, P))
    elif v.shape != (B, P):
        raise ValueError(f"{name}: expected shape (P={P},) or (B={B}, P={P}), got {v.shape}")
    if np.isnan(v).any():
        raise ValueError(f"{name}: expected numbers or +-inf, got NaN")
    return np.array(v, dtype=np.float64)


#: the damping's scaling (``damping_scale``): the code every backend reads from the solver's globals
DAMPING_SCALES = {m.name.lower(): int(m) for m in LMScale}  # "identity", "marquardt", "minpack"
#: the initial damping C when ``damping=None``: paper 000's 1e-5 for C I; for the scaled modes C is
#: relative to each parameter's own diag(J^T J), and 1e-3 is Nielsen's usual tau
DEFAULT_DAMPING = {"identity": 1e-5, "marquardt": 1e-3, "minpack": 1e-3}
#: the global slot of the solver's packed state holding the scaling (gputrack.abi.LMLayout.G_SCALE)
G_SCALE = LMLayout.G_SCALE


class LeastSquaresSolver:
    """Batched Levenberg-Marquardt for B problems of P parameters, solved again and again.

    ``LeastSquaresSolver(device, (B, P), **settings)`` checks the settings once; each
    :meth:`solve` (residual function, start points, and optionally a Jacobian callable, the
    Jacobian's sparsity, bounds and initial damping) runs on device buffers the solver keeps between solves (its state,
    workspace, points and constants: allocated at the first solve, the constants uploaded again
    only when they change). A tracker holds one solver and calls ``solve`` per frame;
    :func:`least_squares` is the one-shot form (a solver used once, its buffers handed back to the
    device's LM pool for the next). :meth:`close` hands them back early; a solver may not be
    re-entered from its own residual function (a nested solve uses another solver).

    **Settings.** ``step`` (scalar or (P,) absolute finite-difference steps; None: relative, see
    below), ``diff`` (``"central"``, default, or ``"forward"`` differences), ``damping_scale``,
    ``max_iter``, ``ftol``, ``xtol``, ``gtol``, ``dtype``, ``points_dtype``, ``early_stop``: as
    described below. ``profile=True`` times each part of a solve between two device
    synchronisations (``init``, ``residuals``, ``jacobian``, ``update``, ``status`` with
    ``early_stop``, ``result``; a solve is a frame) in ``solver.profiler`` (a
    :class:`gputrack.Profiler`: ``solver.profiler.table()``); the waits slow the solve, so it is
    for finding where the time goes, not for running.

    **Residual function.** ``residuals(X)`` receives an (n, P) array of points — a NumPy array
    on the ``numpy`` device, else a DeviceArray of ``device`` — in ``points_dtype`` (default: the
    solver precision) and returns (n, M) residuals (NumPy or DeviceArray, float32 or float64;
    M is fixed by each solve's first call (by ``jac_sparsity`` when given), M < P is allowed since
    the step is damped). It must not keep or modify X. Without a ``jacobian`` callable each
    iteration makes ONE call with every problem's points stacked, ``2P + 1`` rows per problem:
    row ``b*(2P+1)`` is problem b's point, rows ``b*(2P+1) + 1 + 2n`` and ``+ 2 + 2n`` are it
    with parameter n moved by +eps_n and -eps_n (eq. 24; the Jacobian column is their difference
    over the actual distance between them); with ``diff="forward"`` ``P + 1`` rows per problem:
    the point, then row ``b*(P+1) + 1 + n`` moved by +eps_n (by -eps_n where +eps_n would cross
    the upper bound; the column is the difference with the point's residuals over the distance,
    MINPACK's scheme, half the points for a less accurate Jacobian). The last call of a solve that reaches ``max_iter``
    has only the B points (n = B). ``jacobian(X) -> (B, M, P)`` (a callable given to
    :meth:`solve`) is instead evaluated at the same (B, P) points as ``residuals`` (one call each
    per iteration, n = B).

    **Steps.** ``step=None``: eps_n = rel * |x_n| (rel where x_n = 0, as MINPACK's fdjac2: a
    parameter near 1e-6 gets a step near 1e-6 rel) with rel = cbrt(machine eps) for central
    differences, sqrt(machine eps) for forward ones, of the lower of the solver precision and
    ``points_dtype`` (central 6.1e-6 in float64, 4.9e-3 in float32; forward 1.5e-8 and 3.5e-4: a
    float32 residual function needs the larger step, its rounding would swamp a small one). A
    scalar or (P,) ``step`` gives absolute steps (paper 000's per-parameter constants).

    **Algorithm** (per problem, every problem independently): cost F = sum r^2; J^T J and J^T r
    by eq. 22-24; delta from (J^T J + C D) delta = J^T r by Cholesky, D by ``damping_scale``:

    - ``"identity"``: D = I, paper 000's C I (eq. 22; not scale-invariant: a parameter whose
      columns of J are 1e6 times smaller than another's is barely damped, or barely moved);
    - ``"marquardt"``: D = diag(J^T J) at the current point (Marquardt 1963);
    - ``"minpack"``: D = the running maximum of diag(J^T J) over the problem's iterations, the
      squares of MINPACK's column-norm scaling (More 1978); with either scaled mode the solve is
      invariant to a rescaling of the parameters, and a column that is 0 gets 1.

    A factorisation failure raises C tenfold and retries in the same step (in the same launch,
    or on lavapipe, whose shaders may run only 65535 loop passes each, over a planned number of
    launches with room for 4 retries of the whole factorisation, past which the problem fails as
    not positive definite); trial x_t = clip(x - delta, lower, upper) (projection onto the box,
    paper 003 eq. 8-9). The next call evaluates the residuals at x_t together with the perturbed
    points around x_t (its Jacobian, used if x_t is accepted), so one call and one launch make an
    iteration. x_t is accepted iff its cost is lower than F; the damping follows Nielsen's rule
    with the gain ratio rho = (F - F_t) / predicted reduction: accepted: C *= max(1/3, 1 - (2 rho
    - 1)^3); rejected: C *= nu, nu *= 2. The gain ratio, the damping update, the acceptance and
    every stopping test run on the device. ``damping`` (per :meth:`solve`, scalar or (B,)) is the
    initial C (None: ``DEFAULT_DAMPING``: paper 000's 1e-5 for C I, 1e-3 scaled).

    **Stopping**, per problem: converged when an accepted step reduced the cost by less than
    ``ftol * F``, or moved by less than ``xtol * (xtol + |x|)`` (scaled modes: the norms
    weighted by D, as MINPACK's ||D x||), or the projected gradient (components pushing against an
    active bound removed) has max-norm <= ``gtol`` (scaled modes: MINPACK's
    max_n |J_n^T r| / (||J_n|| ||r||)); max_iter after ``max_iter`` trial steps; failed when its
    residuals or Jacobian (at the start or at a trial) are not finite — the problem keeps its last
    accepted x and cost, the batch goes on — or when the damping needed exceeds 1e16 (float32:
    1e10) x (1 + max diag J^T J) (scaled modes: x 1). The batch stops when every problem has
    stopped. ``iterations`` counts the trial steps each problem evaluated. The last trial of a
    solve that reaches ``max_iter`` is evaluated without its Jacobian, so only ftol and xtol can
    mark it converged.

    **Bounds** (per :meth:`solve`): ``lower``/``upper`` scalar, (P,) or (B, P), +-inf allowed,
    lower == upper fixes a parameter. Perturbed points are clipped into the box too (the
    difference quotient then uses the clipped distance: one-sided at a bound). x0 outside the box
    is clipped into it and flagged in ``x0_clipped`` (logged at INFO); a value of x0 within
    ``BOUND_ULPS`` units in the last place of a bound starts on it (a parameter is held at a bound
    by an exact comparison). lower > upper raises ValueError.

    **Sparsity** (per :meth:`solve`): ``jac_sparsity`` (M, P) bool: J[m, n] is computed only where it is True (paper
    000 Fig. 2), 0 elsewhere. If ``residuals`` has a ``rows`` keyword parameter it is called as
    ``residuals(X, rows=need)`` with ``need`` an (n, M) uint8 array on the device (NumPy for
    numpy; uploaded like the mask: only when it differs from the previous solve's, so the
    function must not modify it): it only has to compute r[i, m] where ``need[i, m]`` is 1
    (point rows: all ones; the rows of parameter n: ``jac_sparsity[:, n]``); other entries are
    ignored and may hold anything. Without a ``rows`` parameter every residual is computed.

    **Precision**: ``dtype`` float64 (default, paper 000 uses double for the differences) runs in
    float64 on a device with fp64 and falls back to float32 (with the larger default step above)
    elsewhere; ``result.dtype`` says which. ``points_dtype=np.float32`` hands float32 points to a
    float32 residual function (the differences are then taken over the rounded points).

    **Traffic**: the solver state and its workspace (J^T J, the Cholesky factor, J^T: O(B P M)
    values) live only on the device and are initialised there; the first points to evaluate are
    computed there too. A solve uploads x0 (B P values, as float32 when that is exact) and the
    constants (bounds, steps, initial damping, tolerances, the Jacobian mask), the constants only
    when they differ from those of the previous solve in the same buffer. Per iteration the
    residual function's output stays on the device (a NumPy output is uploaded, counted) and,
    with ``early_stop`` (default), the small int32 status block (8 + B (P + 4) values) is
    downloaded to decide whether every problem has stopped: with a device residual function that
    is the iteration's one host round trip. With ``solve(..., host=True)`` (NumPy callables) the
    points are handed as NumPy: on taichi:cpu (and the reference) the kernels write them straight
    into a NumPy array the solver holds and read the callables' NumPy results where they are (no
    copy, no per-iteration allocation; the bytes are counted as transfers all the same); on an
    OpenCL device with fine-grained shared virtual memory (PoCL on a CPU) the points are a NumPy
    array in that memory and the kernels read the results through buffers over them (one command
    and one wait an iteration); on the other devices they are downloaded once per residual call (the
    Jacobian call reuses them) into a held host array and the results are uploaded into held
    device buffers (asynchronously on OpenCL). ``early_stop=False`` downloads nothing until the end
    (stopped problems stay frozen on the device; the batch runs ``max_iter`` iterations). The
    result, B (P + 5) values (x, cost, damping, status, iterations, reason), is downloaded once at
    the end. Exact sizes: :class:`Layout`.

    **Bad input**: invalid settings raise ValueError/TypeError here; at :meth:`solve`, NaN/inf in
    x0, a non-float x0, x0 not (B, P), a residual output of the wrong shape or dtype (cannot be
    attributed to one problem) raise ValueError/TypeError; non-finite residuals at the start or
    at a trial point, or a damped J^T J that stays singular, give that problem a FAILED status
    (``reason``) and keep its last finite x. B = 0 returns an empty result without calling
    ``residuals``.
    """

    def __init__(
        self,
        device: Device,
        shape,
        *,
        step=None,
        damping_scale: str = "identity",
        max_iter: int = 10,
        ftol: float = 1e-8,
        xtol: float = 1e-8,
        gtol: float = 1e-8,
        dtype=np.float64,
        points_dtype=None,
        early_stop: bool = True,
        diff: str = "central",
        profile: bool = False,
    ):
        device = check_device(device)
        B, P = _batch_shape(shape)
        if not isinstance(diff, str) or diff not in DIFF_ROWS:
            raise ValueError(f"diff: expected one of {', '.join(map(repr, DIFF_ROWS))}, got {diff!r}")
        if step is not None:
            _shape_in(step, "step", ((), (P,)), f"a positive number or (P={P},) positive numbers")
        if not isinstance(damping_scale, str) or damping_scale not in DAMPING_SCALES:
            raise ValueError(f"damping_scale: expected one of {', '.join(map(repr, DAMPING_SCALES))}, got {damping_scale!r}")
        want = np.dtype(dtype)
        if want not in (np.dtype(np.float32), np.dtype(np.float64)):
            raise TypeError(f"dtype: expected float32 or float64, got {want.name}")
        dt = np.dtype(np.float64) if (want == np.float64 and device.fp64) else np.dtype(np.float32)
        if want == np.float64 and dt != want:
            log.info("least_squares: %s has no float64; running in float32", device.spec)
        pdt = dt if points_dtype is None else np.dtype(points_dtype)
        if pdt not in (np.dtype(np.float32), np.dtype(np.float64)) or (pdt == np.float64 and not device.fp64):
            raise TypeError(f"points_dtype: expected float32{' or float64' if device.fp64 else ''}, got {pdt.name}")
        # the solver's arrays fit the device (the stacked points of a central-difference call the largest)
        device.check_alloc((B * DIFF_ROWS[diff](P), P), pdt)
        if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 0:
            raise ValueError(f"max_iter: expected an int >= 0, got {max_iter!r}")
        for name, v in (("ftol", ftol), ("xtol", xtol), ("gtol", gtol)):
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise TypeError(f"{name}: expected a real number, got {type(v).__name__}")
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"{name}: expected a finite number >= 0, got {v!r}")
        if step is None:
            h = np.zeros(P)
        else:
            h = real_array(step, "step").astype(np.float64)
            if h.ndim == 0:
                h = np.full(P, float(h))
            if h.shape != (P,) or not np.isfinite(h).all() or (h <= 0).any():
                raise ValueError(f"step: expected a positive number or (P={P},) positive numbers, got {np.asarray(step)!r}")
        self.device, self.B, self.P, self.shape, self.dtype, self.points_dtype = device, B, P, (B, P), dt, pdt
        self.damping_scale, self.max_iter, self.early_stop = damping_scale, int(max_iter), bool(early_stop)
        self.diff = diff
        self.tols = (float(ftol), float(xtol), float(gtol))
        self._h = h
        self._be = backend_module(device, "lm")
        self._bufs = _Buffers(device)
        self._busy = False
        self.profiler = Profiler(device) if profile else None

    def __repr__(self):
        return (f"LeastSquaresSolver({self.device.spec}, B={self.B}, P={self.P}, {self.dtype.name}, "
                f"damping_scale={self.damping_scale!r}, max_iter={self.max_iter})")  # fmt: skip

    def close(self) -> None:
        """Hand the solver's device buffers back to the device's LM pool (the next solve takes new ones)."""
        if self._busy:
            raise RuntimeError("LeastSquaresSolver.close: the solver is solving (called from its residual function)")
        self._bufs.release()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def solve(self, residuals, x0, *, jacobian=None, jac_sparsity=None, lower=None, upper=None,
              damping=None, host: bool = False) -> LeastSquaresResult:  # fmt: skip
        """Minimise sum_m r_m(x_b)^2 for the B problems from the start points x0 (B, P) (NumPy, or
        a DeviceArray of the solver's device, downloaded once: the bounds are applied on the host).

        ``jacobian``: None (central differences) or a callable ``jacobian(X) -> (B, M, P)``;
        ``jac_sparsity``: None or the (M, P) bool mask of the Jacobian's entries (central
        differences only; it may change from solve to solve, e.g. with a tracker's template);
        ``lower``, ``upper``: scalar, (P,) or (B, P) bounds; ``damping``: the initial C, scalar or
        (B,) (None: ``DEFAULT_DAMPING[damping_scale]``); ``host``: the callables are host (NumPy)
        functions: they get the points as a NumPy array (the same array for the residual and the
        Jacobian call at the same points; valid during the call only) and return NumPy arrays, which
        the kernels read in place where the device can (taichi:cpu) or which are uploaded into
        buffers the solver holds (see the class docstring, **Traffic**). Returns a
        :class:`LeastSquaresResult`."""
        if self._busy:
            raise RuntimeError("LeastSquaresSolver.solve: expected one solve at a time, got a call from the solver's "
                               "own residual function (use another solver, e.g. least_squares, for a nested solve)")  # fmt: skip
        device, B, P, dt = self.device, self.B, self.P, self.dtype
        device._check_open()
        if not callable(residuals):
            raise TypeError(f"residuals: expected a callable, got {type(residuals).__name__}")
        if jacobian is not None:
            if not callable(jacobian):
                raise TypeError(f"jacobian: expected a callable or None, got {type(jacobian).__name__}")
            if jac_sparsity is not None:
                raise ValueError("jac_sparsity: expected jacobian='central' (a Jacobian callable computes its own entries)")
        x0 = _host_x0(device, x0)
        if x0.shape != (B, P):
            raise ValueError(f"x0: expected shape (B={B}, P={P}), got {x0.shape}")
        _solve_shapes(B, P, damping, lower, upper, jac_sparsity)
        mask = None
        if jac_sparsity is not None:
            mask = np.asarray(jac_sparsity)
            if mask.dtype != np.bool_:
                if mask.dtype.kind in "iu" and mask.size and set(np.unique(mask)) <= {0, 1}:
                    mask = mask.astype(bool)
                else:
                    raise TypeError(f"jac_sparsity: expected a bool array, got dtype {mask.dtype.name}")
            if mask.ndim != 2 or mask.shape[1] != P:
                raise ValueError(f"jac_sparsity: expected shape (M, P={P}), got {mask.shape}")
        if not np.isfinite(compact(x0)).all():
            bad = np.argwhere(~np.isfinite(x0))[0]
            raise ValueError(f"x0: expected finite values, got {x0[tuple(bad)]} at index {tuple(int(i) for i in bad)}")
        if damping is None:
            damping = DEFAULT_DAMPING[self.damping_scale]
        c0 = real_array(damping, "damping").astype(np.float64)
        if c0.ndim == 0:
            c0 = np.full(B, float(c0))
        if c0.shape != (B,) or not np.isfinite(c0).all() or (c0 < 0).any():
            raise ValueError(f"damping: expected a finite number >= 0 or (B={B},) of them, got {np.asarray(damping)!r}")
        lo = _bounds(lower, "lower", B, P, dt, -np.inf)
        hi = _bounds(upper, "upper", B, P, dt, np.inf)
        if (lo > hi).any():
            b, n = (int(i) for i in np.argwhere(lo > hi)[0])
            raise ValueError(f"lower/upper: expected lower <= upper, got lower={lo[b, n]} > upper={hi[b, n]} at [{b}, {n}]")
        x0c = np.clip(x0.astype(np.float64), lo, hi)
        clipped = (x0c != x0).any(axis=1)
        if clipped.any():
            log.info("least_squares: x0 of problems %s was outside the bounds and was clipped",
                     np.flatnonzero(clipped).tolist())  # fmt: skip
        x0c = _onto_bounds(x0c, lo, hi, dt)
        if B == 0:
            e = np.empty(0)
            return LeastSquaresResult(np.empty((0, P), dt), e.astype(dt), e.astype(np.int32), e.astype(np.int8),
                                      e.astype(np.int8), e.astype(dt), 0, 0, 0, dt, e.astype(bool))  # fmt: skip
        self._busy = True
        try:
            with self.profiler.frame() if self.profiler else contextlib.nullcontext():
                return _Run(self, residuals, jacobian, mask, host).run(x0c, lo, hi, c0, clipped)
        finally:
            self._busy = False


def _batch_shape(shape) -> tuple[int, int]:
    try:
        B, P = (operator.index(s) for s in shape)
    except (TypeError, ValueError):
        raise TypeError(f"shape: expected (B, P) integers, got {shape!r}") from None
    if B < 0 or P < 1:
        raise ValueError(f"shape: expected B >= 0 problems of P >= 1 parameters, got {(B, P)}")
    return int(B), int(P)


def _host_x0(device, x0) -> np.ndarray:
    """x0 on the host (a DeviceArray of ``device`` downloaded, counted), a real (B, P) array with P >= 1."""
    if isinstance(x0, DeviceArray):
        if x0.device is not device:
            raise foreign_array_error(x0, device, "x0")
        x0 = x0.numpy()  # B x P values, downloaded once (counted)
    x0 = as_host_array(x0, "x0")
    if x0.dtype.kind not in "fiu":
        raise TypeError(f"x0: expected a float array, got dtype {x0.dtype.name}")
    if x0.ndim != 2:
        raise ValueError(f"x0: expected shape (B, P), got {x0.shape}")
    if x0.shape[1] == 0:
        raise ValueError("x0: expected P >= 1 parameters, got shape (B, 0)")
    return x0


def _solve_shapes(B, P, damping, lower, upper, jac_sparsity=None):
    """The shapes of a solve's array arguments, before any value is read or converted."""
    if jac_sparsity is not None and len(shape_of(jac_sparsity, "jac_sparsity")) == 2:
        check_shapes({}, (jac_sparsity, "jac_sparsity", ("M", P)))
    if damping is not None:
        _shape_in(damping, "damping", ((), (B,)), f"a finite number >= 0 or (B={B},) of them")
    for name, v in (("lower", lower), ("upper", upper)):
        if v is not None:
            _shape_in(v, name, ((), (P,), (B, P)), f"shape (P={P},) or (B={B}, P={P})")


def least_squares(
    residuals,
    x0,
    *,
    device: Device,
    jacobian="central",
    step=None,
    lower=None,
    upper=None,
    damping=None,
    damping_scale: str = "identity",
    max_iter: int = 10,
    ftol: float = 1e-8,
    xtol: float = 1e-8,
    gtol: float = 1e-8,
    dtype=np.float64,
    jac_sparsity=None,
    points_dtype=None,
    early_stop: bool = True,
    host: bool = False,
) -> LeastSquaresResult:
    """Minimise sum_m r_m(x_b)^2 for B problems at once by Levenberg-Marquardt: the one-shot form of
    :class:`LeastSquaresSolver` (its docstring has the algorithm, the residual-function protocol,
    bounds, sparsity, precision, traffic and the bad-input policy).

    Equivalent to ``LeastSquaresSolver(device, x0.shape, step=..., damping_scale=..., max_iter=...,
    ftol=..., xtol=..., gtol=..., dtype=..., points_dtype=..., early_stop=..., diff=...).solve(residuals, x0,
    jacobian=..., jac_sparsity=..., lower=..., upper=..., damping=..., host=...)`` with
    ``jacobian="central"`` or ``"forward"`` (None there, and that ``diff``) or a callable. A loop of
    solves of one shape should hold a solver.
    """
    device = check_device(device)
    if not callable(residuals):
        raise TypeError(f"residuals: expected a callable, got {type(residuals).__name__}")
    central = isinstance(jacobian, str)
    if central and jacobian not in DIFF_ROWS:
        raise ValueError(f"jacobian: expected 'central', 'forward' or a callable, got {jacobian!r}")
    if not central and not callable(jacobian):
        raise TypeError(f"jacobian: expected 'central', 'forward' or a callable, got {type(jacobian).__name__}")
    if not central and jac_sparsity is not None:
        raise ValueError("jac_sparsity: expected jacobian='central' (a Jacobian callable computes its own entries)")
    x0 = _host_x0(device, x0)
    _solve_shapes(*x0.shape, damping, lower, upper, jac_sparsity)  # every array's shape before any value is read
    solver = LeastSquaresSolver(device, x0.shape, step=step, damping_scale=damping_scale, max_iter=max_iter, ftol=ftol,
                                xtol=xtol, gtol=gtol, dtype=dtype, points_dtype=points_dtype,
                                early_stop=early_stop, diff=jacobian if central else "central")  # fmt: skip
    with solver:
        return solver.solve(residuals, x0, jacobian=None if central else jacobian, jac_sparsity=jac_sparsity,
                            lower=lower, upper=upper, damping=damping, host=host)  # fmt: skip


class _Run:
    """One solve of a :class:`LeastSquaresSolver`: residual calls on the host side, one backend
    launch per iteration, on the solver's buffers.

    With ``host`` the callables get NumPy points and give NumPy results: where the backend's
    kernels read and write host memory in place (``reads_host``: the NumPy reference, taichi:cpu,
    OpenCL with fine-grained shared virtual memory) the points are written by the kernels straight
    into a NumPy array the solver holds (``_Buffers.host_array(..., shared=True)``), and the results
    are read where the callable left them (OpenCL: through a buffer over the result; a read-only
    result is copied into shared memory first; the bytes are counted as transfers all the same);
    elsewhere the points are downloaded into a held host array and the results uploaded into held
    device buffers, once each per call."""

    def __init__(self, solver, residuals, jacobian, mask, host=False):
        self.s, self.device, self.fn, self.jac, self.mask = solver, solver.device, residuals, jacobian, mask
        self.B, self.P, self.dt, self.pdt = solver.B, solver.P, solver.dtype, solver.points_dtype
        self.rows_protocol = self.mask is not None and _rows_protocol(residuals)
        self.nfev = self.njev = self.npoints = 0
        self.M = None
        numpy_dev = self.device.backend == "numpy"
        self.host = bool(host) and not numpy_dev
        self.direct = self.host and solver._be.reads_host(self.device)
        self._xh = None  # (device points, host copy) of the last download (host mode, not direct)
        self._keep = []  # host results an asynchronous upload still reads
        self.stage = solver.profiler.stage if solver.profiler else _no_stage

    # -- user calls ------------------------------------------------------------------------------
    def _check_out(self, out, n, what, shape, role):
        dev = self.device
        if isinstance(out, DeviceArray):
            if out.device is not dev:
                raise foreign_array_error(out, dev, what)
        elif type(out) is not np.ndarray:
            out = np.asarray(out)
        if out.dtype not in (np.dtype(np.float32), np.dtype(np.float64)):
            raise TypeError(f"{what}: expected a float32 or float64 result, got dtype {out.dtype.name}")
        if tuple(out.shape) != shape:
            want = ", ".join(str(s) for s in shape)
            raise ValueError(f"{what}: expected a result of shape ({want}), got {tuple(out.shape)}")
        if isinstance(out, DeviceArray):
            return out
        if out.dtype == np.float64 and not dev.fp64:
            out = out.astype(np.float32)
        if dev.backend == "numpy":
            return np.ascontiguousarray(out)
        if self.direct:  # the kernels read it where it is (counted as an upload)
            out = np.ascontiguousarray(out)
            dev.transfers.h2d += out.nbytes
            return out
        if self.host:  # into a buffer the solver holds, asynchronously where the backend can
            out = np.ascontiguousarray(out)
            self._keep.append(out)
            return self.s._bufs.upload(role, out, asynchronous=True)
        return dev.asarray(out)

    def _points(self, X, fresh=True):
        """The points handed to the callables: X itself, or in host mode (not direct) its host copy,
        downloaded by each residual call (``fresh``) and reused by the Jacobian call after it."""
        if not self.host or self.direct:
            return X
        if fresh or self._xh is None or self._xh[0] is not X:
            self._keep.clear()  # the download waits for every upload before it (one in-order queue)
            self._xh = (X, self.s._bufs.download(f"Xh{X.shape[0]}", X))
        return self._xh[1]

    def _call(self, X, need):
        with self.stage("residuals"):  # the points' download, the call, its result's upload
            return self._residuals(X, need)

    def _residuals(self, X, need):
        n = X.shape[0]
        self.nfev += 1
        self.npoints += n
        Xc = self._points(X)
        out = self.fn(Xc, rows=need) if (need is not None) else self.fn(Xc)
        if self.M is None:
            shp = getattr(out, "shape", None)
            if shp is None:
                out = np.asarray(out)
                shp = out.shape
            if len(shp) != 2 or shp[0] != n:
                raise ValueError(f"residuals: expected a result of shape (n={n}, M), got {tuple(shp)}")
            if shp[1] == 0:
                raise ValueError(f"residuals: expected M >= 1 residuals, got shape {tuple(shp)}")
            self.M = int(shp[1])
            if self.mask is not None and self.mask.shape[0] != self.M:
                raise ValueError(f"jac_sparsity: expected shape (M={self.M}, P={self.P}), got {self.mask.shape}")
        return self._check_out(out, n, "residuals", (n, self.M), f"R{n}")

    def _call_jac(self, X):
        self.njev += 1
        with self.stage("jacobian"):
            out = self.jac(self._points(X, fresh=False))
            return self._check_out(out, X.shape[0], "jacobian", (self.B, self.M, self.P), "J")

    # -- loop ------------------------------------------------------------------------------------
    def run(self, x0, lo, hi, c0, clipped):
        s = self.s
        B, P, be, dt, bufs = self.B, self.P, s._be, self.dt, s._bufs
        max_iter = s.max_iter
        central = self.jac is None
        S_rows = (DIFF_ROWS[s.diff](P)) if central else 1
        mask = self.mask
        lay = Layout(B, P, mask.shape[0] if mask is not None else 0, mask is not None)
        K = _constants(lay, lo, hi, s._h, c0, s.tols, dt, self.pdt, mask, DAMPING_SCALES[s.damping_scale],
                       s.diff if central else "central")  # fmt: skip
        x0_32 = x0.astype(np.float32)
        x0_up = x0_32 if np.array_equal(x0_32, x0) else x0.astype(dt)  # float32 when exact
        K_d = bufs.upload_cached("K", K)
        X0_d = bufs.upload("X0", x0_up)
        points = functools.partial(bufs.host_array, shared=True) if self.direct else bufs.empty
        X_full = points("X", (B * S_rows, P), self.pdt)
        X_last = X_full if S_rows == 1 else points("X_last", (B, P), self.pdt)
        state = be.solver_state(self.device, lay, bufs.empty("S", (lay.s_size(),), dt),
                                bufs.empty("I", (lay.i_size(),), np.int32), bufs.empty("Out", (B, lay.OB), dt))  # fmt: skip
        need_full = need_last = None
        if self.rows_protocol:
            need_host = self._need(S_rows)
            if self.host:
                need_full, need_last = need_host
            else:
                need_full, need_last = (bufs.upload_cached(f"need{i}", a) for i, a in enumerate(need_host))
        # the first points: x0 (and the perturbed points around it), written on the device
        first_X, first_need = (X_full, need_full) if max_iter > 0 else (X_last, need_last)
        with self.stage("init"):
            be.solver_init(state, X0_d, K_d, first_X)
        if self.direct:
            self.device.transfers.d2h += first_X.nbytes
        R = self._call(first_X, first_need)  # fixes M
        lay = Layout(B, P, self.M, mask is not None)
        be.solver_workspace(state, lay, bufs.empty("W", (lay.w_size(),), dt))
        Jg = self._call_jac(first_X) if not central else None
        for it in range(max_iter + 1):
            final = it == max_iter
            nxt = X_last if it == max_iter - 1 else X_full
            with self.stage("update"):
                be.solver_update(state, R, nxt, first=(it == 0), final=final, jac=Jg)
            if final:
                break
            if s.early_stop:
                with self.stage("status"):
                    active = be.solver_active(state)
                if active == 0:
                    break
            if self.direct:
                self.device.transfers.d2h += nxt.nbytes
            R = self._call(nxt, need_last if (nxt is X_last and S_rows > 1) else need_full)
            if not central and it < max_iter - 1:  # the final update reads no Jacobian (given the last)
                Jg = self._call_jac(nxt)
        with self.stage("result"):
            out = be.solver_result(state)  # (B, OB): x, F, C, status, iterations, reason
        self._keep.clear()
        L = LMLayout
        status = out[:, P + L.O_STATUS].astype(np.int8)
        status[status == Status.RUNNING] = Status.MAX_ITER  # stopped early only when none is running
        reason = out[:, P + L.O_REASON].astype(np.int8)
        reason[(reason == LMReason.RUNNING)] = LMReason.MAX_ITER
        return LeastSquaresResult(
            x=out[:, :P].astype(dt, copy=True),
            cost=out[:, P + L.O_F].astype(dt, copy=True),
            iterations=out[:, P + L.O_ITER].astype(np.int32),
            status=status,
            reason=reason,
            damping=out[:, P + L.O_C].astype(dt, copy=True),
            nfev=self.nfev,
            njev=self.njev,
            npoints=self.npoints,
            dtype=dt,
            x0_clipped=clipped,
        )

    def _need(self, S_rows):
        """The (n, M) uint8 row masks handed to a residual function with a ``rows`` parameter."""
        mask = self.mask
        M, B = mask.shape[0], self.B
        block = np.ones((S_rows, M), np.uint8)
        if S_rows == 2 * self.P + 1:  # central: the rows of parameter n are 1 + 2n and 2 + 2n
            block[1::2] = mask.T
            block[2::2] = mask.T
        else:  # forward: row 1 + n
            block[1:] = mask.T
        return np.tile(block, (B, 1)), np.ones((B, M), np.uint8)


def _no_stage(name):
    """The stage of a solver without a profiler: nothing recorded."""
    return contextlib.nullcontext()


_HOST_KINDS = ("host", "shared")  # held NumPy arrays (_Buffers.host_array), never in the device pool


class _Buffers:
    """The device buffers of one :class:`LeastSquaresSolver`, by role (state, workspace, points,
    constants, ...): taken at first use from the device's LM pool (or allocated), kept between
    solves, handed back to the pool by :meth:`release` (a one-shot :func:`least_squares` releases
    at its end, so the next one reuses them; a nested solve takes buffers of its own).

    Allocating a Taichi ndarray costs ~0.5 ms, a solve needs seven. Uploads into a reused buffer
    are counted in ``device.transfers`` like any other. The pool keeps at most ``POOL_MAX`` buffers
    per device, the least recently returned sizes dropped first: a solver whose residual count
    changes from call to call (a tracker's template of N + N' points) holds only its current sizes.
    """

    POOL_MAX = 32
    _free: ClassVar[weakref.WeakKeyDictionary] = per_device_cache()  # device -> {key: [arrays]}, oldest first
    _sent: ClassVar[weakref.WeakKeyDictionary] = per_device_cache()  # cached uploads

    def __init__(self, device):
        self.device = device
        self.held: dict = {}  # role -> (key, array)

    def _take(self, role, shape, dtype, kind="work"):
        dev = self.device
        key = (kind, tuple(shape), np.dtype(dtype))  # a dtype, not its name: NumPy builds .name on each read
        have = self.held.get(role)
        if have is not None and have[0] == key:
            return have[1]
        free = self._free.setdefault(dev, {})
        if have is not None and have[0][0] not in _HOST_KINDS:  # another size: back to the pool
            self._give_back(free, *have)
        avail = free.get(key)
        arr = avail.pop() if avail else dev.empty(shape, dtype)
        if avail == []:
            del free[key]
        self.held[role] = (key, arr)
        return arr

    def _give_back(self, free: dict, key, arr):
        """``arr`` into the pool (its size the most recent), then the oldest sizes dropped beyond POOL_MAX."""
        free[key] = [*free.pop(key, []), arr]
        n = sum(len(v) for v in free.values())
        sent = self._sent.get(self.device, {})
        while n > self.POOL_MAX:
            oldest = next(iter(free))
            dropped = free[oldest].pop(0)
            sent.pop(id(dropped), None)  # its host copy goes too (it holds a reference to the buffer)
            if not free[oldest]:
                del free[oldest]
            n -= 1

    def empty(self, role, shape, dtype):
        if self.device.backend == "numpy":
            return np.empty(shape, dtype)
        return self._take(role, shape, dtype)

    def upload(self, role, host, asynchronous=False):
        """``host`` into the buffer of ``role`` (counted). ``asynchronous``: the copy may still be
        reading ``host`` when this returns (the caller keeps it until a download orders the queue)."""
        dev = self.device
        if dev.backend == "numpy":
            return host
        arr = self._take(role, host.shape, host.dtype)
        backend_module(dev, "lm").upload_into(dev, arr, np.ascontiguousarray(host), asynchronous)
        dev.transfers.h2d += host.nbytes
        return arr

    def host_array(self, role, shape, dtype, shared=False):
        """A NumPy array of ``role`` kept between solves; ``shared``: one the backend's kernels read
        and write in place (the points where the backend ``reads_host``; its ``shared_empty`` where
        it has one)."""
        key = ("shared" if shared else "host", tuple(shape), np.dtype(dtype))
        have = self.held.get(role)
        if have is None or have[0] != key:
            alloc = getattr(backend_module(self.device, "lm"), "shared_empty", None) if shared else None
            have = (key, alloc(self.device, shape, dtype) if alloc else np.empty(shape, dtype))
            self.held[role] = have
        return have[1]

    def download(self, role, arr):
        """``arr`` (a device array) into the host array of ``role`` (counted); returns the host array."""
        host = self.host_array(role, arr.shape, arr.dtype)
        backend_module(self.device, "lm").download_into(self.device, arr, host)
        self.device.transfers.d2h += host.nbytes
        return host

    def upload_cached(self, role, host):
        """Like :meth:`upload`, but skips the copy when the buffer already holds ``host``.

        Buffers for cached uploads come from their own free list (never written by a kernel);
        each remembers the host copy it was last given. A solve with the same shapes and the same
        constants as an earlier one (of this solver, or of a one-shot solve before it on this
        device) then uploads nothing for them.
        """
        dev = self.device
        if dev.backend == "numpy":
            return host
        host = np.ascontiguousarray(host)
        arr = self._take(role, host.shape, host.dtype, "cached")
        sent = self._sent.setdefault(dev, {})
        prev = sent.get(id(arr))
        if prev is not None and prev[0] is arr and np.array_equal(prev[1], host):
            return arr
        backend_module(dev, "lm").upload_into(dev, arr, host)
        dev.transfers.h2d += host.nbytes
        sent[id(arr)] = (arr, host.copy())
        return arr

    def release(self):
        held, self.held = self.held, {}
        if self.device.backend == "numpy" or self.device.closed:
            return
        free = self._free.setdefault(self.device, {})
        for key, arr in held.values():
            if key[0] not in _HOST_KINDS:
                self._give_back(free, key, arr)


def _rel_step(dt, pdt=None, diff="central") -> float:
    """Default relative step (``DEFAULT_REL_STEP``) of the lower of the solver and the points precision."""
    low = np.float32 if np.float32 in (np.dtype(dt), np.dtype(pdt or dt)) else np.float64
    return DEFAULT_REL_STEP[diff][np.dtype(low).name]


def _constants(lay, lo, hi, h, c0, tols, dt, pdt=None, mask=None, scale=0, diff="central"):
    """The constants array K of a solve (see :class:`Layout`), on the host."""
    L = LMLayout
    K = np.zeros(lay.k_size(), dtype=dt)
    kb = lay.kblock(K)
    P = lay.P
    kb[:, L.K_LO * P : (L.K_LO + 1) * P] = np.maximum(lo, np.finfo(dt).min)
    kb[:, L.K_HI * P : (L.K_HI + 1) * P] = np.minimum(hi, np.finfo(dt).max)
    kb[:, L.K_NVEC * P] = c0
    K[lay.kh : lay.kh + P] = h
    glob = K[lay.kglob : lay.kglob + lay.NGLOB]
    glob[[L.G_FTOL, L.G_XTOL, L.G_GTOL]] = tols
    glob[[L.G_REL, L.G_CTINY, L.G_CMAX]] = (_rel_step(dt, pdt, diff), _CTINY[dt.name], _CMAX[dt.name])
    glob[G_SCALE] = scale  # the damping's scaling (DAMPING_SCALES)
    if mask is not None:
        K[lay.kmask : lay.kmask + lay.M * P] = np.asarray(mask, dtype=dt).ravel()
    return K

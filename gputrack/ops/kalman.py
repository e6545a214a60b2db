"""Batched Kalman filters: every track of a tracker predicted, updated and gated in one call.

Papers 001 (groups, stereo EKF, eq. 1-8) and 002 (pedestrians, occlusion-adaptive gain, eq. 4-6)
run one Kalman filter per tracked object; these ops update all T tracks at once. Shapes (T tracks,
state size n, observation size m, D detections)::

    x (T,n)   P (T,n,n)   F, Q (n,n) shared or (T,n,n) per track
    z (T,m)   H (m,n) or (T,m,n)   R (m,m) or (T,m,m)   mask (T,) bool   gain_scale (T,)

Everything is float32 by default; float64 works where the device has it (the dtype of ``x``
decides; NumPy inputs of another float dtype are converted to it, device arrays must match).

Results: :func:`kf_predict` returns ``(x, P)``; :func:`kf_update` and :func:`ekf_update_stereo`
return a :class:`KalmanState` ``(x, P, status)`` with a per-track ``status`` (uint8,
:class:`KalmanStatus`): 0 UPDATED, 1 SKIPPED (mask False or a non-finite observation), 2 NOT_PD
(the innovation covariance S is not positive definite), 3 BAD_DEPTH (stereo: predicted z <= 0).
Every track whose status is not UPDATED is returned exactly as it came in (after the prediction,
when ``predict=`` is given). Arrays are DeviceArrays on a device, NumPy arrays on ``numpy``.

Numerics (identical on every backend):

- P and R are symmetrised, (A + A^T)/2, before use; returned covariances are exactly symmetric.
- S = H P H^T + R is factorised by Cholesky (S = L L^T); the gain comes from two triangular
  solves, K^T = S^-1 (H P), never from an inverse. A pivot d_j <= 4 eps S_jj (eps of the dtype)
  marks S as not positive definite (status NOT_PD, track unchanged).
- Covariance update in Joseph form, P+ = (I - K H) P (I - K H)^T + K R K^T: it stays symmetric
  positive semi-definite and is the exact covariance for any gain, so with ``gain_scale`` s
  (paper 002: trust strongly occluded, shrunken segments less) the gain is s K and the same
  formula gives the consistent covariance: s = 0 returns the prediction unchanged, s = 1 the
  plain update. NumPy ``gain_scale`` must be >= 0 (device arrays are not inspected; the
  covariance stays positive semi-definite for any s).
- Observations: NaN (or any non-finite value) in a row of z means "missing": that track is
  SKIPPED. NumPy observations with +-inf are rejected (ValueError); device arrays are not
  inspected on the host.
- ``predict=(F, Q)`` on an update runs the prediction first in the same launch (one kernel
  instead of two; equal to kf_predict followed by the update). Masked tracks are then predicted
  only, as paper 001 does for a tracker with fewer than 2 observations.
- ``out=`` (optional, on updates and kf_predict): arrays of the device to write the results
  into instead of allocating new ones, ``(x, P)`` or ``(x, P, status)``; they may be the input
  x and P themselves (an in-place update: each track reads its own inputs before it writes).
  Allocating fresh outputs costs real time on some backends (a (1e5,6,6) Taichi ndarray is
  ~6 ms on a 2-core CPU), so a tracker that keeps its state on the device passes ``out``.
- Shared model matrices: the device kernels skip the known zero entries of a shared F, Q, H
  and R (the constant-velocity F and Q, a selection H and a diagonal R are mostly zeros). They know them for a NumPy
  matrix, which is uploaded on every call, and for a :class:`SharedMatrix` from
  :func:`shared_matrix` (uploaded once, zero pattern recorded); a plain DeviceArray is treated
  as dense. Each zero pattern compiles its own kernel variant.
- Empty batches (T = 0, D = 0) return empty results of the right shapes (``out`` is then
  returned as it is).
- Steady state: a call whose array arguments are all arrays of the device (or SharedMatrix
  objects) is validated once per signature (device, shape, dtype, zero pattern of each argument);
  later calls with the same signature, e.g. a tracker's in-place update every frame, go straight
  to the backend. Host (NumPy) arguments are validated on every call.

Sizes: 1 <= n <= MAX_N and 1 <= m <= MAX_M (the device kernels unroll the small matrix algebra
for the n and m of each call and compile once per combination).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..abi import KalmanStatus
from ..device import DeviceArray
from . import backend_module
from ._args import FLOAT, arg, check_device, check_shapes, compact, out_arrays, real, shape_of

__all__ = [
    "KalmanState",
    "KalmanStatus",
    "SharedMatrix",
    "constant_velocity",
    "ekf_update_stereo",
    "kf_predict",
    "kf_update",
    "mahalanobis",
    "shared_matrix",
]

MAX_N = 12
MAX_M = 6


class KalmanState(NamedTuple):
    """Result of an update: state x (T,n), covariance P (T,n,n), status (T,) uint8 (KalmanStatus)."""

    x: object
    P: object
    status: object


class SharedMatrix(NamedTuple):
    """A shared model matrix uploaded once, with the bitmask of its non-zero entries (row-major).

    Made by :func:`shared_matrix`; accepted wherever F, Q, H or R is. The kernels skip the
    entries the pattern marks zero, so the device array's zero entries must stay zero.
    """

    array: object
    pattern: int


def shared_matrix(device, A, dtype=np.float32) -> SharedMatrix:
    """Upload the shared (r,c) NumPy matrix ``A`` to ``device`` once and record its zero pattern."""
    device = check_device(device)
    if hasattr(A, "buffer"):
        raise TypeError("A: expected a NumPy matrix (its zero pattern is read on the host), got a DeviceArray")
    host = np.asarray(A)
    if host.dtype.kind not in "biuf":
        raise TypeError(f"A: expected a real matrix, got dtype {host.dtype.name}")
    if host.ndim != 2:
        raise ValueError(f"A: expected a shared (rows, cols) matrix, got shape {host.shape}")
    if not np.isfinite(host).all():
        raise ValueError("A: expected finite values")
    host = np.ascontiguousarray(host, dtype=dtype)
    bits = 0
    for i, k in zip(*np.nonzero(host)):
        bits |= 1 << (int(i) * host.shape[1] + int(k))
    return SharedMatrix(device.asarray(host), bits)


def constant_velocity(dim: int = 3, dt: float = 1.0, q=1.0, dtype=np.float32):
    """F and Q (2 dim x 2 dim) of the constant-velocity model (paper 001 eq. 1-3).

    State order [x xdot y ydot z zdot] (``dim`` axes, position then velocity per axis); F has the
    block [[1, dt], [0, 1]] per axis (eq. 3 with dt = 1). Q is the discrete white-noise
    acceleration model: per axis Q = q G G^T with G = [dt^2/2, dt]^T (the Gamma of eq. 2), i.e.
    q [[dt^4/4, dt^3/2], [dt^3/2, dt^2]]; ``q`` is the acceleration variance, a scalar or one
    value per axis. Returns NumPy arrays of ``dtype``.
    """
    if not isinstance(dim, (int, np.integer)) or isinstance(dim, bool) or dim < 1:
        raise ValueError(f"dim: expected a positive integer, got {dim!r}")
    dt = float(dt)
    if not np.isfinite(dt) or dt <= 0:
        raise ValueError(f"dt: expected a positive finite time step, got {dt}")
    qa = np.broadcast_to(np.asarray(q, dtype=np.float64), (dim,)) if np.ndim(q) == 0 else np.asarray(q, np.float64)
    if qa.shape != (dim,):
        raise ValueError(f"q: expected a scalar or {dim} values (one per axis), got shape {np.shape(q)}")
    if not (np.isfinite(qa).all() and (qa >= 0).all()):
        raise ValueError(f"q: expected finite non-negative acceleration variances, got {qa.tolist()}")
    F = np.eye(2 * dim)
    Q = np.zeros((2 * dim, 2 * dim))
    G = np.array([dt * dt / 2.0, dt])
    for a in range(dim):
        F[2 * a, 2 * a + 1] = dt  # eq. 3
        Q[2 * a : 2 * a + 2, 2 * a : 2 * a + 2] = qa[a] * np.outer(G, G)  # eq. 2: Gamma w
    return F.astype(dtype), Q.astype(dtype)


# -- validation ------------------------------------------------------------------------------------
def _arg(device, a, name, shape=None, dims=None, *, dtype=np.float32, **kw):
    """``arg`` with a fast path for an array already on ``device`` with an accepted dtype and the
    expected shape (the common case of a tracker's per-frame call); anything else goes to
    ``arg``, which validates and reports."""
    if type(a) is DeviceArray and a.device is device and shape is not None:
        accepted = dtype if isinstance(dtype, tuple) else (dtype,)
        if a.dtype in accepted and len(a.shape) == len(shape):
            for got, want in zip(a.shape, shape):
                if isinstance(want, str):
                    if want not in dims:
                        dims[want] = got
                    elif dims[want] != got:
                        break
                elif want is not None and want != got:
                    break
            else:
                return a
    return arg(device, a, name, shape, dims, dtype=dtype, **kw)


def _state(device, x, P, dims):
    x = _arg(device, x, "x", ("T", "n"), dims, dtype=FLOAT)
    dt = x.dtype
    n = dims["n"]
    if not 1 <= n <= MAX_N:
        raise ValueError(f"x: expected a state size n between 1 and {MAX_N}, got n={n}")
    P = _arg(device, P, "P", ("T", "n", "n"), dims, dtype=dt, cast=True)
    return x, P, dt


def _matrix(device, A, name, rows, cols, dims, dt):
    """A shared (rows, cols) matrix or a per-track (T, rows, cols) one."""
    if isinstance(A, SharedMatrix):
        return _arg(device, A.array, name, (rows, cols), dims, dtype=dt, cast=True)
    nd = getattr(A, "ndim", None)
    if nd is None:
        nd = np.ndim(A)
    if nd == 3:
        return _arg(device, A, name, ("T", rows, cols), dims, dtype=dt, cast=True)
    if nd == 2:
        return _arg(device, A, name, (rows, cols), dims, dtype=dt, cast=True)
    shape = getattr(A, "shape", np.shape(A))
    want = f"({rows}={dims.get(rows, '?')}, {cols}={dims.get(cols, '?')})"
    raise ValueError(f"{name}: expected shape {want} shared or (T={dims['T']}, ...) per track, got {tuple(shape)}")


def _shapes_first(x, P, *, z=None, z_spec=("T", "m"), H=None, R=None, mask=None, gain_scale=None, predict=None,
                  F=None, Q=None, m=None):
    """Check every argument's shape, in the order the op validates them, before any value is read
    or converted (a wrong-shaped argument, e.g. a broadcast view of 2**32 rows, is reported at once,
    without validating the others first). A matrix of an unexpected rank is left to _matrix."""
    dims: dict = {} if m is None else {"m": m}
    check_shapes(dims, (x, "x", ("T", "n")), (P, "P", ("T", "n", "n")), (z, "z", z_spec))
    if isinstance(predict, (tuple, list)) and len(predict) == 2:
        F, Q = predict
    mats = ((H, "H", "m", "n"), (R, "R", "m", "m"), (F, "F", "n", "n"), (Q, "Q", "n", "n"))
    opts = ((mask, "mask"), (gain_scale, "gain_scale"))
    for A, name, rows, cols in mats[:2]:
        _shape_of_matrix(dims, A, name, rows, cols)
    check_shapes(dims, *((a, name, ("T",)) for a, name in opts))
    for A, name, rows, cols in mats[2:]:
        _shape_of_matrix(dims, A, name, rows, cols)


def _shape_of_matrix(dims, A, name, rows, cols):
    if A is None:
        return
    a = A.array if isinstance(A, SharedMatrix) else A
    nd = len(shape_of(a, name))
    if nd in (2, 3):
        check_shapes(dims, (a, name, ("T", rows, cols) if nd == 3 else (rows, cols)))


def _host(a):
    """``a`` as a NumPy array if it is host data (not a DeviceArray), else None."""
    if a is None or hasattr(a, "buffer"):
        return None
    h = np.asarray(a)
    return h if h.dtype.kind in "biuf" else None


def _observations(device, z, dims, dt):
    h = _host(z)
    if h is not None and np.isinf(compact(h)).any():
        h = compact(h)
        bad = np.argwhere(np.isinf(h))[0]
        raise ValueError(
            f"z: expected finite values or NaN (missing), got {h[tuple(bad)]} at index {tuple(int(i) for i in bad)}"
        )
    z = _arg(device, z, "z", ("T", "m"), dims, dtype=dt, cast=True, finite=False)
    m = dims["m"]
    if not 1 <= m <= MAX_M:
        raise ValueError(f"z: expected an observation size m between 1 and {MAX_M}, got m={m}")
    return z


def _options(device, mask, gain_scale, predict, dims, dt):
    if mask is not None:
        mask = _arg(device, mask, "mask", ("T",), dims, dtype=np.uint8, cast=True)
    if gain_scale is not None:
        h = _host(gain_scale)
        if h is not None and h.ndim == 1 and (h < 0).any():
            i = int(np.argmax(h < 0))
            raise ValueError(f"gain_scale: expected values >= 0, got {h[i]} at index {i}")
        gain_scale = _arg(device, gain_scale, "gain_scale", ("T",), dims, dtype=dt, cast=True)
    F = Q = None
    if predict is not None:
        if not isinstance(predict, (tuple, list)) or len(predict) != 2:
            raise TypeError(f"predict: expected a pair (F, Q) or None, got {type(predict).__name__}")
        F = _matrix(device, predict[0], "F", "n", "n", dims, dt)
        Q = _matrix(device, predict[1], "Q", "n", "n", dims, dt)
    return mask, gain_scale, F, Q


def _outputs(device, out, dims, dt, with_status):
    """Caller-provided output arrays (x, P[, status]: exact shape and dtype, on the device), or None."""
    want = [("x", (dims["T"], dims["n"]), dt), ("P", (dims["T"], dims["n"], dims["n"]), dt)]
    if with_status:
        want.append(("status", (dims["T"],), np.dtype(np.uint8)))
    return out_arrays(device, out, want, allocate=False)


def _pattern(A, cols):
    """Bitmask of the non-zero entries of a shared host matrix or a SharedMatrix (the device
    kernels skip the zeros); -1 where unknown (device arrays, per-track matrices, None)."""
    if isinstance(A, SharedMatrix):
        shape = tuple(A.array.shape)
    elif isinstance(A, np.ndarray) and A.ndim == 2:
        shape = A.shape
    else:
        return -1
    if len(shape) != 2 or shape[1] != cols or shape[0] > MAX_N:
        return -1  # a shape error is reported by _matrix (checked before the zero pattern is read)
    if isinstance(A, SharedMatrix):
        bits = int(A.pattern)
    else:
        bits = 0
        for i, k in zip(*np.nonzero(A)):
            bits |= 1 << (int(i) * cols + int(k))
    return -1 if bits == (1 << (shape[0] * shape[1])) - 1 else bits  # dense: the same variant as a DeviceArray


def _patterns(predict, H, R, dims):
    """(F, Q, H, R) zero patterns for the kernels (see _pattern)."""
    F = Q = None
    if isinstance(predict, (tuple, list)) and len(predict) == 2:
        F, Q = predict
    n, m = dims["n"], dims["m"]
    return (_pattern(F, n), _pattern(Q, n), _pattern(H, n), _pattern(R, m))


def _empty_state(device, dims, dt, with_status=True, out=None):
    if out is not None:
        return KalmanState(*out) if with_status else tuple(out)
    T, n = dims["T"], dims["n"]
    x, P = device.empty((T, n), dt), device.empty((T, n, n), dt)
    return KalmanState(x, P, device.empty((T,), np.uint8)) if with_status else (x, P)


# -- steady-state fast path -----------------------------------------------------------------------
# A tracker calls the same op every frame with the same device-resident arrays. For arrays
# already on the device the validation above depends only on their device, shape and dtype (and
# on a SharedMatrix's pattern), so the outcome of a validated call is remembered under that
# signature: a later call with the same signature skips straight to the backend. NumPy inputs
# (whose values are checked) and empty batches always take the full path.
class _Slow(Exception):
    """An argument the fast path does not cover (host data, a bad type): validate in full."""


def _sig(a):
    t = type(a)
    if t is DeviceArray:
        return (a.device, a.shape, a.dtype)
    if a is None:
        return None
    if t is SharedMatrix and type(a.array) is DeviceArray:
        return (a.array.device, a.array.shape, a.array.dtype, a.pattern)
    raise _Slow


def _sigs(items):
    if items is None:
        return None
    if type(items) not in (tuple, list):
        raise _Slow
    return tuple(_sig(a) for a in items)


def _raw(a):
    """The device array of a validated argument (a SharedMatrix's array)."""
    return a.array if type(a) is SharedMatrix else a


_FAST: dict = {}  # (op, device, argument signatures) -> (backend module, pats)


def _fast(key):
    return _FAST.get(key) if key is not None else None


def _remember(key, device, pats):
    if key is not None:
        if len(_FAST) > 256:
            _FAST.clear()
        _FAST[key] = (backend_module(device, "kalman"), pats)


# -- ops -------------------------------------------------------------------------------------------
def kf_predict(device, x, P, F, Q, *, out=None):
    """Predict every track: x' = F x, P' = F P F^T + Q (paper 001 eq. 2-3).

    x (T,n), P (T,n,n), F and Q (n,n) shared or (T,n,n) per track. Returns ``(x', P')`` with P'
    symmetrised. ``out=(x_out, P_out)`` writes into those arrays (they may be x and P).
    """
    device = check_device(device)
    try:
        key = ("predict", device, _sig(x), _sig(P), _sig(F), _sig(Q), _sigs(out))
    except _Slow:
        key = None
    hit = _fast(key)
    if hit is not None:
        return tuple(hit[0].kf_predict(device, x, P, _raw(F), _raw(Q), out=out, pats=hit[1]))
    _shapes_first(x, P, F=F, Q=Q)
    dims: dict = {}
    x, P, dt = _state(device, x, P, dims)
    pats = (_pattern(F, dims["n"]), _pattern(Q, dims["n"]), -1, -1)
    F = _matrix(device, F, "F", "n", "n", dims, dt)
    Q = _matrix(device, Q, "Q", "n", "n", dims, dt)
    out = _outputs(device, out, dims, dt, False)
    if dims["T"] == 0:
        return _empty_state(device, dims, dt, with_status=False, out=out)
    _remember(key, device, pats)
    return tuple(backend_module(device, "kalman").kf_predict(device, x, P, F, Q, out=out, pats=pats))


def kf_update(device, x, P, z, H, R, *, mask=None, gain_scale=None, predict=None, out=None) -> KalmanState:
    """Linear Kalman update of every track with its observation z (T,m).

    y = z - H x; S = H P H^T + R (Cholesky); K = gain_scale * P H^T S^-1; x+ = x + K y;
    P+ = (I - K H) P (I - K H)^T + K R K^T (Joseph form). H (m,n) or (T,m,n), R (m,m) or (T,m,m).
    ``mask`` (T,) bool: False leaves the track unchanged (predict-only frame). ``gain_scale`` (T,)
    >= 0 multiplies each track's gain (paper 002 eq. 4-6). ``predict=(F, Q)`` predicts first in
    the same launch. ``out=(x_out, P_out, status_out)`` writes into those arrays (x_out, P_out may
    be x and P). Returns :class:`KalmanState` (x, P, status); see the module docstring.
    """
    device = check_device(device)
    try:
        key = ("update", device, _sig(x), _sig(P), _sig(z), _sig(H), _sig(R), _sig(mask), _sig(gain_scale),
               _sigs(predict), _sigs(out))  # fmt: skip
    except _Slow:
        key = None
    hit = _fast(key)
    if hit is not None:
        F, Q = (None, None) if predict is None else (_raw(predict[0]), _raw(predict[1]))
        res = hit[0].kf_update(device, x, P, z, _raw(H), _raw(R), mask, gain_scale, F, Q, out=out, pats=hit[1])
        return KalmanState(*res)
    _shapes_first(x, P, z=z, H=H, R=R, mask=mask, gain_scale=gain_scale, predict=predict)
    dims: dict = {}
    x, P, dt = _state(device, x, P, dims)
    z = _observations(device, z, dims, dt)
    pats = _patterns(predict, H, R, dims)
    H = _matrix(device, H, "H", "m", "n", dims, dt)
    R = _matrix(device, R, "R", "m", "m", dims, dt)
    mask, gain_scale, F, Q = _options(device, mask, gain_scale, predict, dims, dt)
    out = _outputs(device, out, dims, dt, True)
    if dims["T"] == 0:
        return _empty_state(device, dims, dt, out=out)
    _remember(key, device, pats)
    res = backend_module(device, "kalman").kf_update(device, x, P, z, H, R, mask, gain_scale, F, Q, out=out, pats=pats)
    return KalmanState(*res)


def ekf_update_stereo(
    device, x, P, z, R, *, f, b, cx=0.0, cy=0.0, mask=None, gain_scale=None, predict=None, out=None
) -> KalmanState:
    """Extended Kalman update with the stereo observation of paper 001 (eq. 1, 4-6).

    State x (T,6) = [x xdot y ydot z zdot] (camera frame), observation z (T,3) = [u v d] with
    h(x) = [f x/z + cx, f y/z + cy, f b/z] (f focal length in pixels, b baseline, (cx, cy) the
    principal point; d the disparity). The analytic Jacobian of h at the (predicted) state is the
    H of the linear update; everything else is as in :func:`kf_update`. A track whose state has
    z <= 0 is left unchanged with status BAD_DEPTH. R (3,3) or (T,3,3). ``out`` as in kf_update.
    """
    device = check_device(device)
    try:
        key = ("stereo", device, _sig(x), _sig(P), _sig(z), _sig(R), _sig(mask), _sig(gain_scale), _sigs(predict),
               _sigs(out))  # fmt: skip
    except _Slow:
        key = None
    hit = _fast(key)
    if hit is not None:
        f, b = real("f", f, positive=True), real("b", b, positive=True)
        cx, cy = real("cx", cx), real("cy", cy)
        F, Q = (None, None) if predict is None else (_raw(predict[0]), _raw(predict[1]))
        res = hit[0].ekf_update_stereo(
            device, x, P, z, _raw(R), f, b, cx, cy, mask, gain_scale, F, Q, out=out, pats=hit[1]
        )
        return KalmanState(*res)
    _shapes_first(x, P, z=z, R=R, mask=mask, gain_scale=gain_scale, predict=predict, m=3)
    dims: dict = {}
    x, P, dt = _state(device, x, P, dims)
    if dims["n"] != 6:
        raise ValueError(f"x: expected shape (T={dims['T']}, 6) ([x xdot y ydot z zdot]), got {tuple(x.shape)}")
    dims["m"] = 3
    z = _observations(device, z, dims, dt)
    R = _matrix(device, R, "R", "m", "m", dims, dt)
    f = real("f", f, positive=True)
    b = real("b", b, positive=True)
    cx, cy = real("cx", cx), real("cy", cy)
    pats = _patterns(predict, None, R, dims)
    mask, gain_scale, F, Q = _options(device, mask, gain_scale, predict, dims, dt)
    out = _outputs(device, out, dims, dt, True)
    if dims["T"] == 0:
        return _empty_state(device, dims, dt, out=out)
    _remember(key, device, pats)
    res = backend_module(device, "kalman").ekf_update_stereo(
        device, x, P, z, R, f, b, cx, cy, mask, gain_scale, F, Q, out=out, pats=pats
    )
    return KalmanState(*res)


def mahalanobis(device, x, P, H, R, z, *, out=None):
    """Squared Mahalanobis distance of every detection to every track's predicted observation.

    d2[t, i] = (z_i - H x_t)^T S_t^-1 (z_i - H x_t), S_t = H P_t H^T + R (paper 001 eq. 8 gating;
    association costs for paper 002). x (T,n), P (T,n,n), H (m,n) or (T,m,n), R (m,m) or (T,m,m),
    z (D,m) finite detections. Returns (T,D) in the dtype of x; inf for a track whose S is not
    positive definite. One Cholesky per track, then D triangular solves. ``out`` (T,D): an array
    of the device to write into instead of allocating one.
    """
    device = check_device(device)
    try:
        key = ("gate", device, _sig(x), _sig(P), _sig(H), _sig(R), _sig(z), _sig(out))
    except _Slow:
        key = None
    hit = _fast(key)
    if hit is not None:
        return hit[0].mahalanobis(device, x, P, _raw(H), _raw(R), z, out=out, pats=hit[1])
    _shapes_first(x, P, z=z, z_spec=("D", "m"), H=H, R=R)
    dims: dict = {}
    x, P, dt = _state(device, x, P, dims)
    z = _arg(device, z, "z", ("D", "m"), dims, dtype=dt, cast=True)
    if not 1 <= dims["m"] <= MAX_M:
        raise ValueError(f"z: expected an observation size m between 1 and {MAX_M}, got m={dims['m']}")
    pats = (-1, -1, _pattern(H, dims["n"]), _pattern(R, dims["m"]))
    H = _matrix(device, H, "H", "m", "n", dims, dt)
    R = _matrix(device, R, "R", "m", "m", dims, dt)
    if out is not None:
        if device.backend == "numpy":
            ok = isinstance(out, np.ndarray) and out.flags.c_contiguous and out.flags.writeable
        else:
            ok = hasattr(out, "buffer") and out.device is device
        if not ok or tuple(out.shape) != (dims["T"], dims["D"]) or out.dtype != dt:
            raise ValueError(
                f"out: expected a writeable array of shape ({dims['T']}, {dims['D']}) and dtype {dt.name} on "
                f"{device.spec}, got {type(out).__name__} {tuple(getattr(out, 'shape', ()))}"
            )
    if out is None:
        device.check_alloc((dims["T"], dims["D"]), dt)  # the (T, D) result fits, before any work
    if dims["T"] == 0 or dims["D"] == 0:
        return out if out is not None else device.empty((dims["T"], dims["D"]), dt)
    _remember(key, device, pats)
    return backend_module(device, "kalman").mahalanobis(device, x, P, H, R, z, out=out, pats=pats)

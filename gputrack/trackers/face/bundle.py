"""Paper 003's incremental bundle adjustment (sec. 3, eq. 5-10): the identity s of a face from the K
feature points of n key frames.

**Problem** (:class:`BundleProblem`, eq. 5-7). Frame i has a pose p_i = (rvec_i, tvec_i) (Rodrigues
vector, model -> camera, and translation in mm) and a deformation a_i (A',); the identity s (S',) is
shared. Its points are X_ik = shape(s, a_i)_k (eq. 4) in the model frame, seen at
Y_ik = R(rvec_i) X_ik + tvec_i and projected by the pinhole camera, m_ik = P(p_i, M_i(a_i, s)) (eq. 5).
The cost is (eq. 6)

    F = sum_i sum_k w_ik ||m-hat_ik - P(p_i, M_i(a_i, s))_k||^2    (px^2)

over all n frames' poses and deformations and the identity at once: ONE least-squares problem with
P = n (6 + A') + S' parameters, packed as [rvec_0, tvec_0, a_0, ..., rvec_{n-1}, tvec_{n-1}, a_{n-1}, s],
and M = 2 K n residuals sqrt(w_ik) (P(...)_k - m-hat_ik), ordered (frame, point, u/v). A landmark with
a NaN coordinate is unknown (occluded): its weight is 0. ``weights`` (n, K) >= 0 scale the rest.

**Box** (eq. 7-9), lower == upper fixing a parameter:

- p_i within its start value +- ``pose_range`` (eq. 8): (rotation rad per rvec component, translation
  mm), or 6 numbers;
- a_i within its start value +- ``expression_range`` (eq. 8, "likewise"); default 2 x
  ``model.expression_std`` per component (the same two-sigma width the identity gets);
- s within ``identity_mean`` +- ``identity_sigmas`` x ``identity_std`` (eq. 9, two sigma: the paper's
  95 % of a normal distribution);
- a component of s or a whose std is 0 (the multilinear model's first identity and first deformation
  columns are constant; "0" means below ``ZERO_STD_RTOL`` x the largest std) is fixed at the model's mean;
- ``fixed_first=True`` fixes the first frame's pose at its start value.

**Jacobian**: analytic (:mod:`gputrack.ops.face_bundle`: a device kernel, and vectorised NumPy on the
host, :meth:`BundleProblem.jacobian`). Through the camera,
dm/dY = [[fx/Z, 0, -fx X/Z^2], [0, fy/Z, -fy Y/Z^2]]; dY/dtvec = I; dY/da = R (dX/da); dY/ds = R (dX/ds);
and for the rotation the exact derivative of the Rodrigues map: R(r + dr) = exp([J_l(r) dr]x) R(r) to
first order, J_l the left Jacobian of SO(3), so d(R X)/dr = -[R X]x J_l(r).

The shape model is used through its public interface only: ``expression_basis(s)`` is affine in s (the
multilinear model: linear; the generic PCA model: constant, with S' = 0), so
X = mean + (L0 + sum_p s_p G_p) a with L0 = basis(0), G_p = basis(e_p) - L0 (:func:`model_terms`).

**Solve** (:func:`bundle_adjust`): a :class:`gputrack.LeastSquaresSolver` with B = 1, the analytic
Jacobian, the box and MINPACK's damping scale (each parameter damped relative to its own diag(J^T J):
radians, millimetres and model coordinates alike), on any device (:class:`IncrementalBundle` holds
its solvers and residual kernels from frame to frame). The residuals and Jacobian come from a device kernel
(:class:`gputrack.ops.face_bundle.LandmarkResiduals`: one launch per iteration, nothing through the
host; the model and each solve's landmarks uploaded once) where :func:`device_model` says so, else
from the host model in float64, handed to the solver as NumPy arrays (its ``host`` mode).

**Key frames** (:class:`IncrementalBundle`, sec. 3.1, eq. 10): see its docstring.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ...models.camera import Camera
from ...models.pose import rodrigues
from ...ops.face_bundle import LandmarkFrames, LandmarkModel, LandmarkResiduals, evaluate, geometry
from ...ops.face_points import MIN_DEPTH  # the near plane of the projection (keeps residuals finite)
from ...ops.lm import LeastSquaresSolver, LMStatus

log = logging.getLogger("gputrack")

__all__ = [
    "MIN_KEYFRAME_POINTS",
    "BundleProblem",
    "BundleResult",
    "IncrementalBundle",
    "bundle_adjust",
    "keyframe_slot",
    "keyframe_spread",
    "model_terms",
]

#: default box half-widths of a pose (eq. 8): rotation (rad per rvec component), translation (mm)
POSE_RANGE = (0.15, 30.0)
#: the LM's damping scale (:class:`gputrack.LeastSquaresSolver`'s ``damping_scale``) and initial
#: damping C: 1e-3 of each parameter's diag(J^T J) (Nielsen's usual tau)
DAMPING_SCALE = "minpack"
DAMPING = 1e-3
#: the box of the start poses in :meth:`IncrementalBundle.start` (rad, mm)
START_POSE_RANGE = (0.5, 300.0)
#: default expression box half-width in units of ``model.expression_std`` (eq. 8)
EXPRESSION_SIGMAS = 2.0
#: a new frame with fewer usable landmarks than this never enters the key-frame set
MIN_KEYFRAME_POINTS = 4
#: a prior std below this fraction of the largest of its vector counts as 0 (the component is fixed)
ZERO_STD_RTOL = 1e-9
#: relative tolerance of the key-frame choice: spreads within it of the largest count as equal
SPREAD_RTOL = 1e-9


# ------------------------------------------------------------------------------------------------
# key frames


def keyframe_spread(rvecs) -> np.ndarray:
    """The variance of the face directions of a frame set (sec. 3.1): rvecs (..., n, 3) -> (...).

    Face direction d_i = the model's z axis in the camera frame, R(rvec_i)[:, 2] (a unit vector); the
    variance is the trace of their population covariance, (1/n) sum_i |d_i - mean d|^2 = 1 - |mean d|^2:
    0 for n equal directions, at most 1.
    """
    r = np.asarray(rvecs, dtype=np.float64)
    if r.ndim < 2 or r.shape[-1] != 3 or r.shape[-2] < 1:
        raise ValueError(f"rvecs: expected shape (..., n >= 1, 3), got {r.shape}")
    if not np.isfinite(r).all():
        raise ValueError("rvecs: expected finite values, got non-finite ones")
    d = rodrigues(r)[..., :, 2]  # (..., n, 3) face directions
    mean = d.mean(axis=-2)
    return np.maximum(1.0 - np.einsum("...c,...c->...", mean, mean), 0.0)


def keyframe_slot(rvecs, frames, rvec, keep_previous: bool = False) -> int:
    """The key-frame rule of :class:`IncrementalBundle` (sec. 3.1): the slot of the key frames
    (rvecs (n, 3), their frame numbers ``frames`` (n,)) that a new frame with ``rvec`` (3,) replaces,
    the one whose set has the largest :func:`keyframe_spread` (within ``SPREAD_RTOL``: the oldest
    frame's), or -1 where ``keep_previous`` and no replacement widens the spread."""
    n = len(frames)
    d = rodrigues(np.vstack([rvecs, rvec]))[:, :, 2]  # the key frames' face directions, the new one's
    total = d[:-1].sum(axis=0)
    means = (total - d[:-1] + d[-1]) / n  # candidate j: the new frame in slot j
    spreads = np.maximum(1.0 - np.einsum("jc,jc->j", means, means), 0.0)  # keyframe_spread of each candidate
    best = float(spreads.max())
    if keep_previous:
        mean = total / n
        previous = max(1.0 - float(mean @ mean), 0.0)
        if previous >= best * (1 - SPREAD_RTOL):
            return -1  # no replacement widens the spread
    equal = np.flatnonzero(spreads >= best * (1 - SPREAD_RTOL))
    return int(equal[np.argmin(np.asarray(frames)[equal])])  # among equals, the oldest key frame


# ------------------------------------------------------------------------------------------------
# the problem


@dataclasses.dataclass(frozen=True)
class ModelTerms:
    """A face model as X(s, a) = mean + (L0 + sum_p s_p G_p) a (eq. 4): mean (K, 3), L0 (K, 3, A'),
    G (K, 3, S', A'); the identity/expression means and stds (the priors of eq. 9)."""

    mean: np.ndarray
    L0: np.ndarray
    G: np.ndarray
    identity_mean: np.ndarray
    identity_std: np.ndarray
    expression_mean: np.ndarray
    expression_std: np.ndarray

    @property
    def K(self) -> int:
        return self.mean.shape[0]

    @property
    def S(self) -> int:
        return self.G.shape[2]

    @property
    def A(self) -> int:
        return self.L0.shape[2]


def model_terms(model) -> ModelTerms:
    """:class:`ModelTerms` of a :class:`~gputrack.models.face.FaceModel` or ``PcaFaceModel`` (or any
    model with the same interface whose ``expression_basis(s)`` is affine in s)."""
    if isinstance(model, ModelTerms):
        return model
    if not all(hasattr(model, a) for a in ("expression_basis", "identity_dims", "identity_std", "expression_std")):
        raise TypeError(f"model: expected a FaceModel or PcaFaceModel, got {type(model).__name__}")
    S = int(model.identity_dims)
    mean, L0 = (np.asarray(v, np.float64) for v in model.expression_basis(np.zeros(S)))
    G = np.stack([np.asarray(model.expression_basis(e)[1], np.float64) - L0 for e in np.eye(S)], axis=2) \
        if S else np.zeros((*L0.shape[:2], 0, L0.shape[2]))  # fmt: skip
    f = lambda v: np.asarray(v, np.float64).reshape(-1)
    return ModelTerms(mean, L0, G, f(model.identity_mean), f(model.identity_std), f(model.expression_mean),
                      f(model.expression_std))  # fmt: skip


def _zero(std: np.ndarray) -> np.ndarray:
    """The components of a prior std that count as 0 (bool, same shape)."""
    return std <= ZERO_STD_RTOL * (std.max() if std.size else 0.0)


def _real_array(x, name: str, shape: tuple, *, allow_nan: bool = False) -> np.ndarray:
    a = np.asarray(x)
    if a.dtype.kind not in "iuf":
        raise ValueError(f"{name}: expected a real array of shape {shape}, got dtype {a.dtype.name}")
    if a.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    a = a.astype(np.float64)
    bad = np.isinf(a) if allow_nan else ~np.isfinite(a)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        what = "finite values or NaN (unknown)" if allow_nan else "finite values"
        raise ValueError(f"{name}: expected {what}, got {a[idx]} at index {idx}")
    return a


def _ranges(value, name: str, n: int, default=None) -> np.ndarray:
    """A box half-width: a number, or ``n`` numbers, finite and >= 0 (None: ``default``)."""
    if value is None:
        return np.asarray(default, np.float64)
    v = np.asarray(value, dtype=np.float64)
    if v.ndim == 0:
        v = np.full(n, float(v))
    if v.shape != (n,) or not np.isfinite(v).all() or (v < 0).any():
        raise ValueError(f"{name}: expected a number or {n} numbers, finite and >= 0, got {value!r}")
    return v


def _sigmas(value) -> float:
    if isinstance(value, bool) or not np.isscalar(value) or not np.isfinite(value) or value < 0:
        raise ValueError(f"identity_sigmas: expected a finite number >= 0, got {value!r}")
    return float(value)


def _pose_range(value) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.shape == (2,):
        v = np.repeat(v, 3)
    if v.shape != (6,) or not np.isfinite(v).all() or (v < 0).any():
        raise ValueError(
            f"pose_range: expected (rotation rad, translation mm) or 6 numbers, finite and >= 0, got {value!r}"
        )
    return v


class BundleProblem:
    """Eq. 6 over n frames as one least-squares problem: packing, residuals, analytic Jacobian, box.

    landmarks (n, K, 2) px (NaN: unknown); rvecs, tvecs (n, 3); expressions (n, A'); identity (S',) or
    None (``identity_mean``); the box settings as in :func:`bundle_adjust`. Attributes: ``x0`` (P,) the
    start, ``lower``/``upper`` (P,) the box (eq. 8-9), ``weights`` (n, K) the effective weights (0 for
    unknown landmarks), ``points`` = number of landmarks with weight > 0.
    """

    def __init__(self, model, camera: Camera, landmarks, rvecs, tvecs, expressions, identity=None, *,
                 pose_range=POSE_RANGE, expression_range=None, identity_sigmas=2.0, fixed_first: bool = False,
                 weights=None, identity_prior: float = 0.0):  # fmt: skip
        if not isinstance(camera, Camera):
            raise TypeError(f"camera: expected a gputrack.models.Camera, got {type(camera).__name__}")
        self.terms = tm = model_terms(model)
        self.camera = camera
        K, A, S = tm.K, tm.A, tm.S
        lm = np.asarray(landmarks)
        if lm.ndim != 3 or lm.shape[1:] != (K, 2) or lm.shape[0] < 1:
            raise ValueError(f"landmarks: expected shape (n >= 1, K={K}, 2), got {lm.shape}")
        n = lm.shape[0]
        lm = _real_array(lm, "landmarks", (n, K, 2), allow_nan=True)
        rv = _real_array(rvecs, "rvecs", (n, 3))
        tv = _real_array(tvecs, "tvecs", (n, 3))
        ex = _real_array(expressions, "expressions", (n, A))
        s = tm.identity_mean if identity is None else _real_array(identity, "identity", (S,))
        w = np.ones((n, K)) if weights is None else _real_array(weights, "weights", (n, K))
        if (w < 0).any():
            raise ValueError(f"weights: expected values >= 0, got {w.min()}")
        w = np.where(np.isnan(lm).any(axis=2), 0.0, w)  # unknown landmarks: weight 0
        self.points = int((w > 0).sum())
        if self.points < 1:
            raise ValueError("landmarks: expected at least 1 usable landmark (finite, weight > 0), got 0")
        self.n, self.K, self.A, self.S = n, K, A, S
        self.F = 6 + A  # parameters per frame
        self.P = n * self.F + S
        self.M = 2 * K * n
        prior = float(identity_prior)
        if not np.isfinite(prior) or prior < 0:
            raise ValueError(f"identity_prior: expected a finite number >= 0, got {identity_prior!r}")
        free = ~_zero(tm.identity_std)
        # beyond eq. 6: a Gaussian prior on the identity, rows sqrt(prior) (s - s-bar) / sigma_s (px per sigma)
        self._prior = np.where(free, np.sqrt(prior) / np.where(free, tm.identity_std, 1.0), 0.0) if prior > 0 else None
        self.rows = self.M + (S if self._prior is not None else 0)  # residuals handed to the solver
        self.weights = w
        self._sw = np.sqrt(w)
        self._target = np.where(w[..., None] > 0, np.nan_to_num(lm), 0.0)
        self._model = LandmarkModel(tm.mean, tm.L0, tm.G, camera, MIN_DEPTH)
        self._frames = LandmarkFrames(self._target, self._sw, prior=self._prior,
                                      prior_mean=None if self._prior is None else tm.identity_mean)  # fmt: skip
        self._frames.check(self._model)
        self.x0 = self.pack(rv, tv, ex, s)
        self.lower, self.upper = self._box(_pose_range(pose_range), expression_range, identity_sigmas, fixed_first)
        depth = geometry(self._model, self.x0[None])[..., 2]
        if (depth <= MIN_DEPTH).any():
            i, k = (int(j) for j in np.argwhere(depth[0] <= MIN_DEPTH)[0])
            raise ValueError(f"tvecs: expected every model point in front of the camera (depth > {MIN_DEPTH} mm), "
                             f"got depth {depth[0, i, k]:.3g} mm at frame {i}, point {k}")  # fmt: skip

    # -- packing ---------------------------------------------------------------------------------
    def pack(self, rvecs, tvecs, expressions, identity) -> np.ndarray:
        """(P,) parameter vector [rvec_i, tvec_i, a_i for each frame i, then s]."""
        frames = np.concatenate([rvecs, tvecs, expressions], axis=1).reshape(-1)
        return np.concatenate([frames, np.asarray(identity, np.float64).reshape(-1)])

    def unpack(self, x):
        """(..., P) -> rvecs (..., n, 3), tvecs (..., n, 3), expressions (..., n, A'), identity (..., S')."""
        x = np.asarray(x, np.float64)
        fr = x[..., : self.n * self.F].reshape((*x.shape[:-1], self.n, self.F))
        return fr[..., :3], fr[..., 3:6], fr[..., 6:], x[..., self.n * self.F :]

    def _box(self, pose_range, expression_range, identity_sigmas, fixed_first):
        """lower/upper (P,) of eq. 8-9."""
        tm = self.terms
        identity_sigmas = _sigmas(identity_sigmas)
        ex_range = _ranges(expression_range, "expression_range", self.A, EXPRESSION_SIGMAS * tm.expression_std)
        rv, tv, ex, _ = self.unpack(self.x0)
        pose = np.concatenate([rv, tv], axis=1)
        pose_lo, pose_hi = pose - pose_range, pose + pose_range  # eq. 8: p-hat_i -+ lambda_p
        if fixed_first:
            pose_lo[0] = pose_hi[0] = pose[0]
        ex_lo, ex_hi = ex - ex_range, ex + ex_range  # eq. 8 for a: a-hat_i -+ lambda_a
        fixed = _zero(tm.expression_std)
        ex_lo[:, fixed] = ex_hi[:, fixed] = tm.expression_mean[fixed]
        s_lo = tm.identity_mean - identity_sigmas * tm.identity_std  # eq. 9: s-bar -+ 2 sigma_s
        s_hi = tm.identity_mean + identity_sigmas * tm.identity_std
        fixed = _zero(tm.identity_std)
        s_lo[fixed] = s_hi[fixed] = tm.identity_mean[fixed]
        lower = self.pack(pose_lo[:, :3], pose_lo[:, 3:], ex_lo, s_lo)
        upper = self.pack(pose_hi[:, :3], pose_hi[:, 3:], ex_hi, s_hi)
        return lower, upper

    # -- evaluation ------------------------------------------------------------------------------
    def residuals(self, x) -> np.ndarray:
        """(B, P) -> (B, M) float64: sqrt(w_ik) (P(p_i, M_i(a_i, s))_k - m-hat_ik) (eq. 5-6)."""
        return self.evaluate(x, jacobian=False)[0]

    def jacobian(self, x) -> np.ndarray:
        """(B, P) -> (B, M, P) float64: d residuals / d parameters, analytic (module docstring)."""
        return self.evaluate(x, jacobian=True)[1]

    def evaluate(self, x, jacobian: bool = True):
        """(B, P) -> (residuals (B, M), Jacobian (B, M, P) or None), on the host in float64
        (:func:`gputrack.ops.face_bundle.evaluate`, the device kernels' oracle)."""
        return evaluate(self._model, self._frames, np.atleast_2d(np.asarray(x, np.float64)), jacobian)

    def cost(self, x) -> float:
        """F of eq. 6 at x (P,), float64."""
        r = self.residuals(np.asarray(x)[None])[0, : self.M]
        return float(np.dot(r, r))

    # -- solve -----------------------------------------------------------------------------------
    def solver(self, device, max_iter: int = 10, profile: bool = False) -> LeastSquaresSolver:
        """A :class:`gputrack.LeastSquaresSolver` for problems of this one's size (B = 1, P): hold it
        and pass it to :meth:`solve` to solve problem after problem on the same device buffers
        (``profile``: the solver times each part of a solve, see :class:`gputrack.LeastSquaresSolver`)."""
        if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 0:
            raise ValueError(f"max_iter: expected an int >= 0, got {max_iter!r}")
        return LeastSquaresSolver(device, (1, self.P), max_iter=int(max_iter), early_stop=False, damping_scale=DAMPING_SCALE,
                                  profile=profile)  # fmt: skip

    def landmarks(self, device) -> LandmarkResiduals | None:
        """The residuals and Jacobian of problems of this one's size as a device kernel on ``device``
        (:class:`gputrack.ops.face_bundle.LandmarkResiduals`; hold it and pass it to :meth:`solve`
        with the solver, for problems of the same model and camera), or None where the solve calls the
        host model (see :func:`device_model`)."""
        return LandmarkResiduals(device, self._model, self._frames) if device_model(device) else None

    def solve(self, device, max_iter: int = 10, solver: LeastSquaresSolver | None = None,
              landmarks: LandmarkResiduals | None = None) -> BundleResult:  # fmt: skip
        """Minimise eq. 6 in the box by Levenberg-Marquardt on ``device`` (B = 1): with ``solver`` (from
        :meth:`solver`, for this ``device``, P and ``max_iter``), else with a solver used once; the
        residuals from ``landmarks`` (from :meth:`landmarks`), else from a kernel made for this solve
        where :func:`device_model` says so, else from the host model."""
        if solver is None:
            with self.solver(device, max_iter) as once:
                return self.solve(device, max_iter, once, landmarks)
        if solver.device is not device or solver.shape != (1, self.P) or solver.max_iter != max_iter:
            raise ValueError(f"solver: expected one for {device.spec}, shape (1, {self.P}), max_iter={max_iter}, "
                             f"got {solver!r}")  # fmt: skip
        if landmarks is None:
            landmarks = self.landmarks(device)
        elif not isinstance(landmarks, LandmarkResiduals) or landmarks.device is not device or landmarks.P != self.P:
            raise ValueError(f"landmarks: expected residuals of this problem's size (P={self.P}) on {device.spec}, "
                             f"got {landmarks!r}")  # fmt: skip
        # the damping scaled as MINPACK's (the running maximum of diag(J^T J)): C relative to each
        # parameter's own curvature treats radians, millimetres and model coordinates alike, and the
        # solver keeps the scale on the device (scaling the parameters by the start Jacobian's column
        # norms instead took one more Jacobian launch, its download and a second upload a solve)
        if landmarks is not None:  # on the device: one kernel per iteration, nothing through the host
            landmarks.update(self._frames)
            fns, host = landmarks, False
        else:
            fns, host = _Callables(self), True
        res = solver.solve(fns.residuals, self.x0[None], jacobian=fns.jacobian, lower=self.lower, upper=self.upper,
                           damping=DAMPING, host=host)  # fmt: skip
        x = np.clip(res.x[0].astype(np.float64), self.lower, self.upper)
        rv, tv, ex, s = self.unpack(x)
        # F of eq. 6 at x: the solver's cost there less the identity prior's rows (a host evaluation
        # of the landmarks took ~0.2 ms a frame)
        cost = float(res.cost[0])
        if self._prior is not None:
            cost = max(cost - float(np.sum((self._prior * (s - self.terms.identity_mean)) ** 2)), 0.0)
        return BundleResult(rvecs=rv, tvecs=tv, expressions=ex, identity=s, cost=cost,
                            rms=float(np.sqrt(cost / self.weights.sum())), status=LMStatus(int(res.status[0])),
                            iterations=int(res.iterations[0]))  # fmt: skip


def device_model(device) -> bool:
    """Whether a bundle solve on ``device`` evaluates its residuals and Jacobian with the device
    kernel (:class:`gputrack.ops.face_bundle.LandmarkResiduals`) rather than the host model: on every
    device but the numpy one and taichi:vulkan on a CPU (lavapipe), where the kernel took ~35 ms a
    launch against ~0.2 ms for the host model (2026-12-06)."""
    if device.backend == "numpy":
        return False
    return not (device.spec == "taichi:vulkan" and device.info.kind != "gpu")


class _Callables:
    """The residual and Jacobian callables handed to the solver in its host mode (NumPy points in,
    NumPy results out). Both are evaluated at the same point each iteration: the residual call
    computes the Jacobian too and keeps it for the Jacobian call that the solver makes next at the
    same points (its protocol)."""

    def __init__(self, problem: BundleProblem):
        self.problem = problem
        self._J, self._dtype = None, np.dtype(np.float64)

    def residuals(self, X):
        r, self._J = self.problem.evaluate(X.astype(np.float64), jacobian=X.shape[0] == 1)
        self._dtype = X.dtype
        return r.astype(X.dtype, copy=False)

    def jacobian(self, X):
        if self._J is None:
            self.residuals(X)
        J, self._J = self._J, None
        return J.astype(self._dtype, copy=False)


@dataclasses.dataclass(frozen=True)
class BundleResult:
    """Result of :func:`bundle_adjust`: rvecs, tvecs (n, 3), expressions (n, A'), identity (S',)
    (float64); cost = F of eq. 6 at them (px^2, float64 on the host); rms = sqrt(cost / sum of weights)
    (px: the root mean square reprojection distance of a landmark with unit weight); status
    (:class:`~gputrack.ops.lm.LMStatus`) and iterations of the LM solve."""

    rvecs: np.ndarray
    tvecs: np.ndarray
    expressions: np.ndarray
    identity: np.ndarray
    cost: float
    rms: float
    status: LMStatus
    iterations: int


def bundle_adjust(device, model, camera, landmarks, rvecs, tvecs, expressions, identity, *, pose_range=POSE_RANGE,
                  expression_range=None, identity_sigmas=2.0, max_iter: int = 10, fixed_first: bool = False,
                  weights=None, identity_prior: float = 0.0) -> BundleResult:  # fmt: skip
    """Bundle adjustment of n frames (paper 003 eq. 6-9): every frame's pose and deformation and the
    shared identity in ONE box-constrained LM problem on ``device``.

    model: :class:`~gputrack.models.face.FaceModel` or ``PcaFaceModel`` (identity_dims == 0: pass an
    empty identity or None); camera: :class:`gputrack.models.Camera`; landmarks (n, K, 2) px, NaN where
    unknown; rvecs, tvecs (n, 3) start poses (model -> camera, Rodrigues, mm); expressions (n, A') start
    deformations; identity (S',) start identity (None: ``model.identity_mean``).

    pose_range: (rotation rad, translation mm) or 6 numbers, the box around each start pose (eq. 8);
    expression_range: a number or A' numbers around each start deformation, default 2 x
    ``model.expression_std`` (eq. 8); identity_sigmas: the identity box ``identity_mean`` +- this x
    ``identity_std`` (eq. 9); components with std 0 are fixed at the model's mean; fixed_first: fix the
    first frame's pose; weights (n, K) >= 0 (NaN landmarks get 0); max_iter: LM iterations (the paper: 10
    to initialise, 5 per frame while tracking); identity_prior (beyond the paper, 0 = off): adds the
    residuals sqrt(identity_prior) (s - identity_mean) / identity_std, a Gaussian prior that holds the
    directions of s the landmarks cannot see (the head's size trades against its depth) at the mean.

    Returns a :class:`BundleResult`. Bad shapes, non-finite poses / deformations / identity, n = 0, no
    usable landmark or a start with a model point behind the camera raise ValueError ("expected ..., got
    ..."). See the module docstring for the residuals, the Jacobian and the buffers reused between calls.
    """
    problem = BundleProblem(model, camera, landmarks, rvecs, tvecs, expressions, identity, pose_range=pose_range,
                            expression_range=expression_range, identity_sigmas=identity_sigmas,
                            fixed_first=fixed_first, weights=weights, identity_prior=identity_prior)  # fmt: skip
    return problem.solve(device, max_iter)


# ------------------------------------------------------------------------------------------------
# incremental bundle adjustment


def _usable(landmarks, weights) -> int:
    return int(((weights > 0) & ~np.isnan(landmarks).any(axis=-1)).sum())


class IncrementalBundle:
    """The incremental bundle adjustment of paper 003 (sec. 3.1, eq. 6-10): the identity of the tracked
    face, refined on a set of n key frames that changes frame by frame.

    :meth:`start` runs the initial adjustment over the first n frames (``init_iterations`` LM
    iterations; the identity starts at ``model.identity_mean`` unless given) and sets s(1) = its identity.

    :meth:`add` takes frame t's landmarks and the tracker's pose/deformation estimate for it, and

    1. chooses the key-frame set (sec. 3.1). The candidates are the n sets in which the new frame
       replaces one key frame (the paper's "n combinations"); with ``keep_previous=True`` the unchanged
       set is a candidate too. The candidate with the largest spread (:func:`keyframe_spread`, the
       variance of the face directions) is kept; spreads within ``SPREAD_RTOL`` (relative) of the
       largest count as equal, and among equal candidates the unchanged set wins, then the one that
       replaces the oldest key frame. A frame with fewer than ``MIN_KEYFRAME_POINTS`` usable landmarks
       never enters (the set stays unchanged). The new frame takes the slot of the frame it replaces;
    2. runs ``iterations`` LM iterations of :func:`bundle_adjust` on that set: the new frame's pose and
       deformation start from the given estimate, the other key frames' from their values after the
       previous adjustment, each boxed around its start (eq. 8); the identity starts from s(t-1), boxed
       by eq. 9. The key frames keep their adjusted poses and deformations;
    3. updates the identity as the running mean (eq. 10): s(t) = (t-1)/t s(t-1) + 1/t s', s' the
       adjustment's identity, t = :attr:`count` (1 after :meth:`start`, +1 per :meth:`add`).

    ``profile=True``: each of its solvers times the parts of its solves (:meth:`profile_tables`).

    Attributes: :attr:`identity` s(t); :attr:`keyframes` (n,) frame numbers of the key frames in slot
    order (:meth:`start`'s frames are 0..n-1, each :meth:`add` the next number), the order of the
    arrays of :attr:`last`; :attr:`count` t; :attr:`last` the last :class:`BundleResult`.
    """

    def __init__(self, device, model, camera: Camera, *, n: int = 7, iterations: int = 5, init_iterations: int = 10,
                 pose_range=POSE_RANGE, expression_range=None, identity_sigmas=2.0,
                 keep_previous: bool = False, identity_prior: float = 0.0, profile: bool = False):  # fmt: skip
        for name, v, lo in (("n", n, 1), ("iterations", iterations, 0), ("init_iterations", init_iterations, 0)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ValueError(f"{name}: expected an int >= {lo}, got {v!r}")
        if not isinstance(camera, Camera):
            raise TypeError(f"camera: expected a gputrack.models.Camera, got {type(camera).__name__}")
        self.device, self.camera = device, camera
        self.terms = model_terms(model)
        self.n, self.iterations, self.init_iterations = int(n), int(iterations), int(init_iterations)
        self.pose_range = _pose_range(pose_range)
        self.expression_range = _ranges(expression_range, "expression_range", self.terms.A,
                                        EXPRESSION_SIGMAS * self.terms.expression_std)  # fmt: skip
        self.identity_sigmas = _sigmas(identity_sigmas)
        self.keep_previous = bool(keep_previous)
        self.identity_prior = float(identity_prior)
        self.identity: np.ndarray | None = None
        self.count = 0
        self.last: BundleResult | None = None
        self._frames = 0  # frame numbers handed out
        self._keys: dict | None = None
        self._solvers: dict = {}  # (P, max_iter) -> LeastSquaresSolver, holding its device buffers
        self._landmarks: dict = {}  # P -> LandmarkResiduals (None: the host model), holding theirs
        self.profile = bool(profile)

    def profile_tables(self) -> str:
        """With ``profile=True``: the time of each part of the solves (:class:`gputrack.Profiler`
        tables), one table per solver that has solved since its profiler's last reset (the start's
        and the per-frame solves' sizes)."""
        if not self.profile:
            raise RuntimeError("IncrementalBundle.profile_tables: made without profile=True")
        return "\n".join(s.profiler.table(f"bundle adjustment P={P}, {it} iterations on {self.device.spec}")
                         for (P, it), s in self._solvers.items() if s.profiler.stats)

    def reset_profile(self) -> None:
        """With ``profile=True``: forget the solvers' figures so far (e.g. their first, compiling solves)."""
        if not self.profile:
            raise RuntimeError("IncrementalBundle.reset_profile: made without profile=True")
        for s in self._solvers.values():
            s.profiler.reset()

    @property
    def keyframes(self) -> np.ndarray:
        return np.array([] if self._keys is None else self._keys["frame"], dtype=np.int64)

    @property
    def spread(self) -> float:
        """:func:`keyframe_spread` of the current key frames (0 before :meth:`start`)."""
        return 0.0 if self._keys is None else float(keyframe_spread(self._keys["rvecs"]))

    def _solve(self, keys, identity, max_iter, pose_range=None, identity_sigmas=None) -> BundleResult:
        problem = BundleProblem(self.terms, self.camera, keys["landmarks"], keys["rvecs"], keys["tvecs"],
                                keys["expressions"], identity,
                                pose_range=self.pose_range if pose_range is None else pose_range,
                                expression_range=self.expression_range,
                                identity_sigmas=self.identity_sigmas if identity_sigmas is None else identity_sigmas,
                                weights=keys["weights"], identity_prior=self.identity_prior)  # fmt: skip
        key = (problem.P, int(max_iter))  # the start's and the per-frame solves: a solver each, kept
        if key not in self._solvers:
            self._solvers[key] = problem.solver(self.device, max_iter, profile=self.profile)
        if problem.P not in self._landmarks:  # the device residuals of problems of this size, kept
            self._landmarks[problem.P] = problem.landmarks(self.device)
        res = problem.solve(self.device, max_iter, self._solvers[key], self._landmarks[problem.P])
        keys.update(rvecs=res.rvecs, tvecs=res.tvecs, expressions=res.expressions)
        self._keys, self.last = keys, res
        return res

    def start(self, landmarks, rvecs, tvecs, expressions, identity=None, weights=None,
              pose_range=START_POSE_RANGE, hold_identity: bool = False) -> np.ndarray:  # fmt: skip
        """The initial adjustment over the first n frames (sec. 4.1): landmarks (n, K, 2) (NaN: unknown),
        rvecs, tvecs (n, 3), expressions (n, A'), identity (S',) or None (``identity_mean``), weights
        (n, K) or None. Returns s(1). Restarts the running mean.

        ``pose_range`` boxes the start poses (default :data:`START_POSE_RANGE`, wider than the
        tracking box: start poses found with the mean shape are off in depth by as much as the
        person's size differs from the mean, and the adjustment must be free to move them).
        ``hold_identity`` (beyond the paper): adjust the poses and deformations only, the identity
        held where it starts (s(1) = ``identity``), for the frames after to learn."""
        K, A = self.terms.K, self.terms.A
        lm = np.asarray(landmarks)
        if lm.ndim != 3 or lm.shape[1:] != (K, 2) or lm.shape[0] != self.n:
            raise ValueError(
                f"start: expected landmarks of n={self.n} frames, shape ({self.n}, {K}, 2), got {lm.shape}"
            )
        n = self.n
        keys = {
            "landmarks": _real_array(lm, "landmarks", (n, K, 2), allow_nan=True),
            "rvecs": _real_array(rvecs, "rvecs", (n, 3)),
            "tvecs": _real_array(tvecs, "tvecs", (n, 3)),
            "expressions": _real_array(expressions, "expressions", (n, A)),
            "weights": np.ones((n, K)) if weights is None else _real_array(weights, "weights", (n, K)),
            "frame": list(range(n)),
        }
        s = self.terms.identity_mean if identity is None else _real_array(identity, "identity", (self.terms.S,))
        res = self._solve(keys, s, self.init_iterations, _pose_range(pose_range), 0.0 if hold_identity else None)
        self._frames, self.count = n, 1
        self.identity = res.identity.copy()  # s(1)
        return self.identity.copy()

    def choose(self, rvec) -> int:
        """The key-frame slot the new frame with ``rvec`` replaces by the rule of the class docstring,
        or -1 for the unchanged set."""
        if self._keys is None:
            raise RuntimeError("IncrementalBundle: call start() before choose() or add()")
        return keyframe_slot(self._keys["rvecs"], self._keys["frame"], _real_array(rvec, "rvec", (3,)),
                             self.keep_previous)  # fmt: skip

    def add(self, landmarks, rvec, tvec, expression, weights=None) -> np.ndarray:
        """Frame t: landmarks (K, 2) (NaN: unknown), the tracker's rvec, tvec (3,) and expression (A',)
        for it, weights (K,) or None. Chooses the key frames, adjusts them (``iterations`` LM iterations)
        and returns s(t) (eq. 10)."""
        if self._keys is None:
            raise RuntimeError("IncrementalBundle: call start() before add()")
        K, A = self.terms.K, self.terms.A
        lm = _real_array(landmarks, "landmarks", (K, 2), allow_nan=True)
        r = _real_array(rvec, "rvec", (3,))
        t = _real_array(tvec, "tvec", (3,))
        a = _real_array(expression, "expression", (A,))
        w = np.ones(K) if weights is None else _real_array(weights, "weights", (K,))
        if (w < 0).any():
            raise ValueError(f"weights: expected values >= 0, got {w.min()}")
        frame = self._frames
        slot = self.choose(r) if _usable(lm, w) >= MIN_KEYFRAME_POINTS else -1
        keys = {k: (np.array(v, copy=True) if k != "frame" else list(v)) for k, v in self._keys.items()}
        if slot >= 0:
            for name, v in (("landmarks", lm), ("rvecs", r), ("tvecs", t), ("expressions", a), ("weights", w)):
                keys[name][slot] = v
            keys["frame"][slot] = frame
        log.debug("IncrementalBundle: frame %d %s", frame, f"replaces slot {slot}" if slot >= 0 else "not kept")
        res = self._solve(keys, self.identity, self.iterations)
        self._frames += 1
        t_count = self.count + 1
        self.identity = (t_count - 1) / t_count * self.identity + res.identity / t_count  # eq. 10
        self.count = t_count
        return self.identity.copy()

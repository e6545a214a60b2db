"""Landmark residuals of paper 003's bundle adjustment (eq. 4-6) and their Jacobian, on the device.

A :class:`LandmarkModel` is the shape model X(s, a) = mean + (L0 + sum_p s_p G_p) a (eq. 4) of K
points seen by a pinhole camera (eq. 5; a point nearer than ``min_depth`` along the optical axis is
projected as if it were there). :class:`LandmarkFrames` is one solve's data: the n frames' target
landmarks, their square-root weights, the parameters' scale and an optional Gaussian prior on the
identity. For B parameter vectors y (B, P), scaled (x = y * scale, P = n (6 + A) + S packed as
[rvec_0, tvec_0, a_0, ..., rvec_{n-1}, tvec_{n-1}, a_{n-1}, s]), :class:`LandmarkResiduals` gives

- the residuals (B, rows): sqrt(w_ik) (P(p_i, X_ik) - m-hat_ik) ordered (frame, point, u/v) (eq. 6),
  then, with a prior, prior_p (s_p - prior_mean_p);
- their Jacobian with respect to y (B, rows, P): analytic (dm/dY of the projection; dY/dt = I;
  dY/da = R Bs; dY/ds = R G a; d(R X)/dr = -[R X]x J_l(r), J_l the left Jacobian of SO(3)), each
  column times its scale. Only the entries that can be non-zero are written (frame i's rows in
  frame i's columns and the identity's; the prior's diagonal): the rest of the held array stays 0.

It is the residual function of :class:`gputrack.LeastSquaresSolver` for the face tracker's bundle
adjustment on a device (its ``residuals`` and ``jacobian`` callables: the Jacobian is computed with
the residuals and returned by the Jacobian call that follows at the same points), one launch per
iteration and nothing through the host. The model and each solve's data are uploaded once.
The NumPy backend (backends/reference/face_bundle.py) is the oracle.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..device import DeviceArray
from ..models.camera import Camera
from ..uploads import constant
from . import backend_module
from ._args import check_device

__all__ = ["LandmarkFrames", "LandmarkModel", "LandmarkResiduals", "evaluate", "landmark_residuals"]


def _real(x, name: str, shape: tuple) -> np.ndarray:
    a = np.asarray(x, np.float64)
    if a.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: expected finite values, got non-finite ones")
    return a


@dataclasses.dataclass(frozen=True, eq=False)
class LandmarkModel:
    """X(s, a) = mean + (L0 + sum_p s_p G_p) a (eq. 4): mean (K, 3), L0 (K, 3, A), G (K, 3, S, A) in
    mm, seen by ``camera`` (eq. 5); ``min_depth`` mm."""

    mean: np.ndarray
    L0: np.ndarray
    G: np.ndarray
    camera: Camera
    min_depth: float = 1.0

    def __post_init__(self):
        if not isinstance(self.camera, Camera):
            raise TypeError(f"camera: expected a gputrack.models.Camera, got {type(self.camera).__name__}")
        mean = np.asarray(self.mean)
        if mean.ndim != 2 or mean.shape[1] != 3 or mean.shape[0] < 1:
            raise ValueError(f"mean: expected shape (K >= 1, 3), got {mean.shape}")
        K = mean.shape[0]
        L0 = np.asarray(self.L0)
        if L0.ndim != 3 or L0.shape[:2] != (K, 3):
            raise ValueError(f"L0: expected shape (K={K}, 3, A), got {L0.shape}")
        G = np.asarray(self.G)
        if G.ndim != 4 or G.shape[:2] != (K, 3) or G.shape[3] != L0.shape[2]:
            raise ValueError(f"G: expected shape (K={K}, 3, S, A={L0.shape[2]}), got {G.shape}")
        object.__setattr__(self, "mean", _real(mean, "mean", mean.shape))
        object.__setattr__(self, "L0", _real(L0, "L0", L0.shape))
        object.__setattr__(self, "G", _real(G, "G", G.shape))
        if not (np.isfinite(self.min_depth) and self.min_depth > 0):
            raise ValueError(f"min_depth: expected a finite number > 0, got {self.min_depth!r}")

    @property
    def K(self) -> int:
        return self.mean.shape[0]

    @property
    def A(self) -> int:
        return self.L0.shape[2]

    @property
    def S(self) -> int:
        return self.G.shape[2]

    def packed(self) -> np.ndarray:
        """The kernels' constants: fx, fy, cx, cy, min_depth, mean, L0, G (C order), float64."""
        c = self.camera
        head = np.array([c.fx, c.fy, c.cx, c.cy, self.min_depth], np.float64)
        return np.concatenate([head, self.mean.ravel(), self.L0.ravel(), self.G.ravel()])


@dataclasses.dataclass(frozen=True, eq=False)
class LandmarkFrames:
    """One solve's data for a :class:`LandmarkModel` with K points: ``target`` (n, K, 2) px and
    ``sqrt_weights`` (n, K) >= 0 (a landmark of weight 0 adds nothing: give it any finite target),
    ``scale`` (P,) > 0 (x = y * scale; default 1), ``prior`` (S,) >= 0 or None (no prior rows),
    ``prior_mean`` (S,)."""

    target: np.ndarray
    sqrt_weights: np.ndarray
    scale: np.ndarray | None = None
    prior: np.ndarray | None = None
    prior_mean: np.ndarray | None = None

    def check(self, model: LandmarkModel) -> None:
        """Validate against ``model`` (once per solve; the kernels trust these values)."""
        t = np.asarray(self.target)
        if t.ndim != 3 or t.shape[1:] != (model.K, 2) or t.shape[0] < 1:
            raise ValueError(f"target: expected shape (n >= 1, K={model.K}, 2), got {t.shape}")
        n = t.shape[0]
        object.__setattr__(self, "target", _real(t, "target", t.shape))
        sw = _real(self.sqrt_weights, "sqrt_weights", (n, model.K))
        if (sw < 0).any():
            raise ValueError(f"sqrt_weights: expected values >= 0, got {sw.min()}")
        object.__setattr__(self, "sqrt_weights", sw)
        P = n * (6 + model.A) + model.S
        scale = np.ones(P) if self.scale is None else _real(self.scale, "scale", (P,))
        if (scale <= 0).any():
            raise ValueError(f"scale: expected values > 0, got {scale.min()}")
        object.__setattr__(self, "scale", scale)
        if self.prior is not None:
            prior = _real(self.prior, "prior", (model.S,))
            if (prior < 0).any():
                raise ValueError(f"prior: expected values >= 0, got {prior.min()}")
            object.__setattr__(self, "prior", prior)
            object.__setattr__(self, "prior_mean", _real(self.prior_mean, "prior_mean", (model.S,)))

    @property
    def n(self) -> int:
        return self.target.shape[0]

    @property
    def rows(self) -> int:
        """Residuals per parameter vector: 2 K n, plus S with a prior."""
        K = self.target.shape[1]
        return 2 * K * self.n + (0 if self.prior is None else len(self.prior))

    def packed(self, S: int) -> np.ndarray:
        """The kernels' per-solve values: target, sqrt_weights, scale, prior (0 without), prior_mean."""
        prior = np.zeros(S) if self.prior is None else self.prior
        mean = np.zeros(S) if self.prior is None else self.prior_mean
        return np.concatenate([self.target.ravel(), self.sqrt_weights.ravel(), self.scale, prior, mean])


def evaluate(model: LandmarkModel, frames: LandmarkFrames, x, jacobian: bool = True):
    """The same on the host in float64 for unscaled parameters x (B, P) (``frames.scale`` is not
    applied): (residuals (B, rows), Jacobian (B, rows, P) or None). The arguments are trusted
    (:meth:`LandmarkFrames.check` them once)."""
    from ..backends.reference.face_bundle import evaluate as host

    return host(model, frames, np.asarray(x, np.float64), jacobian)


def geometry(model: LandmarkModel, x):
    """The host's camera-frame points Y (B, n, K, 3) of unscaled parameters x (B, P) (eq. 4-5)."""
    from ..backends.reference.face_bundle import geometry as host

    return host(model, np.asarray(x, np.float64))[3]


class LandmarkResiduals:
    """The residuals and Jacobian of one solve on ``device`` (see the module docstring): the model's
    constants and the frames' values uploaded once, output arrays held per number of points B.

    ``residuals(Y)`` (Y (B, P) on the device, or NumPy) returns the residuals (B, rows) and keeps the
    Jacobian computed with them; ``jacobian(Y)`` returns it (B, rows, P) when Y is the last residual
    call's points, else computes it; ``plan(Y)`` returns both. The returned arrays are the held
    ones: read them before the next call."""

    def __init__(self, device, model: LandmarkModel, frames: LandmarkFrames):
        check_device(device)
        if not isinstance(model, LandmarkModel):
            raise TypeError(f"model: expected a LandmarkModel, got {type(model).__name__}")
        if not isinstance(frames, LandmarkFrames):
            raise TypeError(f"frames: expected LandmarkFrames, got {type(frames).__name__}")
        frames.check(model)
        self.device, self.model, self.frames = device, model, frames
        self.P = frames.n * (6 + model.A) + model.S
        self.dtype = np.dtype(np.float64 if device.fp64 else np.float32)
        self._be = backend_module(device, "face_bundle")
        numpy_dev = device.backend == "numpy"
        self._consts = None if numpy_dev else constant(device, model.packed().astype(self.dtype))
        self._values = None if numpy_dev else device.asarray(frames.packed(model.S).astype(self.dtype))
        self._out: dict = {}  # B -> (R, J)
        self._last = None  # the points of the last residual call

    def update(self, frames: LandmarkFrames) -> None:
        """Take the next solve's ``frames`` (the same number of frames, and a prior again if there
        was one): their values go into the held device buffer; the outputs are kept (the Jacobian's
        zero entries stay where they are)."""
        if not isinstance(frames, LandmarkFrames):
            raise TypeError(f"frames: expected LandmarkFrames, got {type(frames).__name__}")
        frames.check(self.model)
        if frames.n != self.frames.n or (frames.prior is None) != (self.frames.prior is None):
            raise ValueError(f"frames: expected {self.frames.n} frames {'without' if self.frames.prior is None else 'with'}"
                             f" a prior (this plan's), got {frames.n} frames {'without' if frames.prior is None else 'with'}"
                             " one")  # fmt: skip
        self.frames = frames
        if self._values is not None:
            self.device.asarray(frames.packed(self.model.S).astype(self.dtype), out=self._values)
        self._last = None

    def _outputs(self, B: int):
        out = self._out.get(B)
        if out is None:
            rows = self.frames.rows
            if self.device.backend == "numpy":
                out = (np.empty((B, rows), self.dtype), np.zeros((B, rows, self.P), self.dtype))
            else:
                out = (self.device.empty((B, rows), self.dtype),
                       self.device.asarray(np.zeros((B, rows, self.P), self.dtype)))  # fmt: skip
            self._out[B] = out
        return out

    def _points(self, Y):
        if isinstance(Y, DeviceArray):
            if Y.device is not self.device:
                raise ValueError(f"points: expected an array on {self.device.spec}, got one on {Y.device.spec}")
        else:
            Y = np.asarray(Y)
        if Y.ndim != 2 or Y.shape[1] != self.P or Y.shape[0] < 1:
            raise ValueError(f"points: expected shape (B >= 1, P={self.P}), got {tuple(Y.shape)}")
        if not isinstance(Y, DeviceArray) and self.device.backend != "numpy":
            Y = self.device.asarray(Y.astype(self.dtype))
        return Y

    def __call__(self, Y):
        """(residuals (B, rows), Jacobian (B, rows, P)) at the points Y (B, P): the held arrays."""
        Y = self._points(Y)
        R, J = self._outputs(Y.shape[0])
        self._be.landmark_residuals(self.device, Y, self.model, self.frames, self._consts, self._values, True,
                                    (R, J))  # fmt: skip
        self._last = Y
        return R, J

    def residuals(self, Y):
        return self(Y)[0]

    def jacobian(self, Y):
        if Y is not self._last:
            self.residuals(Y)
        self._last = None
        return self._outputs(Y.shape[0])[1]


def landmark_residuals(device, points, model: LandmarkModel, frames: LandmarkFrames):
    """The one-shot form of :class:`LandmarkResiduals`: (residuals (B, rows), Jacobian (B, rows, P))
    of the scaled parameter vectors ``points`` (B, P) on ``device``, in new arrays."""
    return LandmarkResiduals(device, model, frames)(points)

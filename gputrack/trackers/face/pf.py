"""The particle filter of paper 003 sec. 4.1: pose and deformation hypotheses scored by NCC (eq. 11-13).

State u = (r (3) Rodrigues vector model -> camera, t (3) mm, a (D) deformation), D = A' of the
multilinear model (or the generic model's coefficients). With the identity s fixed from the last
bundle adjustment the shape is linear in a (eq. 11): M_t = mean + basis a.

Per frame (:meth:`FaceParticleFilter.propose_states`, the projection, the scores, :meth:`FaceParticleFilter.update`):

1. **Sample** (eq. 12): N hypotheses u_i = u'_i + tau v + omega, u'_i drawn from the previous
   hypotheses by their weights (systematic resampling), v the estimate's velocity over the last
   frame (zero for a), omega ~ N(0, diag(sigma^2)): pose noise adapting to speed,
   sigma_pose = base + speed_gain |v| per component (as Oka et al.), and kappa sigma_a for a.
   Components of a whose model std is 0 do not move.
2. **Score** (eq. 13) on the device, one launch: N(u_i) = the sum over the K feature points of
   the zero-mean NCC of their 16 x 16 templates with the image patch at the projected point
   (:func:`gputrack.ops.ncc.patch_ncc`); log pi_i = -(K - N(u_i))^2 / (2 sigma^2)
   - 1/2 sum_b ((a_ib - abar_b) / sigma_a_b)^2, normalised to sum 1.
3. **Estimate**: the weighted mean of the hypotheses near the best one (within ``near`` standard
   deviations of the sampling noise, per component).

The hypotheses are sampled on the host (N (6 + D) values go up); the tracker projects their N K
points on the device (:func:`gputrack.ops.face_points.project_faces`, which also gives each
hypothesis's facing for the turn test of eq. 13) and scores the N K S^2 patch samples there;
:meth:`FaceParticleFilter.propose` is the same on the host.
"""

from __future__ import annotations

import numpy as np

from ...models.camera import Camera
from ...models.pose import facing as pose_facing
from ...models.pose import rodrigues
from ...ops.face_points import project_faces
from ...registry import device as get_device
from .config import FaceConfig

__all__ = ["FaceParticleFilter", "project_hypotheses", "shape_model"]

#: Standard deviations of the hypotheses drawn around a detected face (:meth:`FaceParticleFilter.mix`):
#: rotation (rad, about x, y, z: the frontal cascade fires up to ~30 deg of pitch and yaw, less of
#: roll) and translation as fractions of the depth (x, y, z: the box's centre and size, and the
#: mean shape's scale against the person's)
DETECTION_SPREAD = (0.2, 0.2, 0.1, 0.01, 0.01, 0.05)


def shape_model(mean, basis, dtype=np.float32) -> np.ndarray:
    """The (K, 3, 1 + D) shape model of :func:`gputrack.ops.face_points.project_faces`: the mean
    shape (K, 3) in column 0, the deformation basis (K, 3, D) after it."""
    return np.concatenate([np.asarray(mean, dtype)[:, :, None], np.asarray(basis, dtype)], axis=2)


def project_hypotheses(camera: Camera, states, mean, basis) -> np.ndarray:
    """(N, K, 2) float32 pixels of the K model points of each hypothesis (N, 6 + D) (eq. 5, 11), on
    the host in float64 (:func:`gputrack.ops.face_points.project_faces` on the numpy device)."""
    states = np.asarray(states, np.float64)
    return project_faces(get_device("numpy"), states, shape_model(mean, basis, np.float64), camera)[0]


class FaceParticleFilter:
    """N hypotheses over pose + deformation of one face (sec. 4.1); see the module docstring.

    ``a_mean``/``a_std`` (D,): the model's deformation prior (eq. 13); components with std 0 are
    held at their mean. ``rng``: a seeded ``numpy.random.Generator``. Per frame: :meth:`propose`
    the hypotheses' points, score them on the device, :meth:`update` with the scores.
    """

    def __init__(self, camera: Camera, a_mean, a_std, config: FaceConfig, rng):
        self.camera = camera
        self.config = config
        self.rng = rng
        self.a_mean = np.asarray(a_mean, np.float64)
        a_std = np.asarray(a_std, np.float64)
        self.a_free = a_std > 1e-9 * max(float(a_std.max(initial=0.0)), 1e-300)
        self.a_std = np.where(self.a_free, a_std, 1.0)
        self.D = len(self.a_mean)
        self.K = 0  # feature points, set by reset
        self.proposed = None  # (N, 6 + D) the hypotheses being scored
        self.best_score = 0.0
        self.states = None  # (N, 6 + D) the hypotheses of the last step
        self.weights = None  # (N,)
        self.scores = None  # (N,) N(u_i) of eq. 13
        self.estimate = None  # (6 + D,) the last state estimate
        self.velocity = np.zeros(6 + self.D)
        self._mix = None  # (state, share) of the next proposal's detection hypotheses (:meth:`mix`)
        self._mixed = 0  # how many of the proposed hypotheses (the last ones) were drawn around a detection
        self.from_detection = False  # the last estimate moved to a detection's hypothesis (:meth:`mix`)

    def reset(self, state, K: int) -> None:
        """Start every hypothesis at ``state`` (6 + D,), at rest; ``K`` feature points are scored."""
        self.K = int(K)
        state = np.asarray(state, np.float64)
        if state.shape != (6 + self.D,) or not np.isfinite(state).all():
            raise ValueError(f"state: expected {6 + self.D} finite values, got {state.shape}")
        state = state.copy()
        state[6:][~self.a_free] = self.a_mean[~self.a_free]
        n = self.config.particles
        self.states = np.tile(state, (n, 1))
        self.weights = np.full(n, 1.0 / n)
        self.estimate = state
        self.velocity = np.zeros(6 + self.D)
        self._mix, self._mixed = None, 0

    def noise(self) -> np.ndarray:
        """(6 + D,) standard deviations of omega (eq. 12): pose noise adapted to speed, kappa sigma_a for a."""
        c = self.config
        base = np.concatenate([np.full(3, c.rotation_noise), np.asarray(c.translation_noise, np.float64)])
        pose = base + c.speed_gain * np.abs(self.velocity[:6])
        return np.concatenate([pose, np.where(self.a_free, c.kappa * self.a_std, 0.0)])

    def mix(self, state, share: float) -> None:
        """Draw the fraction ``share`` of the next proposal's hypotheses around ``state`` (6 + D,)
        (a detected face) instead of from the dynamics, with the spread DETECTION_SPREAD (a mixture
        proposal, as the boosted particle filter of Okuma et al., ECCV 2004): eq. 13 then weighs
        them with the others, so that a filter locked on a wrong pose can move to the face again.
        An estimate that moves to one of them starts at rest (the jump is not motion for eq. 12's
        velocity)."""
        state = np.asarray(state, np.float64)
        if state.shape != (6 + self.D,) or not np.isfinite(state).all():
            raise ValueError(f"state: expected {6 + self.D} finite values, got {state.shape}")
        if isinstance(share, bool) or not isinstance(share, (int, float, np.integer, np.floating)) or not 0 <= share <= 1:
            raise ValueError(f"share: expected a fraction in [0, 1], got {share!r}")
        self._mix = (state, float(share))

    def move(self, state) -> None:
        """Move the estimate to ``state`` (6 + D,) (a refinement of it, e.g. fitted to the feature
        points) and every hypothesis with it by the same step; the step counts as motion (eq. 12's
        velocity)."""
        state = np.asarray(state, np.float64)
        if self.estimate is None:
            raise RuntimeError("FaceParticleFilter: call reset() before move()")
        if state.shape != (6 + self.D,) or not np.isfinite(state).all():
            raise ValueError(f"state: expected {6 + self.D} finite values, got {state.shape}")
        step = state - self.estimate
        self.states = self.states + step
        self.velocity = self.velocity + step
        self.estimate = state.copy()

    def sample(self) -> np.ndarray:
        """(N, 6 + D) new hypotheses (eq. 12) from the last ones, resampled by weight (and some around
        a detection, :meth:`mix`)."""
        n = self.config.particles
        u = (self.rng.random() + np.arange(n)) / n  # systematic resampling
        idx = np.minimum(np.searchsorted(np.cumsum(self.weights), u), n - 1)
        drift = self.velocity.copy()
        drift[6:] = 0.0  # eq. 12: no velocity term for the deformation
        out = self.states[idx] + drift + self.rng.standard_normal((n, 6 + self.D)) * self.noise()
        self._mixed = 0
        if self._mix is not None:
            state, share = self._mix
            self._mix = None
            m = self._mixed = round(share * n)
            if m:
                z = abs(state[5])
                spread = np.concatenate([DETECTION_SPREAD[:3], np.asarray(DETECTION_SPREAD[3:]) * z,
                                         np.where(self.a_free, self.config.kappa * self.a_std, 0.0)])  # fmt: skip
                out[n - m:] = state + self.rng.standard_normal((m, 6 + self.D)) * spread
        return out

    def log_weights(self, scores, states, facing=None) -> np.ndarray:
        """Eq. 13 in logs: -(K - N)^2 / (2 sigma^2) - 1/2 sum_b ((a_b - abar_b) / sigma_a_b)^2; -inf for a
        hypothesis whose face is turned more than ``config.max_turn`` degrees from the camera (its
        feature points would be hidden: no NCC can speak for it) or whose depth is outside
        ``config.depth_range`` (a filter that loses the face must not run away in depth).
        ``facing``: the states' cosines between the model's z axis and the ray to the head
        (:func:`gputrack.ops.face_points.project_faces`), where already known."""
        lw = -((self.K - scores) ** 2) / (2.0 * self.config.sigma**2)
        if facing is None:
            facing = pose_facing(rodrigues(states[:, :3]), states[:, 3:6])
        lw[np.asarray(facing) < np.cos(np.radians(self.config.max_turn))] = -np.inf
        lo, hi = self.config.depth_range
        lw[(states[:, 5] < lo) | (states[:, 5] > hi)] = -np.inf  # a head nearer or farther than a camera sees one
        if self.config.prior:
            z = (states[:, 6:] - self.a_mean) / self.a_std
            lw -= 0.5 * np.sum(np.where(self.a_free, z * z, 0.0), axis=1)
        return lw

    def propose(self, mean, basis) -> np.ndarray:
        """Sample the frame's hypotheses (eq. 12) and return their K points (N, K, 2) float32 to score,
        projected on the host (eq. 11 with the shape ``mean`` (K, 3) and ``basis`` (K, 3, D) of the
        current identity); :meth:`propose_states` leaves the projection to the caller's device."""
        return project_hypotheses(self.camera, self.propose_states(), mean, basis)

    def propose_states(self) -> np.ndarray:
        """Sample the frame's hypotheses (eq. 12): (N, 6 + D) float64, also kept as ``proposed``."""
        self.proposed = self.sample()
        return self.proposed

    def update(self, scores, facing=None) -> np.ndarray:
        """Weigh the proposed hypotheses by their NCC sums ``scores`` (N,) (eq. 13) and return the
        state estimate (6 + D,): the weighted mean of the hypotheses near the best one. ``facing``:
        as in :meth:`log_weights`, where the projection computed it."""
        states = self.proposed
        scores = np.asarray(scores, np.float64)
        lw = self.log_weights(scores, states, facing)
        if not np.isfinite(lw).any():  # every hypothesis turned away: keep them all, equally weighted
            lw = np.zeros_like(lw)
        w = np.exp(lw - lw.max())
        w /= w.sum()
        best = int(np.argmax(lw))
        near = np.all(np.abs(states - states[best]) <= self.config.near * np.maximum(self.noise(), 1e-12), axis=1)
        est = np.average(states[near], axis=0, weights=w[near])
        est[6:][~self.a_free] = self.a_mean[~self.a_free]  # held exactly (a weighted mean rounds)
        # a move to a detection's hypothesis (:meth:`mix`) is a new start, not motion
        self.from_detection = best >= len(states) - self._mixed
        self.velocity = np.zeros_like(est) if self.from_detection else est - self.estimate
        self.states, self.weights, self.scores, self.estimate = states, w, scores, est
        self.best_score = float(scores[best])
        return est

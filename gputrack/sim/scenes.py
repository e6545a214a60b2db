"""A neutral multi-target scene: constant-velocity targets, noisy detections, misses and clutter.

Used by the tests and benchmarks of :mod:`gputrack.tracking` (trackers never import this
module). ``cv_scene(rng, frames=..., ...)`` returns a :class:`Scene`: per frame the detections
(shuffled, clutter mixed in) with the ground truth behind them, and the true states of every
target alive. All randomness comes from the ``numpy.random.Generator`` passed in.

Model (paper 001 eq. 1-3, per axis; state order [x xdot y ydot (z zdot)] as
:func:`gputrack.ops.constant_velocity`):

- motion: x_{k+1} = F x_k + G w_k, w_k ~ N(0, q) per axis, G = [dt^2/2, dt]^T;
- detection of a target alive at frame k with probability ``p_detect``: z = H x_k + v,
  v ~ N(0, r^2 I) (H selects the positions);
- clutter: Poisson(``clutter``) detections per frame, uniform over ``extent``;
- births: Poisson(``birth_rate``) targets per frame, uniform positions in ``extent``, velocities
  N(0, ``speed``^2) per axis; deaths: each alive target ends with probability ``death_prob`` per
  frame (a target dies before it moves; one born at frame k is alive from frame k on).
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["Scene", "SceneFrame", "cv_scene"]


@dataclasses.dataclass(frozen=True)
class SceneFrame:
    """One frame of a :class:`Scene`.

    - ``detections`` (D, dim) float32: the detections, in random order;
    - ``source`` (D,) int64: the target id behind each detection, -1 for clutter;
    - ``target_ids`` (K,) int64: the targets alive this frame (ascending);
    - ``states`` (K, 2 dim) float64: their true states, in the order of ``target_ids``.
    """

    detections: np.ndarray
    source: np.ndarray
    target_ids: np.ndarray
    states: np.ndarray


@dataclasses.dataclass(frozen=True)
class Scene:
    """A simulated scene: ``frames`` (list of :class:`SceneFrame`) and the model that made it:
    ``F``, ``Q`` (2 dim, 2 dim) and ``H`` (dim, 2 dim), ``R`` (dim, dim), float64, and ``dt``."""

    frames: list
    F: np.ndarray
    Q: np.ndarray
    H: np.ndarray
    R: np.ndarray
    dt: float

    @property
    def dim(self) -> int:
        return self.H.shape[0]

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, k) -> SceneFrame:
        return self.frames[k]

    def __iter__(self):
        return iter(self.frames)


def _cv_model(dim: int, dt: float, q: float):
    F = np.eye(2 * dim)
    G = np.zeros((2 * dim, dim))
    for a in range(dim):
        F[2 * a, 2 * a + 1] = dt  # eq. 3
        G[2 * a, a], G[2 * a + 1, a] = dt * dt / 2.0, dt  # eq. 2: Gamma
    return F, G, q * G @ G.T


def cv_scene(
    rng: np.random.Generator,
    *,
    frames: int,
    targets: int = 20,
    dim: int = 2,
    dt: float = 1.0,
    q: float = 0.01,
    r: float = 0.1,
    p_detect: float = 0.9,
    clutter: float = 2.0,
    birth_rate: float = 0.5,
    death_prob: float = 0.01,
    extent: float = 100.0,
    speed: float = 1.0,
) -> Scene:
    """Simulate ``frames`` frames of a constant-velocity multi-target scene (see the module).

    ``targets`` alive at frame 0; positions uniform in [0, extent)^dim. Target ids count from 0
    in order of birth. Raises ValueError for a parameter out of range.
    """
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng: expected a numpy.random.Generator (np.random.default_rng(seed)), got "
                        f"{type(rng).__name__}")
    for name, v in (("frames", frames), ("targets", targets), ("dim", dim)):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < (1 if name == "dim" else 0):
            raise ValueError(f"{name}: expected a {'positive' if name == 'dim' else 'non-negative'} integer, got {v!r}")
    for name, v in (("dt", dt), ("extent", extent)):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name}: expected a positive finite number, got {v!r}")
    for name, v in (("q", q), ("r", r), ("clutter", clutter), ("birth_rate", birth_rate), ("speed", speed)):
        if not (np.isfinite(v) and v >= 0):
            raise ValueError(f"{name}: expected a finite number >= 0, got {v!r}")
    for name, v in (("p_detect", p_detect), ("death_prob", death_prob)):
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"{name}: expected a probability in [0, 1], got {v!r}")
    F, G, Q = _cv_model(dim, float(dt), float(q))
    H = np.zeros((dim, 2 * dim))
    H[np.arange(dim), 2 * np.arange(dim)] = 1.0
    R = (r * r) * np.eye(dim)

    def born(k):
        x = np.zeros((k, 2 * dim))
        x[:, 0::2] = rng.uniform(0.0, extent, (k, dim))
        x[:, 1::2] = rng.normal(0.0, speed, (k, dim))
        return x

    ids = np.arange(targets, dtype=np.int64)
    states = born(targets)
    next_id = targets
    out = []
    for k in range(frames):
        if k > 0:
            alive = rng.random(len(ids)) >= death_prob
            ids, states = ids[alive], states[alive]
            w = rng.normal(0.0, np.sqrt(q), (len(ids), dim))
            states = states @ F.T + w @ G.T  # eq. 2
            nb = int(rng.poisson(birth_rate))
            ids = np.concatenate([ids, np.arange(next_id, next_id + nb, dtype=np.int64)])
            states = np.concatenate([states, born(nb)])
            next_id += nb
        seen = rng.random(len(ids)) < p_detect
        z_true = states[seen] @ H.T + rng.normal(0.0, r, (int(seen.sum()), dim))
        nc = int(rng.poisson(clutter))
        z_clutter = rng.uniform(0.0, extent, (nc, dim))
        z = np.concatenate([z_true, z_clutter])
        src = np.concatenate([ids[seen], np.full(nc, -1, np.int64)])
        order = rng.permutation(len(z))
        out.append(
            SceneFrame(
                detections=z[order].astype(np.float32),
                source=src[order],
                target_ids=ids.copy(),
                states=states.copy(),
            )
        )
    return Scene(frames=out, F=F, Q=Q, H=H, R=R, dt=float(dt))

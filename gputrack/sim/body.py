"""Paper 000's simulated input: upper-body motion sequences at 30 fps with ground-truth poses.

``sequence(index, frames=60, seed=0)`` returns a :class:`Sequence`: ``.params`` (F, P) ground
truth (float64), and frames rendered on demand (``seq[i]`` or iteration) with ``.gray``,
``.depth`` (mm, quantised to 5 mm), ``.part`` and ``.params``. Each sequence is a smooth motion
of the 5-part model (:func:`gputrack.models.upper_body`); ``seed`` varies the person's position
and the motion's amplitudes and phases a little, reproducibly (``default_rng([seed, index])``).
The person stays 1.5-2.5 m from the camera and fully in view. :func:`shoulders_off` gives
Table 7's start pose (the shoulders 30 mm off their true positions).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..models.camera import DEFAULT_CAMERA, DEFAULT_SIZE
from ..models.render import render
from ..models.upper_body import upper_body

__all__ = ["FPS", "Frame", "SEQUENCES", "Sequence", "sequence", "sequence_params"]

FPS = 30.0
DEG = np.pi / 180.0

#: names, in index order
SEQUENCES = (
    "arm_swing",  # 0: arms swing forward and back in opposition, elbows flexing
    "arm_raise",  # 1: both arms raised sideways above the shoulders and lowered
    "arm_cross",  # 2: arms brought forward and crossed in front of the torso (occlusion)
    "torso_turn",  # 3: the torso turns left and right, arms hanging
    "wave",  # 4: right arm up, forearm waving; left arm swinging a little
    "reach",  # 5: both arms reach towards the camera, elbows extending
    "sway",  # 6: the whole body sways sideways and back and forth, rolls, arms swing
    "punch",  # 7: alternating punches towards the camera
    "shoulder_spread",  # 8: arms spread beside the torso, lowered about the shoulders (sec. 5.2)
)


def _ease(x):
    """0 -> 1 -> 0 over one period, smooth: (1 - cos 2 pi x) / 2."""
    return 0.5 - 0.5 * np.cos(2.0 * np.pi * x)


def _motion(name: str, t: np.ndarray, amp: float, ph: float):
    """Joint angles in degrees for times t (s): dict of left-arm-style angles and torso values.

    Arms are given as the left arm's angles; the right arm mirrors them (th -> 180 - th for the
    shoulder, th -> -th for the elbow) unless given explicitly.
    """
    z = np.zeros_like(t)
    m = dict(th_O=z, ph_O=z, ps_O=z, dx=z, dy=z, dz=z)
    tau = t + ph
    if name == "arm_swing":
        s = np.sin(2 * np.pi * tau / 1.6)
        m.update(L=(80 + z, 35 * amp * s, z, 30 + 20 * amp * np.sin(2 * np.pi * tau / 1.6 + 0.6)),
                 R=(100 + z, -35 * amp * s, z, 30 - 20 * amp * np.sin(2 * np.pi * tau / 1.6 + 0.6)))  # fmt: skip
    elif name == "arm_raise":
        e = _ease(tau / 3.0)
        e2 = _ease((tau - 0.25) / 3.0)
        m.update(L=(75 - 95 * amp * e, 10 * e, z, 15 + 10 * e),
                 R=(105 + 95 * amp * e2, 10 * e2, z, 15 + 10 * e2))  # fmt: skip
    elif name == "arm_cross":
        e = _ease(tau / 3.2)  # forearms folded across in front of the chest, left over right
        m.update(L=(75 + 20 * e, 45 * amp * e, 75 * amp * e, 20 + z),
                 R=(105 - 20 * e, 35 * amp * e, -75 * amp * e, 20 + 5 * e))  # fmt: skip
    elif name == "torso_turn":
        s = np.sin(2 * np.pi * tau / 3.0)
        m.update(ph_O=25 * amp * s, ps_O=4 * np.sin(2 * np.pi * tau / 2.1), th_O=3 * s,
                 L=(75 + 5 * s, 15 * s, z, 20 + z), R=(105 + 5 * s, -15 * s, z, 20 + z))  # fmt: skip
    elif name == "wave":
        w = np.sin(2 * np.pi * tau / 1.5)
        m.update(L=(78 + 3 * w, 10 * np.sin(2 * np.pi * tau / 2.5), z, 15 + z),
                 R=(210 + 5 * w, 10 + z, 60 + 25 * amp * w, 10 + z))  # fmt: skip
    elif name == "reach":
        e = _ease(tau / 2.8)
        m.update(ps_O=-6 * e, L=(85 + z, 80 * amp * e, z, 90 - 80 * e), R=(95 + z, 80 * amp * e, z, 90 - 80 * e))
    elif name == "sway":
        s = np.sin(2 * np.pi * tau / 3.5)
        c = np.sin(2 * np.pi * tau / 4.5)
        m.update(dx=120 * amp * s, dz=150 * c, th_O=8 * amp * s, ps_O=4 * c,
                 L=(75 - 15 * s, 25 * c, z, 25 + 15 * s), R=(105 - 15 * s, -25 * c, z, 25 - 15 * s))  # fmt: skip
    elif name == "punch":
        a = _ease(tau / 2.0)
        b = _ease(tau / 2.0 + 0.5)
        m.update(ph_O=-8 * (a - b),
                 L=(95 - 10 * a, 35 + 45 * amp * a, z, 100 - 90 * a),
                 R=(85 + 10 * b, 35 + 45 * amp * b, z, 100 - 90 * b))  # fmt: skip
    elif name == "shoulder_spread":
        e = np.clip(tau / 2.5, 0.0, 1.0)
        e = e * e * (3 - 2 * e)  # smoothstep: spread (th = 0) -> hanging (th = 75)
        m.update(L=(75 * amp * e, 5 + z, z, 0 * z), R=(180 - 75 * amp * e, 5 + z, z, 0 * z))
    else:
        raise ValueError(f"sequence: expected one of {', '.join(SEQUENCES)}, got {name!r}")
    return m


def _resolve(index) -> tuple[int, str]:
    if isinstance(index, str):
        if index not in SEQUENCES:
            raise ValueError(f"sequence: expected one of {', '.join(SEQUENCES)}, got {index!r}")
        return SEQUENCES.index(index), index
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < len(SEQUENCES):
        raise ValueError(f"sequence index: expected 0..{len(SEQUENCES) - 1} or a name, got {index!r}")
    return int(index), SEQUENCES[int(index)]


def sequence_params(index, frames: int = 60, seed: int = 0, shoulders: bool = False) -> np.ndarray:
    """Ground-truth parameters (frames, 14) or (frames, 20) float64 of sequence ``index`` at 30 fps."""
    i, name = _resolve(index)
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
        raise ValueError(f"frames: expected a positive integer, got {frames!r}")
    chain = upper_body(shoulders=shoulders)
    rng = np.random.default_rng([int(seed), i])
    amp = rng.uniform(0.85, 1.1)
    phase = rng.uniform(0.0, 0.3)
    base = np.array([rng.uniform(-120, 120), rng.uniform(-60, 60), rng.uniform(1800, 2150)])
    t = np.arange(frames) / FPS
    m = _motion(name, t, amp, phase)
    lth, lph, lthe, lphe = (np.asarray(v, float) for v in m["L"])
    if "R" in m:
        rth, rph, rthe, rphe = (np.asarray(v, float) for v in m["R"])
    else:
        rth, rph, rthe, rphe = 180 - lth, lph, -lthe, lphe
    p = np.zeros((frames, chain.n_params))
    p[:, 0] = m["th_O"] * DEG
    p[:, 1] = m["ph_O"] * DEG
    p[:, 2] = m["ps_O"] * DEG
    p[:, 3] = base[0] + m["dx"]
    p[:, 4] = base[1] + m["dy"]
    p[:, 5] = base[2] + m["dz"]
    p[:, 6], p[:, 7] = rth * DEG, rph * DEG
    p[:, 8], p[:, 9] = lth * DEG, lph * DEG
    p[:, 10], p[:, 11] = rthe * DEG, rphe * DEG
    p[:, 12], p[:, 13] = lthe * DEG, lphe * DEG
    if shoulders:
        p[:, 14:] = chain.rest_params()[14:]
    return p


@dataclasses.dataclass(frozen=True)
class Frame:
    """One simulated frame: input images and the ground truth."""

    index: int
    time: float  # seconds
    params: np.ndarray  # (P,) float64 ground truth
    gray: np.ndarray  # (H, W) float32 in [0, 1]
    depth: np.ndarray  # (H, W) float32 mm, quantised; 0 = no measurement
    part: np.ndarray  # (H, W) int32 part id, -1 = background
    points: np.ndarray  # (H, W, 3) float32 camera-space points of the (unquantised) surface


class Sequence:
    """A simulated sequence: ground truth ``params`` (F, P) and frames rendered on demand."""

    def __init__(self, index, frames: int = 60, seed: int = 0, *, shoulders: bool = False, camera=None,
                 size=DEFAULT_SIZE, noise: float = 0.0, **render_kwargs):  # fmt: skip
        self.index, self.name = _resolve(index)
        self.seed = int(seed)
        self.chain = upper_body(shoulders=shoulders)
        self.camera = camera or DEFAULT_CAMERA
        self.size = tuple(size)
        self.fps = FPS
        self.noise = float(noise)
        self.render_kwargs = render_kwargs
        self.params = sequence_params(self.index, frames, seed, shoulders)
        self.params.setflags(write=False)

    def __len__(self) -> int:
        return self.params.shape[0]

    def __repr__(self) -> str:
        return f"Sequence({self.index} {self.name!r}, frames={len(self)}, seed={self.seed})"

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not -n <= i < n:
            raise IndexError(f"frame index: expected an integer in [-{n}, {n}), got {i!r}")
        i = int(i) % n
        rng = np.random.default_rng([self.seed, self.index, i]) if self.noise > 0 else None
        r = render(self.chain, self.params[i], self.camera, self.size, noise=self.noise, rng=rng, **self.render_kwargs)
        return Frame(i, i / self.fps, self.params[i].copy(), r.gray, r.depth, r.part, r.points)

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]


def sequence(index, frames: int = 60, seed: int = 0, **kwargs) -> Sequence:
    """Sequence ``index`` (0..8 or a name from :data:`SEQUENCES`) with ``frames`` frames at 30 fps.

    Keyword arguments: ``shoulders`` (20-parameter ground truth), ``camera``, ``size``,
    ``noise`` (gray noise sigma, seeded per frame) and :func:`gputrack.models.render.render` options.
    """
    return Sequence(index, frames, seed, **kwargs)


def shoulders_off(params, seed: int, mm: float = 30.0) -> np.ndarray:
    """A copy of the 20-parameter pose ``params`` with t_RS and t_LS each moved ``mm`` in a seeded direction.

    Table 7's start: the shoulder positions are not known, the tracker starts them off by 30 mm.
    """
    out = np.array(params, dtype=np.float64)
    if out.shape != (20,):
        raise ValueError(f"params: expected a 20-parameter pose (shoulders estimated), got shape {out.shape}")
    direction = np.random.default_rng([7, seed]).normal(size=(2, 3))
    out[14:] += (mm * direction / np.linalg.norm(direction, axis=1, keepdims=True)).ravel()
    return out

"""Articulated models as data: a kinematic chain of rigid parts (paper 000, eq. 2-11).

A :class:`Chain` is a tuple of :class:`Part` objects in topological order (every part's parent
comes before it). Each part's joint is a rigid transform parent-from-part

    D = [ R_a0(p[i0]) R_a1(p[i1]) R_a2(p[i2]) | t ],   t_k = offset_k + (p[tidx_k] if tidx_k >= 0)

with up to three rotation axes (``"x"``, ``"y"``, ``"z"``) whose angles (radians) are entries of
the parameter vector ``p``, and a translation that is a fixed offset plus, per axis, optionally
a parameter (millimetres). The root's parent is the camera, so the root's joint is the
camera-from-root pose. Forward kinematics composes camera-from-part = camera-from-parent @ D.

- the torso's free joint of eq. 6-9: ``axes="zyx"`` (R = Rz(th) Ry(ph) Rx(ps)), translation from
  three parameters (t_O);
- a shoulder or elbow of eq. 10-11: ``axes="zy"`` (R = Rz(th) Ry(ph)), translation the fixed joint
  position t_S / t_E in the parent's coordinates, or taken from parameters (t_RS, t_LS of eq. 25-27).

Each part also carries a :class:`Shape` (its surface, for rendering and for the template).
The chain is plain data; :meth:`Chain.packed` gives the small integer/float tables that the
device kernels read, so that kernels are generic over the chain (any number of parts).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ..abi import ANGLE_MAX
from ..device import per_device_cache

__all__ = ["AXES", "Chain", "Part", "Shape", "chain_tables", "compose", "joint_transform", "rotation"]

#: axis letter -> code used in the packed tables (-1 = no rotation)
AXES = {"x": 0, "y": 1, "z": 2}

#: columns of the packed int32 table, one row per part
PACK_COLUMNS = ("parent", "axis0", "axis1", "axis2", "angle0", "angle1", "angle2", "trans0", "trans1", "trans2")


@dataclasses.dataclass(frozen=True)
class Shape:
    """The surface of a part, in that part's coordinates (millimetres).

    ``kind`` is ``"capsule"`` (a circular cylinder of radius ``radii[0]`` along ``axis`` from
    ``start`` to ``end``, closed by hemispheres) or ``"cylinder"`` (an elliptic cylinder along
    ``axis`` from ``start`` to ``end`` with flat caps; semi-axes ``radii`` along the two other axes
    in increasing axis order, e.g. (x, z) for ``axis=1``).
    """

    kind: str
    axis: int
    start: float
    end: float
    radii: tuple[float, float]

    def __post_init__(self):
        if self.kind not in ("capsule", "cylinder"):
            raise ValueError(f"shape kind: expected 'capsule' or 'cylinder', got {self.kind!r}")
        if self.axis not in (0, 1, 2):
            raise ValueError(f"shape axis: expected 0, 1 or 2, got {self.axis!r}")
        if not self.end > self.start:
            raise ValueError(f"shape extent: expected end > start, got start={self.start}, end={self.end}")
        if len(self.radii) != 2 or min(self.radii) <= 0:
            raise ValueError(f"shape radii: expected two positive semi-axes, got {self.radii!r}")
        if self.kind == "capsule" and self.radii[0] != self.radii[1]:
            raise ValueError(f"capsule radii: expected a circular section (equal radii), got {self.radii!r}")

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """(centre (3,), radius) of a sphere enclosing the shape, in part coordinates."""
        centre = np.zeros(3)
        centre[self.axis] = 0.5 * (self.start + self.end)
        half = 0.5 * (self.end - self.start) + (max(self.radii) if self.kind == "capsule" else 0.0)
        return centre, float(np.hypot(half, max(self.radii)))


@dataclasses.dataclass(frozen=True)
class Part:
    """One rigid part and the joint that attaches it to its parent (-1: the camera)."""

    name: str
    parent: int
    axes: str  # rotation axes applied left to right, e.g. "zyx" (eq. 6) or "zy" (eq. 10-11)
    angles: tuple[int, ...]  # parameter index of each rotation angle (radians)
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  # fixed translation in parent coords (mm)
    translation: tuple[int, int, int] = (-1, -1, -1)  # parameter added to each offset axis, -1: none
    shape: Shape | None = None

    def __post_init__(self):
        if len(self.axes) > 3 or any(a not in AXES for a in self.axes):
            raise ValueError(f"part {self.name}: axes: expected up to 3 of 'x', 'y', 'z', got {self.axes!r}")
        if len(self.angles) != len(self.axes):
            raise ValueError(
                f"part {self.name}: angles: expected one parameter index per axis ({len(self.axes)}), "
                f"got {self.angles!r}"
            )
        if len(self.offset) != 3 or len(self.translation) != 3:
            raise ValueError(f"part {self.name}: offset and translation: expected 3 entries each")

    @property
    def params(self) -> tuple[int, ...]:
        """The parameter indices this joint reads (angles, then translation)."""
        return tuple(self.angles) + tuple(i for i in self.translation if i >= 0)


@dataclasses.dataclass(frozen=True)
class Chain:
    """A kinematic chain: parts in topological order and the size of the parameter vector.

    ``rest`` is a natural parameter vector (a plausible pose, the model's generic joint positions
    where they are parameters); ``param_names`` names every parameter.
    """

    parts: tuple[Part, ...]
    n_params: int
    param_names: tuple[str, ...]
    rest: tuple[float, ...]
    name: str = "chain"

    def __post_init__(self):
        if not self.parts:
            raise ValueError("chain: expected at least one part, got none")
        if len(self.param_names) != self.n_params or len(self.rest) != self.n_params:
            raise ValueError(
                f"chain: expected {self.n_params} parameter names and rest values, "
                f"got {len(self.param_names)} and {len(self.rest)}"
            )
        for j, p in enumerate(self.parts):
            if not -1 <= p.parent < j:
                raise ValueError(f"part {j} ({p.name}): parent: expected -1 or an earlier part (< {j}), got {p.parent}")
            for i in p.params:
                if not 0 <= i < self.n_params:
                    raise ValueError(f"part {j} ({p.name}): parameter index {i} outside [0, {self.n_params})")

    # -- description ---------------------------------------------------------------------------
    @property
    def n_parts(self) -> int:
        return len(self.parts)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parts)

    def index(self, name: str) -> int:
        """The index of the part called ``name``."""
        for j, p in enumerate(self.parts):
            if p.name == name:
                return j
        raise KeyError(f"no part named {name!r}; parts: {', '.join(self.names)}")

    def rest_params(self, dtype=np.float64) -> np.ndarray:
        """The rest parameter vector, (P,)."""
        return np.asarray(self.rest, dtype=dtype)

    def ancestors(self, j: int) -> tuple[int, ...]:
        """Part ``j`` and every part above it, from ``j`` up to the root."""
        out = []
        while j >= 0:
            out.append(j)
            j = self.parts[j].parent
        return tuple(out)

    def dependency_mask(self) -> np.ndarray:
        """(J, P) bool: part j's pose depends on parameter n (its own joint's and its ancestors')."""
        return self._dependency.copy()

    @functools.cached_property
    def _dependency(self) -> np.ndarray:
        mask = np.zeros((self.n_parts, self.n_params), dtype=bool)
        for j in range(self.n_parts):
            for a in self.ancestors(j):
                mask[j, list(self.parts[a].params)] = True
        return mask

    def jacobian_sparsity(self, part_of_residual) -> np.ndarray:
        """(M, P) bool: the Fig. 2 block pattern of the Jacobian for residuals of the given parts.

        ``part_of_residual`` (M,) holds the part index of each residual; row m is True for the
        parameters that part's pose depends on (its own and its ancestors'), False elsewhere.
        """
        parts = np.asarray(part_of_residual)
        if parts.ndim != 1 or parts.dtype.kind not in "iu":
            raise ValueError(f"part_of_residual: expected a 1-D integer array, got shape {parts.shape} {parts.dtype}")
        if parts.size and (parts.min() < 0 or parts.max() >= self.n_parts):
            raise ValueError(
                f"part_of_residual: expected part indices in [0, {self.n_parts}), got {parts.min()}..{parts.max()}"
            )
        return self.dependency_mask()[parts]

    # -- kinematics on the host ----------------------------------------------------------------
    def transforms(self, params) -> np.ndarray:
        """Camera-from-part transforms (B, J, 3, 4) float64 of parameter vectors (B, P), on the host.

        The readable form of forward kinematics (the device op is
        :func:`gputrack.ops.kinematics.forward_kinematics`): each part's joint transform D
        composed onto its parent's camera-from-part transform.
        """
        p = np.asarray(params, dtype=np.float64)
        t = np.empty((p.shape[0], self.n_parts, 3, 4), dtype=np.float64)
        for j, part in enumerate(self.parts):
            d = joint_transform(part, p)  # eq. 6 (root), eq. 10 (shoulder), eq. 11 (elbow)
            if part.parent < 0:
                t[:, j] = d  # eq. 4: camera-from-root is the root's pose D
            else:
                t[:, j] = compose(t[:, part.parent], d)  # eq. 2-3: D D_OU, D D_OU D_UL
        return t

    # -- tables for the kernels ----------------------------------------------------------------
    def packed(self) -> tuple[np.ndarray, np.ndarray]:
        """(table (J, 10) int32, offsets (J, 3) float64): the chain as the kernels read it.

        Columns of ``table``: parent, axis code of rotations 0-2 (-1 unused), parameter index of
        angles 0-2 (-1 unused), parameter index added to translation x, y, z (-1 none).
        """
        table = np.full((self.n_parts, len(PACK_COLUMNS)), -1, dtype=np.int32)
        offsets = np.zeros((self.n_parts, 3), dtype=np.float64)
        for j, p in enumerate(self.parts):
            table[j, 0] = p.parent
            for k, (a, i) in enumerate(zip(p.axes, p.angles)):
                table[j, 1 + k] = AXES[a]
                table[j, 4 + k] = i
            table[j, 7:10] = p.translation
            offsets[j] = p.offset
        return table, offsets

    def structure(self) -> tuple:
        """``packed()``'s table as nested tuples of ints (hashable): what a kernel compiled for
        this chain's structure needs, the offsets aside."""
        return self._structure

    @functools.cached_property
    def _structure(self) -> tuple:
        return tuple(tuple(int(v) for v in row) for row in self.packed()[0])

    def key(self) -> tuple:
        """A hashable summary of what the kernels read (for caching uploaded tables)."""
        return self._key

    @functools.cached_property
    def _key(self) -> tuple:
        table, offsets = self.packed()
        return (self.n_params, table.tobytes(), offsets.tobytes())


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Product of rigid transforms [Ra|ta] [Rb|tb] = [Ra Rb | Ra tb + ta], batched (..., 3, 4)."""
    r = a[..., :3] @ b[..., :3]
    t = a[..., :3] @ b[..., 3:] + a[..., 3:]
    return np.concatenate([r, t], axis=-1)


def rotation(axis: str, angle) -> np.ndarray:
    """Rotation matrices about ``axis`` for an array of angles: (..., 3, 3) (eq. 7-9)."""
    angle = np.asarray(angle)
    c, s = np.cos(angle), np.sin(angle)
    one, zero = np.ones_like(c), np.zeros_like(c)
    if axis == "x":  # eq. 7
        rows = [[one, zero, zero], [zero, c, -s], [zero, s, c]]
    elif axis == "y":  # eq. 8
        rows = [[c, zero, s], [zero, one, zero], [-s, zero, c]]
    elif axis == "z":  # eq. 9
        rows = [[c, -s, zero], [s, c, zero], [zero, zero, one]]
    else:
        raise ValueError(f"axis: expected 'x', 'y' or 'z', got {axis!r}")
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def rotation_zyx(th, ph, ps) -> np.ndarray:
    """Rz(th) Ry(ph) Rx(ps) (eq. 6): (..., 3, 3) for arrays of angles."""
    return rotation("z", th) @ rotation("y", ph) @ rotation("x", ps)


def clamp_angle(a) -> np.ndarray:
    """Finite angles clamped to [-ANGLE_MAX, ANGLE_MAX] rad (gputrack/abi.py: what every backend's
    forward kinematics does before sin and cos); inf and NaN are kept."""
    a = np.asarray(a)
    return np.where(np.isfinite(a) & (np.abs(a) > ANGLE_MAX), np.copysign(ANGLE_MAX, a).astype(a.dtype), a)


def joint_transform(part: Part, params: np.ndarray) -> np.ndarray:
    """Parent-from-part transforms (B, 3, 4) of one joint for parameters (B, P) (eq. 6, 10, 11);
    angles past ANGLE_MAX are clamped (:func:`clamp_angle`)."""
    params = np.asarray(params)
    b = params.shape[0]
    r = np.broadcast_to(np.eye(3, dtype=params.dtype), (b, 3, 3))
    for axis, i in zip(part.axes, part.angles):
        r = r @ rotation(axis, clamp_angle(params[:, i]))
    t = np.broadcast_to(np.asarray(part.offset, dtype=params.dtype), (b, 3)).copy()
    for k, i in enumerate(part.translation):
        if i >= 0:
            t[:, k] += params[:, i]
    return np.concatenate([r, t[:, :, None]], axis=2)


# device -> {(chain key, dtype): (table, offsets)}; weak so that a closed device's arrays go with it
_TABLES = per_device_cache()


def chain_tables(device, chain: Chain, dtype=np.float32):
    """The chain's :meth:`Chain.packed` tables on ``device``: (table (J, 10) int32, offsets (J, 3)
    of ``dtype``), uploaded once per device, chain and dtype and cached (every kernel that poses
    the chain reads them)."""
    per_device = _TABLES.setdefault(device, {})
    key = (chain.key(), np.dtype(dtype).name)
    if key not in per_device:
        table, offsets = chain.packed()
        per_device[key] = (device.asarray(table), device.asarray(offsets.astype(dtype)))
    return per_device[key]

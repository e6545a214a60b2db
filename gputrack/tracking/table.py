"""The track table: every track of a tracker in one set of device arrays, one row per slot.

Device arrays (of the table's device, float32 by default), C = capacity::

    x       (C, n)      state of each slot
    P       (C, n, n)   covariance of each slot
    active  (C,) uint8  1 where a slot holds a track (read by the gate; uploaded when it changed)

Host mirror of the lifecycle, (C,) each::

    ids     int64   the track's id (-1 in a free slot); ids count up from 0 and are never reused
    status  uint8   TrackStatus: FREE, TENTATIVE, CONFIRMED
    hits    int32   frames in which the track was detected (its first detection counts)
    misses  int32   consecutive frames without a detection, up to the last one
    age     int32   frames since the track started (1 in the frame it starts)

The mirror is computed from what the host already has (the assignment of each frame, which the
association downloads anyway, and the births it decides), so keeping it costs no transfer. The
states never come to the host unless asked for: :meth:`TrackTable.tracks` downloads them.

Every op runs over all C slots (predict, gate, update in one launch each); a free slot keeps
finite values (zeros and an identity covariance when the table grows, the last track's state
after a deletion) and is never gated (``active``) or updated (the update's mask). Rows of free
slots are unspecified to the user.

Growth: when the free slots run out, the capacity doubles (up to ``max_capacity``): new arrays
are made on the device and the old rows copied into them with one
:func:`gputrack.ops.rows.scatter_rows` call per array, without a host round trip per track.
Full: :meth:`TrackTable.add` raises :class:`TrackTableFull` when the tracks asked for do not fit
in ``max_capacity``; :meth:`TrackTable.room` says how many do (the tracker's initiator starts
only that many; see :class:`gputrack.tracking.MofNInitiator`).
"""

from __future__ import annotations

import dataclasses
import enum

import numpy as np

from ..device import Device, DeviceArray
from ..ops._args import check_device
from ..uploads import constant
from ..ops.rows import scatter_rows
from ._staging import Staging

__all__ = ["TrackStatus", "TrackTable", "TrackTableFull", "Tracks"]


class TrackStatus(enum.IntEnum):
    """The state of a slot (the ``status`` mirror holds these values as uint8)."""

    FREE = 0  # an empty slot
    TENTATIVE = 1  # started, not yet confirmed
    CONFIRMED = 2  # confirmed (M of N detections)


class TrackTableFull(RuntimeError):
    """More tracks were added than ``max_capacity`` holds."""


@dataclasses.dataclass(frozen=True)
class Tracks:
    """A host copy of the tracks of a table, sorted by id (K tracks).

    ``ids`` (K,) int64, ``status`` (K,) uint8, ``x`` (K,n), ``P`` (K,n,n) or None (not
    downloaded), ``hits``, ``misses``, ``age`` (K,) int32, ``slots`` (K,) int64 (their rows).
    """

    ids: np.ndarray
    status: np.ndarray
    x: np.ndarray
    P: np.ndarray | None
    hits: np.ndarray
    misses: np.ndarray
    age: np.ndarray
    slots: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


def _to_host(a) -> np.ndarray:
    return a.numpy() if isinstance(a, DeviceArray) else a


class TrackTable:
    """All tracks of one tracker in device arrays of ``capacity`` slots (see the module).

    ``n``: state size; ``capacity``: initial slots (>= 1); ``max_capacity``: the most slots the
    table grows to; ``dtype``: float32 (default) or float64 where the device has it.
    """

    def __init__(self, device: Device, n: int, *, capacity: int = 64, max_capacity: int = 1 << 20, dtype=np.float32):
        self.device = check_device(device)
        for name, v in (("n", n), ("capacity", capacity), ("max_capacity", max_capacity)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name}: expected a positive integer, got {v!r}")
        if capacity > max_capacity:
            raise ValueError(f"capacity: expected at most max_capacity={max_capacity}, got {capacity}")
        dt = np.dtype(dtype)
        if dt not in (np.float32, np.float64):
            raise TypeError(f"dtype: expected float32 or float64, got {dt.name}")
        self.dtype = self.device.check_dtype(dt)
        self.n = int(n)
        self.max_capacity = int(max_capacity)
        self.next_id = 0
        C = int(capacity)
        self.ids = np.full(C, -1, np.int64)
        self.status = np.zeros(C, np.uint8)
        self.hits = np.zeros(C, np.int32)
        self.misses = np.zeros(C, np.int32)
        self.age = np.zeros(C, np.int32)
        self.x, self.P = self._fresh(C)
        self.active = self.device.asarray(np.zeros(C, np.uint8))
        self._active_dirty = False
        self._staging = Staging(self.device)

    # -- sizes -------------------------------------------------------------------------------
    @property
    def capacity(self) -> int:
        return len(self.ids)

    @property
    def size(self) -> int:
        """The number of tracks (occupied slots)."""
        return int(np.count_nonzero(self.status))

    def __len__(self) -> int:
        return self.size

    def slots(self, status: TrackStatus | None = None) -> np.ndarray:
        """Occupied slots (ascending), or those of one status."""
        if status is None:
            return np.flatnonzero(self.status)
        return np.flatnonzero(self.status == status)

    def room(self) -> int:
        """How many more tracks fit (growing up to ``max_capacity``)."""
        return self.max_capacity - self.size

    # -- device arrays -----------------------------------------------------------------------
    def _fresh(self, C: int):
        """New device arrays of C slots holding x = 0, P = I (finite values for the free slots)."""
        x = np.zeros((C, self.n), self.dtype)
        P = np.broadcast_to(np.eye(self.n, dtype=self.dtype), (C, self.n, self.n)).copy()
        return self.device.asarray(x), self.device.asarray(P)

    def _grow(self, need: int) -> None:
        """Make room for ``need`` slots: double the capacity (capped at max_capacity); the old
        rows are copied on the device, one scatter_rows call per array."""
        C = self.capacity
        new = C
        while new < need:
            new *= 2
        new = min(new, self.max_capacity)
        x, P = self._fresh(new)
        keep = self.device.asarray(np.arange(C, dtype=np.int32))
        self.x = scatter_rows(self.device, x, keep, self.x)
        self.P = scatter_rows(self.device, P, keep, self.P)
        grow = new - C
        self.ids = np.concatenate([self.ids, np.full(grow, -1, np.int64)])
        for name in ("status", "hits", "misses", "age"):
            a = getattr(self, name)
            setattr(self, name, np.concatenate([a, np.zeros(grow, a.dtype)]))
        self.active = self.device.asarray((self.status != TrackStatus.FREE).astype(np.uint8))
        self._active_dirty = False

    def sync_active(self):
        """The ``active`` device array, uploaded first if the occupied slots changed (C bytes)."""
        if self._active_dirty:
            self.active = self.device.asarray((self.status != TrackStatus.FREE).astype(np.uint8), out=self.active)
            self._active_dirty = False
        return self.active

    # -- lifecycle ---------------------------------------------------------------------------
    def add(self, x0, P0, status: TrackStatus = TrackStatus.TENTATIVE):
        """Start k tracks with states x0 (k,n) and covariances P0 (k,n,n), or one covariance
        (n,n) for all of them (host arrays, finite; a shared P0 is uploaded once per value).

        They take the lowest free slots (the table grows if needed) and new ids in order, with
        hits = age = 1 and misses = 0. Returns (slots (k,) int64, ids (k,) int64). Raises
        TrackTableFull if they do not fit in max_capacity (nothing is added then).
        """
        if isinstance(x0, DeviceArray) or isinstance(P0, DeviceArray):
            raise TypeError("x0, P0: expected host (NumPy) arrays, got a DeviceArray")
        x0 = np.asarray(x0)
        P0 = np.asarray(P0)
        if x0.ndim != 2 or x0.shape[1] != self.n:
            raise ValueError(f"x0: expected shape (k, {self.n}), got {x0.shape}")
        k = x0.shape[0]
        if P0.shape != (k, self.n, self.n) and P0.shape != (self.n, self.n):
            raise ValueError(f"P0: expected shape ({k}, {self.n}, {self.n}) or ({self.n}, {self.n}) (one for all), "
                             f"got {P0.shape}")  # fmt: skip
        for name, a in (("x0", x0), ("P0", P0)):
            if a.dtype.kind not in "iuf":
                raise TypeError(f"{name}: expected a real array, got dtype {a.dtype.name}")
            if not np.isfinite(a).all():
                bad = np.argwhere(~np.isfinite(a))[0]
                where = tuple(int(i) for i in bad)
                raise ValueError(f"{name}: expected finite values, got {a[tuple(bad)]} at index {where}")
        status = TrackStatus(status)
        if status == TrackStatus.FREE:
            raise ValueError("status: expected TENTATIVE or CONFIRMED for a new track, got FREE")
        if k > self.room():
            raise TrackTableFull(
                f"track table full: {k} new tracks asked for, {self.room()} fit (max_capacity {self.max_capacity} "
                f"holds {self.size} tracks); raise max_capacity or delete tracks first"
            )
        if k == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        free = np.flatnonzero(self.status == TrackStatus.FREE)
        if len(free) < k:
            self._grow(self.size + k)
            free = np.flatnonzero(self.status == TrackStatus.FREE)
        slots = free[:k]
        index, _ = self._staging.put_rows("index", slots.astype(np.int32))
        xs, _ = self._staging.put_rows("x0", x0.astype(self.dtype, copy=False))
        scatter_rows(self.device, self.x, index, xs, n_rows=k)
        if P0.ndim == 2:  # one covariance for every new track: uploaded once per value
            Ps = constant(self.device, np.ascontiguousarray(P0[None], dtype=self.dtype))
        else:
            Ps, _ = self._staging.put_rows("P0", P0.astype(self.dtype, copy=False))
        scatter_rows(self.device, self.P, index, Ps, n_rows=k)
        ids = np.arange(self.next_id, self.next_id + k, dtype=np.int64)
        self.next_id += k
        self.ids[slots] = ids
        self.status[slots] = status
        self.hits[slots] = 1
        self.misses[slots] = 0
        self.age[slots] = 1
        self._active_dirty = True
        return slots.astype(np.int64), ids

    def remove(self, slots) -> np.ndarray:
        """Free the given slots (occupied ones; host only). Returns the ids they held."""
        slots = np.asarray(slots, dtype=np.int64).reshape(-1)
        if slots.size == 0:
            return np.zeros(0, np.int64)
        if slots.min() < 0 or slots.max() >= self.capacity:
            raise ValueError(f"slots: expected slots in [0, {self.capacity}), got {slots.min()}..{slots.max()}")
        if (self.status[slots] == TrackStatus.FREE).any():
            raise ValueError(f"slots: expected occupied slots, got free slot {int(slots[self.status[slots] == 0][0])}")
        ids = self.ids[slots].copy()
        self.ids[slots] = -1
        self.status[slots] = TrackStatus.FREE
        self.hits[slots] = self.misses[slots] = self.age[slots] = 0
        self._active_dirty = True
        return ids

    def record(self, detected) -> None:
        """Book one frame: every track ages by one; ``detected`` (C,) bool marks the slots that
        were updated with a detection (hits + 1, misses = 0), the others miss (misses + 1)."""
        detected = np.asarray(detected, dtype=bool)
        if detected.shape != (self.capacity,):
            raise ValueError(f"detected: expected shape ({self.capacity},), got {detected.shape}")
        occupied = self.status != TrackStatus.FREE
        self.age += occupied
        self.hits += occupied & detected
        self.misses = np.where(occupied & ~detected, self.misses + 1, 0).astype(np.int32)

    def confirm(self, slots) -> np.ndarray:
        """Mark tentative slots confirmed; returns their ids."""
        slots = np.asarray(slots, dtype=np.int64).reshape(-1)
        self.status[slots] = TrackStatus.CONFIRMED
        return self.ids[slots].copy()

    # -- reading -----------------------------------------------------------------------------
    def tracks(self, *, covariance: bool = False, status: TrackStatus | None = None) -> Tracks:
        """Download the tracks (x, and P with ``covariance``), sorted by id; optionally of one status."""
        slots = self.slots(status)
        slots = slots[np.argsort(self.ids[slots], kind="stable")]
        x = _to_host(self.x)[slots]
        P = _to_host(self.P)[slots] if covariance else None
        return Tracks(self.ids[slots].copy(), self.status[slots].copy(), x, P, self.hits[slots].copy(),
                      self.misses[slots].copy(), self.age[slots].copy(), slots)  # fmt: skip

    def __repr__(self) -> str:
        return f"TrackTable({self.size} tracks, capacity {self.capacity}, n={self.n}, {self.device.spec})"

"""Group tracker of paper 001 (Hoshikawa et al.): groups of people followed by the 3D points of
their KLT tracks, one extended Kalman filter per group, all groups in one device table.

A frame (:meth:`GroupTracker.update_points`, the observation-level entry point) is two stages
of a :class:`gputrack.Scheduler` over one device table of the groups (a (C, 96) float32 row per
slot: state, Kalman covariance, spread, live flag, this frame's moments and merge candidates):

=========  ===========================================================================  ======
stage      what                                                                         where
=========  ===========================================================================  ======
track      the points and their velocities uploaded once, (N, 3) each; then one         device
           call (:func:`gputrack.ops.point_groups.group_frame`, one launch on Taichi):
           every group predicted with constant velocity x = [x xdot y ydot z zdot]
           (eq. 1-3); all points x all groups: gate (eq. 8), tie-break m_p m_v (eq.
           9-11); each group's point count, mean and covariance; the spreads (eq. 7);
           the stereo EKF update from the mean of each group's points as z = [u v d]
           (eq. 4-6) for every group with at least ``min_points`` points (the others
           are predicted only); the merge pre-test of every pair (bounding spheres)
groups     the table and the labels downloaded (two reads); merges (eq. 13-15: the      host,
           exact test of the pre-test's pairs), splits, new groups from unassigned      small
           points whose search regions overlap (eq. 12), deletions; the table goes
           back to the device only on a frame where a rule changed it
=========  ===========================================================================  ======

Per frame the host moves the points and velocities (N x 24 bytes) in and the labels (N int32)
and the table (C x 96 float32) out; nothing else, and no Python loop over points or groups runs
unless a rule fires.

Rules beyond the paper, written down:

- **Gate**: eq. 8 with the position block of the group's spread Sigma widened by
  diag(``min_spread``^2) (mm^2; velocity block likewise), so that a group of one person, or one
  whose points were all in a line, still gates its own points; the merge test uses the same.
- **Merge** (eq. 13): groups whose gate regions intersect in position *and* in velocity
  (exact ellipsoid test, :func:`rules.ellipsoids_overlap`, at ``merge_gamma``) merge, all
  connected groups at once. The velocity region is centred on the mean velocity of the group's
  points this frame (the state's velocity, observed only through positions, lags a change of
  pace by the filter's time constant; the KLT tracks measure it directly), or on the state's
  where the group has fewer than ``min_points`` points. The merged group keeps the id of the
  oldest member (ties: the lowest id), its state and spread by eq. 14-15 (weights: the members'
  points this frame), its Kalman covariance by the same rule. Merging runs after splits and
  starts, so a group started beside an existing one from the points that one lost for a frame
  (an occlusion) is merged back into it at once.
- **Split**: a group whose points fall into two or more sets, each with at least ``min_new``
  points, for ``split_frames`` frames in a row, splits: the largest set keeps the id, each
  other becomes a new group (with its points' mean, spread and velocity). The sets are cut
  where the points' projections on the group's principal axis leave a gap wider than
  ``link_radius`` (so eq. 12's relation does not link them), examined only for groups wider
  than one person along that axis (standard deviation above ``link_radius`` / 2). People
  walking apart end as two groups.
- **Start**: unassigned points whose ``link_radius`` regions overlap are linked (eq. 12:
  connected components of the radius graph); a component of at least ``min_new`` points starts
  a group. (The device call is skipped when fewer than ``min_new`` of the
  unassigned points have any neighbour within ``link_radius``, a necessary condition checked on
  the host for up to 256 points: a launch costs more than that test.)
- **End**: a group with fewer than ``min_points`` points for more than ``max_missed`` frames in a
  row is deleted. Ids are never reused.

- **Surface to axis**: KLT points lie on the surfaces facing the camera, in front of the people's
  axes; each point is moved ``surface_offset`` mm further along its viewing ray first, so that a
  group's state is the mean of its members' axes rather than of their visible fronts.

Units: millimetres and frames (velocities in mm per frame), camera coordinates x right, y down,
z forward.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import NamedTuple

import numpy as np

from ...device import Device, DeviceArray, as_host_array
from ...models.camera import StereoCamera
from ...ops import constant_velocity, radius_components
from ...ops._args import check_device
from ...ops.point_groups import (
    ACTIVE,
    CAND,
    COLUMNS,
    COUNT,
    MAX_CAND,
    MEAN,
    NCAND,
    SEEN,
    SIGMA,
    P,
    X,
    group_constants,
    group_frame,
)
from ...scheduler import Scheduler, Stage
from . import rules
from .front import FrontEndConfig, StereoFrontEnd
from .rules import POS, VEL

__all__ = ["Group", "GroupConfig", "GroupFrame", "GroupTracker"]



@dataclasses.dataclass(frozen=True)
class GroupConfig:
    """Constants of the group tracker (paper 001), with the paper's values where it gives them.

    - ``gamma``: eq. 8 gate on the squared Mahalanobis distance (chi-square 3 dof, 99 %);
    - ``alpha_s``: eq. 7 weight of the previous spread;
    - ``min_points``: a group is updated from its points only with at least this many (paper: 2);
    - ``link_radius``: eq. 12 search region, mm (paper: 1 m);
    - ``min_new``: points a linked set needs to start a group (and each part to split one);
    - ``merge_gamma``: eq. 13 regions (squared Mahalanobis radius in position and velocity);
    - ``split_frames``: frames a group's points must stay apart before it splits;
    - ``max_missed``: frames without ``min_points`` points before a group ends;
    - ``q``: acceleration variance of the constant-velocity model, (mm/frame^2)^2;
    - ``R``: (3,) observation variances of the group mean's (u, v, d), px^2;
    - ``p0``: (2,) initial standard deviations of a new group's position (mm) and velocity (mm/frame);
    - ``min_spread``: (2,) standard deviations added to the spread for gating and merging, position
      (mm) and velocity (mm/frame);
    - ``capacity``: initial slots of the group table (it grows);
    - ``surface_offset``: mm each point is moved away from the camera along its viewing ray, from
      the visible surface of a person to the body's axis (about a body's half depth; 0: off);
    - ``front``: the stereo front end's constants (:class:`FrontEndConfig`) for :meth:`GroupTracker.track`.
    """

    gamma: float = 11.34
    alpha_s: float = 0.9
    min_points: int = 2
    link_radius: float = 1000.0
    min_new: int = 8
    merge_gamma: float = 11.34
    split_frames: int = 12
    max_missed: int = 24
    q: float = 1.0
    R: tuple = (16.0, 16.0, 0.04)
    p0: tuple = (150.0, 8.0)
    min_spread: tuple = (150.0, 3.0)
    capacity: int = 16
    surface_offset: float = 120.0
    front: FrontEndConfig = dataclasses.field(default_factory=FrontEndConfig)

    def __post_init__(self):
        if not (isinstance(self.surface_offset, (int, float)) and 0 <= self.surface_offset < 1e4):
            raise ValueError(f"GroupConfig.surface_offset: expected a distance in [0, 1e4) mm, got {self.surface_offset!r}")
        if not isinstance(self.front, FrontEndConfig):
            raise TypeError(f"GroupConfig.front: expected a FrontEndConfig, got {type(self.front).__name__}")
        for name in ("gamma", "link_radius", "merge_gamma", "q"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
                raise ValueError(f"GroupConfig.{name}: expected a positive finite number, got {v!r}")
        if not (isinstance(self.alpha_s, (int, float)) and 0.0 <= self.alpha_s <= 1.0):
            raise ValueError(f"GroupConfig.alpha_s: expected a weight in [0, 1], got {self.alpha_s!r}")
        for name in ("min_points", "min_new", "split_frames", "max_missed", "capacity"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"GroupConfig.{name}: expected a positive integer, got {v!r}")
        for name, k in (("R", 3), ("p0", 2), ("min_spread", 2)):
            v = np.asarray(getattr(self, name), dtype=float)
            if v.shape != (k,) or not (np.isfinite(v).all() and (v > 0).all()):
                raise ValueError(f"GroupConfig.{name}: expected {k} positive finite numbers, got {getattr(self, name)!r}")


class Group(NamedTuple):
    """One tracked group: ``position`` (3,) mm and ``velocity`` (3,) mm/frame (camera frame),
    ``covariance`` (6, 6) the Kalman covariance of the state [x xdot y ydot z zdot],
    ``spread`` (6, 6) the spread of its points (eq. 7), ``n_points`` this frame, ``age`` frames.
    (A named tuple: a frame lists every group, and a tuple is made in a fifth of a frozen
    dataclass's time.)"""

    id: int
    position: np.ndarray
    velocity: np.ndarray
    covariance: np.ndarray
    spread: np.ndarray
    n_points: int
    age: int


@dataclasses.dataclass(frozen=True)
class GroupFrame:
    """One frame's result: ``labels`` (N,) int64 the group id of each point (-1: none);
    ``groups`` the live groups (ascending id); ``started``, ``merged`` ((absorbed id, into id)
    pairs), ``split`` ((new id, from id) pairs), ``ended``: what changed. From :meth:`GroupTracker.track`
    also ``uv`` (N, 2) the points' pixels in the left image and ``foreground`` the share of
    foreground pixels (None from :meth:`GroupTracker.update_points`)."""

    labels: np.ndarray
    groups: list
    started: list
    merged: list
    split: list
    ended: list
    uv: np.ndarray | None = None
    foreground: float | None = None


def _points(a, name: str, N=None) -> np.ndarray:
    if isinstance(a, DeviceArray):
        raise TypeError(f"{name}: expected host (NumPy) points (N, 3), got a DeviceArray")
    h = as_host_array(a, name)
    if h.dtype.kind not in "iuf":
        raise TypeError(f"{name}: expected real values, got dtype {h.dtype.name}")
    if h.size == 0 and h.ndim <= 2:
        h = h.reshape(0, 3)
    if h.ndim != 2 or h.shape[1] != 3 or (N is not None and len(h) != N):
        want = "(N, 3)" if N is None else f"(N={N}, 3)"
        raise ValueError(f"{name}: expected shape {want}, got {h.shape}")
    if np.isinf(h).any():
        bad = tuple(int(i) for i in np.argwhere(np.isinf(h))[0])
        raise ValueError(f"{name}: expected finite values or NaN rows (no point), got {h[bad]} at index {bad}")
    return h.astype(np.float32, copy=False)


def _components(device, points: np.ndarray, radius: float) -> np.ndarray:
    """Connected components of the graph linking points within ``radius`` (eq. 12), on the
    device (:func:`gputrack.ops.radius_components`): (k,) labels. The points are padded with NaN
    rows (no point) to a power of two, so that the kernels see a few sizes only (an OpenCL driver
    may compile a kernel again for every new launch size)."""
    k = len(points)
    if k == 0:
        return np.zeros(0, np.int64)
    rows = max(16, 1 << (k - 1).bit_length())
    padded = np.full((rows, 3), np.nan, np.float32)
    padded[:k] = points
    labels = radius_components(device, padded, float(radius), n_points=k)
    return np.asarray(labels if device.backend == "numpy" else labels.numpy())[:k].astype(np.int64)


class GroupTracker:
    """Paper 001's group tracker on one device (see the module for the frame and the rules).

    ``camera``: the rectified stereo pair (:class:`gputrack.models.StereoCamera`, f in pixels,
    baseline in mm); ``config``: :class:`GroupConfig`; ``profile``: time each stage on the device.
    """

    def __init__(self, device: Device, *, camera: StereoCamera, config: GroupConfig | None = None,
                 profile: bool = False):  # fmt: skip
        self.device = check_device(device)
        if not isinstance(camera, StereoCamera):
            raise TypeError(f"camera: expected a gputrack.models.StereoCamera, got {type(camera).__name__}")
        config = GroupConfig() if config is None else config
        if not isinstance(config, GroupConfig):
            raise TypeError(f"config: expected a GroupConfig, got {type(config).__name__}")
        self.camera, self.config = camera, config
        F, Q = constant_velocity(3, 1.0, config.q)
        consts = group_constants(F, Q, config.R, f=camera.f, b=camera.b, cx=camera.cx, cy=camera.cy,
                                 gamma=config.gamma, alpha_s=config.alpha_s, min_points=config.min_points,
                                 min_spread=config.min_spread, surface_offset=config.surface_offset,
                                 merge_gamma=config.merge_gamma)  # fmt: skip
        self._floor = np.zeros((6, 6))
        self._floor[POS, POS], self._floor[VEL, VEL] = config.min_spread[0] ** 2, config.min_spread[1] ** 2
        C = config.capacity
        self.ids = np.full(C, -1, np.int64)  # host mirror of the table: -1 = free slot
        self.age = np.zeros(C, np.int64)
        self.missed = np.zeros(C, np.int64)
        self.apart = np.zeros(C, np.int64)  # frames in a row a group's points stayed apart
        self._set_table(_empty_table(C))
        self.next_id = 0
        self._host = None  # the points and velocities padded with NaN rows, reused frame after frame
        self.front = StereoFrontEnd(self.device, camera, config.front, profile=profile)
        self.scheduler = Scheduler(self.device, [
            Stage("track", self._track, reads=("points", "velocities", "table", "constants"),
                  writes=("table", "labels")),
            Stage("groups", self._groups, host_reads=("table", "labels"), writes=("table",)),
        ], inputs=("points", "velocities"), state=("table", "constants"), profile=profile)  # fmt: skip
        self.scheduler.set("constants", consts)
        self.scheduler.set("table", self._t.astype(np.float32))
        self._frame = None

    # -- the table on the host -------------------------------------------------------------------
    @property
    def capacity(self) -> int:
        return len(self.ids)

    def _set_table(self, t: np.ndarray) -> None:
        """The host mirror (C, 96) float64 of the device table and its views: x (C, 6), P and
        Sigma (C, 6, 6)."""
        C = len(t)
        self._t = t
        self._x = t[:, X : X + 6]
        self._P = t[:, P : P + 36].reshape(C, 6, 6)
        self.Sigma = t[:, SIGMA : SIGMA + 36].reshape(C, 6, 6)

    def _grow(self, need: int) -> None:
        C = self.capacity
        new = max(2 * C, need)
        grow = new - C
        self.ids = np.concatenate([self.ids, np.full(grow, -1, np.int64)])
        for name in ("age", "missed", "apart"):
            setattr(self, name, np.concatenate([getattr(self, name), np.zeros(grow, np.int64)]))
        self._set_table(np.concatenate([self._t, _empty_table(grow)]))

    # -- one frame -----------------------------------------------------------------------------
    def update_points(self, xyz, velocity) -> GroupFrame:
        """Track one frame of observation points: ``xyz`` (N, 3) mm camera coordinates, ``velocity``
        (N, 3) mm per frame (host arrays; a NaN row is no point). Returns a :class:`GroupFrame`."""
        y = _points(xyz, "xyz")
        lam = _points(velocity, "velocity", len(y))
        N = len(y)
        h = self._host  # (2, rows, 3): the points, then their velocities
        if h is None or h.shape[1] < N or h.shape[1] > 4 * max(N, 16):  # a power of two rows (few shapes)
            h = self._host = np.full((2, max(16, 1 << max(N - 1, 0).bit_length()), 3), np.nan, np.float32)
        h[0, :N], h[1, :N] = y, lam
        h[:, N:] = np.nan
        self._frame = {"y": y, "lam": lam, "n": N}
        try:
            self.scheduler.run(points=h[0], velocities=h[1])
            return self._result
        finally:
            self._frame = None

    def track(self, left, right) -> GroupFrame:
        """The whole pipeline on one rectified pair (H, W) uint8 grey each: subtraction stereo and
        KLT (:class:`StereoFrontEnd`, ``self.front``), then :meth:`update_points`. Until the
        background is learnt (``config.front.background_frames`` frames, or
        :meth:`learn_background`) a frame has no points and the groups are only predicted."""
        pts = self.front.points(left, right)
        fr = self.update_points(pts.xyz, pts.velocity)
        return dataclasses.replace(fr, uv=pts.uv, foreground=pts.foreground)

    def learn_background(self, lefts) -> None:
        """The left camera's background from empty frames (F, H, W) uint8 (per-pixel median)."""
        self.front.learn_background(lefts)

    def _track(self, b) -> None:
        """The device's part of the frame, one call: predict, gate, moments, spreads, update,
        merge pre-test (:func:`gputrack.ops.point_groups.group_frame`)."""
        pts = b["points"]
        lab = b.get("labels")
        if lab is not None and lab.shape[0] != pts.shape[0]:
            lab = None
        b["table"], b["labels"] = group_frame(self.device, b["table"], pts, b["velocities"], b["constants"],
                                              n_points=self._frame["n"], labels=lab)  # fmt: skip

    def _offset(self, y: np.ndarray) -> np.ndarray:
        """Points moved ``surface_offset`` mm along their viewing rays, as the device moved them."""
        off = self.config.surface_offset
        if not off or not len(y):
            return y
        r = np.sqrt(y[:, 0] * y[:, 0] + y[:, 1] * y[:, 1] + y[:, 2] * y[:, 2])
        with np.errstate(invalid="ignore", divide="ignore"):
            return y * (np.float32(1) + np.float32(off) / np.where(r > 0, r, np.float32(np.nan)))[:, None]

    def _groups(self, b) -> None:
        cfg = self.config
        N = self._frame["n"]
        self._set_table(np.array(b["table"], np.float64))  # the host mirror of this frame
        t = self._t
        labels = b["labels"][:N].astype(np.int64)
        seen = (t[:, SEEN] > 0.5) & (self.ids >= 0)
        live = self.ids >= 0
        self.age[live] += 1
        self.missed = np.where(live & ~seen, self.missed + 1, 0)
        y, lam = self._frame["y"], self._frame["lam"]
        owner = labels  # each point's slot (-1: none, and every point that is no point), changed by the rules
        split = self._split(owner, y, lam)
        started = self._start(owner, y, lam)
        merged = self._merge(owner, lam, exact=bool(split or started))
        gone = np.flatnonzero((self.ids >= 0) & (self.missed > cfg.max_missed))
        ended = [int(i) for i in self.ids[gone]]
        self.ids[gone] = -1
        t = self._t  # (a new array if a start or split grew the table)
        changed = bool(merged or split or started or ended) or len(t) != b["table"].shape[0]
        if changed:  # the rules changed the table: it goes back to the device, whole
            t[:, ACTIVE] = self.ids >= 0
            b["table"] = self._put(t.astype(np.float32))
        out = np.where(owner >= 0, self.ids[np.maximum(owner, 0)], -1)
        counts = np.bincount(owner[owner >= 0], minlength=self.capacity) if changed else t[:, COUNT].astype(np.int64)
        self._result = GroupFrame(out, self._list(self._x, self._P, counts), started, merged, split, ended)

    def _put(self, host):
        """``host`` (the table) on the device, into last frame's array when the shape still fits."""
        dev = self.scheduler.buffers.get("table")
        if self.device.backend == "numpy":
            if dev is not None and dev.shape == host.shape:
                dev[...] = host
                return dev
            return host.copy()
        if dev is not None and tuple(dev.shape) == host.shape and dev.dtype == host.dtype:
            return self.device.asarray(host, out=dev)
        return self.device.asarray(host)

    # the rules, on the host copies of the table --------------------------------------------------
    def _merge(self, owner, lam, *, exact: bool) -> list:
        """Eq. 13-15: groups whose regions intersect in position and velocity become one. The
        device listed the pairs whose bounding spheres meet (``group_frame``); only those get the
        exact test, unless a split or a start changed the table this frame (``exact``: every
        pair, on the host)."""
        cfg, t = self.config, self._t
        live = np.flatnonzero(self.ids >= 0)
        if len(live) < 2:
            return []
        ncand = t[:, NCAND].astype(np.int64)
        if not exact and (ncand[live] > MAX_CAND).any():
            exact = True
        if not exact and not ncand[live].any():
            return []
        if exact:
            counts = np.bincount(owner[owner >= 0], minlength=self.capacity).astype(np.float64)
            vsum = np.stack([np.bincount(owner[owner >= 0], lam[owner >= 0, a], minlength=self.capacity)
                             for a in range(3)], 1)  # fmt: skip
            centre = self._x[live].copy()
            has = counts[live] >= cfg.min_points
            centre[np.ix_(np.flatnonzero(has), VEL)] = vsum[live[has]] / counts[live[has], None]
            pairs = rules.overlapping_pairs(centre, self._gate_spreads()[live], cfg.merge_gamma)
        else:  # the device's candidates: counts and mean velocities are this frame's
            counts = t[:, COUNT]
            i = np.repeat(live, np.minimum(ncand[live], MAX_CAND))
            j = t[live][:, CAND : CAND + MAX_CAND][np.arange(MAX_CAND)[None, :] < ncand[live, None]].astype(np.int64)
            if not len(i):
                return []
            centre = self._x.copy()
            has = counts >= cfg.min_points
            centre[np.ix_(np.flatnonzero(has), VEL)] = t[np.ix_(np.flatnonzero(has), MEAN + VEL)]
            G = self._gate_spreads()
            keep = np.ones(len(i), bool)
            for idx in (POS, VEL):
                keep &= rules.ellipsoids_overlap(centre[i][:, idx], G[i][:, idx][:, :, idx], centre[j][:, idx],
                                                 G[j][:, idx][:, :, idx], cfg.merge_gamma)  # fmt: skip
            rank = np.full(self.capacity, -1, np.int64)
            rank[live] = np.arange(len(live))
            pairs = np.stack([rank[i[keep]], rank[j[keep]]], 1)
        if not len(pairs):
            return []
        comp = _union(len(live), pairs)
        out = []
        for c in np.unique(comp):
            members = live[comp == c]
            if len(members) < 2:
                continue
            order = sorted(members, key=lambda s: (-self.age[s], self.ids[s]))
            keep = order[0]  # the oldest group keeps its id
            w = counts[members]
            xs = self._x[members].copy()
            self._x[keep], self.Sigma[keep] = rules.merge_states(w, xs, self.Sigma[members].copy())
            _, self._P[keep] = rules.merge_states(w, xs, self._P[members].copy())
            self.missed[keep] = self.missed[members].min()
            for s in order[1:]:
                out.append((int(self.ids[s]), int(self.ids[keep])))
                owner[owner == s] = keep
                self.ids[s] = -1
        return out

    def _split(self, owner, y, lam) -> list:
        """A group whose points stay in two or more sets for ``split_frames`` frames splits (see
        the module): the sets are cut where the points' projections on the group's principal
        axis leave a gap wider than ``link_radius`` (then no point of one set is within
        link_radius of the other: eq. 12's relation does not link them). Only groups wider than
        a person along that axis (standard deviation above link_radius / 2) are examined."""
        cfg = self.config
        live = np.flatnonzero(self.ids >= 0)
        B = self.Sigma[live][:, POS][:, :, POS]
        c = (cfg.link_radius / 2) ** 2
        wide = rules.may_exceed(B, c)  # the largest eigenvalue may exceed c: eigh for those only
        axes = np.zeros((len(live), 3))
        if wide.any():
            w, V = np.linalg.eigh(B[wide])
            axes[wide] = V[:, :, -1]
            wide[wide] = w[:, -1] > c
        self.apart[live[~wide]] = 0
        out = []
        if not wide.any():
            return out
        order_all = np.argsort(owner, kind="stable")
        bounds = np.searchsorted(owner[order_all], np.arange(self.capacity + 1))
        for s, axis in zip(live[wide], axes[wide]):
            mine = order_all[bounds[s] : bounds[s + 1]]
            ym = self._offset(y[mine])
            proj = ym @ axis
            order = np.argsort(proj, kind="stable")
            cut = np.concatenate([[0], np.flatnonzero(np.diff(proj[order]) > cfg.link_radius) + 1, [len(mine)]])
            parts = [order[a:b] for a, b in itertools.pairwise(cut) if b - a >= cfg.min_new]
            if len(parts) < 2:
                self.apart[s] = 0
                continue
            self.apart[s] += 1
            if self.apart[s] < cfg.split_frames:
                continue
            self.apart[s] = 0
            parts.sort(key=len, reverse=True)
            for i, k in enumerate(parts):
                m, S = rules.moments(ym[k], lam[mine[k]])
                if i == 0:  # the largest part keeps the group
                    self._x[s, POS], self.Sigma[s] = m[POS], S
                    continue
                new = self._add(m, S, self._P[s].copy())
                owner[mine[k]] = new
                out.append((int(self.ids[new]), int(self.ids[s])))
        return out

    def _start(self, owner, y, lam) -> list:
        """Eq. 12: unassigned points whose search regions overlap, linked; big sets start groups."""
        cfg = self.config
        free = np.flatnonzero(owner < 0)
        if len(free) < cfg.min_new:
            return []
        yf = self._offset(y[free])
        ok = np.isfinite(yf).all(1) & np.isfinite(lam[free]).all(1)
        free, yf = free[ok], yf[ok]
        if len(free) < cfg.min_new or not _may_link(yf, cfg.link_radius, cfg.min_new):
            return []
        comp = _components(self.device, yf, cfg.link_radius)
        ids, n = np.unique(comp[comp >= 0], return_counts=True)
        p0 = np.zeros(6)
        p0[POS], p0[VEL] = cfg.p0[0] ** 2, cfg.p0[1] ** 2
        out = []
        for c in ids[n >= cfg.min_new]:
            k = np.flatnonzero(comp == c)
            m, S = rules.moments(yf[k], lam[free[k]])
            slot = self._add(m, S, np.diag(p0))
            owner[free[k]] = slot
            out.append(int(self.ids[slot]))
        return out

    def _add(self, m, S, P0) -> int:
        """A new group in the lowest free slot (the table grows when full); returns the slot."""
        free = np.flatnonzero(self.ids < 0)
        if not len(free):
            self._grow(self.capacity + 1)
            free = np.flatnonzero(self.ids < 0)
        s = int(free[0])
        self.ids[s] = self.next_id
        self.next_id += 1
        self.age[s], self.missed[s], self.apart[s] = 1, 0, 0
        self.Sigma[s] = S
        self._x[s], self._P[s] = m, P0
        return s

    def _gate_spreads(self) -> np.ndarray:
        """The spreads the gate and the merge test use: Sigma + diag(min_spread^2) (see the module)."""
        return self.Sigma + self._floor

    # -- reading -------------------------------------------------------------------------------
    def groups(self) -> list:
        """The live groups (ascending id), downloaded from the device (n_points: 0)."""
        t = np.asarray(self.device.to_numpy(self.scheduler.buffers["table"]), np.float64)
        C = len(t)
        return self._list(t[:, X : X + 6], t[:, P : P + 36].reshape(C, 6, 6), np.zeros(C, np.int64))

    def _list(self, x, P, counts) -> list:
        live = np.flatnonzero(self.ids >= 0)
        live = live[np.argsort(self.ids[live], kind="stable")]
        xs = x[live]
        columns = (self.ids[live].tolist(), list(xs[:, POS]), list(xs[:, VEL]), list(P[live]), list(self.Sigma[live]),
                   counts[live].tolist(), self.age[live].tolist())  # fmt: skip
        return list(map(Group, *columns))


def _empty_table(C: int) -> np.ndarray:
    """C free slots of the group table (float64 host mirror): identity P and Sigma."""
    t = np.zeros((C, COLUMNS))
    eye = np.eye(6).ravel()
    t[:, P : P + 36] = eye
    t[:, SIGMA : SIGMA + 36] = eye
    return t


def _may_link(points: np.ndarray, radius: float, need: int) -> bool:
    """Whether the radius graph of the points may have a component of ``need`` or more points:
    decided on the host for up to 256 points, with the radius widened by a margin over the
    device's float32 test (so False is certain), else assumed."""
    k = len(points)
    if need < 2 or k > 256:
        return True
    from scipy.spatial import cKDTree

    pairs = cKDTree(points.astype(np.float64)).query_pairs(radius * (1 + 1e-5), output_type="ndarray")
    if len(pairs) < need - 1 or len(np.unique(pairs)) < need:  # a tree of `need` points has need - 1 edges
        return False
    return int(np.bincount(_union(k, pairs)).max()) >= need


def _union(k: int, pairs: np.ndarray) -> np.ndarray:
    """Connected components of k nodes joined by ``pairs`` (m, 2): (k,) labels, each node's
    smallest connected index (eq. 13's relation, transitive; and the host test of eq. 12's).
    Minimum-label propagation along the edges with pointer jumping: few NumPy passes on the small
    graphs of a frame, where scipy's csgraph costs ~0.15 ms in conversions."""
    lab = np.arange(k)
    if not len(pairs):
        return lab
    a, b = np.asarray(pairs[:, 0], np.intp), np.asarray(pairs[:, 1], np.intp)
    while True:
        m = np.minimum(lab[a], lab[b])
        new = lab.copy()
        np.minimum.at(new, a, m)
        np.minimum.at(new, b, m)
        new = new[new]
        if (new == lab).all():
            return lab
        lab = new

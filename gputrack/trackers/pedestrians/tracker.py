"""Pedestrian tracker of paper 002 (Ukyo et al.): pedestrians from a level depth camera's frames,
one Kalman filter per pedestrian, all of them in one device table.

A frame (:meth:`PedestrianTracker.track`) is five stages of a :class:`gputrack.Scheduler`:

=========  ===========================================================================  ======
stage      what                                                                         where
=========  ===========================================================================  ======
predict    every track, constant velocity x = [x xdot y ydot z zdot], one launch         device
points     foreground vs background, back-projection, 5 m cut, 1024 random points       device
           (:func:`gputrack.ops.depth_points`, sec. 4.1)
segments   the points above the sensor, ground-plane DBSCAN (:func:`gputrack.ops.dbscan`),  device,
           segment positions and volumes (sec. 4.2; :mod:`.front`)                      host
associate  Hungarian assignment on eq. 1-3, the causes of unassigned pedestrians and      host,
           segments (Fig. 6-7), new and deleted tracks, each track's observation and      small
           occlusion gain (eq. 4-6); the weak segments nobody took are dropped
update     every observed track, one :func:`gputrack.ops.kf_update` with ``gain_scale``    device
=========  ===========================================================================  ======

The host waits for the device three times a frame: for the count and the points (one read after
the depth image's upload and the five kernels, enqueued without a wait on OpenCL), for the DBSCAN
labels together with the predicted table (x, P: predicted first, so that they come back in the
same wait; the front end's :class:`~.front.FrameCopies`), and for the updated x at the end. The
associate stage's uploads (the table where it changed; z, mask and gain as one copy into one
buffer on OpenCL) are enqueued without a wait, into the buffers of the last frame.

Rules (sec. 4.3), written down:

- **Assignment**: pedestrians (stage 1), then the split/merge children (stage 2, on the segments
  left, or their parent's), each by :func:`rules.assign` on c = alpha d + (1 - alpha)|V_j - V_i|
  (eq. 1-3, d in m, V in m^3), pairs farther than ``max_distance`` or differing in volume by more
  than ``max_volume_change`` rejected. A track's V_i is the volume of its last observation.
  Beyond the paper (``weak_points``), a cluster of at least ``weak_points`` but fewer than
  ``min_segment_points`` points is a *weak* segment, as ByteTrack keeps its low-score detections:
  stage 1 assigns the (strong) segments, then the pedestrians left over take weak ones (stage 1b);
  a weak segment nobody took starts nothing and is dropped (its points are loose, for the faint
  rule below). A far child shows only its head and shoulders above the sensor, often in 8-11 of
  the 1024 points: too few to start a pedestrian on, enough to be seen again.
  Beyond the paper (``gated``), leaving a track or a segment unassigned costs half the largest
  feasible cost, so the assignment does not make two far pairs where one near pair and two left
  over cost less (a missed track taking a neighbour's segment, the neighbour then taking the next).
- **Unassigned pedestrian** (Fig. 6): if it has split/merge children, it is updated from them
  (below); else if its predicted position lies inside a segment (ground-plane box grown by
  ``containment_margin``) that another pedestrian k took and, beyond the paper, that segment is
  at least ``merge_volume`` times k's largest recent volume (else it holds k alone: the other is
  hidden behind k or gone), the two have *merged*: a child track
  starts at that segment with parents {i, k}, k's assignment is undone, and both parents are
  predicted only in this first frame; inside a segment nobody took, it is that pedestrian's own
  segment whose volume changed too much (a merge of one): assigned. Beyond the paper: a
  pedestrian whose prediction lies in the shadow of a nearer segment (behind it, within its
  bearings) is hidden there, predicted only and kept but not output (``report_hidden=True``:
  output at its prediction with status "hidden"), for up to ``max_hidden`` frames (a depth
  camera's full occlusion:
  in the ground plane the two are apart, so DBSCAN never merges them; when it reappears the
  assignment finds it again, with its id). Otherwise it *left*: after ``max_missed`` (2)
  unmatched frames in a row it is deleted; beyond the paper (``leave_view``), at once when its
  prediction is beyond the image's left or right side (widened by ``view_margin`` mm at its
  depth): it walked out of the view, and a track kept there would take the next person who
  enters at that side.
- **Unassigned segment** (Fig. 7): if it lies inside a pedestrian's predicted extent (its last
  segment's box centred on the prediction, half extents at least ``person_radius`` across and
  ``person_depth`` along the view, grown by ``containment_margin``), is no larger than
  ``split_volume`` times its largest volume of the last frames and of this frame's own segment
  (else someone beside it entered)
  and, beyond the paper (``split_occluder``), is not seen apart from the pedestrian's nearest
  part (where the frame reads the background through a gap wider than ``split_gap`` between their
  bearings they are two people, :func:`rules.seen_apart`; a nearer reading there, an occluder
  moving or static, or missing readings keep the split), that pedestrian has *split*
  (occlusion): each part gets a child track with that parent.
  A split part later seen apart from the others so becomes a pedestrian of its own (a new id;
  a child on the pedestrian's own segment is the pedestrian itself). A pedestrian merged in the
  frame before and seen whole now can split like any other.
  Otherwise a pedestrian *entered*: a new one at the segment's position with zero velocity.
  Segments are taken largest first, so a person who enters in two pieces is one new pedestrian
  with a split part (the same extent as any pedestrian's: two people who enter side by side are
  told apart by the gap seen between them).
- **Faint pedestrian** (beyond the paper): a pedestrian left without an observation that has at
  least ``faint_points`` of the points no segment kept within ``faint_radius`` of its prediction is
  observed from them (status "faint"): a far person gets few of the 1024 points, often too few for
  a segment, and would otherwise be deleted after 2 frames and come back with a new id.
- **Parents**: a parent with two or more observed parts (its own segment and its split
  children's) is updated from their combined points (the midpoint of the union of their boxes,
  volume the sum); with one observed child only, from the child's displacement since its last
  frame applied to the parent's position (predicted only in the child's first frame). A merged
  parent is never updated from the merged segment itself. A parent *seen again* (assigned in
  stage 1, no split child on another segment) for ``end_children_after`` (2) frames in a row ends
  the children it is a parent of (a merge ends when either of its two is seen again whole: the
  other is then judged afresh, merged again, hidden or missed); children also end after
  ``max_missed`` unmatched frames or when they have no parent left. Children are internal: only pedestrians are output.
- **Occlusion gain** (eq. 4-6, :func:`rules.occlusion_gain`): each observed track's Kalman gain is
  scaled by O_ocl = beta V_abs + (1 - beta) V_rel (clipped to [0, 1]) with V_max the largest volume
  it was observed with in the last ``volume_frames`` (5) frames.
- Ids are never reused; the table grows as needed (a crowd of 50 is fine).

Switches: ``occlusion_gain=False`` (gain 1), ``split_merge=False`` (no children: an unassigned
segment is new, an unassigned pedestrian missed) give the plain Kalman + Hungarian tracker.

Units: millimetres and frames (velocity mm/frame), camera coordinates x right, y down, z forward.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ...device import Device
from ...models.camera import Camera, DepthCamera
from ...ops import backend_module, constant_velocity, kf_predict, kf_update, shared_matrix
from ...ops._args import check_device
from ...scheduler import Scheduler, Stage
from . import rules
from .front import DepthFrontEnd, Segment, segments_of

__all__ = ["Pedestrian", "PedestrianConfig", "PedestrianFrame", "PedestrianTracker"]

POS = np.array([0, 2, 4])  # x = [x xdot y ydot z zdot]
VEL = np.array([1, 3, 5])
FREE, PEDESTRIAN, CHILD = 0, 1, 2
CHILD_IDS = 1 << 40  # the first id of the internal child tracks


@dataclasses.dataclass(frozen=True)
class PedestrianConfig:
    """Constants of the pedestrian tracker, the paper's value as default where it gives one.

    Front end (sec. 4.1-4.2): ``background_frames`` (30), ``foreground_threshold`` (100 mm),
    ``max_range`` (5000 mm), ``n_points`` (1024), ``seed`` (of the random subsets),
    ``camera_height`` (1000 mm, level camera) or ``ground_plane`` (a, b, c, d) mm for another
    mounting, DBSCAN ``eps`` (mm) and ``min_samples``, ``min_segment_points`` (smaller clusters
    start no pedestrian), ``weak_points`` (clusters of this many points up to
    ``min_segment_points`` are weak segments: they observe a pedestrian no other segment took and
    are otherwise dropped; 0: off), ``min_width`` (mm: narrower clusters in the ground plane are
    no segment, e.g. the sliver of someone at the image's side or behind a nearer person's edge;
    0: off), ``max_height`` (mm above the floor: a cluster reaching higher is no person),
    ``min_extent`` (mm, the least extent per axis in a volume).
    Assignment (eq. 1-3): ``alpha`` (0.8), ``max_distance`` (mm), ``max_volume_change`` (m^3),
    ``gated`` (a pair only where it lowers the total cost against leaving both unassigned at half
    the largest feasible cost each; False: as many feasible pairs as possible).
    Kalman: ``q`` acceleration variance (mm/frame^2)^2, ``r`` observation standard deviation
    (mm), ``p0`` initial standard deviations (position mm, velocity mm/frame).
    Gain (eq. 4-6): ``beta`` (0.2), ``v_thr`` (m^3), ``volume_frames`` (5), ``occlusion_gain``.
    Causes (Fig. 6-7): ``split_merge``, ``max_missed`` (2), ``end_children_after`` (2),
    ``containment_margin`` (mm), ``person_radius`` and ``person_depth`` (mm, the least half
    extents of a predicted pedestrian across and along the view in the containment tests),
    ``max_hidden`` (frames a pedestrian hidden behind a nearer segment is kept, predicted only;
    0: off, the paper's plain rule), ``report_hidden`` (output hidden pedestrians at their
    prediction, status "hidden"), ``leave_view`` and ``view_margin`` (mm: a missed pedestrian
    predicted beyond the image's side by more than this has left at once), ``split_volume`` (a
    split part is at most this times the pedestrian's largest recent volume), ``merge_volume`` (a
    merged segment is at least this times its owner's largest recent volume), ``split_occluder``
    (a split needs an occluder: where the frame reads the background through a gap wider than
    ``split_gap`` mm between the parts' bearings, they are two people), ``faint_points`` and
    ``faint_radius`` (mm: a pedestrian without a segment is observed from at least this many of
    the points no segment kept within this radius of its prediction; 0: off). ``capacity``:
    initial table slots (it grows).
    """

    background_frames: int = 30
    foreground_threshold: float = 100.0
    max_range: float = 5000.0
    n_points: int = 1024
    seed: int = 0
    camera_height: float = 1000.0
    ground_plane: tuple | None = None
    eps: float = 120.0
    min_samples: int = 6
    min_segment_points: int = 12
    weak_points: int = 8
    min_extent: float = 50.0
    min_width: float = 50.0
    max_height: float = 2300.0
    alpha: float = 0.8
    max_distance: float = 900.0
    max_volume_change: float = 0.15
    gated: bool = True
    q: float = 1600.0
    r: float = 60.0
    p0: tuple = (150.0, 100.0)
    beta: float = 0.2
    v_thr: float = 0.05
    volume_frames: int = 5
    occlusion_gain: bool = True
    split_merge: bool = True
    max_missed: int = 2
    end_children_after: int = 2
    containment_margin: float = 150.0
    person_radius: float = 400.0
    person_depth: float = 250.0
    max_hidden: int = 5
    report_hidden: bool = False
    leave_view: bool = True
    view_margin: float = 0.0
    split_volume: float = 0.5
    merge_volume: float = 1.2
    split_occluder: bool = True
    split_gap: float = 50.0
    faint_points: int = 3
    faint_radius: float = 300.0
    capacity: int = 16

    def __post_init__(self):
        for name in ("background_frames", "n_points", "min_samples", "min_segment_points", "volume_frames",
                     "max_missed", "end_children_after", "capacity"):  # fmt: skip
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"PedestrianConfig.{name}: expected a positive integer, got {v!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or not 0 <= self.seed < 2**32:
            raise ValueError(f"PedestrianConfig.seed: expected an integer in [0, 2**32), got {self.seed!r}")
        for name in ("foreground_threshold", "camera_height", "eps", "max_distance", "max_volume_change", "q", "r",
                     "v_thr", "min_extent", "person_radius", "split_volume", "max_height", "person_depth",
                     "split_gap", "faint_radius", "merge_volume"):  # fmt: skip
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
                raise ValueError(f"PedestrianConfig.{name}: expected a positive finite number, got {v!r}")
        if not (isinstance(self.max_range, (int, float)) and self.max_range > 0):
            raise ValueError(f"PedestrianConfig.max_range: expected a number > 0 (inf: no cut), got {self.max_range!r}")
        if not (isinstance(self.containment_margin, (int, float)) and 0 <= self.containment_margin < 1e4):
            raise ValueError(f"PedestrianConfig.containment_margin: expected mm in [0, 1e4), got "
                             f"{self.containment_margin!r}")  # fmt: skip
        for name in ("faint_points", "weak_points"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"PedestrianConfig.{name}: expected an integer >= 0 (0: off), got {v!r}")
        v = self.view_margin
        if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v)):
            raise ValueError(f"PedestrianConfig.view_margin: expected a finite number of mm, got {v!r}")
        v = self.min_width
        if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
            raise ValueError(f"PedestrianConfig.min_width: expected mm >= 0 (0: off), got {v!r}")
        for name in ("alpha", "beta"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 <= v <= 1.0):
                raise ValueError(f"PedestrianConfig.{name}: expected a weight in [0, 1], got {v!r}")
        p0 = np.asarray(self.p0, dtype=float)
        if p0.shape != (2,) or not (np.isfinite(p0).all() and (p0 > 0).all()):
            raise ValueError(f"PedestrianConfig.p0: expected 2 positive finite numbers, got {self.p0!r}")
        if self.ground_plane is not None:
            from .front import ground_plane

            ground_plane(self.ground_plane)


@dataclasses.dataclass(frozen=True)
class Pedestrian:
    """One tracked pedestrian: ``position`` (3,) mm and ``velocity`` (3,) mm/frame (camera
    coordinates), ``volume`` (m^3, of its last observation), ``status``: "new" (entered this
    frame), "tracked" (assigned a segment), "split" (updated from its split parts), "merged"
    (inside a segment shared with another pedestrian), "faint" (observed from a few points that
    make no segment), "missed" (no observation this frame),
    "hidden" (behind a nearer segment, see the module; output only with ``report_hidden=True``)."""

    id: int
    position: np.ndarray
    velocity: np.ndarray
    volume: float
    status: str


@dataclasses.dataclass(frozen=True)
class PedestrianFrame:
    """One frame's result: ``pedestrians`` (ascending id), ``segments`` (:class:`Segment`),
    ``points`` (N, 3) the points above the sensor (mm) and ``labels`` (N,) their segment index
    (-1: none), ``foreground`` the foreground pixels before downsampling, ``started`` and ``ended``
    the ids that began and ended this frame."""

    pedestrians: list
    segments: list
    points: np.ndarray
    labels: np.ndarray
    foreground: int
    started: list
    ended: list


class PedestrianTracker:
    """Paper 002's pedestrian tracker on one device (see the module for the frame and the rules).

    ``camera``: intrinsics (:class:`gputrack.models.Camera` or ``DepthCamera``; fx, fy, cx, cy in
    pixels); ``config``: :class:`PedestrianConfig`; ``profile``: time each stage on the device.
    Call :meth:`learn_background` (or :meth:`floor_background`) before the first :meth:`track`.
    """

    def __init__(self, device: Device, *, camera, config: PedestrianConfig | None = None, profile: bool = False):
        self.device = check_device(device)
        if not isinstance(camera, (Camera, DepthCamera)):
            raise TypeError(f"camera: expected a gputrack.models.Camera or DepthCamera, got {type(camera).__name__}")
        config = PedestrianConfig() if config is None else config
        if not isinstance(config, PedestrianConfig):
            raise TypeError(f"config: expected a PedestrianConfig, got {type(config).__name__}")
        self.camera, self.config = camera, config
        self.front = DepthFrontEnd(self.device, camera, config)
        #: least half extents (x, y, z) of a predicted pedestrian in the containment tests
        self._least_half = np.array([config.person_radius, config.person_radius, config.person_depth])
        self.F, self.Q = constant_velocity(3, 1.0, config.q)
        self.H = np.zeros((3, 6), np.float32)
        self.H[[0, 1, 2], POS] = 1.0
        self.R = np.eye(3, dtype=np.float32) * np.float32(config.r**2)
        # the filter's matrices on the device once, with their zero patterns (not uploaded every frame)
        self._kf = tuple(m if self.device.backend == "numpy" else shared_matrix(self.device, m)
                         for m in (self.F, self.Q, self.H, self.R))  # fmt: skip
        C = config.capacity
        self.ids = np.full(C, -1, np.int64)
        self.kind = np.zeros(C, np.int64)
        self.missed = np.zeros(C, np.int64)
        self.again = np.zeros(C, np.int64)  # frames in a row a parent was seen again whole
        self.hidden = np.zeros(C, np.int64)  # frames in a row a pedestrian was hidden behind a segment
        self.age = np.zeros(C, np.int64)
        self.volume = np.zeros(C)  # volume of the last observation (m^3)
        self.vols = np.full((C, config.volume_frames), np.nan)  # the last volume_frames observed volumes
        self.half = np.zeros((C, 3))  # half extents of the last segment (mm)
        self.last_seg = np.full((C, 3), np.nan)  # a child's last segment position (displacements)
        self.status = np.array(["tracked"] * C, dtype=object)
        self.parents: dict[int, set] = {}  # child slot -> parent slots
        self.next_id = 0
        self.next_child = 0
        self._x, self._P = np.zeros((C, 6)), np.tile(np.eye(6), (C, 1, 1))
        self.scheduler = Scheduler(self.device, [
            Stage("predict", self._predict, reads=("x", "P"), writes=("x", "P")),
            Stage("points", self._points, writes=("points",)),
            Stage("segments", self._segments, reads=("points", "x", "P"), writes=("segments",)),
            Stage("associate", self._associate, reads=("points", "segments", "x", "P"),
                  writes=("x", "P", "z", "mask", "gain", "segments")),
            Stage("update", self._update, reads=("x", "P", "z", "mask", "gain"), writes=("x", "P")),
        ], state=("x", "P"), outputs=("x",), profile=profile)  # fmt: skip
        self.scheduler.set("x", self._x.astype(np.float32))
        self.scheduler.set("P", self._P.astype(np.float32))
        self._frame = None
        self._inputs = None  # OpenCL: z, gain and mask in one buffer, (C, arrays, whole, host, views)

    # -- background ------------------------------------------------------------------------------
    def learn_background(self, frames) -> None:
        """Background from empty frames (F, H, W) uint16 or float32 mm, 0 = no reading (sec. 4.1:
        the per-pixel median ignoring missing readings; F < 30 warns, F > 64 is an error)."""
        self.front.learn_background(frames)

    def floor_background(self, shape) -> None:
        """The empty floor as background, for a scene without empty frames: (H, W) of the frames;
        the floor is the config's ground plane (see :mod:`.front`)."""
        self.front.floor_background(shape)

    @property
    def capacity(self) -> int:
        return len(self.ids)

    # -- one frame -------------------------------------------------------------------------------
    def track(self, depth) -> PedestrianFrame:
        """Track one depth frame (H, W) uint16 or float32 mm (0 or NaN: no reading)."""
        self._frame = {"depth": self.front.check_frame(depth)}
        try:
            out = self.scheduler.run()
            return self._result(np.asarray(out["x"], np.float64))
        finally:
            self._frame = None
            self.front.copies.release()  # done where the output's download waited (else waited for here)

    def _points(self, b) -> None:
        pts, count = self.front.points(self._frame["depth"])
        self._frame["count"] = count
        b["points"] = self.front.upper(pts)

    def _segments(self, b) -> None:
        # the predicted table comes back in the wait for the labels
        copies = self.front.copies
        self._frame["x"] = copies.download(b["x"], np.empty(b["x"].shape, np.float32))
        self._frame["P"] = copies.download(b["P"], np.empty(b["P"].shape, np.float32))
        segs, labels = self.front.segments(b["points"])
        copies.wait()  # (none left where the front end waited for the labels)
        self._frame["labels"] = labels
        b["segments"] = segs

    def _predict(self, b) -> None:
        F, Q = self._kf[:2]
        b["x"], b["P"] = kf_predict(self.device, b["x"], b["P"], F, Q, out=(b["x"], b["P"]))

    def _update(self, b) -> None:
        H, R = self._kf[2:]
        res = kf_update(self.device, b["x"], b["P"], b["z"], H, R, mask=b["mask"], gain_scale=b["gain"],
                        out=(b["x"], b["P"], self._status()))  # fmt: skip
        b["x"], b["P"] = res.x, res.P

    def _status(self):
        st = getattr(self, "_status_array", None)
        if st is None or tuple(st.shape) != (self.capacity,):
            st = self._status_array = (np.zeros(self.capacity, np.uint8) if self.device.backend == "numpy"
                                       else self.device.empty((self.capacity,), np.uint8))  # fmt: skip
        return st

    # -- the rules -------------------------------------------------------------------------------
    def _associate(self, b) -> None:
        cfg = self.config
        segs: list[Segment] = b["segments"]
        self._x, self._P = self._frame["x"].astype(np.float64), self._frame["P"].astype(np.float64)
        C0 = self.capacity
        self._born, self._waiting = set(), set()
        M = len(segs)
        pred = self._x[:, POS]
        self.age[self.ids >= 0] += 1
        peds = np.flatnonzero(self.kind == PEDESTRIAN)
        weak = np.array([sg.n_points < cfg.min_segment_points for sg in segs], bool)
        owner, seg_of = self._assignment(peds, segs, weak)
        taken = np.zeros(M, bool)
        for j in seg_of.values():
            taken[j] = True
        merged_now: set = set()  # parents predicted only this frame (a merge began)
        if cfg.split_merge:
            self._merges(peds, seg_of, owner, taken, segs, pred, merged_now)
        union: dict = {}  # parent slot -> segment indices of its split parts
        dropped = weak & ~taken  # weak segments nobody took (not even as its own, in the merge test)
        taken |= weak  # no split part, no new pedestrian
        if cfg.split_merge:
            started = self._splits(peds, seg_of, taken, segs, union, merged_now)
        else:
            started = []
            for j in np.flatnonzero(~taken):  # entered the view (Fig. 7)
                s = self._add(PEDESTRIAN, segs[j], velocity=None)
                seg_of[s] = int(j)
                started.append(int(self.ids[s]))
        C = self.capacity
        z, obs_vol, new = self._observations(seg_of, union, segs)
        gain = np.ones(C, np.float32)
        displaced = self._parent_updates(peds, seg_of, union, merged_now, segs, z, obs_vol)
        if dropped.any():  # out of the frame's segments: their points are loose
            self._frame["labels"] = rules.drop_labels(self._frame["labels"], dropped)
            b["segments"] = [sg for sg, d in zip(segs, dropped) if not d]
        if cfg.faint_points:
            self._faint(peds, new, b["points"], z, obs_vol, merged_now)
        explained = merged_now | self._waiting
        # occlusion gain (eq. 4-6) and the volume history
        for s in np.flatnonzero(np.isfinite(obs_vol)):
            if cfg.occlusion_gain and s not in displaced:
                vmax = np.nanmax(self.vols[s]) if np.isfinite(self.vols[s]).any() else np.nan
                gain[s] = rules.occlusion_gain(obs_vol[s], vmax, v_thr=cfg.v_thr, beta=cfg.beta)
            if s not in displaced:
                self.vols[s] = np.roll(self.vols[s], -1)
                self.vols[s, -1] = obs_vol[s]
                self.volume[s] = obs_vol[s]
        for s, j in seg_of.items():
            if self.kind[s] == CHILD:
                self.last_seg[s] = segs[j].position
        # bookkeeping: missed, seen again, deletions
        observed = np.isfinite(z).all(axis=1) | new
        for s in np.flatnonzero(self.ids >= 0):
            if observed[s]:
                self.hidden[s] = 0
            if observed[s] or s in explained:
                self.missed[s] = 0
            else:
                self.missed[s] += 1
                if self.kind[s] == PEDESTRIAN:
                    self.status[s] = "missed"
        for s in peds:
            if self.ids[s] < 0:
                continue
            whole = s in seg_of and s not in union and s not in merged_now
            self.again[s] = self.again[s] + 1 if whole else 0
            if whole and s not in self._born:
                self.status[s] = "tracked"
        gone = (self.ids >= 0) & (self.missed >= cfg.max_missed)
        if cfg.leave_view:  # missed with its prediction beyond the image's side: it left the view now
            for s in np.flatnonzero((self.ids >= 0) & (self.kind == PEDESTRIAN) & (self.missed > 0)):
                gone[s] |= not self._in_view(self._x[s, POS])
        ended = []
        for s in np.flatnonzero(gone):
            if self.kind[s] == PEDESTRIAN:
                ended.append(int(self.ids[s]))
            self._free(s)
        for c in list(self.parents):
            ps = self.parents[c]
            ps &= {p for p in ps if self.ids[p] >= 0 and self.kind[p] == PEDESTRIAN}
            if not ps or any(self.again[p] >= cfg.end_children_after for p in ps):
                self._free(c)
        mask = np.isfinite(z).all(axis=1) & (self.ids >= 0)
        z[~mask] = np.nan
        self._put_table(b, C != C0 or bool(self._born))  # new tracks (pedestrians and children) start on the host
        self._put_inputs(b, z, mask.astype(np.uint8), gain if cfg.occlusion_gain else None)
        self._frame["started"], self._frame["ended"] = started, ended

    def _assignment(self, peds, segs, weak) -> tuple:
        """Stages 1, 1b and 2 (eq. 1-3): the pedestrians on the segments, those left on the weak
        segments, then the split/merge children on the (strong) segments left or their parents'.
        Returns (owner (M,): the pedestrian slot that took segment j in stage 1 or 1b, else -1;
        seg_of: {slot: segment index})."""
        cfg = self.config
        M = len(segs)
        sp = np.array([sg.position for sg in segs]).reshape(-1, 3)
        sv = np.array([sg.volume for sg in segs])
        pred = self._x[:, POS]
        owner = np.full(M, -1, np.int64)
        seg_of = {}
        limits = {"alpha": cfg.alpha, "max_distance": cfg.max_distance, "max_volume_change": cfg.max_volume_change}
        # leaving a track or a segment without a partner costs half the largest feasible cost
        U = (cfg.alpha * cfg.max_distance / 1000 + (1 - cfg.alpha) * cfg.max_volume_change) / 2 if cfg.gated else None
        cost, ok = rules.cost_matrix(pred[peds], self.volume[peds], sp, sv, **limits)
        for i, j in rules.assign(cost, ok & ~weak, U):  # stage 1: the segments
            owner[j] = peds[i]
            seg_of[int(peds[i])] = j
        if weak.any():  # stage 1b: the pedestrians left, on the weak segments
            left = np.array([int(i) not in seg_of for i in peds], bool)
            for i, j in rules.assign(cost, ok & weak & left[:, None], U):
                owner[j] = peds[i]
                seg_of[int(peds[i])] = j
        kids = np.flatnonzero(self.kind == CHILD)
        if len(kids):  # stage 2: children, on the segments left or their parent's
            cost, ok = rules.cost_matrix(pred[kids], self.volume[kids], sp, sv, **limits)
            ok &= ~weak
            for a, c in enumerate(kids):
                ps = self.parents.get(int(c), ())
                for j in range(M):
                    if owner[j] >= 0 and owner[j] not in ps:
                        ok[a, j] = False  # another pedestrian's segment
                    elif not any(self._near(p, segs[j].position) for p in ps):
                        ok[a, j] = False  # a child stays within its parents' extent
            for a, j in rules.assign(cost, ok, U):
                seg_of[int(kids[a])] = j
        return owner, seg_of

    def _observations(self, seg_of, union, segs) -> tuple:
        """Each track's observation this frame: (z (C, 3) float32, NaN where none; its volume (C,);
        new (C,) bool, the tracks started now at their detection, which get no update). A track
        on one segment observes it; a split parent the midpoint of the union of its parts' boxes,
        with their summed volume (status "split"). Sets each observed track's half extents."""
        C = self.capacity
        z = np.full((C, 3), np.nan, np.float32)
        obs_vol = np.full(C, np.nan)
        new = np.zeros(C, bool)
        new[list(self._born)] = True
        for s, j in seg_of.items():
            if (self.kind[s] == CHILD or s not in union) and not new[s]:
                z[s], obs_vol[s] = segs[j].position, segs[j].volume
                self.half[s] = (segs[j].hi - segs[j].lo) / 2
        for s, parts in union.items():
            if new[s]:
                continue
            lo = np.min([segs[j].lo for j in parts], axis=0)
            hi = np.max([segs[j].hi for j in parts], axis=0)
            z[s], obs_vol[s] = (lo + hi) / 2, float(sum(segs[j].volume for j in parts))
            # the extent stays one person's: the largest part's (a union's box would grow)
            big = max(parts, key=lambda j: segs[j].volume)
            self.half[s] = (segs[big].hi - segs[big].lo) / 2
            self.status[s] = "split"
        return z, obs_vol, new

    def _merges(self, peds, seg_of, owner, taken, segs, pred, merged_now) -> None:
        """Fig. 6: an unassigned pedestrian inside a segment another pedestrian took has merged."""
        m = self.config.containment_margin
        for i in peds:
            if i in seg_of or self._children(i):
                continue
            for j, sg in enumerate(segs):
                if not rules.inside(pred[i], sg.lo, sg.hi, m):
                    continue
                k = int(owner[j])
                if k >= 0 and sg.volume < self.config.merge_volume * self._vmax(k):
                    continue  # one person's volume: the other pedestrian is not in it
                if k >= 0:
                    kid = next((c for c, ps in self.parents.items() if k in ps and seg_of.get(c) == j), None)
                    if kid is None:
                        kid = self._add(CHILD, sg, velocity=self._x[k, VEL])
                        seg_of[kid] = j
                        self.parents[kid] = {k}
                        merged_now.add(k)
                    self.parents[kid].add(int(i))
                    merged_now.add(int(i))
                    seg_of.pop(k, None)
                    self.status[k] = self.status[i] = "merged"
                    owner[j] = -1
                elif not taken[j]:  # its own segment, whose volume changed too much
                    seg_of[int(i)] = j
                    owner[j] = i
                taken[j] = True
                break
            else:  # hidden behind a nearer segment (its shadow): predicted only, for a while
                shadow = any(rules.behind(pred[i], sg.lo, sg.hi, m) for sg in segs)
                if shadow and self.hidden[i] < self.config.max_hidden:
                    self.hidden[i] += 1
                    merged_now.add(int(i))
                    self.status[i] = "hidden"

    def _splits(self, peds, seg_of, taken, segs, union, merged_now) -> list:
        """Fig. 7: an unassigned segment inside a pedestrian's predicted extent, no larger than
        ``split_volume`` times its largest recent volume, is a part of it (split); any other starts
        a pedestrian (entered). Largest segments first, so that a person entering in two pieces is
        one new pedestrian and a split part. Returns the ids started."""
        cfg = self.config
        started = []
        cands = [int(i) for i in peds]
        for j in sorted(np.flatnonzero(~taken), key=lambda j: -segs[j].volume):
            sg = segs[j]
            parent = None
            for i in cands:
                if self.ids[i] < 0 or (i in merged_now and self.status[i] == "merged"):  # merged now
                    continue
                if not self._near(i, sg.position):
                    continue
                vmax = max(self._vmax(i), segs[seg_of[i]].volume if i in seg_of else 0.0)  # its size now too
                if sg.volume > cfg.split_volume * vmax:
                    continue  # too big to be a part of it: someone else (e.g. entering beside it)
                if cfg.split_occluder and not self._occlusion_split(j, self._parts(i, seg_of), segs):
                    continue  # seen past it through the gap: someone beside it
                parent = i
                break
            taken[j] = True
            if parent is None:  # entered the view
                s = self._add(PEDESTRIAN, sg, velocity=None)
                seg_of[s] = int(j)
                started.append(int(self.ids[s]))
                cands.append(s)
                continue
            i = parent
            parts = union.setdefault(i, [])
            if not parts:
                if i in seg_of:
                    parts.append(seg_of[i])
                parts.extend(seg_of[c] for c in self._children(i) if c in seg_of and seg_of[c] not in parts)
            if not parts:  # unassigned and no children: its own segment, rejected by volume
                seg_of[i] = int(j)
                union.pop(i)
                continue
            parts.append(int(j))
            for p in list(parts):
                if not any(seg_of.get(c) == p for c in self._children(i)):
                    c = self._add(CHILD, segs[p], velocity=self._x[i, VEL])
                    seg_of[c] = p
                    self.parents[c] = {i}
        for i in peds:  # ongoing splits: the parent and its children on two or more segments
            if int(i) in union or self.ids[i] < 0:
                continue
            near = [c for c in self._children(i) if c in seg_of and len(self.parents[c]) == 1
                    and self._near(i, segs[seg_of[c]].position)]  # fmt: skip
            for c in self._children(i):  # a split child that walked off is no part of it any more
                if c in seg_of and len(self.parents[c]) == 1 and c not in near:
                    self.parents[c].discard(int(i))
            if cfg.split_occluder:  # a part seen apart from the others (no occluder between): a pedestrian
                for c in list(near):
                    if seg_of[c] == seg_of.get(int(i)):
                        continue  # on its parent's own segment: no part apart from it
                    rest = [p for p in self._parts(i, seg_of) if p != seg_of[c]]
                    if not self._occlusion_split(seg_of[c], rest, segs):
                        near.remove(c)
                        started.append(self._promote(c))
            parts = sorted({seg_of[c] for c in near} | ({seg_of[i]} if i in seg_of else set()))
            if len(parts) >= 2:
                union[int(i)] = parts
        return started

    def _faint(self, peds, new, points, z, obs_vol, merged_now) -> None:
        """A pedestrian with no observation yet that has at least ``faint_points`` of the points
        no segment kept (DBSCAN's noise, clusters too small or too narrow) within ``faint_radius``
        of its prediction in the ground plane is observed from them: a far or mostly hidden person
        whom the 1024 points sample too thinly for a segment (status "faint"; the occlusion gain
        weighs the small volume)."""
        labels = self._frame["labels"]
        loose = points[labels < 0] if len(points) else points
        if len(loose) < self.config.faint_points:
            return
        for i in peds:  # unobserved: no segment of its own, no split parts (their z is set), not born now
            if self.ids[i] < 0 or new[i] or np.isfinite(z[i]).all() or (i in merged_now and self.status[i] == "merged"):
                continue
            x, _, zz = self._x[i, POS]
            near = np.hypot(loose[:, 0] - x, loose[:, 2] - zz) <= self.config.faint_radius
            n = int(near.sum())
            if n < self.config.faint_points:
                continue
            seg = segments_of(loose[near], np.zeros(n, np.int64), 1, self.config.min_extent)[0][0]
            z[i], obs_vol[i] = seg.position, seg.volume
            self.status[i] = "faint"

    def _parts(self, i, seg_of) -> list:
        """Segment indices of pedestrian i's own segment and its children's this frame."""
        parts = [seg_of[i]] if i in seg_of else []
        return parts + [seg_of[c] for c in self._children(i) if c in seg_of and seg_of[c] not in parts]

    def _occlusion_split(self, j, parts, segs) -> bool:
        """Could segment j be a part split by occlusion from the segments ``parts`` (indices; none:
        yes)? Not when the frame shows the background between it and the nearest part
        (:func:`rules.seen_apart`)."""
        if not parts:
            return True
        near = rules.nearest_in_bearing(segs[j], [segs[p] for p in parts])
        cfg = self.config
        return not rules.seen_apart(self._frame["depth"], self.camera, segs[j], near, min_gap=cfg.split_gap,
                                    beyond=cfg.foreground_threshold)  # fmt: skip

    def _promote(self, c) -> int:
        """A child track becomes a pedestrian of its own (a new id, its state kept); returns the id."""
        self.parents.pop(int(c), None)
        self.kind[c] = PEDESTRIAN
        self.ids[c] = self.next_id
        self.next_id += 1
        self.again[c] = self.hidden[c] = self.missed[c] = 0
        self.status[c] = "new"
        return int(self.ids[c])

    def _parent_updates(self, peds, seg_of, union, merged_now, segs, z, obs_vol) -> set:
        """Unassigned parents follow their one observed child's displacement (predicted only in the
        child's first frame). Returns the slots updated so."""
        out = set()
        for i in peds:
            if self.ids[i] < 0 or i in seg_of or i in union or i in merged_now:
                continue
            half = np.maximum(self.half[i], self._least_half) + self.config.containment_margin
            seen = [c for c in self._children(i) if c in seg_of
                    and rules.inside(segs[seg_of[c]].position, self._x[i, POS] - half, self._x[i, POS] + half, 0.0)]
            if not seen:
                continue
            c = seen[0]
            j = seg_of[c]
            if np.isfinite(self.last_seg[c]).all() and self.age[c] > 0:
                z[i] = self._x[i, POS] - self._x[i, VEL] + (segs[j].position - self.last_seg[c])
                obs_vol[i] = self.volume[i]
                out.add(int(i))
            else:
                self._waiting.add(int(i))  # the child's first frame: predicted only, not missed
            if self.status[i] != "merged":
                self.status[i] = "split"
        return out

    def _vmax(self, i) -> float:
        """Pedestrian i's largest volume of the last ``volume_frames`` observations (m^3)."""
        return float(np.nanmax(self.vols[i])) if np.isfinite(self.vols[i]).any() else float(self.volume[i])

    def _near(self, i, position) -> bool:
        """Is ``position`` inside pedestrian i's predicted extent (its last segment's half extents,
        at least ``person_radius``, grown by ``containment_margin``)?"""
        half = np.maximum(self.half[i], self._least_half)
        return rules.inside(position, self._x[i, POS] - half, self._x[i, POS] + half, self.config.containment_margin)

    def _in_view(self, position) -> bool:
        """Is ``position`` (mm) within the image's columns, widened by ``view_margin`` mm at its
        depth on either side (the horizontal field of view)?"""
        x, z = float(position[0]), float(position[2])
        if not z > 0:
            return False
        cam, w = self.camera, self.front.shape[1]
        m = self.config.view_margin
        return (0.0 - cam.cx) * z / cam.fx - m <= x <= (w - 1 - cam.cx) * z / cam.fx + m

    def _children(self, parent) -> list:
        return [c for c, ps in self.parents.items() if parent in ps and self.ids[c] >= 0]

    def _add(self, kind: int, seg: Segment, velocity) -> int:
        """A new track in the lowest free slot at ``seg`` (velocity: 0 for a new pedestrian)."""
        free = np.flatnonzero(self.ids < 0)
        if not len(free):
            self._grow()
            free = np.flatnonzero(self.ids < 0)
        s = int(free[0])
        cfg = self.config
        self._born.add(s)
        if kind == PEDESTRIAN:
            self.ids[s] = self.next_id
            self.next_id += 1
        else:  # children are internal: ids of their own, never output
            self.ids[s] = CHILD_IDS + self.next_child
            self.next_child += 1
        self.kind[s] = kind
        self.missed[s] = self.again[s] = self.age[s] = self.hidden[s] = 0
        self.volume[s] = seg.volume
        self.vols[s] = np.nan
        self.vols[s, -1] = seg.volume
        self.half[s] = (seg.hi - seg.lo) / 2
        self.last_seg[s] = seg.position
        self.status[s] = "new" if kind == PEDESTRIAN else "child"
        x = np.zeros(6)
        x[POS] = seg.position
        if velocity is not None:
            x[VEL] = velocity
        self._x[s] = x
        self._P[s] = np.diag(np.tile([cfg.p0[0] ** 2, cfg.p0[1] ** 2], 3))
        return s

    def _free(self, s) -> None:
        self.ids[s], self.kind[s] = -1, FREE
        self.parents.pop(int(s), None)
        for ps in self.parents.values():
            ps.discard(int(s))

    def _grow(self) -> None:
        C = self.capacity
        g = C
        self.ids = np.concatenate([self.ids, np.full(g, -1, np.int64)])
        for name in ("kind", "missed", "again", "age", "hidden"):
            setattr(self, name, np.concatenate([getattr(self, name), np.zeros(g, np.int64)]))
        self.volume = np.concatenate([self.volume, np.zeros(g)])
        self.vols = np.concatenate([self.vols, np.full((g, self.vols.shape[1]), np.nan)])
        self.half = np.concatenate([self.half, np.zeros((g, 3))])
        self.last_seg = np.concatenate([self.last_seg, np.full((g, 3), np.nan)])
        self.status = np.concatenate([self.status, np.array(["tracked"] * g, dtype=object)])
        self._x = np.concatenate([self._x, np.zeros((g, 6))])
        self._P = np.concatenate([self._P, np.tile(np.eye(6), (g, 1, 1))])

    def _put_table(self, b, changed) -> None:
        if changed or b["x"].shape[0] != self.capacity:
            b["x"] = self._put("x", self._x.astype(np.float32))
            b["P"] = self._put("P", self._P.astype(np.float32))

    def _put(self, name, host):
        host = np.ascontiguousarray(host)
        if self.device.backend == "numpy":
            return host.copy()
        dev = self.scheduler.buffers.get(name)
        if dev is not None and tuple(dev.shape) == host.shape and dev.dtype == host.dtype:
            return self.front.copies.upload(dev, host)  # OpenCL: enqueued, no wait
        return self.device.asarray(host)

    def _put_inputs(self, b, z, mask, gain) -> None:
        """The update's observations, mask and gains (None: no gain): on OpenCL one copy into one
        buffer of three sub-buffers (kept while the capacity stays), enqueued without a wait."""
        if self.device.backend != "opencl":
            b["z"], b["mask"] = self._put("z", z), self._put("mask", mask)
            b["gain"] = None if gain is None else self._put("gain", gain)
            return
        C = len(z)
        if self._inputs is None or self._inputs[0] != C:
            impl = backend_module(self.device, "depth_points")
            self._inputs = (C, *impl.packed_arrays(self.device, [((C, 3), np.float32), ((C,), np.uint8),
                                                                  ((C,), np.float32)]))  # fmt: skip
        _, arrays, whole, host, views = self._inputs
        views[0][...], views[1][...], views[2][...] = z, mask, 1.0 if gain is None else gain
        self.front.copies.upload(whole, host)  # the previous frame's copy is done: its end waited
        b["z"], b["mask"] = arrays[0], arrays[1]
        b["gain"] = None if gain is None else arrays[2]

    # -- reading ---------------------------------------------------------------------------------
    def _result(self, x) -> PedestrianFrame:
        if not np.isfinite(x[self.ids >= 0]).all():  # never expected: the filter is in Joseph form
            raise FloatingPointError("pedestrian tracker: a track's state became non-finite")
        peds = np.flatnonzero(self.kind == PEDESTRIAN)
        if not self.config.report_hidden:
            peds = peds[self.status[peds] != "hidden"]  # hidden: kept, not output
        peds = peds[np.argsort(self.ids[peds], kind="stable")]
        out = [Pedestrian(int(self.ids[s]), x[s, POS].copy(), x[s, VEL].copy(), float(self.volume[s]),
                          str(self.status[s])) for s in peds]  # fmt: skip
        f = self._frame
        return PedestrianFrame(out, list(self.scheduler.buffers["segments"]), self.scheduler.buffers["points"],
                               f["labels"], f["count"], f["started"], f["ended"])  # fmt: skip

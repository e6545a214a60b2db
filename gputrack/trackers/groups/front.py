"""The front end of paper 001: subtraction stereo and KLT tracks -> 3D points with velocities.

Per frame (:meth:`StereoFrontEnd.points`):

1. **Background subtraction** on the device (:mod:`gputrack.ops.background`): the left camera's
   background is the per-pixel median of the first ``background_frames`` frames (or of frames
   given to :meth:`StereoFrontEnd.learn_background`), then follows slow changes with a running
   average of rate ``background_rate`` where the pixel is background; the foreground is where
   the frame differs from it by ``foreground_threshold`` grey levels or more.
2. **Subtraction stereo** on the device (:func:`gputrack.ops.stereo_match`): block matching of
   the rectified pair restricted to the left foreground: the work scales with the
   moving people, not with the image. Disparity NaN where invalid.
3. **KLT** on the host (OpenCV: ``goodFeaturesToTrack`` in the foreground, pyramidal
   ``calcOpticalFlowPyrLK`` over ``klt_levels`` levels above the image (1: the people move a few
   pixels a frame at 48 fps; 2 cost 1.5x the CPU time for the same tracks) with a forward-backward
   check of ``fb_error`` px), in a worker thread started by the stereo stage with the mask it
   read: OpenCV releases the GIL, so KLT runs while the device matches. New corners are searched
   only when at least ``topup`` tracks are missing from ``max_features`` (a search of the
   foreground costs as much for one corner as for fifty). As in the paper's
   Fig. 3, only tracks that have survived ``window`` frames are observation points; each gives
   (u, v, d) -> a 3D point (eq. 6 inverted, :meth:`StereoCamera.unproject`; d the median of the
   valid disparities in a 5 x 5 window at the point) and a velocity, the mean 3D displacement
   per frame over the window.

Frames before the background is learnt give no points (a documented result, not an error).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools

import numpy as np

from ...device import Device, as_host_array
from ...models.camera import StereoCamera
from ...ops.background import background_median, foreground_mask, update_background
from ...ops.stereo import stereo_match
from ...scheduler import Scheduler, Stage

__all__ = ["FrontEndConfig", "StereoFrontEnd", "StereoPoints"]


@functools.lru_cache(maxsize=4)
def _disc(r: int):
    """The pixel offsets (dy, dx) that cv2.circle fills for a disc of radius r at an integer centre."""
    import cv2

    m = np.zeros((2 * r + 3, 2 * r + 3), np.uint8)
    cv2.circle(m, (r + 1, r + 1), r, 1, -1)
    dy, dx = np.nonzero(m)
    return dy - (r + 1), dx - (r + 1)


@dataclasses.dataclass(frozen=True)
class FrontEndConfig:
    """Constants of the stereo front end (see the module)."""

    max_disparity: int = 64
    block: int = 9
    background_frames: int = 24
    background_rate: float = 0.02
    foreground_threshold: float = 20.0
    window: int = 5
    max_features: int = 800
    min_distance: int = 5
    fb_error: float = 1.0
    klt_window: int = 11
    klt_levels: int = 1
    topup: int = 50

    def __post_init__(self):
        for name in ("max_disparity", "block", "background_frames", "window", "max_features", "min_distance",
                     "klt_window", "topup", "klt_levels"):  # fmt: skip
            v, lo = getattr(self, name), 0 if name == "klt_levels" else 1  # 0 levels: the image alone
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f"FrontEndConfig.{name}: expected an integer >= {lo}, got {v!r}")
        if not 0.0 <= float(self.background_rate) <= 1.0:
            raise ValueError(f"FrontEndConfig.background_rate: expected a rate in [0, 1], got {self.background_rate!r}")
        for name in ("foreground_threshold", "fb_error"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"FrontEndConfig.{name}: expected a positive number, got {getattr(self, name)!r}")


@dataclasses.dataclass(frozen=True)
class StereoPoints:
    """One frame's observation points: ``xyz`` (N, 3) mm, ``velocity`` (N, 3) mm/frame, ``uv``
    (N, 2) pixels in the left image, ``track`` (N,) KLT track ids; ``foreground`` the share of
    foreground pixels; ``disparity`` the frame's disparity map on the device (or None)."""

    xyz: np.ndarray
    velocity: np.ndarray
    uv: np.ndarray
    track: np.ndarray
    foreground: float
    disparity: object = None


def _gray(a, name: str, shape=None) -> np.ndarray:
    h = as_host_array(a, name)
    if h.dtype != np.uint8:
        raise TypeError(f"{name}: expected a uint8 grey image (H, W), got dtype {h.dtype.name}")
    if h.ndim != 2 or min(h.shape) < 16:
        raise ValueError(f"{name}: expected a grey image (H, W) of at least 16 x 16, got shape {h.shape}")
    if shape is not None and h.shape != shape:
        raise ValueError(f"{name}: expected shape {shape} (the left image's and the first frame's), got {h.shape}")
    return np.ascontiguousarray(h)


class StereoFrontEnd:
    """Subtraction stereo + KLT on one device (see the module). Its frame is four stages of a
    :class:`gputrack.Scheduler` (``self.scheduler``): foreground and stereo on the device (stereo
    reads the foreground mask on the host and starts KLT in a worker thread), KLT (the wait for that
    thread) and triangulation on the host (which reads the disparity map)."""

    def __init__(self, device: Device, camera: StereoCamera, config: FrontEndConfig | None = None, *,
                 profile: bool = False):  # fmt: skip
        self.device, self.camera = device, camera
        self.config = FrontEndConfig() if config is None else config
        if not isinstance(self.config, FrontEndConfig):
            raise TypeError(f"config: expected a FrontEndConfig, got {type(self.config).__name__}")
        self.shape = None
        self._learning: list = []
        self._prev = None
        self._pts = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)
        self._age = np.zeros(0, np.int64)
        self._hist = np.zeros((0, self.config.window, 3))  # the last `window` 3D positions of each track
        self._next = 0
        self._gray = None
        self._pool = None  # the KLT thread (made at the first frame)
        self._job = None
        self.scheduler = Scheduler(device, [
            Stage("foreground", self._foreground, reads=("left", "background"), writes=("fg", "background")),
            # the stereo stage reads the mask on the host (stereo_match finds its runs there), hands
            # it with the left image to the KLT thread, then launches the matching: KLT (OpenCV,
            # GIL released) runs while the device matches; the klt stage waits for it
            Stage("stereo", self._stereo, reads=("left", "right"), host_reads=("fg",), writes=("disparity",)),
            Stage("klt", self._track),  # the tracks live on the host (self._pts, ...)
            Stage("points", self._triangulate, host_reads=("disparity",)),
        ], inputs=("left", "right"), state=("background",), profile=profile)  # fmt: skip

    @property
    def ready(self) -> bool:
        """Whether the background is learnt (until then frames give no points)."""
        return "background" in self.scheduler.buffers

    def learn_background(self, lefts) -> None:
        """The left camera's background from empty frames (F, H, W) uint8 (per-pixel median)."""
        frames = as_host_array(lefts, "lefts")
        if frames.ndim != 3 or len(frames) == 0:
            raise ValueError(f"lefts: expected empty frames (F, H, W) with F >= 1, got shape {frames.shape}")
        for k, f in enumerate(frames):
            _gray(f, f"lefts[{k}]", self.shape if self.shape is not None else frames.shape[1:])
        self.shape = frames.shape[1:]
        self.scheduler.set("background", background_median(self.device, frames))
        self._learning = []

    def points(self, left, right) -> StereoPoints:
        """3D points with velocities of one rectified pair (uint8 grey, same shape)."""
        left = _gray(left, "left", self.shape)
        self.shape = left.shape
        right = _gray(right, "right", self.shape)
        if not self.ready:
            self._learning.append(left)
            if len(self._learning) >= self.config.background_frames:
                self.learn_background(np.stack(self._learning))
            z = np.zeros((0, 3), np.float32)
            return StereoPoints(z, z.copy(), np.zeros((0, 2), np.float32), np.zeros(0, np.int64), 0.0, None)
        self._gray = left
        try:
            self.scheduler.run(left=left, right=right)
        finally:
            self._gray = None
        return self._result

    # -- the stages ----------------------------------------------------------------------------
    def _foreground(self, b) -> None:
        cfg, dev = self.config, self.device
        b["fg"] = foreground_mask(dev, b["left"], b["background"], cfg.foreground_threshold, out=b.get("fg"))
        if cfg.background_rate > 0:
            b["background"] = update_background(dev, b["background"], b["left"], rate=cfg.background_rate,
                                                mask=b["fg"], out=b["background"])  # fmt: skip

    def _stereo(self, b) -> None:
        cfg = self.config
        fg = b["fg"]  # on the host
        if self._pool is None:
            self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="gputrack-klt")
        self._job = self._pool.submit(self._klt, self._gray, fg)
        try:
            b["disparity"] = stereo_match(self.device, b["left"], b["right"], mask=fg, max_disparity=cfg.max_disparity,
                                          block=cfg.block, out=b.get("disparity"))
        except BaseException:
            self._job.exception()  # the tracks are consistent again before the error goes on
            raise
        self._fg_share = float(np.count_nonzero(fg)) / fg.size

    def _track(self, b) -> None:
        self._job.result()  # the KLT thread's tracks (its error, if it raised)

    def _triangulate(self, b) -> None:
        cfg = self.config
        xyz = self._xyz(np.asarray(b["disparity"]))
        self._hist = np.concatenate([self._hist[:, 1:], xyz[:, None]], axis=1)
        ok = (self._age >= cfg.window) & np.isfinite(self._hist[:, [0, -1]]).all((1, 2))
        vel = (self._hist[ok, -1] - self._hist[ok, 0]) / (cfg.window - 1)
        self._result = StereoPoints(xyz[ok].astype(np.float32), vel.astype(np.float32), self._pts[ok].copy(),
                                    self._ids[ok].copy(), self._fg_share, self.scheduler.buffers["disparity"])  # fmt: skip

    def _klt(self, gray, fg) -> None:
        """Track the KLT points into ``gray`` (forward-backward checked, in the foreground), then
        top them up with new corners of the foreground."""
        import cv2

        cfg = self.config
        H, W = gray.shape
        win = (cfg.klt_window, cfg.klt_window)
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)
        lk = dict(winSize=win, maxLevel=cfg.klt_levels, criteria=criteria)
        if self._prev is not None and len(self._pts):
            p0 = self._pts.reshape(-1, 1, 2)
            p1, st, _ = cv2.calcOpticalFlowPyrLK(self._prev, gray, p0, None, **lk)
            pb, st2, _ = cv2.calcOpticalFlowPyrLK(gray, self._prev, p1, None, **lk)
            p1, pb = p1.reshape(-1, 2), pb.reshape(-1, 2)
            ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(pb - self._pts, axis=1) < cfg.fb_error)
            ui, vi = np.round(p1[:, 0]).astype(int), np.round(p1[:, 1]).astype(int)
            ok &= (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
            ok[ok] &= fg[vi[ok], ui[ok]] > 0  # a track that leaves the foreground ends
            self._pts, self._ids, self._age, self._hist = p1[ok], self._ids[ok], self._age[ok] + 1, self._hist[ok]
        room = cfg.max_features - len(self._pts)
        rows, cols = np.flatnonzero(fg.any(1)), np.flatnonzero(fg.any(0))
        if room >= min(cfg.topup, cfg.max_features) and len(rows):
            # new corners only inside the foreground's bounding box (the work follows the people)
            r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
            m = (fg[r0:r1, c0:c1] > 0).astype(np.uint8) * 255
            if len(self._pts):  # no new corner within min_distance of a track (cv2.circle's discs, at once)
                dy, dx = _disc(cfg.min_distance)
                c = np.round(self._pts).astype(np.int64)
                vv, uu = (c[:, 1, None] - r0 + dy).ravel(), (c[:, 0, None] - c0 + dx).ravel()
                inside = (vv >= 0) & (vv < m.shape[0]) & (uu >= 0) & (uu < m.shape[1])
                m[vv[inside], uu[inside]] = 0
            new = None
            if min(m.shape) >= 8:
                new = cv2.goodFeaturesToTrack(np.ascontiguousarray(gray[r0:r1, c0:c1]), maxCorners=room,
                                              qualityLevel=0.01, minDistance=cfg.min_distance, mask=m, blockSize=5)  # fmt: skip
            if new is not None:
                new = new.reshape(-1, 2).astype(np.float32) + np.array([c0, r0], np.float32)
                k = len(new)
                self._pts = np.concatenate([self._pts, new])
                self._ids = np.concatenate([self._ids, np.arange(self._next, self._next + k)])
                self._next += k
                self._age = np.concatenate([self._age, np.ones(k, np.int64)])
                self._hist = np.concatenate([self._hist, np.full((k, cfg.window, 3), np.nan)])
        self._prev = gray

    def _xyz(self, disp) -> np.ndarray:
        """(n, 3) mm of the KLT points: the median valid disparity in a 5 x 5 window (NaN if none)."""
        n = len(self._pts)
        if n == 0:
            return np.zeros((0, 3))
        H, W = disp.shape
        u = np.clip(np.round(self._pts[:, 0]).astype(int), 2, W - 3)
        v = np.clip(np.round(self._pts[:, 1]).astype(int), 2, H - 3)
        off = np.arange(-2, 3)
        win = disp[v[:, None, None] + off[None, :, None], u[:, None, None] + off[None, None, :]].reshape(n, -1)
        win = np.where(win > 0, win, np.nan)
        win.sort(axis=1)  # NaN last: the median of each row's k valid values (as np.nanmedian, faster)
        k = np.isfinite(win).sum(1)
        some = k > 0
        lo = np.take_along_axis(win, np.maximum(k - 1, 0)[:, None] // 2, 1)[:, 0]
        hi = np.take_along_axis(win, (k // 2)[:, None], 1)[:, 0]
        d = np.where(some, (lo + hi) / 2, np.nan)
        out = np.full((n, 3), np.nan)
        if some.any():
            out[some] = self.camera.unproject(np.column_stack([self._pts[some], d[some]]))
        return out

"""The front end of paper 002 (sec. 4.1-4.2): a depth frame -> the upper bodies' points -> segments.

Per frame (:meth:`DepthFrontEnd.points`, :meth:`DepthFrontEnd.segments`):

1. **Foreground points** on the device (:func:`gputrack.ops.depth_points`): readings at least
   ``foreground_threshold`` (100 mm) from the background, back-projected, those beyond
   ``max_range`` (5 m) dropped, downsampled to ``n_points`` (1024) at random (seeded and
   counter-based: frame k uses counter k, the same subset on every backend). A frame with fewer
   than ``n_points`` foreground points has no pedestrian (sec. 4.1): no points, no segments.
2. **Upper bodies** (host, on the <= 1024 points): only points higher than the sensor are kept
   (sec. 4.2: upper bodies touch less than hands and feet); the vertical axis is dropped: each
   point becomes (e_x . p, e_z . p), its coordinates in the ground plane.
3. **Segments** on the device (:func:`gputrack.ops.dbscan` of the 2D points, ``eps`` and
   ``min_samples``); a cluster of at least ``min_segment_points`` points (``weak_points``: a weak
   segment, which the tracker keeps only where it observes a pedestrian) and at least ``min_width``
   wide in the ground plane, with no point higher than ``max_height`` above the floor (2.3 m, the
   tallest person of PCL's people detector: a structure reaching higher, e.g. a door frame when the
   background is the floor plane, is no person) is a segment. Its
   ``position`` is the midpoint of the minimum and maximum of its 3D points per camera axis
   (sec. 4.2), its ``volume`` V the volume of that axis-aligned bounding box in m^3 (the paper
   does not define V; this is its plain reading: x extent * y extent * z extent, each extent at
   least ``min_extent`` so that a flat surface still has a volume).

Background (sec. 4.1): the per-pixel median of empty frames ignoring missing readings
(:func:`gputrack.ops.background_median` with ``missing=0``; at most 64 frames; fewer than
``background_frames`` (30) is allowed with a warning). Without empty frames the documented
alternative is the floor: :func:`plane_background`, the depth at which the camera sees the empty
ground plane, with foreground = at least ``foreground_threshold`` in front of it (``nearer``).
There every static thing above the floor is foreground as well (PCL's five-people cloud: 160k of
its 240k readings), and the random points would mostly land on it. But a ray that reaches the floor
(n . d > 0) holds only points below the sensor, which step 2 drops, so :meth:`floor_background`
gives those pixels no background (never foreground): the points are drawn among the readings on
rays above the sensor's horizon, where the segments come from (the same points step 2 keeps, at
a density that no longer depends on how much static structure stands below the horizon).

Vertical: the ground plane is ``(a, b, c, d)`` in camera coordinates (mm): a x + b y + c z + d = 0
for floor points, (a, b, c) the unit normal pointing down (away from the camera, d < 0: the camera
is -d above the floor). Paper 002's sensor is level and 1 m up: (0, 1, 0, -1000). A point is higher
than the sensor where n . p < 0.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np

from ...device import DeviceArray, as_host_array
from ...models.camera import Camera, DepthCamera
from ...ops import backend_module, background_median, dbscan, depth_points
from ...ops.background import MAX_FRAMES

__all__ = ["DepthFrontEnd", "FrameCopies", "Segment", "ground_axes", "ground_plane", "plane_background",
           "segments_of"]  # fmt: skip


class FrameCopies:
    """A frame's copies between host and device arrays without a wait each. On OpenCL they are
    enqueued without blocking on the device's in-order queue, and :meth:`wait` finishes the queue
    once for all of them (each blocking copy would wait for PoCL's threads);
    their events, which keep the host arrays alive, are held until then. Elsewhere they are plain
    copies (taichi:cpu: a memcpy) and :meth:`wait` does nothing. A downloaded host array holds
    its values after the next :meth:`wait`; an uploaded one must not change before it."""

    def __init__(self, device):
        self.device = device
        self._impl = backend_module(device, "depth_points") if device.backend == "opencl" else None
        self._events: list = []

    def upload(self, arr, host: np.ndarray):
        """Copy ``host`` into the device array ``arr`` (same shape and dtype); returns ``arr``."""
        host = np.ascontiguousarray(host)
        if self._impl is None:
            return self.device.asarray(host, out=arr)
        if host.shape != arr.shape or host.dtype != arr.dtype:
            raise ValueError(f"upload: expected {arr.dtype.name} {arr.shape}, got {host.dtype.name} {host.shape}")
        self._events.append(self._impl.enqueue_upload(self.device, arr, host))
        return arr

    def download(self, arr, host: np.ndarray) -> np.ndarray:
        """Copy the array ``arr`` (device, or NumPy on ``numpy``) into the C-contiguous NumPy
        array ``host`` of its shape and dtype; returns ``host``."""
        if self._impl is None:
            host[...] = arr if isinstance(arr, np.ndarray) else arr.numpy()
            return host
        if host.shape != arr.shape or host.dtype != arr.dtype or not host.flags.c_contiguous:
            raise ValueError(f"download: expected a C-contiguous {arr.dtype.name} {arr.shape}, got {host.dtype.name} "
                             f"{host.shape}")  # fmt: skip
        self._events.append(self._impl.enqueue_download(self.device, arr, host))
        return host

    def wait(self) -> None:
        """Wait for every copy enqueued (one finish of the queue, none if nothing is pending)."""
        if self._events:
            self.device.synchronize()
            self._events.clear()

    def release(self) -> None:
        """Forget the copies after a blocking read of the same queue (they are done; one still
        running would be waited for)."""
        self._events.clear()


@dataclasses.dataclass(frozen=True)
class Segment:
    """One segment (sec. 4.2): ``position`` (3,) mm (camera coordinates, midpoint of the min and
    max per axis), ``volume`` (m^3, bounding box), ``n_points`` its points (of the <= 1024),
    ``lo`` and ``hi`` (3,) its points' minimum and maximum per axis (mm)."""

    position: np.ndarray
    volume: float
    n_points: int
    lo: np.ndarray
    hi: np.ndarray


def ground_plane(plane=None, camera_height: float = 1000.0) -> np.ndarray:
    """(4,) float64 ground plane [a, b, c, d] (mm), normal of unit length pointing down (d < 0):
    ``plane`` as given (any scale of the normal, either orientation), or a level camera
    ``camera_height`` mm above the floor: (0, 1, 0, -camera_height)."""
    if plane is None:
        h = float(camera_height)
        if not (math.isfinite(h) and h > 0):
            raise ValueError(f"camera_height: expected a height above the floor > 0 mm, got {camera_height!r}")
        return np.array([0.0, 1.0, 0.0, -h])
    p = np.asarray(plane, dtype=np.float64)
    if p.shape != (4,) or not np.isfinite(p).all():
        raise ValueError(f"ground_plane: expected 4 finite numbers (a, b, c, d) in mm, got {plane!r}")
    n = np.linalg.norm(p[:3])
    if n == 0 or p[3] == 0:
        raise ValueError(f"ground_plane: expected a normal (a, b, c) != 0 and the camera off the plane (d != 0), "
                         f"got {plane!r}")  # fmt: skip
    p = p / n
    return -p if p[3] > 0 else p


def ground_axes(plane) -> np.ndarray:
    """(2, 3) the ground plane's axes: e_x (the camera's x projected on the plane) and e_z = e_x x n
    (forward); a point's ground coordinates are ``axes @ p``. Level camera: x and z."""
    n = np.asarray(plane, dtype=np.float64)[:3]
    ex = np.array([1.0, 0.0, 0.0]) - n[0] * n
    ex /= np.linalg.norm(ex)
    return np.stack([ex, np.cross(ex, n)])


def plane_background(camera, plane, shape) -> np.ndarray:
    """The depth image (H, W) float32 (mm) of the empty ground plane seen by ``camera``: along the
    ray d = ((u - cx)/fx, (v - cy)/fy, 1) the floor is at z = -d0 / (n . d) where n . d > 0, +inf
    (nothing in range: every reading foreground) elsewhere. For a level plane (0, 1, 0, -h) this is
    :func:`gputrack.ops.floor_background` (camera, h, shape)."""
    if not isinstance(camera, (Camera, DepthCamera)):
        raise TypeError(f"camera: expected a gputrack.models.Camera or DepthCamera, got {type(camera).__name__}")
    p = ground_plane(plane)
    H, W = (int(s) for s in shape)
    u = (np.arange(W, dtype=np.float64) - camera.cx) / camera.fx
    v = (np.arange(H, dtype=np.float64) - camera.cy) / camera.fy
    nd = p[0] * u[None, :] + p[1] * v[:, None] + p[2]
    with np.errstate(divide="ignore"):
        z = np.where(nd > 0, -p[3] / np.where(nd > 0, nd, 1.0), np.inf)
    return z.astype(np.float32)


def segments_of(points: np.ndarray, labels: np.ndarray, min_points: int = 1, min_extent: float = 50.0,
                min_width: float = 0.0, axes=None, plane=None, max_height: float = np.inf) -> list:
    """Segments (sec. 4.2) of 3D points (N, 3) mm with cluster labels (N,) (-1: noise): one per
    label with at least ``min_points`` points and a ground-plane width (the larger extent along the
    ground ``axes`` (2, 3), default x and z) of at least ``min_width`` mm and no point higher than
    ``max_height`` above the ground ``plane`` (4,), in increasing label order. Returns (segments,
    kept labels)."""
    out, kept = [], []
    lab = np.asarray(labels)
    g = np.array([[1.0, 0, 0], [0, 0, 1.0]]) if axes is None else np.asarray(axes, np.float64)
    for c in np.unique(lab[lab >= 0]):
        p = points[lab == c].astype(np.float64)
        if len(p) < min_points:
            continue
        xz = p @ g.T
        if (xz.max(axis=0) - xz.min(axis=0)).max() < min_width:
            continue
        if plane is not None and np.isfinite(max_height) and (-(p @ plane[:3] + plane[3])).max() > max_height:
            continue
        kept.append(int(c))
        lo, hi = p.min(axis=0), p.max(axis=0)
        ext = np.maximum(hi - lo, min_extent) / 1000.0  # m
        out.append(Segment((lo + hi) / 2, float(np.prod(ext)), int(len(p)), lo, hi))
    return out, kept


class DepthFrontEnd:
    """Background, foreground points and segments of depth frames on one device (see the module).

    ``camera``: intrinsics (:class:`gputrack.models.Camera` or ``DepthCamera``); ``config``: the
    tracker's :class:`~gputrack.trackers.pedestrians.PedestrianConfig` (its front-end constants).
    """

    def __init__(self, device, camera, config):
        if not isinstance(camera, (Camera, DepthCamera)):
            raise TypeError(f"camera: expected a gputrack.models.Camera or DepthCamera, got {type(camera).__name__}")
        self.device, self.camera, self.config = device, camera, config
        self.plane = ground_plane(config.ground_plane, config.camera_height)
        self.axes = ground_axes(self.plane)
        self.background = None  # (H, W) float32 on the device
        self.nearer = False
        self.shape = None
        self.counter = 0
        self.copies = FrameCopies(device)
        # device buffers kept between frames (and their host sides): the points, the 2D points
        # and their labels
        self._points = self._points_host = None
        self._xz = self._labels = self._labels_host = None

    # -- background --------------------------------------------------------------------------
    def learn_background(self, frames) -> None:
        """Per-pixel median of empty frames (F, H, W) uint16 or float32 mm (0 or NaN: no reading),
        ignoring missing readings (sec. 4.1). 1 <= F <= 64; F < ``background_frames`` warns."""
        if isinstance(frames, DeviceArray):
            raise TypeError("frames: expected host (NumPy) depth frames (F, H, W), got a DeviceArray")
        f = np.asarray(frames)
        if f.dtype not in (np.uint16, np.float32):
            raise TypeError(f"frames: expected depth frames of dtype uint16 or float32 (mm), got {f.dtype.name}")
        if f.ndim != 3 or f.shape[0] < 1 or f.shape[1] < 1 or f.shape[2] < 1:
            raise ValueError(f"frames: expected (F, H, W) depth frames with F >= 1, got shape {f.shape}")
        if f.shape[0] > MAX_FRAMES:
            raise ValueError(f"frames: expected at most {MAX_FRAMES} frames, got F = {f.shape[0]}")
        if f.shape[0] < self.config.background_frames:
            warnings.warn(f"learn_background: {f.shape[0]} frames, fewer than the paper's "
                          f"{self.config.background_frames}: the median removes fewer dropouts",
                          stacklevel=3)  # fmt: skip
        if f.dtype == np.float32 and np.isinf(f).any():
            raise ValueError("frames: expected finite depths, 0 or NaN (no reading), got an infinity")
        bg = background_median(self.device, f, missing=0)
        host = bg if self.device.backend == "numpy" else bg.numpy()
        if not np.isfinite(host).any():
            raise ValueError("frames: expected some readings, got every pixel missing in every frame")
        self.background, self.nearer, self.shape = bg, False, tuple(f.shape[1:])

    def floor_background(self, shape) -> None:
        """Use the empty ground plane as the background (no empty frames; see the module)."""
        if not (isinstance(shape, (tuple, list)) and len(shape) == 2 and all(int(s) >= 1 for s in shape)):
            raise ValueError(f"shape: expected (H, W), got {shape!r}")
        bg = plane_background(self.camera, self.plane, shape)
        bg[np.isfinite(bg)] = np.nan  # rays that reach the floor hold only points below the sensor
        self.background = bg if self.device.backend == "numpy" else self.device.asarray(bg)
        self.nearer, self.shape = True, (int(shape[0]), int(shape[1]))

    # -- a frame -----------------------------------------------------------------------------
    def check_frame(self, depth) -> np.ndarray:
        if isinstance(depth, DeviceArray):
            raise TypeError("depth: expected a host (NumPy) depth frame (H, W), got a DeviceArray")
        d = as_host_array(depth, "depth")
        if d.dtype not in (np.uint16, np.float32):
            raise TypeError(f"depth: expected a depth frame of dtype uint16 or float32 (mm), got {d.dtype.name}")
        if self.background is None:
            raise ValueError("depth: expected learn_background(frames) (or floor_background) before the first frame")
        if d.shape != self.shape:
            raise ValueError(f"depth: expected a frame of the background's shape {self.shape}, got {d.shape}")
        if d.dtype == np.float32 and np.isinf(d).any():
            raise ValueError("depth: expected finite depths, 0 or NaN (no reading), got an infinity")
        return d

    def points(self, depth) -> tuple:
        """(points (n, 3) float32 host, count): the frame's foreground points (step 1), NaN rows
        dropped, none when fewer than ``n_points`` pixels are foreground; ``count`` the foreground
        pixels before downsampling."""
        c = self.config
        d = self.check_frame(depth)
        kw = dict(threshold=c.foreground_threshold, max_range=c.max_range, n_points=c.n_points, seed=c.seed,
                  counter=self.counter % 2**32, nearer=self.nearer)  # fmt: skip
        if self.device.backend == "numpy":
            host, count = depth_points(self.device, d, self.background, self.camera, **kw)
        else:  # into kept buffers, the points read back in the wait for the count
            if self._points is None or self._points.shape != (c.n_points, 3):
                self._points = self.device.empty((c.n_points, 3), np.float32)
                self._points_host = np.empty((c.n_points, 3), np.float32)
            host = self._points_host
            _, count = depth_points(self.device, d, self.background, self.camera, out=self._points, host_out=host,
                                    **kw)  # fmt: skip
        self.counter += 1
        if count < c.n_points:  # sec. 4.1: no pedestrian in this frame
            return np.zeros((0, 3), np.float32), int(count)
        return np.asarray(host[np.isfinite(host).all(axis=1)], np.float32), int(count)

    def upper(self, points: np.ndarray) -> np.ndarray:
        """The points higher than the sensor (step 2)."""
        return points[points.astype(np.float64) @ self.plane[:3] < 0]

    def segments(self, points: np.ndarray) -> tuple:
        """(segments, labels): DBSCAN of the points' ground coordinates (step 3); labels (N,) of
        the points' segment index (-1: none). On a device the 2D points go up and the labels come
        back through :attr:`copies`, with one wait (which also completes the copies enqueued
        before)."""
        c = self.config
        if len(points) == 0:
            return [], np.zeros(0, np.int64)
        k = len(points)
        # one buffer size and one launch size every frame, the rows after the k points NaN (no
        # point): the device kernels compile once (PoCL builds a kernel per launch size)
        xz = np.full((max(c.n_points, k), 2), np.nan, np.float32)
        xz[:k] = points.astype(np.float64) @ self.axes.T
        if self.device.backend == "numpy":
            lab = dbscan(self.device, xz, c.eps, c.min_samples, n_points=k)
        else:
            if self._xz is None or self._xz.shape != xz.shape:
                self._xz = self.device.empty(xz.shape, np.float32)
                self._labels = self.device.empty((len(xz),), np.int32)
                self._labels_host = np.empty(len(xz), np.int32)
            self.copies.upload(self._xz, xz)
            res = dbscan(self.device, self._xz, c.eps, c.min_samples, out=self._labels)
            lab = self.copies.download(res, self._labels_host)
            self.copies.wait()
        lab = np.asarray(lab[:k]).astype(np.int64)
        least = min(c.weak_points, c.min_segment_points) if c.weak_points else c.min_segment_points
        segs, keep = segments_of(points, lab, least, c.min_extent, c.min_width, self.axes,
                                 self.plane, c.max_height)  # fmt: skip
        idx = np.full(len(lab), -1, np.int64)
        for i, k in enumerate(keep):
            idx[lab == k] = i
        return segs, idx

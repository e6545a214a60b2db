"""Paper 003's monocular face tracker: head pose, facial deformation and the person's identity.

:class:`FaceTracker` composes the parts of this package (Fig. 1 of the paper):

- **Start** (:meth:`FaceTracker.start`, sec. 4.1 "initialisation"): the first n frames with the K
  feature points of each (given, or found from OpenCV's Haar face box in the first frame with the
  model's mean shape and followed into the next frames by pyramidal Lucas-Kanade); each frame's
  pose from its points by PnP with the mean shape; then the bundle adjustment of all n frames
  (``init_iterations`` LM iterations, eq. 6-9) gives the poses, deformations and the identity
  s(1). The K templates (16 x 16) are the first frame's patches at its points (anchored, beyond the
  paper: each point followed into the other start frames and moved by its mean offset from theirs,
  so one frame's detector error does not stay in the templates; ``config.anchor_templates``).
- **Per frame** (:meth:`FaceTracker.track`), as :class:`gputrack.Scheduler` stages:
  ``detect`` (the detection proposals below, host, every ``config.detect_every`` frames and every
  frame while the estimate is turned more than ``DETECT_FAR``),
  ``templates`` (beyond the paper, ``config.warp_templates``: the K templates sampled again from the
  first frame, turned and scaled as the estimate sees the face, :mod:`.templates`; host, uploaded),
  ``sample`` (eq. 12, host; the N x K hypothesis points uploaded), ``score`` (eq. 13's NCC sum of
  every hypothesis, ONE device launch), ``estimate`` (eq. 13 weights and the state, host reads the N
  scores), ``relocate`` (eq. 14, one device launch: :func:`gputrack.ops.face_relocate.relocate_points`,
  the K points, the frame's patches at them, which stay on the device for the next frame, and each
  point's match with its template), ``refine`` (the K points and their matches come down; beyond
  the paper, points matching worse than ``config.min_match`` are left out of the fits; with
  ``config.refine_pose``: the estimate's pose
  and, with ``config.refine_deformation``, its deformation fitted to them from the filter's
  estimate (:mod:`.refine`; the pose alone by PnP), and the filter's hypotheses moved by the same
  step, as paper 000 follows its particle filter with LM) and ``bundle`` (the incremental bundle
  adjustment on the key frames, eq. 6-10,
  ``iterations`` LM iterations through :func:`gputrack.least_squares` on the device; the identity's
  running mean, eq. 10).
- **Loss** (beyond the paper): a frame whose best hypothesis has a mean NCC below
  ``config.lost_score`` (an occluded or vanished face) is returned with confidence 0 and neither
  re-localises nor adjusts; after ``config.redetect_after`` such frames in a row the face is searched
  again with the Haar cascade and the filter restarts at the box nearest to the face's last place of
  about its last size (the identity is kept). A face that
  leaves the image scores 0 and is lost the same way.
- **Detection proposals** (beyond the paper): every ``config.detect_every`` frames (every frame while
  the estimate is turned more than ``DETECT_FAR``) the Haar cascade
  looks for the face near its estimate; where its box contradicts the estimate (a turned estimate,
  or points off the box), a share of that frame's hypotheses is drawn around the box's frontal pose
  (a mixture proposal, as Okuma et al.'s boosted particle filter): a filter locked on a wrong pose
  whose NCC stays fair (the loss test cannot see it) can come back.

The image is uploaded once per frame as float32 (and the K templates, 16 x 16 each, with
``warp_templates``); the previous frame's patches stay on the device.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ...device import Device, DeviceArray, as_host_array
from ...models.camera import Camera
from ...models.pose import MIN_POSE_POINTS, facing, fit_pose, project, rodrigues, rotation_vector
from ...ops.face_points import project_faces
from ...ops.face_relocate import relocate_points, sample_patches
from ...ops.ncc import patch_ncc
from ...scheduler import Scheduler, Stage
from .bundle import IncrementalBundle, _real_array
from .config import FaceConfig
from .pf import FaceParticleFilter, shape_model
from .refine import fit_pose_deformation
from .templates import TemplateViews

log = logging.getLogger("gputrack")

__all__ = ["FaceEstimate", "FaceTracker", "detect_face", "detect_faces"]


@dataclasses.dataclass(frozen=True)
class FaceEstimate:
    """One frame's result. rotation (3, 3) and translation (3,) mm: model -> camera; rvec (3,) the
    rotation as a Rodrigues vector; expression (D,) the deformation; identity (S',) s(t);
    landmarks (K, 2) px: the projection of the estimate (m'_t); features (K, 2) px: the
    re-localised points (eq. 14; NaN when lost, and where a point does not match its template,
    ``FaceConfig.min_match``); confidence in [0, 1]: the best hypothesis' mean NCC (0 when lost);
    lost: the face was not found in this frame."""

    rotation: np.ndarray
    translation: np.ndarray
    rvec: np.ndarray
    expression: np.ndarray
    identity: np.ndarray
    landmarks: np.ndarray
    features: np.ndarray
    confidence: float
    lost: bool


_CASCADE = None
#: detection proposals (``FaceTracker._propose_detected``): an estimate turned more than this (deg)
#: from the camera, or whose points are off the detected box's by more than this fraction of their
#: width (place or size), gets hypotheses around the box
DETECT_TURN, DETECT_OFF = 25.0, 0.15
#: an estimate turned further than this (deg) from the camera is searched for every frame, not every
#: ``detect_every``-th: faces are rarely turned so far, and a filter that has run on past a turn's end
#: must get back before the face turns away again
DETECT_FAR = 45.0
#: the start's anchoring (``FaceTracker._anchored``): a followed point farther than this (px) from
#: its frame's own point is a failed follow or a detector's outlier and is not used
ANCHOR_REACH = 5.0
#: the most template sources kept (``config.template_views``), the first frame's included
MAX_VIEWS = 16


def detect_faces(gray, sizes=None, scale_factor: float = 1.1) -> list[tuple[int, int, int, int]]:
    """Face boxes (x, y, w, h) px found by OpenCV's bundled frontal Haar cascade, at least 40 px
    wide; ``sizes`` (lo, hi) px: only boxes of that width (the cascade then scans fewer scales; on
    simulated 640 x 480 frames, 2-core VM: ~52 ms for every size with a 220 px face, 5-14 ms for
    1/1.4 to 1.4 times the width of 150-290 px faces, 2-5 ms with ``scale_factor`` 1.2)."""
    import cv2

    global _CASCADE
    if _CASCADE is None:
        _CASCADE = cv2.CascadeClassifier(cv2.data.haarcascades + "haarcascade_frontalface_default.xml")
    lo, hi = (40, 0) if sizes is None else (max(40, int(sizes[0])), int(np.ceil(sizes[1])))
    if sizes is not None and hi < lo:
        return []
    boxes = _CASCADE.detectMultiScale(np.asarray(gray, np.uint8), scaleFactor=scale_factor, minNeighbors=5,
                                      minSize=(lo, lo), maxSize=(hi, hi))  # fmt: skip
    return [tuple(int(v) for v in b) for b in boxes]


def detect_face(gray) -> tuple[int, int, int, int] | None:
    """The largest face box (x, y, w, h) px of :func:`detect_faces`, or None."""
    boxes = detect_faces(gray)
    return max(boxes, key=lambda b: b[2] * b[3]) if boxes else None


def _host(image, name: str) -> np.ndarray:
    if isinstance(image, DeviceArray):
        raise TypeError(f"{name}: expected a host (NumPy) (H, W) image, got a DeviceArray (download it with .numpy())")
    return as_host_array(image, name)


def _u8(image) -> np.ndarray:
    """A gray image as OpenCV's uint8 (float values clipped to 0-255)."""
    a = np.asarray(image)
    return a if a.dtype == np.uint8 else np.clip(a, 0, 255).astype(np.uint8)


def _lucas_kanade(a, b, points, guess, **options):
    """Pyramidal Lucas-Kanade (21 x 21 window) of ``points`` (K, 1, 2) float32 from image ``a`` into
    ``b`` (uint8), from ``guess`` (or None): ((K, 2) float64, NaN where lost; OpenCV's (K, 1, 2) result)."""
    import cv2

    nxt, st, _ = cv2.calcOpticalFlowPyrLK(a, b, points, guess, winSize=(21, 21), **options)
    pts = nxt.reshape(-1, 2).astype(np.float64)
    pts[st.ravel() == 0] = np.nan
    return pts, nxt


def _gray(image, name: str, shape=None) -> np.ndarray:
    a = _host(image, name)
    if a.dtype.kind not in "uif" or a.ndim != 2:
        raise ValueError(f"{name}: expected a (H, W) gray image of uint8 or float, got {a.dtype.name} {a.shape}")
    if shape is not None and a.shape != shape:
        raise ValueError(f"{name}: expected a frame of the started size {shape}, got {a.shape}")
    if a.shape[0] < 32 or a.shape[1] < 32:
        raise ValueError(f"{name}: expected an image of at least 32 x 32 pixels, got {a.shape}")
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise ValueError(f"{name}: expected finite pixel values, got NaN or inf")
    return a


class FaceTracker:
    """Track one face's pose, deformation and identity (paper 003); see the module docstring.

    model: :class:`gputrack.models.face.FaceModel` (multilinear) or ``PcaFaceModel`` (the generic
    comparison model, no identity); camera: :class:`gputrack.models.Camera`; config: FaceConfig.
    """

    def __init__(self, device: Device, model, camera: Camera, config: FaceConfig | None = None):
        config = FaceConfig() if config is None else config
        if not isinstance(device, Device):
            raise TypeError(f"device: expected a gputrack.Device, got {type(device).__name__}")
        if not isinstance(camera, Camera):
            raise TypeError(f"camera: expected a gputrack.models.Camera, got {type(camera).__name__}")
        if not isinstance(config, FaceConfig):
            raise TypeError(f"config: expected a FaceConfig, got {type(config).__name__}")
        if not hasattr(model, "expression_basis"):
            raise TypeError(f"model: expected a FaceModel or PcaFaceModel, got {type(model).__name__}")
        self.device, self.model, self.camera, self.config = device, model, camera, config
        self.bundle = IncrementalBundle(device, model, camera, n=config.keyframes, iterations=config.iterations,
                                        init_iterations=config.init_iterations, pose_range=config.pose_range,
                                        identity_sigmas=config.identity_sigmas,
                                        identity_prior=config.identity_prior)  # fmt: skip
        self.pf = FaceParticleFilter(camera, model.expression_mean, model.expression_std, config,
                                     np.random.default_rng(config.seed))  # fmt: skip
        self.identity = np.asarray(model.identity_mean, np.float64).copy()
        self._basis = model.expression_basis(self.identity)
        self.shape = None  # (H, W) of the started frames
        self.lost_frames = 0
        self.frame = 0
        self.proposals = 0  # frames whose hypotheses were partly drawn around a detection (``_propose_detected``)
        self.proposals_taken = 0  # of them, frames whose estimate moved to one of those hypotheses
        self._host = {}  # this frame's host-side values between stages
        self.views = None  # the templates' sources (templates.TemplateViews), from start()
        self.scheduler = Scheduler(device, [
            Stage("detect", self._detect),
            Stage("templates", self._templates, writes=("templates",)),
            Stage("sample", self._sample, writes=("states", "shape", "points", "facing")),
            Stage("score", self._score, reads=("image", "points", "templates"), writes=("scores",)),
            Stage("estimate", self._estimate, host_reads=("scores", "facing")),
            Stage("relocate", self._relocate, reads=("image", "templates", "previous"),
                  writes=("features", "previous", "spare", "match")),
            Stage("refine", self._refine, host_reads=("features", "match")),
            Stage("bundle", self._bundle),
        ], inputs=("image",), state=("templates", "previous", "features", "match"))  # fmt: skip

    # -- start ---------------------------------------------------------------------------------------

    @property
    def template_sources(self) -> int:
        """How many frames the templates are cut from (``config.template_views``): the first frame and
        the tracked frames kept since as seen from other directions (0 before :meth:`start`)."""
        return 0 if self.views is None else len(self.views)

    def _shape(self, a):
        """(K, 3) the current identity's shape at deformation ``a`` (A',) (eq. 11)."""
        mean, basis = self._basis
        return mean + basis @ a

    def _mean_shape(self):
        """(K, 3) the current identity's shape at the model's mean deformation."""
        return self._shape(self.model.expression_mean)

    def _pose_from_points(self, points, guess=None):
        """(rvec, tvec) of the current shape at expression mean seen at ``points`` (K, 2) (PnP)."""
        ok = np.isfinite(points).all(axis=1)
        if ok.sum() < MIN_POSE_POINTS:
            raise ValueError(f"landmarks: expected at least {MIN_POSE_POINTS} finite points for the start pose, got "
                             f"{int(ok.sum())}")  # fmt: skip
        if guess is None:
            guess = self._box_pose(points)
        fit = fit_pose(self.camera, self._mean_shape(), points, guess)
        return guess if fit is None else fit

    def _box_pose(self, points):
        """A frontal pose whose mean shape spans the points' extent (the start guess of PnP)."""
        X = self._mean_shape()
        pts = np.asarray(points, np.float64)
        ok = np.isfinite(pts).all(axis=1)
        span = np.ptp(pts[ok, 0]) if ok.sum() >= 2 else 100.0
        z = self.camera.fx * np.ptp(X[:, 0]) / max(span, 1.0)
        c = pts[ok].mean(axis=0) if ok.any() else np.array([self.camera.cx, self.camera.cy])
        t = np.array([(c[0] - self.camera.cx) * z / self.camera.fx, (c[1] - self.camera.cy) * z / self.camera.fy, z])
        return np.zeros(3), t - np.array([0.0, 0.0, X[:, 2].mean()])

    def _points_from_box(self, box):
        """K points of the mean shape placed in a Haar face box: frontal, their extent across 49 % of the
        box's width, their centroid at (49 %, 53 %) of it (OpenCV's frontal cascade on simulated faces
        of 18 people at 400-900 mm: std 2.7 %, 0.8 % and 1.1 %)."""
        x, y, w, h = box
        X = self._mean_shape()
        span = np.ptp(X[:, 0])
        z = self.camera.fx * span / (0.49 * w)
        t = np.array([(x + 0.49 * w - self.camera.cx) * z / self.camera.fx,
                      (y + 0.53 * h - self.camera.cy) * z / self.camera.fy, z])  # fmt: skip
        return project(self.camera, np.eye(3), t, X)

    def start(self, frames, landmarks=None) -> list[FaceEstimate]:
        """Initialise on the first n = ``config.keyframes`` frames (n, H, W) gray, with their K feature
        points (n, K, 2) px (NaN: unknown), or the first frame's only (K, 2) (followed into the next
        frames by pyramidal Lucas-Kanade), or, without them, from a Haar face box in the first frame.
        Returns the estimates of the n frames (their ``features``: the points used; every frame's points
        given are anchored to the templates with ``config.anchor_templates``, points followed from the
        first frame already are). Raises ValueError for fewer or more frames than n, or
        when no face is found."""
        n, K = self.config.keyframes, self.model.K
        if frames is None or isinstance(frames, (DeviceArray, str, bytes)) or not hasattr(frames, "__iter__"):
            got = type(frames).__name__
            if isinstance(frames, DeviceArray):
                got = "a DeviceArray (download it with .numpy())"
            raise TypeError(f"frames: expected a sequence of (H, W) uint8 images, got {got}")
        if not isinstance(frames, np.ndarray):
            frames = [_host(f, f"frames[{i}]") for i, f in enumerate(frames)]
        frames = list(frames)
        if len(frames) != n:
            raise ValueError(f"frames: expected the first n={n} frames (FaceConfig.keyframes), got {len(frames)}")
        frames = [_gray(f, f"frames[{i}]", None if i == 0 else frames[0].shape) for i, f in enumerate(frames)]
        if landmarks is not None:
            landmarks = as_host_array(landmarks, "landmarks")
            if landmarks.dtype.kind not in "iuf":
                raise TypeError(f"landmarks: expected real points (px), got dtype {landmarks.dtype.name}")
        followed = landmarks is None or landmarks.ndim == 2  # the other frames' points come from the first's
        if landmarks is None:
            landmarks = self._follow(frames, self._detected_points(frames[0]))
        elif landmarks.ndim == 2:
            first = np.asarray(landmarks, np.float64)
            if first.shape != (K, 2) or not np.isfinite(first).all():
                raise ValueError(f"landmarks: expected the first frame's K={K} finite points (K, 2), got {first.shape}")
            landmarks = self._follow(frames, first)
        lm = np.asarray(landmarks, np.float64)
        if lm.shape != (n, K, 2):
            raise ValueError(f"landmarks: expected shape (n={n}, K={K}, 2), got {lm.shape}")
        if np.isinf(lm).any():
            raise ValueError("landmarks: expected finite values or NaN (unknown), got inf")
        if not np.isfinite(lm[0]).all():
            raise ValueError("landmarks: expected every point of the first frame (its templates), got NaN")
        self.shape = frames[0].shape
        if self.config.anchor_templates and not followed:
            lm = self._anchored(frames, lm)
        poses = [self._pose_from_points(lm[0])]
        for i in range(1, n):
            poses.append(self._pose_from_points(lm[i], poses[-1]))
        rv, tv = np.array([p[0] for p in poses]), np.array([p[1] for p in poses])
        A = np.tile(self.model.expression_mean, (n, 1))
        self.identity = self.bundle.start(lm, rv, tv, A, hold_identity=self.config.hold_identity_at_start)
        self._basis = self.model.expression_basis(self.identity)
        res = self.bundle.last
        S = self.config.template
        first = frames[0].astype(np.float64)  # the sampler's own type: no conversion per frame
        self.views = TemplateViews(self.camera, S, self.config.template_views, MAX_VIEWS)
        self.views.add(first, lm[0], (res.rvecs[0], res.tvecs[0]), self._shape(res.expressions[0]))
        self.scheduler.set("templates", sample_patches(first, lm[0], S).astype(np.float32))
        last = n - 1
        features = lm[last].copy()
        features[~np.isfinite(features)] = self._predicted(res.rvecs[last], res.tvecs[last],
                                                           res.expressions[last])[~np.isfinite(lm[last])]
        self.scheduler.set("features", features.astype(np.float32))
        self.scheduler.set("match", np.ones(K, np.float32))  # the start's points are the templates' own
        self.scheduler.set("previous", sample_patches(frames[last].astype(np.float32), features, S).astype(np.float32))
        self.pf.reset(np.concatenate([res.rvecs[last], res.tvecs[last], res.expressions[last]]), K)
        self.lost_frames, self.frame = 0, n
        out = []
        for i in range(n):
            pts = self._predicted(res.rvecs[i], res.tvecs[i], res.expressions[i])
            out.append(self._estimate_of(res.rvecs[i], res.tvecs[i], res.expressions[i], pts, lm[i], 1.0, False))
        return out

    def _detected_points(self, gray):
        box = detect_face(gray)
        if box is None:
            raise ValueError("frames[0]: expected a face (OpenCV's Haar cascade found none); pass landmarks=")
        return self._points_from_box(box)

    @staticmethod
    def _anchored(frames, lm):
        """(n, K, 2) the start frames' points made consistent with the first frame's templates.

        The templates are cut at the first frame's points, so a detector's error there stays with
        them in every later frame. Each template's point is followed into the other start frames
        (pyramidal Lucas-Kanade from the first frame, started at that frame's own point); its offset
        from that frame's point is the first frame's error minus that frame's. The mean offset over
        the n frames (0 for the first) is taken off every followed point, so all n frames' points,
        and the first frame's templates cut at them, carry only the mean of the n frames' errors."""
        import cv2

        n = len(lm)
        first = _u8(frames[0])
        p0 = np.asarray(lm[0], np.float32).reshape(-1, 1, 2)
        followed = np.full(lm.shape, np.nan)
        followed[0] = lm[0]
        for i in range(1, n):
            guess = np.where(np.isfinite(lm[i]), lm[i], lm[0]).astype(np.float32).reshape(-1, 1, 2)
            followed[i], _ = _lucas_kanade(first, _u8(frames[i]), p0, guess, maxLevel=1,
                                           flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                           criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))  # fmt: skip
        offset = followed - lm  # (n, K, 2): e_0 - e_i where both are known
        ok = np.isfinite(offset).all(axis=2) & (np.hypot(*np.moveaxis(offset, 2, 0)) < ANCHOR_REACH)
        count = ok.sum(axis=0)
        mean = np.where(ok[..., None], offset, 0.0).sum(axis=0) / np.maximum(count, 1)[:, None]
        return np.where(ok[..., None], followed - mean, lm)

    @staticmethod
    def _follow(frames, p0):
        """(n, K, 2): the points ``p0`` of the first frame followed by pyramidal Lucas-Kanade (NaN: lost)."""
        out = [np.asarray(p0, np.float64)]
        prev, prev_pts = _u8(frames[0]), np.asarray(p0, np.float32).reshape(-1, 1, 2)
        for f in frames[1:]:
            img = _u8(f)
            pts, prev_pts = _lucas_kanade(prev, img, prev_pts, None, maxLevel=3)
            out.append(pts)
            prev = img
        return np.array(out)

    # -- per frame -----------------------------------------------------------------------------------

    def _predicted(self, rvec, tvec, a):
        return project(self.camera, rodrigues(rvec), tvec, self._shape(a))

    def _estimate_of(self, rvec, tvec, a, landmarks, features, confidence, lost) -> FaceEstimate:
        return FaceEstimate(rotation=rodrigues(rvec), translation=np.array(tvec, np.float64),
                            rvec=np.array(rvec, np.float64), expression=np.array(a, np.float64),
                            identity=self.identity.copy(), landmarks=landmarks, features=features,
                            confidence=float(confidence), lost=bool(lost))  # fmt: skip

    def _detect(self, b):
        """Detection proposals (host, every ``config.detect_every`` frames, and every frame while the
        estimate is turned more than ``DETECT_FAR``): :meth:`_propose_detected`."""
        every = self.config.detect_every
        if not every or self.lost_frames:
            return
        est = self.pf.estimate
        if self.frame % every == 0 or facing(rodrigues(est[:3]), est[3:6]) < np.cos(np.radians(DETECT_FAR)):
            self._propose_detected(self._host["gray"])

    def _templates(self, b):
        """The templates turned and scaled as the estimate sees the face, each point's from the source
        nearest the estimate's face direction (host, ``config.warp_templates`` and ``template_views``;
        :mod:`gputrack.trackers.face.templates`), uploaded for eq. 13 and 14."""
        if not self.config.warp_templates:
            return
        est = self.pf.estimate
        templates = self.views.templates((est[:3], est[3:6]), self._shape(est[6:]))
        b["templates"] = self.device.asarray(templates, out=b.get("templates"))

    def _sample(self, b):
        states = self.pf.propose_states().astype(np.float32)  # eq. 12 on the host, eq. 5 and 11 on the device
        b["states"] = self.device.asarray(states, out=b.get("states"))
        b["shape"] = self.device.asarray(shape_model(*self._basis), out=b.get("shape"))
        out = (b["points"], b["facing"]) if "points" in b else None
        b["points"], b["facing"] = project_faces(self.device, b["states"], b["shape"], self.camera, out=out)

    def _score(self, b):
        b["scores"] = patch_ncc(self.device, b["points"], b["templates"], b["image"])  # eq. 13 N(u), one launch

    def _estimate(self, b):
        est = self.pf.update(b["scores"], b["facing"])
        self.proposals_taken += int(self.pf.from_detection)
        conf = max(0.0, self.pf.best_score / self.model.K)
        self._host.update(state=est, confidence=conf, lost=conf < self.config.lost_score)

    def _relocate(self, b):
        """Eq. 14 on the device from the estimate's points: the feature points, the frame's patches
        at them (the next frame's I_{t-1}; two arrays in turn) and how each matches its template."""
        h = self._host
        est = h["state"]
        h["landmarks"] = self._predicted(est[:3], est[3:6], est[6:])
        if h["lost"]:
            return
        c = self.config
        spare = b.get("spare")
        out = None if spare is None else (b.get("features"), spare, b.get("match"))  # last frame's arrays
        m, patches, match = relocate_points(self.device, b["image"], h["landmarks"].astype(np.float32),
                                            b["previous"], b["templates"], rho=c.rho, eps=c.eps,
                                            iterations=c.relocate_iterations, contrast=c.relocate_contrast,
                                            shading=c.relocate_shading, out=out)  # fmt: skip
        b["spare"], b["previous"], b["features"], b["match"] = b["previous"], patches, m, match

    def _refine(self, b):
        """The feature points come down, less those that do not match their templates (``config.min_match``:
        NaN, left out of this fit and the bundle adjustment; where fewer than MIN_POSE_POINTS match, all
        but the MIN_POSE_POINTS that match best); the estimate fitted to them (``config.refine_pose``, host): its
        pose (:func:`~gputrack.models.pose.fit_pose` with the estimate's shape), then from there its
        pose and deformation (``config.refine_deformation`` > 0, :func:`.refine.fit_pose_deformation`);
        each fit that moves the pose beyond ``pose_range`` is not taken; the filter moved with it. A
        refined frame seen from a new direction becomes a source of the templates (``config.template_views``)."""
        h = self._host
        if h["lost"]:
            h["features"] = np.full((self.model.K, 2), np.nan)
            return
        given, c = h.get("given"), self.config
        if given is None:
            m = b["features"].astype(np.float64)
            off = b["match"] < c.min_match  # no longer like its template: hidden, or slipped onto other texture
            if (~off).sum() < MIN_POSE_POINTS:  # too few match: the MIN_POSE_POINTS that match best
                off = np.ones(len(off), bool)
                off[np.argsort(-np.asarray(b["match"]), kind="stable")[:MIN_POSE_POINTS]] = False
            m[off] = np.nan
        else:
            m = given
        h["features"] = m
        est = h["state"]
        if not c.refine_pose:
            return
        fit = fit_pose(self.camera, self._shape(est[6:]), m, (est[:3], est[3:6]))
        new = None if fit is None else self._trusted(np.concatenate([fit[0], fit[1], est[6:]]), est)
        if c.refine_deformation > 0:  # then the deformation with the pose, from there
            start = est if new is None else new
            fit = fit_pose_deformation(self.camera, *self._basis, m, start, c.refine_deformation * self.model.expression_std)
            if fit is not None:
                new = self._trusted(fit, start, otherwise=new)
        if new is None:
            return
        self.pf.move(new)
        h["state"] = new
        h["landmarks"] = self._predicted(new[:3], new[3:6], new[6:])
        if given is None and c.warp_templates and c.template_views > 0:  # a source of templates (own points only)
            self.views.add(h["gray"], m, (new[:3], new[3:6]), self._shape(new[6:]))

    def _trusted(self, new, start, otherwise=None):
        """``new`` (6 + D,) unless its pose is more than ``config.pose_range`` from ``start``'s: points
        that disagree this much with the filter are not trusted (then ``otherwise``)."""
        turn = np.linalg.norm(rotation_vector(rodrigues(new[:3]) @ rodrigues(start[:3]).T))
        far = turn > self.config.pose_range[0] or np.linalg.norm(new[3:6] - start[3:6]) > self.config.pose_range[1]
        return otherwise if far else new

    def _bundle(self, b):
        h = self._host
        lost = h["lost"]
        if lost or not self.config.learn_identity or self.model.identity_dims == 0:
            return  # the generic model has no identity to learn
        est = h["state"]
        self.identity = self.bundle.add(h["features"], est[:3], est[3:6], est[6:])  # eq. 6-10
        self._basis = self.model.expression_basis(self.identity)

    def track(self, gray, features=None) -> FaceEstimate:
        """Track one frame (H, W) gray (the size of the start frames). Returns its :class:`FaceEstimate`.

        features: optional (K, 2) px, this frame's feature points from elsewhere (another landmark
        detector, or a simulator's true landmarks to measure what the points bound; NaN: unknown),
        used instead of eq. 14's for the pose fit and the bundle adjustment. Eq. 14 still runs: its
        patches are the next frame's I_{t-1}. A frame found lost uses neither."""
        if self.shape is None:
            raise RuntimeError("FaceTracker: call start() with the first frames before track()")
        img = _gray(gray, "gray", self.shape).astype(np.float32)
        if features is not None:
            features = _real_array(as_host_array(features, "features"), "features", (self.model.K, 2), allow_nan=True)
        self._host = {"gray": img, "given": features}
        self.scheduler.run(image=img)
        h = self._host
        self.frame += 1
        est = h["state"]
        if h["lost"]:
            self.lost_frames += 1
            if self.lost_frames >= self.config.redetect_after:
                self._redetect(img)
        else:
            self.lost_frames = 0
        return self._estimate_of(est[:3], est[3:6], est[6:], h["landmarks"], h["features"],
                                 0.0 if h["lost"] else h["confidence"], h["lost"])  # fmt: skip

    def _frontal_span(self, z) -> float:
        """px: how wide the current shape's points (at the mean deformation) look seen frontally at
        depth ``z`` (mm)."""
        return self.camera.fx * np.ptp(self._mean_shape()[:, 0]) / max(float(z), 1.0)

    def _detected_box(self, img, near=False):
        """(box, last): the Haar box (x, y, w, h) nearest to where the face was last seen, or None,
        and the last estimate's points (K, 2). The face's width is the box width a frontal face at the
        estimate's depth gets (not its points' extent, which a turn shrinks). Boxes within a factor 2
        of that width anywhere (a box elsewhere is more likely background); with ``near``, within a
        factor 1.4 and half a box of the face only, searched in that part of the image with coarser
        scale steps (the detection proposals: a few ms, ``detect_faces``)."""
        est = self.pf.estimate
        last = self._predicted(est[:3], est[3:6], est[6:])
        # the box a frontal face at the estimate's depth gets (the points' own extent shrinks with a turn, and
        # a filter turned away from a frontal face would look for too small a box)
        centre, width = last.mean(axis=0), max(self._frontal_span(est[5]) / 0.49, 1.0)
        x0 = y0 = 0
        if near:
            reach = 1.3 * width  # half a box's offset and half the largest box (0.51 x 1.4 widths), with room
            x0, y0 = (max(0, int(c - reach)) for c in centre)
            x1, y1 = (max(0, int(c + reach) + 1) for c in centre)
            boxes = detect_faces(np.clip(img[y0:y1, x0:x1], 0, 255), sizes=(width / 1.4, width * 1.4), scale_factor=1.2)
        else:
            boxes = detect_faces(np.clip(img, 0, 255), sizes=(width / 2, width * 2))
        boxes = [(x + x0, y + y0, w, h) for x, y, w, h in boxes]
        dist = [np.hypot(b[0] + 0.49 * b[2] - centre[0], b[1] + 0.53 * b[3] - centre[1]) for b in boxes]
        if not boxes or (near and min(dist) > 0.5 * width):
            return None, last
        return boxes[int(np.argmin(dist))], last

    def _redetect(self, img) -> None:
        """Restart the filter at the face found by :meth:`_detected_box`, if any."""
        box, _ = self._detected_box(img)
        if box is None:
            return
        r, t = self._pose_from_points(self._points_from_box(box))
        self.pf.reset(np.concatenate([r, t, self.model.expression_mean]), self.model.K)
        self.lost_frames = 0
        log.info("FaceTracker: face re-detected at frame %d", self.frame)

    def _propose_detected(self, img) -> None:
        """Mix hypotheses around the face found near the estimate (:meth:`_detected_box`) into this
        frame's proposal (``config.detect_every``) where the box contradicts the estimate: the
        estimate turned more than ``DETECT_TURN`` from the camera (the cascade finds faces that look
        at it), or its points off the box's by more than ``DETECT_OFF`` of its width in place or
        size (the size a frontal face at the estimate's depth would have). Where they agree the
        proposal is left alone (a turn's mirror image is one of the poses a frontal guess can lead
        to). The proposal is the box's frontal pose; where the box's size agrees with the estimate's
        depth, at that depth (a box tells a face's distance only to some 10 %: its proportions to
        the box differ from person to person, and the identity learnt knows the size better)."""
        box, last = self._detected_box(img, near=True)
        if box is None:
            return
        est = self.pf.estimate
        turned = facing(rodrigues(est[:3]), est[3:6]) < np.cos(np.radians(DETECT_TURN))
        pts = self._points_from_box(box)
        w = np.ptp(pts[:, 0])
        place = np.hypot(*(pts.mean(axis=0) - last.mean(axis=0))) / w
        size = abs(self._frontal_span(est[5]) - w) / w
        if turned or max(place, size) > DETECT_OFF:
            r, t = self._pose_from_points(pts)
            if size <= DETECT_OFF:
                t = t * (est[5] / t[2])  # along the ray to the box's face: its place kept, the estimate's depth
            self.pf.mix(np.concatenate([r, t, est[6:]]), self.config.detect_share)
            self.proposals += 1

    def fix_identity(self, identity) -> None:
        """Use ``identity`` (S',) from now on (with ``config.learn_identity=False`` it stays: e.g. the
        true identity, for the depth floor of a landmark-only tracker)."""
        s = np.asarray(identity, np.float64)
        if s.shape != (self.model.identity_dims,) or not np.isfinite(s).all():
            raise ValueError(f"identity: expected {self.model.identity_dims} finite values, got shape {s.shape}")
        self.identity = s.copy()
        self._basis = self.model.expression_basis(self.identity)

    @property
    def keyframes(self) -> np.ndarray:
        """Frame numbers of the bundle adjustment's key frames."""
        return self.bundle.keyframes


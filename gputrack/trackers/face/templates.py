"""The templates as the face is seen now (beyond the paper: ``FaceConfig.warp_templates`` and
``template_views``).

Eq. 13 scores the hypotheses and eq. 14 re-localises the points against the K templates cut from the
first frame. As the head rolls or moves in depth, the patch around a feature point turns and scales in
the image, and the template's best match moves off the point: on the simulator's turns sequence,
eq. 14's first-frame term alone, started at the true points, settles 1-7 px away from them on the eye
corners, nostrils and mouth corners (the previous frame's term follows it there over a few frames).
So each frame the templates are sampled again from the first frame, turned and scaled as the
filter's estimate sees the face.

The map. A small patch of the face's frontal plane (the model's x-y plane) at model point X, seen with
the pose (R, t) model -> camera, moves in the image by J d for a step d in that plane, with the 2 x 2
Jacobian

    J(R, t, X) = dpi/dP (R X + t) R [e_x e_y],   dpi/dP (P) = [[fx / z, 0, -fx x / z^2], [0, fy / z, -fy y / z^2]].

A pixel offset d from the point in the current frame is the plane step J^-1 d, which was J_0 J^-1 d in
the first frame (J_0: the first frame's pose and shape). Of A = J_0 J^-1 only the nearest similarity
is kept, [[a, -b], [b, a]] with a = (A_00 + A_11) / 2 and b = (A_10 - A_01) / 2 (nearest in the
Frobenius norm): the in-plane turn and the scale are alike for any surface at the point, while the
foreshortening of a yaw or a pitch depends on the surface's direction there, which the K points do not
tell. (Measured on the simulator, seeds 0-11: the full map A of the frontal plane put the outer eye
corners and the nostrils, which do not lie in it, further off and lost yaw on the turns sequence; the
similarity lowered the yaw error on every sequence; the README's face section.)

The sources (:class:`TemplateViews`). A similarity cannot show how a patch looks once the face has
turned away from the first frame: the far eye's corners and the nostrils foreshorten, the mouth
corners wrap round. So tracked frames seen from other directions become sources too, and each
point's template is cut from the source whose face direction is nearest the estimate's, warped
from that source's pose as above.
"""

from __future__ import annotations

import numpy as np

from ...models.camera import Camera
from ...models.pose import rodrigues

__all__ = ["VIEW_POINTS", "TemplateViews", "frontal_jacobians", "template_warp"]

#: the fewest matched points of a frame kept as a source of templates (:class:`TemplateViews`)
VIEW_POINTS = 8


def frontal_jacobians(camera: Camera, rvec, tvec, X) -> np.ndarray:
    """(K, 2, 2): the image motion (px) of a step (mm) along the model's x and y axes at each model point
    X (K, 3), seen with the pose (rvec Rodrigues, tvec mm) model -> camera."""
    R = rodrigues(np.asarray(rvec, np.float64))
    P = np.asarray(X, np.float64) @ R.T + np.asarray(tvec, np.float64)
    z = np.maximum(P[:, 2], 1e-6)
    D = np.zeros((len(P), 2, 3))
    D[:, 0, 0], D[:, 0, 2] = camera.fx / z, -camera.fx * P[:, 0] / z**2
    D[:, 1, 1], D[:, 1, 2] = camera.fy / z, -camera.fy * P[:, 1] / z**2
    return D @ R[:, :2]


def template_warp(camera: Camera, first_pose, first_shape, pose, shape) -> np.ndarray:
    """(K, 2, 2): for :func:`gputrack.ops.face_relocate.sample_patches` on the first frame, the
    similarity that maps a pixel offset from each feature point now to the offset in the first frame
    (see the module docstring). first_pose, pose: (rvec, tvec) model -> camera; first_shape, shape:
    (K, 3) mm, the model points then and now. A point seen edge-on (a singular J) keeps the identity."""
    return _similarity(frontal_jacobians(camera, *first_pose, first_shape), frontal_jacobians(camera, *pose, shape))


def _similarity(J0, J) -> np.ndarray:
    """(K, 2, 2) the similarity nearest J0 J^-1 per point (the identity where J is singular): J0, J
    (K, 2, 2) the frontal Jacobians then and now (:func:`template_warp`)."""
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    ok = np.abs(det) > 1e-9
    inv = np.stack([np.stack([J[:, 1, 1], -J[:, 0, 1]], -1), np.stack([-J[:, 1, 0], J[:, 0, 0]], -1)], -2)
    A = J0 @ (inv / np.where(ok, det, 1.0)[:, None, None])
    a = (A[:, 0, 0] + A[:, 1, 1]) / 2
    b = (A[:, 1, 0] - A[:, 0, 1]) / 2
    S = np.stack([np.stack([a, -b], -1), np.stack([b, a], -1)], -2)
    S[~ok | ~np.isfinite(S).all(axis=(1, 2))] = np.eye(2)
    return S


class TemplateViews:
    """The templates' sources (beyond the paper: ``FaceConfig.template_views``): the first frame, then
    tracked frames that saw the face from other directions.

    A source is (image, points (K, 2) px with NaN where a point did not match, pose (rvec, tvec), shape
    (K, 3) mm). :meth:`add` keeps a frame where at least ``VIEW_POINTS`` points matched and its
    face direction (the model's z axis in the camera frame) is more than ``spacing`` degrees from every
    kept source's, up to ``most`` sources (``spacing`` 0: the first frame's alone). :meth:`templates`
    cuts each point's template from the source nearest the estimate's face direction among those where
    that point matched, warped by :func:`template_warp` from that source's pose and shape: a turned
    face is matched against patches seen turned, not frontal patches turned by a similarity. The
    sources' images are kept stacked, with their frontal Jacobians, so that a frame's templates take
    one bilinear sampling whatever their sources."""

    def __init__(self, camera: Camera, size: int, spacing: float, most: int):
        self.camera, self.size, self.most = camera, int(size), int(most)
        self.spacing = float(spacing)
        self._directions: list[np.ndarray] = []  # each source's face direction (3,)
        self._poses: list[tuple] = []  # (rvec, tvec)
        self._shapes: list[np.ndarray] = []  # (K, 3)
        self._images = self._points = self._jacobians = None  # (n, H, W), (n, K, 2), (n, K, 2, 2), room for more

    def __len__(self) -> int:
        return len(self._directions)

    @property
    def sources(self) -> list[tuple]:
        """The sources in the order kept: (image (H, W), points (K, 2), pose (rvec, tvec), shape (K, 3))."""
        return [(self._images[i], self._points[i], self._poses[i], self._shapes[i]) for i in range(len(self))]

    def add(self, image, points, pose, shape) -> bool:
        """Keep this frame as a source (the first one always, with every point known); True if kept."""
        pts = np.asarray(points, np.float64)
        rvec, tvec = np.array(pose[0], np.float64), np.array(pose[1], np.float64)
        d = rodrigues(rvec)[:, 2]
        if len(self):
            if self.spacing <= 0 or len(self) >= self.most or np.isfinite(pts).all(axis=1).sum() < VIEW_POINTS:
                return False
            if max(float(e @ d) for e in self._directions) > np.cos(np.radians(self.spacing)):
                return False
        elif not np.isfinite(pts).all():
            raise ValueError("points: expected every point of the first source, got NaN")
        n, shp = len(self), np.asarray(shape, np.float64).copy()
        self._images = self._put(self._images, n, np.asarray(image, np.float64))
        self._points = self._put(self._points, n, pts)
        self._jacobians = self._put(self._jacobians, n, frontal_jacobians(self.camera, rvec, tvec, shp))
        self._poses.append((rvec, tvec))
        self._shapes.append(shp)
        self._directions.append(d)
        return True

    def _put(self, held, n, new):
        """``held`` with ``new`` as its n-th entry: room for twice as many made where it is full (at
        most ``most``), so that the sources are copied a few times, not at every addition."""
        if held is None or n == len(held):
            grown = np.empty((1 if held is None else min(2 * n, self.most), *np.shape(new)), np.float64)
            if held is not None:
                grown[:n] = held
            held = grown
        held[n] = new
        return held

    def choice(self, rvec) -> np.ndarray:
        """(K,) each point's source for a face turned as ``rvec``: the nearest in direction where it matched."""
        d = rodrigues(np.asarray(rvec, np.float64))[:, 2]
        out = np.full(self._points.shape[1], -1)
        for i in np.argsort([-float(e @ d) for e in self._directions], kind="stable"):
            out[(out < 0) & np.isfinite(self._points[i]).all(axis=1)] = i
        return out

    def templates(self, pose, shape) -> np.ndarray:
        """(K, size, size) float32: each point's template as the face is seen at ``pose`` (rvec, tvec)
        with ``shape`` (K, 3)."""
        from ...ops.face_relocate import sample_patches

        K, n = self._points.shape[1], len(self)
        src = self.choice(pose[0]) if n > 1 else np.zeros(K, int)
        k = np.arange(K)
        warp = _similarity(self._jacobians[src, k], frontal_jacobians(self.camera, *pose, shape))
        return sample_patches(self._images[:n], self._points[src, k], self.size, warp, src).astype(np.float32)

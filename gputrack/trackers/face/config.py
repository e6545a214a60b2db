"""The face tracker's constants (paper 003), each with the paper's value as default where it gives one."""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["FaceConfig"]


def _positive(owner, name, v, *, zero=False):
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not np.isfinite(v) \
            or v < 0 or (v == 0 and not zero):
        raise ValueError(f"{owner}.{name}: expected a finite number {'>=' if zero else '>'} 0, got {v!r}")


def _count(owner, name, v, lo):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
        raise ValueError(f"{owner}.{name}: expected an int >= {lo}, got {v!r}")


@dataclasses.dataclass(frozen=True)
class FaceConfig:
    """Constants of :class:`gputrack.trackers.face.FaceTracker`.

    Particle filter (sec. 4.1, eq. 11-13): ``particles`` N = 1000; ``sigma`` = 1.0 of eq. 13;
    ``kappa`` = 0.2: the deformation noise std as a multiple of the model's std; ``rotation_noise``
    (rad) and ``translation_noise`` (mm, x y z): the pose noise at rest, plus ``speed_gain`` times the
    estimate's speed per component (adaptive pose noise, as Oka et al.); ``near``: the state is the
    weighted mean of the hypotheses within this many noise standard deviations of the best one in
    every component; ``prior``: eq. 13's deformation prior term; ``max_turn`` (deg, beyond the paper):
    hypotheses whose face turns further than this from the line of sight get weight 0 (their
    feature points would be hidden; without it a filter can drift to a face seen edge-on);
    ``depth_range`` (mm, beyond the paper): hypotheses of the model origin nearer or farther than this
    get weight 0 (a filter that loses the face must not run away in depth).

    Templates and re-localisation (sec. 4.2, eq. 14): ``template`` = 16 px patches; ``rho`` = 4,
    ``eps`` = 4000; ``relocate_iterations`` Gauss-Newton steps at most (a point stops when its step
    is under 0.01 px); ``relocate_contrast`` (gray levels, beyond the paper; 0 = the paper's raw
    intensities): eq. 14 compares the patches brought to zero mean and this standard deviation, so a
    change of the light does not pull the points (:func:`gputrack.ops.face_relocate.relocate_points`);
    ``relocate_shading`` (beyond the paper, with ``relocate_contrast`` > 0; off by default): the
    comparison with the first frame's templates takes each patch's intensity ramp off too, so that
    light that has come round to one side, shading a patch across its width, does not pull the
    points either (better on the simulator's lighting sequence, a little worse on the others: the
    README's face section); ``anchor_templates`` (beyond the paper; False = the first frame's
    patches at its given points): where every start frame's points are given (a detector's), each
    first-frame template's point is followed into the other start frames (Lucas-Kanade) and moved
    by the mean offset from their given points, so a detector's error in the first frame does not
    stay in the templates (1 px of noise per point: 1.1 -> 0.5 px from the truth on the simulator);
    ``warp_templates`` (beyond the paper; False = the first frame's patches as cut): every frame the
    templates are sampled again from the first frame, turned and scaled by the similarity the
    filter's estimate gives each point (:mod:`gputrack.trackers.face.templates`), so that a roll or a
    move in depth does not pull eq. 13's scores and eq. 14's points; ``template_views`` (beyond the
    paper, degrees, with ``warp_templates``; 0 = the first frame only): a tracked frame where at
    least eight points matched their templates and whose face direction is more than this from every
    source's becomes another source of the templates (at its re-localised points that matched; at
    most 16 sources), and each frame each point's template comes from the source nearest the
    estimate's face direction where that point matched
    (:class:`gputrack.trackers.face.templates.TemplateViews`): a turned face is matched against
    patches seen turned, not frontal patches warped by a similarity (the mixed sequence's errors fell
    by a quarter to a third; the README's face section); ``min_match`` (beyond the paper;
    -1 = every point, as the paper): a re-localised point whose patch matches its template worse than
    this (the NCC with each patch's intensity plane off, ``relocate_points``' ``match``) is hidden,
    e.g. behind the nose as the head turns, or has slipped onto other texture: it is left out of the
    pose fit and the bundle adjustment (NaN in :attr:`FaceEstimate.features`); where fewer than
    ``MIN_POSE_POINTS`` (6) match, the six that match best are kept;
    ``refine_pose`` (beyond the
    paper; False = the filter's estimate): the estimate's pose is refined to fit the re-localised
    points (PnP, Levenberg-Marquardt from the estimate, the shape held) and the filter's hypotheses
    move with it; a step beyond ``pose_range`` is not taken. ``refine_deformation`` (beyond the paper,
    with ``refine_pose``; 0 = the pose only, the filter's deformation held): the deformation is
    fitted with the pose, held near the filter's by a Gaussian prior of this many model standard
    deviations (:func:`gputrack.trackers.face.refine.fit_pose_deformation`; the pose alone took
    up the deformation's error as a pitch of the head).

    Bundle adjustment (sec. 3, eq. 5-10): ``keyframes`` n = 7; ``init_iterations`` = 10 LM
    iterations over the first n frames, ``iterations`` = 5 per tracked frame; ``pose_range``
    (rad, mm) = lambda_p of eq. 8; ``identity_sigmas`` = 2 of eq. 9; ``identity_prior`` (beyond the
    paper; 0 = the paper's box only): the weight of a Gaussian prior on the identity in the bundle
    adjustment (:func:`~gputrack.trackers.face.bundle.bundle_adjust`); ``hold_identity_at_start``
    (beyond the paper): the start's adjustment of the first n frames moves the poses and
    deformations only and keeps the model's mean identity, which the incremental adjustment then
    learns (the start's frames, seen from one direction, show little of the face's proportions:
    learning them there traded them against pitch and depth); ``learn_identity``: run the
    incremental bundle adjustment while tracking (False keeps the identity of the start).

    Loss (beyond the paper): a frame whose best hypothesis has a mean NCC below ``lost_score`` is
    reported with confidence 0 and skips the re-localisation and the bundle adjustment; after
    ``redetect_after`` such frames in a row the face is searched again (Haar cascade) and the
    filter restarts at the detection, keeping the identity. Detection proposals (beyond the paper; 0
    = off): every ``detect_every`` tracked frames, and every frame while the estimate is turned
    more than 45 deg from the camera, the face is searched near its estimate (Haar cascade, boxes
    of 1/1.4 to 1.4 times its size within half a box of it); where the box
    contradicts the estimate (the estimate turned more than 25 deg from the camera, or its points
    off the box's by more than 15 % of their width), the fraction ``detect_share`` of that frame's
    hypotheses is drawn around the frontal pose the box gives
    (:meth:`~gputrack.trackers.face.pf.FaceParticleFilter.mix`): a filter that has locked on a wrong
    pose with a fair NCC (turned too far, a mirrored turn) gets a way back, and eq. 13 decides.
    ``seed``: the filter's random numbers.
    """

    particles: int = 1000
    sigma: float = 1.0
    kappa: float = 0.2
    rotation_noise: float = 0.015
    translation_noise: tuple = (2.0, 2.0, 8.0)
    speed_gain: float = 0.25
    near: float = 4.0
    prior: bool = True
    max_turn: float = 75.0
    depth_range: tuple = (150.0, 3000.0)
    template: int = 16
    rho: float = 4.0
    eps: float = 4000.0
    relocate_iterations: int = 5
    relocate_contrast: float = 30.0
    relocate_shading: bool = False
    min_match: float = 0.5
    anchor_templates: bool = True
    warp_templates: bool = True
    template_views: float = 10.0
    refine_pose: bool = True
    refine_deformation: float = 0.5
    keyframes: int = 7
    init_iterations: int = 10
    iterations: int = 5
    pose_range: tuple = (0.15, 30.0)
    identity_sigmas: float = 2.0
    identity_prior: float = 1.0
    hold_identity_at_start: bool = True
    learn_identity: bool = True
    lost_score: float = 0.3
    redetect_after: int = 5
    detect_every: int = 10
    detect_share: float = 0.2
    seed: int = 0

    def __post_init__(self):
        o = "FaceConfig"
        for name in ("particles", "template", "keyframes"):
            _count(o, name, getattr(self, name), 2 if name == "template" else 1)
        for name in ("relocate_iterations", "init_iterations", "iterations", "redetect_after", "detect_every"):
            _count(o, name, getattr(self, name), 0)
        if not np.isfinite(self.max_turn) or not 0 < self.max_turn <= 180:
            raise ValueError(f"{o}.max_turn: expected degrees in (0, 180], got {self.max_turn!r}")
        for name in ("sigma", "near", "identity_sigmas"):
            _positive(o, name, getattr(self, name))
        for name in ("kappa", "rotation_noise", "speed_gain", "rho", "eps", "identity_prior", "relocate_contrast",
                     "refine_deformation", "template_views"):
            _positive(o, name, getattr(self, name), zero=True)
        for name in ("prior", "anchor_templates", "warp_templates", "refine_pose", "relocate_shading",
                     "hold_identity_at_start", "learn_identity"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise TypeError(f"{o}.{name}: expected a bool, got {getattr(self, name)!r}")
        if self.relocate_shading and self.relocate_contrast == 0:
            raise ValueError(f"{o}.relocate_shading: expected relocate_contrast > 0 (the ramp is taken off normalised "
                             "patches), got relocate_contrast 0")  # fmt: skip
        tn = np.asarray(self.translation_noise, dtype=np.float64)
        if tn.shape != (3,) or not np.isfinite(tn).all() or (tn < 0).any():
            raise ValueError(f"{o}.translation_noise: expected 3 numbers >= 0, got {self.translation_noise!r}")
        dr = np.asarray(self.depth_range, dtype=np.float64)
        if dr.shape != (2,) or not np.isfinite(dr).all() or not 0 < dr[0] < dr[1]:
            raise ValueError(f"{o}.depth_range: expected (near, far) mm with 0 < near < far, got {self.depth_range!r}")
        pr = np.asarray(self.pose_range, dtype=np.float64)
        if pr.shape != (2,) or not np.isfinite(pr).all() or (pr <= 0).any():
            raise ValueError(f"{o}.pose_range: expected (radians, mm) > 0, got {self.pose_range!r}")
        if isinstance(self.detect_share, bool) or not isinstance(self.detect_share, (int, float, np.integer, np.floating)) \
                or not 0.0 <= self.detect_share <= 1.0:
            raise ValueError(f"{o}.detect_share: expected a fraction in [0, 1], got {self.detect_share!r}")
        for name in ("lost_score", "min_match"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not -1.0 <= v <= 1.0:
                raise ValueError(f"{o}.{name}: expected a number in [-1, 1], got {v!r}")

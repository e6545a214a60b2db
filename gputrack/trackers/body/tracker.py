"""Upper-body RGB-D tracker of paper 000: coarse-to-fine particle filter + batched LM on the device.

Per frame (Alg. 1-2 of the paper):

1. upload the gray and depth images (the only per-frame inputs);
2. when due, render the 3D sparse template at the previous estimate and pick its points (sec. 2.3),
   on the device (:func:`gputrack.ops.model_template.model_template`: the host sends the part
   transforms and receives a few counts per part);
3. particle filter, ``stages`` times with sigma halved each stage (sec. 3.1, eq. 12): draw K samples
   around the C candidates, forward kinematics, score eq. 17-19, keep the best C as the next
   candidates — all on the device (optionally in cascade order: torso, right arm, left arm,
   eq. 13-16, by sampling one group of parameters at a time);
4. Levenberg-Marquardt on all C candidates at once (sec. 3.4, eq. 20-24), with central
   differences and the block-sparse Jacobian of Fig. 2 (a part's residuals depend on its own and
   its ancestors' parameters; about half the residual work; ``sparse_jacobian=False``: every
   entry), optionally with the 6 shoulder parameters (sec. 3.6, eq. 25-27);
5. download the best candidate's pose.

The tracker never returns a NaN pose: a frame whose images are unusable (no valid depth, the
model out of view) keeps the last pose and reports ``confidence = 0``.
"""

from __future__ import annotations

import collections
import dataclasses
import logging

import numpy as np

from ...device import Device
from ...models.camera import DEFAULT_CAMERA, DEFAULT_SIZE, Camera
from ...models.upper_body import pf_sigma, upper_body
from ...ops.lm import LeastSquaresSolver
from ...ops.model_template import model_template
from ...ops.pf import pf_stage
from ...ops.pose_residuals import pose_residuals
from ...ops.template import RgbdScene, SparseTemplate
from ...scheduler import Scheduler, SkipFrame, Stage

log = logging.getLogger("gputrack")

__all__ = ["BodyTracker", "BodyEstimate", "BodyTrackerConfig"]

DEG = np.pi / 180.0

#: LM finite-difference steps eps_n (eq. 24) per kind of parameter: large enough to move template
#: points by a fraction of a pixel (the residuals are float32 and bilinear), small enough to be local.
LM_STEP = {"angle": 2e-3, "length": 1.0}


@dataclasses.dataclass
class BodyTrackerConfig:
    """Settings of :class:`BodyTracker` (defaults: the paper's, Tables 3-4)."""

    candidates: int = 10  # C: candidate poses kept between stages and frames
    samples: int = 1500  # K: samples per particle-filter stage
    stages: int = 3  # coarse-to-fine stages, sigma halved each
    cascade: bool = True  # torso, then right arm, then left arm (eq. 13-16); False: all at once
    lm_iterations: int = 10  # m: LM iterations per frame (0: PF only)
    sparse_jacobian: bool = True  # Fig. 2 block-sparse Jacobian (about half the LM's work); False: dense
    shoulders: bool = False  # estimate the shoulder positions too (20 parameters)
    n_rgb: int = 128  # N
    n_depth: int = 128  # N'
    lam: float = 0.9  # lambda of eq. 19 (Table 3)
    c_depth: float = 5.0  # c' of eq. 18 (mm)
    # depth differences up to this (mm) count as none (eq. 18 shrunk; see rgbd_cost): half a
    # quantised sensor's step (2.5 for the simulator's 5 mm) pins the torso's turn, and so the
    # shoulders (Table 7); 0, the plain eq. 18, tracks the arms more closely
    depth_tol: float = 0.0
    template_every: int = 1  # make the template (on the device) every this many frames
    seed: int = 0
    # loss recovery: a frame whose best cost exceeds ``recover_ratio`` times the median of the last
    # ``recover_window`` frames' costs (a lost arm: ~4x) is tracked again from the same start with
    # the particle filter's sigmas times ``recover_sigma``, and the lower cost wins (0: off)
    recover_ratio: float = 2.0
    recover_window: int = 30
    recover_sigma: float = 2.0
    # constant-velocity start: the better half of the C candidates is also moved by the last
    # frame's motion (of the parameters the filter samples; the other half starts where the last
    # frame ended); False: the paper's start.
    # With the LM the motion is measured to ~0.2 deg, and long runs stop losing arms (perf/README.md);
    # the particle filter alone measures it to ~1 deg, and the start helps fast motion (arm_swing's
    # forearms 1.4 -> 1.0 deg) but not slow (arm_cross from rest: 0.8 -> 1.0 deg)
    predict: bool = True

    def __post_init__(self):
        for name in ("candidates", "samples", "stages", "n_rgb", "n_depth", "template_every"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name}: expected a positive integer, got {v!r}")
        if isinstance(self.lm_iterations, bool) or not isinstance(self.lm_iterations, (int, np.integer)) or self.lm_iterations < 0:
            raise ValueError(f"lm_iterations: expected an integer >= 0, got {self.lm_iterations!r}")
        if self.candidates > self.samples:
            raise ValueError(f"candidates: expected at most samples={self.samples}, got {self.candidates}")
        if not 0.0 <= self.lam <= 1.0:
            raise ValueError(f"lam: expected a value in [0, 1], got {self.lam}")
        if not 0.0 <= self.depth_tol < np.inf:
            raise ValueError(f"depth_tol: expected a finite value >= 0 (mm), got {self.depth_tol}")
        if not (self.recover_ratio == 0.0 or 1.0 < self.recover_ratio < np.inf):
            raise ValueError(f"recover_ratio: expected 0 (off) or a finite ratio > 1, got {self.recover_ratio}")
        if isinstance(self.recover_window, bool) or not isinstance(self.recover_window, (int, np.integer)) \
                or self.recover_window < 3:  # fmt: skip
            raise ValueError(f"recover_window: expected an integer >= 3 (frames), got {self.recover_window!r}")
        if not 1.0 <= self.recover_sigma < np.inf:
            raise ValueError(f"recover_sigma: expected a finite factor >= 1, got {self.recover_sigma}")


@dataclasses.dataclass
class BodyEstimate:
    """One frame's result: the best pose, its cost (eq. 19), and whether it could be measured."""

    params: np.ndarray  # (P,) float64
    cost: float
    confidence: float  # 1 = tracked; 0 = kept the last pose (unusable frame)
    candidates: np.ndarray  # (C, P) the candidates carried to the next frame
    message: str = ""


class BodyTracker:
    """Track the upper body of paper 000 in a sequence of gray + depth frames.

    ``BodyTracker(device, initial_params, camera=..., config=BodyTrackerConfig(...))``, then
    ``track(gray, depth)`` per frame -> :class:`BodyEstimate`. The frame runs as stages of a
    :class:`gputrack.Scheduler` (``scheduler``): upload the images and the C candidates, the template,
    the PF stages (one per stage and cascade group), then the LM, whose result is the only download
    besides the LM's own per-iteration exchange. ``scheduler.table()`` gives the per-stage timings and
    transfer counts (Tables 1-2 layout); ``profile=True`` makes them the stages' own times, with a
    device wait before and after each stage (as every tracker's scheduler, off by default: on opencl
    the waits cost ~3 ms of a ~23 ms frame, 2026-12-06).

    The same machinery tracks any chain: pass ``chain`` and the first-stage ``sigma`` (P,)
    (default: Table 4 for :func:`gputrack.models.upper_body`), and give ``track`` the
    templates when they do not come from rendering the model (e.g. a rigid scene whose
    template is taken from the previous real frame, :func:`frame_template`).
    """

    def __init__(self, device: Device, initial_params, *, camera: Camera | None = None, size=DEFAULT_SIZE,
                 config: BodyTrackerConfig | None = None, chain=None, sigma=None, profile: bool = False):  # fmt: skip
        if not isinstance(device, Device):
            raise TypeError(f"device: expected a gputrack.Device, got {type(device).__name__}")
        self.device = device
        self.config = cfg = config or BodyTrackerConfig()
        self.chain = chain or upper_body(shoulders=cfg.shoulders)
        self.camera = camera or DEFAULT_CAMERA
        self.size = tuple(int(s) for s in size)  # (width, height)
        p0 = np.asarray(initial_params, dtype=np.float64)
        if p0.shape != (self.chain.n_params,):
            raise ValueError(f"initial_params: expected shape ({self.chain.n_params},), got {p0.shape}")
        if not np.isfinite(p0).all():
            raise ValueError("initial_params: expected finite values, got NaN or inf")
        self.params = p0
        self.candidates = np.repeat(p0[None], cfg.candidates, axis=0)
        self.frame_index = 0
        self._motion = None  # the last tracked frame's change of the estimate (predict)
        self._rng = np.random.default_rng(cfg.seed)
        self._templates = None
        self._scene = None  # the templates with the camera and eq. 17-19's constants (RgbdScene)
        self._given_templates = None  # templates passed to track() for this frame
        # constant device data, uploaded once: per-stage (and per-cascade-group) sigmas
        sigma = pf_sigma(self.chain) if sigma is None else np.asarray(sigma, dtype=np.float64)
        if sigma.shape != (self.chain.n_params,) or not np.isfinite(sigma).all() or (sigma < 0).any():
            raise ValueError(f"sigma: expected ({self.chain.n_params},) finite values >= 0, got {sigma!r}")
        # the motion of the constant-velocity start: of the parameters the filter samples (the
        # shoulder positions of the 20-parameter chain are the body's build, not motion)
        self._moves = sigma > 0
        groups = self._groups() if cfg.cascade else [np.ones(self.chain.n_params, bool)]
        self._sigmas = [[(sigma * g / 2**s).astype(np.float32) for g in groups] for s in range(cfg.stages)]
        angle = np.zeros(self.chain.n_params, bool)
        angle[[i for part in self.chain.parts for i in part.angles]] = True
        self._lm_step = np.where(angle, LM_STEP["angle"], LM_STEP["length"])
        # the LM of sec. 3.4 on the C candidates: one solver, its device buffers kept between frames
        self._lm = LeastSquaresSolver(device, self.candidates.shape, max_iter=cfg.lm_iterations, step=self._lm_step,
                                      points_dtype=np.float32, early_stop=False) if cfg.lm_iterations else None  # fmt: skip
        self._sparsity = None
        self._residual_out = {}  # rows -> pose_residuals' output array (of the last N + N'), reused as out=
        self._profile = profile
        self.scheduler = self._scheduler(self._sigmas)
        # the recovery pass (see BodyTrackerConfig.recover_ratio): the same stages, wider sigmas,
        # the frame's template kept; made at the first frame that needs it
        self._recovery = None
        self._costs = collections.deque(maxlen=cfg.recover_window)
        self.recoveries = 0  # frames tracked again by the recovery pass
        self.recovered = 0  # ... of which the pass's lower cost was kept

    # -- helpers ---------------------------------------------------------------------------------
    def _groups(self) -> list[np.ndarray]:
        """Cascade groups (eq. 13-16): the root part's parameters (torso), then, for each child of the
        root (right arm, left arm), the joint angles of its subtree. Shoulder positions are not sampled."""
        chain, P = self.chain, self.chain.n_params
        root = [j for j, part in enumerate(chain.parts) if part.parent < 0]
        groups = []
        for r in root:
            g = np.zeros(P, bool)
            g[list(chain.parts[r].params)] = True
            groups.append(g)
            for c in (j for j, part in enumerate(chain.parts) if part.parent == r):
                g = np.zeros(P, bool)
                for j, part in enumerate(chain.parts):
                    if j == c or c in chain.ancestors(j):
                        g[list(part.angles)] = True
                groups.append(g)
        return groups

    def _check_frame(self, gray, depth):
        w, h = self.size
        for name, img in (("gray", gray), ("depth", depth)):
            if not isinstance(img, np.ndarray):
                raise TypeError(f"{name}: expected a NumPy array of shape ({h}, {w}), got {type(img).__name__}")
            if img.shape != (h, w):
                raise ValueError(f"{name}: expected shape ({h}, {w}), got {img.shape}")
            if img.dtype != np.float32:
                raise TypeError(f"{name}: expected float32, got {img.dtype}")
        # the gray frame's values are checked on the host copy, before the upload, on every device
        # (depth may hold non-finite values: no measurement)
        if not np.isfinite(gray).all():
            bad = tuple(int(i) for i in np.argwhere(~np.isfinite(gray))[0])
            raise ValueError(f"gray: expected finite values, got {gray[bad]} at index {bad}")

    @staticmethod
    def _check_templates(templates):
        if templates is None:
            return
        ok = isinstance(templates, (tuple, list)) and len(templates) == 2
        if not ok or not all(isinstance(t, SparseTemplate) for t in templates):
            got = (f"{type(templates).__name__} of {', '.join(type(t).__name__ for t in templates)}"
                   if isinstance(templates, (tuple, list)) else type(templates).__name__)  # fmt: skip
            raise TypeError(f"templates: expected None or a pair (RGB, depth) of gputrack.SparseTemplate, got {got}")

    @property
    def templates(self) -> tuple[SparseTemplate, SparseTemplate] | None:
        """The (RGB, depth) templates the last frame was matched with (None before the first frame).
        Made on the device, their points are downloaded the first time ``xyz`` or ``value`` is read."""
        return self._templates

    def _update_template(self):
        cfg = self.config
        self._set_templates(*model_template(self.device, self.chain, self.params, self.camera, self.size, cfg.n_rgb,
                                            cfg.n_depth))  # fmt: skip

    def _set_templates(self, rgb, dep):
        cfg = self.config
        self._scene = RgbdScene(rgb, dep, self.camera, lam=cfg.lam, c_depth=cfg.c_depth,
                                depth_tol=cfg.depth_tol).to(self.device)  # fmt: skip
        self._templates = (rgb, dep)
        parts = np.concatenate([rgb.part, dep.part])
        self._sparsity = self.chain.jacobian_sparsity(parts)

    def _residuals(self, scene, gray, depth):
        dev, central = self.device, self.config.sparse_jacobian

        def residuals(points):  # with the sparse Jacobian, only the entries it reads (Fig. 2)
            rows = points.shape[0]  # the stack of a step, then the points of the last one
            out = self._residual_out.get(rows)
            if out is not None and out.shape[1] != scene.n:
                out = None  # the template's point count changed: a new array replaces the old one
            out = self._residual_out[rows] = pose_residuals(dev, self.chain, points, scene, gray, depth,
                                                            central=central, out=out)  # fmt: skip
            return out

        return residuals

    # -- the frame's stages (run by self.scheduler) -----------------------------------------------
    def _scheduler(self, sigmas) -> Scheduler:
        """The frame's stages with these per-stage sigmas, run by a Scheduler."""
        return Scheduler(self.device, self._stages(sigmas), inputs=("gray", "depth", "start"),
                         outputs=("estimate", "cost"), profile=self._profile)  # fmt: skip

    def _stages(self, sigmas) -> list[Stage]:
        cfg, images = self.config, ("gray", "depth", "scene")
        stages = [Stage("template", self._template_stage, writes=("scene",))]
        calls = 0
        for s in range(cfg.stages):
            for g, sigma in enumerate(sigmas[s]):
                name = f"PF stage {s + 1}" + (f".{g + 1}" if len(sigmas[s]) > 1 else "")
                prev = "start" if calls == 0 else "candidates"
                stages.append(Stage(name, self._pf_stage(sigma, prev, f"pf{calls % 2}"), reads=(*images, prev),
                                    writes=("candidates", "scores", f"pf{calls % 2}")))  # fmt: skip
                calls += 1
        if cfg.lm_iterations:
            stages.append(Stage("LM", self._lm_stage, reads=images, host_reads=("candidates",),
                                writes=("estimate", "cost")))  # fmt: skip
        else:
            stages.append(Stage("download", self._download_stage, host_reads=("candidates", "scores"),
                                writes=("estimate", "cost")))  # fmt: skip
        return stages

    def _template_stage(self, b):
        """Sec. 2.3: the 3D sparse template, rendered at the previous estimate when due (or given)."""
        if self._given_templates is not None:
            if self._given_templates is not self._templates:  # the recovery pass gives the frame's own
                self._set_templates(*self._given_templates)
        elif self._templates is None or self.frame_index % self.config.template_every == 0:
            try:
                self._update_template()
            except ValueError as e:  # the model is out of view at the last pose
                raise SkipFrame(str(e)) from None
        else:
            return
        b["scene"] = self._scene

    def _pf_stage(self, sigma, prev: str, out: str):
        """One particle-filter stage (sec. 3.1, eq. 12-19) around the candidates in ``prev``; two
        results in turn (``out`` = pf0 / pf1): a stage reads the other's rows."""
        cfg = self.config

        def stage(b):
            seed = int(self._rng.integers(2**63))
            best = pf_stage(self.device, self.chain, b[prev], sigma, cfg.samples, seed, b["scene"], b["gray"],
                            b["depth"], k=cfg.candidates, out=b.get(out))  # fmt: skip
            b[out], b["candidates"], b["scores"] = best, best.rows, best.scores

        return stage

    def _lm_stage(self, b):
        """Sec. 3.4, eq. 20-24: LM on all C candidates at once; the estimate sorted by cost."""
        cfg = self.config
        res = self._lm.solve(self._residuals(b["scene"], b["gray"], b["depth"]), b["candidates"].astype(np.float64),
                             jac_sparsity=self._sparsity if cfg.sparse_jacobian else None)  # fmt: skip
        order = np.argsort(res.cost, kind="stable")
        b["estimate"], b["cost"] = res.x[order], float(res.cost[order[0]])

    def _download_stage(self, b):
        b["estimate"], b["cost"] = b["candidates"].astype(np.float64), float(b["scores"][0])

    # -- one frame ---------------------------------------------------------------------------------
    def track(self, gray, depth, templates=None) -> BodyEstimate:
        """Estimate the pose in one frame (gray (H, W) float32, depth (H, W) float32 mm).

        ``templates``: (RGB, depth) SparseTemplates to use from now on instead of rendering the
        model at the previous estimate. A gray frame with NaN or inf raises ValueError (on every
        device); a frame that gives no finite cost (no valid depth, the model out of view) keeps the
        last pose with ``confidence = 0``.
        """
        self.device._check_open()
        self._check_frame(gray, depth)
        self._check_templates(templates)
        if not (np.isfinite(depth) & (depth > 0)).any():
            return self._keep("no valid depth in the frame")
        self._given_templates = templates
        start = self._start()
        try:
            out = self.scheduler.run(gray=gray, depth=depth, start=start)
        except SkipFrame as e:
            return self._keep(str(e))
        finally:
            self._given_templates = None
        candidates, best_cost = out["estimate"], out["cost"]
        if self._suspect(best_cost):
            candidates, best_cost = self._recover(gray, depth, start, candidates, best_cost)
        if not np.isfinite(candidates).all():
            return self._keep("the estimate is not finite")
        if not np.isfinite(best_cost):
            return self._keep(f"the frame gives no finite cost ({best_cost})")
        self._motion = candidates[0] - self.params
        self.candidates = candidates
        self.params = candidates[0].copy()
        self.frame_index += 1
        self._costs.append(best_cost)
        return BodyEstimate(self.params.copy(), best_cost, 1.0, candidates.copy())

    def _start(self) -> np.ndarray:
        """(C, P) float32: the candidates the frame starts from (see BodyTrackerConfig.predict)."""
        c = self.candidates
        if self.config.predict and self._motion is not None:
            h = len(c) // 2
            c = np.concatenate([c[: len(c) - h], c[:h] + np.where(self._moves, self._motion, 0.0)])
        return c.astype(np.float32)

    def _suspect(self, cost: float) -> bool:
        """A cost jump (a lost part): above recover_ratio x the median of the recent frames' costs."""
        cfg = self.config
        if not cfg.recover_ratio or not self._costs or not np.isfinite(cost):
            return False
        return cost > cfg.recover_ratio * float(np.median(self._costs))

    def _recover(self, gray, depth, start, candidates, cost):
        """Track the frame again from the same start, the sigmas widened, the template kept; the lower
        cost wins."""
        cfg = self.config
        if self._recovery is None:
            wide = [[g * np.float32(cfg.recover_sigma) for g in stage] for stage in self._sigmas]
            self._recovery = self._scheduler(wide)
        self.recoveries += 1
        self._given_templates = self._templates
        try:
            out = self._recovery.run(gray=gray, depth=depth, start=start)
        except SkipFrame:
            return candidates, cost
        finally:
            self._given_templates = None
        if np.isfinite(out["cost"]) and out["cost"] < cost and np.isfinite(out["estimate"]).all():
            self.recovered += 1
            log.info("frame %d: cost %.3g -> %.3g after the recovery pass", self.frame_index, cost, out["cost"])
            return out["estimate"], out["cost"]
        return candidates, cost

    def _keep(self, why: str) -> BodyEstimate:
        log.warning("frame %d: %s; keeping the last pose", self.frame_index, why)
        self.frame_index += 1
        self._motion = None
        return BodyEstimate(self.params.copy(), float("nan"), 0.0, self.candidates.copy(), why)

"""Benchmark: paper 003's face tracker, one tracked 640 x 480 frame, and its two device-heavy parts.

The frames are the simulator's "mixed" sequence (a person not among the model's 26; head turns,
depth, expressions, lighting), rendered once and played back and forth, so the tracker keeps
tracking; the tracker starts on its first 7 frames with their true feature points.

Cases:

- ``face frame N=1000``: :meth:`FaceTracker.track` of one frame (sample, score: NCC of the N x K
  16 x 16 patches in one launch, estimate, re-localisation, the incremental bundle adjustment's 5 LM
  iterations on the 7 key frames); reference: the same on ``numpy``; ``--stages F`` prints the
  device-synchronised per-stage table over F frames;
- ``face score N=1000``: eq. 13's NCC sum of N hypotheses (``patch_ncc``) alone; reference: NumPy;
- ``face bundle step``: one :meth:`IncrementalBundle.add` (5 LM iterations, P = 92); peer:
  scipy's ``least_squares`` (trf, the same box, residuals and analytic Jacobian, 5 iterations);
  ``--bundle-profile F`` prints, over F steps, the time of each part of its solves (the solver's
  init, residual and Jacobian calls with their transfers, update launches, result), each between
  two device synchronisations.
"""

from __future__ import annotations

import functools
import sys

import numpy as np

from ..registry import device as get_device
from .harness import Case, bench_main

NAME = "face"


def add_arguments(parser):
    parser.add_argument("--frames", type=int, default=60, help="frames of the sequence (played back and forth)")
    parser.add_argument("--particles", type=int, default=1000, help="hypotheses N (default 1000, the paper's)")
    parser.add_argument("--stages", type=int, default=0, metavar="F", help="print the per-stage table over F frames")
    parser.add_argument("--no-scipy", action="store_true", help="skip the scipy peer")
    parser.add_argument("--bundle-profile", type=int, default=0, metavar="F",
                        help="print where the bundle step's time goes (each solver call synchronised) over F steps")


@functools.lru_cache(maxsize=2)
def scene(frames: int):
    """(model, camera, frames list, start landmarks (7, K, 2))."""
    from ..models.face import FaceModel, load_ict
    from ..sim.face import face_sequence

    ict = load_ict()
    seq = face_sequence("mixed", frames=frames, ict=ict)
    fr = [seq[k] for k in range(frames)]
    rng = np.random.default_rng(0)
    lm = np.array([f.landmarks2d + rng.normal(0, 1.0, (len(f.landmarks2d), 2)) for f in fr[:7]])
    return FaceModel.from_ict(ict), seq.camera, fr, lm


def _tracker(device, frames: int, particles: int, profile=False):
    from ..trackers.face import FaceConfig, FaceTracker

    model, cam, fr, lm = scene(frames)
    trk = FaceTracker(device, model, cam, FaceConfig(particles=particles))
    trk.scheduler.profile = profile
    trk.start(np.array([f.gray for f in fr[:7]]), lm)
    order = list(range(7, len(fr))) + list(range(len(fr) - 2, 7, -1))
    state = {"k": 0}

    def step():
        est = trk.track(fr[order[state["k"] % len(order)]].gray)
        state["k"] += 1
        return est

    step.tracker = trk
    return step


def _score_case(device, frames, particles):
    from ..ops.ncc import patch_ncc

    trk = _tracker(get_device("numpy"), frames, particles)
    trk()  # one frame: the filter's hypotheses and templates
    t = trk.tracker
    pts = t.pf.propose(*t._basis)
    tpl = t.scheduler.buffers["templates"]
    img = scene(frames)[2][8].gray.astype(np.float32)
    dev_args = [a if device.backend == "numpy" else device.asarray(a) for a in (pts, tpl, img)]
    return (lambda: patch_ncc(device, *dev_args)), (lambda: patch_ncc(get_device("numpy"), pts, tpl, img))


def _bundle_case(device, frames, scipy_peer):
    from ..trackers.face import IncrementalBundle
    from ..trackers.face.bundle import BundleProblem

    model, cam, fr, lm = scene(frames)
    truth = [(f.rvec, f.translation, f.landmarks2d) for f in fr]
    rng = np.random.default_rng(1)
    A = model.expression_mean

    def make(dev, profile=False):
        ib = IncrementalBundle(dev, model, cam, identity_prior=1.0, profile=profile)
        ib.start(lm, np.array([t[0] for t in truth[:7]]), np.array([t[1] for t in truth[:7]]), np.tile(A, (7, 1)))
        state = {"k": 7}

        def step():
            k = 7 + state["k"] % (len(truth) - 7)
            state["k"] += 1
            r, t, m = truth[k]
            return ib.add(m + rng.normal(0, 0.5, m.shape), r, t, A)

        step.bundle = ib
        return step

    run, ref = make(device), make(get_device("numpy"))
    run.profiled = lambda: make(device, profile=True)
    peers = {}
    if scipy_peer:
        from scipy.optimize import least_squares as scipy_ls

        def scipy_step(ib=ref.bundle):
            keys = ib._keys
            p = BundleProblem(model, cam, keys["landmarks"], keys["rvecs"], keys["tvecs"], keys["expressions"],
                              ib.identity, identity_prior=1.0)  # fmt: skip
            free = p.upper > p.lower
            x0 = p.x0.copy()

            def full(y):
                x = x0.copy()
                x[free] = y
                return x

            return scipy_ls(lambda y: p.residuals(full(y)[None])[0], x0[free],
                            jac=lambda y: p.jacobian(full(y)[None])[0][:, free], bounds=(p.lower[free], p.upper[free]),
                            method="trf", max_nfev=5)  # fmt: skip

        peers["scipy least_squares (trf, 5 iterations)"] = scipy_step
    return run, ref, peers


def cases(device, args):
    ref = get_device("numpy")
    n = args.particles
    run = _tracker(device, args.frames, n)
    reference = _tracker(ref, args.frames, n)
    out = [Case(f"face frame N={n}", run=run, reference=reference, params={"particles": n, "frames": args.frames})]
    s_run, s_ref = _score_case(device, args.frames, n)
    out.append(Case(f"face score N={n}", run=s_run, reference=s_ref, params={"particles": n}))
    b_run, b_ref, peers = _bundle_case(device, args.frames, not args.no_scipy)
    out.append(Case("face bundle step (P=92, 5 iterations)", run=b_run, reference=b_ref, peers=peers,
                    params={"parameters": 92, "iterations": 5}))  # fmt: skip
    if args.bundle_profile:
        step = b_run.profiled()
        for _ in range(2):  # the solvers' first solves compile
            step()
        step.bundle.reset_profile()
        for _ in range(args.bundle_profile):
            step()
        print(step.bundle.profile_tables(), file=sys.stderr, flush=True)
    if args.stages:
        prof = _tracker(device, args.frames, n, profile=True)
        for _ in range(2):
            prof()
        prof.tracker.scheduler.reset()
        for _ in range(args.stages):
            prof()
        print(prof.tracker.scheduler.table(f"{device.spec}: face frame N={n}"), file=sys.stderr, flush=True)
    return out


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

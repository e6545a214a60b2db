"""The multi-target tracking cycle: 1000 tracks x 1000 detections per frame in a crowd.

One case per size (--tracks, default 100 and 1000): a constant-velocity crowd from
:func:`gputrack.sim.scenes.cv_scene` (2-D positions, 10 frames per second, 1 m/s walkers, 10 cm
detection noise, p_detect 0.95, about 50 clutter detections per frame, births and deaths) in a
square sized so that the crowd has --density people per square metre (default 0.1: most gates
hold one detection, a few hold two or three: sparse gating). The tracker starts with a
confirmed track on every target (its true state plus noise), so every frame has about T tracks
and T detections. A timed call is one full frame of :class:`gputrack.tracking.MultiTargetTracker`
(predict, gate, assign, update, start/end: births, M-of-N confirmation, deletions) on the next
frame of the scene; the NumPy reference is the same tracker on the ``numpy`` device.

Peers (the same scene and the same initial tracks), timed in the process of one device only
(--stonesoup-on, default taichi:cpu; they do not depend on the device):

- ``stonesoup``: Stone Soup's ``MultiTargetTracker`` with ``KalmanPredictor``,
  ``KalmanUpdater``, ``DistanceHypothesiser`` + ``DistanceGater`` with ``SquaredMahalanobis`` at
  the same chi-square threshold (also the missed distance), ``GNNWith2DAssignment``,
  ``MultiMeasurementInitiator`` (2 points) and ``UpdateTimeStepsDeleter``: the textbook
  composition, which measures every track against every detection in Python. That is T x D
  pairs per frame: about 2 s per frame at T = 100 and 100-200 s at T = 1000 on the 2-core
  development machine, so by default it is timed up to --stonesoup-max-tracks (100) only (the
  harness times 2 warm-up and at least 5 frames);
- ``stonesoup kd-tree``: the same with ``DetectionKDTreeGNN2D`` (Stone Soup's association for
  large scenes: each track is measured only against the detections within 3 m, found in a k-d
  tree; the Mahalanobis gate of a track is well inside that radius).

Each timed call advances the scene by one frame; a run longer than --frames frames stops with
an error naming the option.
"""

import sys

import numpy as np

from ..registry import device as get_device
from .harness import Case, bench_main

NAME = "tracking"
DT, Q, R_STD, P_DETECT, CLUTTER, SPEED = 0.1, 0.5, 0.1, 0.95, 50.0, 1.0
GATE_P, MAX_MISSES = 0.999, 3
KD_RADIUS = 3.0  # m: the k-d tree peer measures each track against the detections within this radius


def add_arguments(parser):
    parser.add_argument("--tracks", type=float, action="append", help="tracks (targets) per frame (default 100, 1000)")
    parser.add_argument("--density", type=float, default=0.1, help="targets per square metre (default 0.1)")
    parser.add_argument("--frames", type=int, default=400, help="frames simulated per case (default 400)")
    parser.add_argument("--stonesoup-on", default="taichi:cpu", help="device whose process times the Stone Soup peers")
    parser.add_argument("--stonesoup-max-tracks", type=float, default=100,
                        help="largest T timed with the all-pairs Stone Soup peer (default 100)")
    parser.add_argument("--no-stonesoup", action="store_true", help="skip the all-pairs Stone Soup peer")
    parser.add_argument("--no-kdtree", action="store_true", help="skip the Stone Soup k-d tree peer")


def crowd(T: int, frames: int, density: float, seed: int = 0):
    """The benchmark scene: (scene, initial states (T, 4), initial covariance (4, 4))."""
    from ..sim.scenes import cv_scene

    rng = np.random.default_rng(seed)
    extent = float(np.sqrt(T / density))
    scene = cv_scene(rng, frames=frames, targets=T, dim=2, dt=DT, q=Q, r=R_STD, p_detect=P_DETECT,
                     clutter=CLUTTER, birth_rate=T * 1e-3, death_prob=1e-3, extent=extent, speed=SPEED)  # fmt: skip
    P0 = np.diag([R_STD**2, 0.1, R_STD**2, 0.1])
    x0 = scene[0].states + rng.normal(0.0, np.sqrt(np.diag(P0)), scene[0].states.shape)
    return scene, x0, P0


class _Frames:
    """The scene's frames after the first, one per call; a clear error past the end."""

    def __init__(self, scene):
        self.frames, self.k = scene.frames, 1

    def next(self):
        if self.k >= len(self.frames):
            raise RuntimeError(f"the scene has {len(self.frames)} frames, all used: run with a larger --frames")
        f = self.frames[self.k]
        self.k += 1
        return f


def gputrack_cycle(device, scene, x0, P0):
    """A callable that tracks the next frame of ``scene`` with gputrack (one full cycle)."""
    from ..tracking import MultiTargetTracker, TrackStatus

    tracker = MultiTargetTracker.constant_velocity(device, dim=2, dt=DT, q=Q, R=R_STD**2,
                                                   gate_probability=GATE_P, max_misses=MAX_MISSES,
                                                   capacity=2 * len(x0))  # fmt: skip
    tracker.table.add(x0, np.broadcast_to(P0, (len(x0), 4, 4)), TrackStatus.CONFIRMED)
    frames = _Frames(scene)

    def step():
        return tracker.step(frames.next().detections)

    step.tracker = tracker
    return step


def stonesoup_cycle(scene, x0, P0, *, kdtree: bool):
    """A callable that tracks the next frame of ``scene`` with Stone Soup's components."""
    import datetime

    from scipy.stats import chi2
    from stonesoup.buffered_generator import BufferedGenerator
    from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
    from stonesoup.dataassociator.tree import DetectionKDTreeGNN2D
    from stonesoup.deleter.time import UpdateTimeStepsDeleter
    from stonesoup.gater.distance import DistanceGater
    from stonesoup.hypothesiser.distance import DistanceHypothesiser
    from stonesoup.initiator.simple import MultiMeasurementInitiator
    from stonesoup.measures import SquaredMahalanobis
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.models.transition.linear import LinearGaussianTimeInvariantTransitionModel
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.reader.base import DetectionReader
    from stonesoup.tracker.simple import MultiTargetTracker
    from stonesoup.types.detection import Detection
    from stonesoup.types.state import GaussianState
    from stonesoup.types.track import Track
    from stonesoup.updater.kalman import KalmanUpdater

    from ..ops.kalman import constant_velocity

    F, Qm = constant_velocity(2, DT, Q, dtype=np.float64)
    transition = LinearGaussianTimeInvariantTransitionModel(transition_matrix=F, covariance_matrix=Qm)
    measurement = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=R_STD**2 * np.eye(2))
    predictor, updater = KalmanPredictor(transition), KalmanUpdater(measurement)
    thr = float(chi2.ppf(GATE_P, 2))
    hyp = DistanceHypothesiser(predictor, updater, measure=SquaredMahalanobis(), missed_distance=thr)
    gater = DistanceGater(hyp, measure=SquaredMahalanobis(), gate_threshold=thr)
    t0 = datetime.datetime(2026, 1, 1)
    stamps = [t0 + datetime.timedelta(seconds=DT * k) for k in range(len(scene))]

    class Reader(DetectionReader):
        @BufferedGenerator.generator_method
        def detections_gen(self):
            for k in range(1, len(scene)):
                yield stamps[k], {Detection(z.reshape(2, 1), timestamp=stamps[k], measurement_model=measurement)
                                  for z in scene[k].detections.astype(np.float64)}  # fmt: skip

    if kdtree:
        associator = DetectionKDTreeGNN2D(hyp, predictor, updater, max_distance=KD_RADIUS)
    else:
        associator = GNNWith2DAssignment(gater)
    deleter = UpdateTimeStepsDeleter(MAX_MISSES + 1)
    prior = GaussianState(np.zeros((4, 1)), np.diag([0.0, 1.0, 0.0, 1.0]))
    initiator = MultiMeasurementInitiator(prior, deleter=UpdateTimeStepsDeleter(2), data_associator=associator,
                                          updater=updater, measurement_model=measurement, min_points=2)  # fmt: skip
    tracker = MultiTargetTracker(initiator=initiator, deleter=deleter, detector=Reader(),
                                 data_associator=associator, updater=updater)  # fmt: skip
    tracker._tracks = {Track([GaussianState(x.reshape(4, 1), P0, timestamp=t0)]) for x in x0}
    it = iter(tracker)
    left = [len(scene) - 1]

    def step():
        if left[0] == 0:
            raise RuntimeError(f"the scene has {len(scene)} frames, all used: run with a larger --frames")
        left[0] -= 1
        return next(it)

    step.tracker = tracker
    return step


def cases(device, args):
    ref = get_device("numpy")
    out = []
    for T in [int(t) for t in (args.tracks or [100, 1000])]:
        scene, x0, P0 = crowd(T, args.frames, args.density)
        run = gputrack_cycle(device, scene, x0, P0)
        reference = gputrack_cycle(ref, scene, x0, P0)
        peers = {}
        if device.spec == args.stonesoup_on:
            if not args.no_stonesoup and T <= args.stonesoup_max_tracks:
                peers["stonesoup"] = stonesoup_cycle(scene, x0, P0, kdtree=False)
            if not args.no_kdtree:
                peers["stonesoup kd-tree"] = stonesoup_cycle(scene, x0, P0, kdtree=True)
        D = float(np.mean([len(f.detections) for f in scene.frames]))
        out.append(
            Case(
                f"tracking cycle T={T} D~{D:.0f}",
                run=run,
                reference=reference,
                peers=peers,
                params={"T": T, "D_mean": D, "density": args.density, "dim": 2, "n": 4, "dt": DT},
            )
        )
    return out


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

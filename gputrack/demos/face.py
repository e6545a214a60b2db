"""``gputrack demo face``: simulate paper 003's head sequences, track them, print Table 1.

The simulator (:mod:`gputrack.sim.face`: the ICT face mesh of a person not among the model's 26,
textured, rendered at 640 x 480 and 30 fps with head turns, motion in depth, expression and
lighting changes) gives the frames and the truth. The multilinear model (HOSVD of 26 people x 10
deformations, :class:`gputrack.models.face.FaceModel`) and the generic PCA model each drive a
:class:`gputrack.trackers.face.FaceTracker`, started from the first n = 7 frames' feature points
(the simulator's, with ``landmark_noise`` px of detector noise) or, with ``init="haar"``, from a
Haar face box. Reported: per-frame progress, Table 1 (errors of x, y, z in mm and roll, pitch, yaw
in deg, mean and std) for both models beside the paper's, the shape error as the identity
converges (Fig. 7), two depth floors (the multilinear tracker with the true identity given and
fixed: how far the z error can fall with the person's size known; and :func:`landmark_floor`, the
bundle adjustment on perfect feature points: the error the size the landmarks give leaves, and
the rotation they leave), how far the tracked feature points lie from the true landmarks
(:func:`feature_error`) and the per-stage timing. ``save``: a directory for pictures (frames with
the feature points and the head's axes; the errors over the frames).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time

import numpy as np

from ..models.face import FaceModel, PcaFaceModel, load_ict
from ..models.pose import rodrigues
from ..registry import device as get_device
from ..sim.face import face_sequence
from ..trackers.face import FaceConfig, FaceTracker
from ..trackers.face.metrics import PAPER_TABLE1, format_table1, pose_errors, shape_error, table1

__all__ = ["feature_error", "landmark_floor", "run", "track_sequence", "true_identity", "visible_landmarks",
           "write_json"]


def visible_landmarks(frame) -> np.ndarray:
    """(K, 2) a simulated frame's true feature points (``landmarks2d``), NaN where hidden (``visible``)."""
    return np.where(np.asarray(frame.visible, bool)[:, None], frame.landmarks2d, np.nan)


def start_landmarks(seq, n: int, noise: float, seed) -> np.ndarray:
    """(n, K, 2) the first n frames' true feature points plus N(0, noise^2) px (a detector's), NaN where hidden."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        f = seq[k]
        out.append(visible_landmarks(f) + rng.normal(0.0, noise, f.landmarks2d.shape))
    return np.array(out)


def track_sequence(device, seq, model, config: FaceConfig, *, frames=None, init="landmarks", landmark_noise=1.0,
                   identity=None, true_points=False, progress=None, save=None, label="") -> dict:  # fmt: skip
    """Track ``seq`` with ``model``; return per-frame records (errors, the same signed, shape errors, times), the
    :class:`FaceEstimate` of every frame (``estimates``), the truth (``truth``: rotations (F, 3, 3),
    translations (F, 3), the visible landmarks' points (F, K, 2), NaN where hidden, and shapes (F, K, 3))
    and the tracker.

    identity: a fixed identity (S',) for the depth-floor run (``config.learn_identity`` should be False);
    true_points: every tracked frame's feature points are its true visible landmarks instead of eq. 14's
    (``FaceTracker.track(features=)``): what the rest of the tracker leaves with perfect points.
    """
    n_frames = len(seq) if frames is None else min(int(frames), len(seq))
    n = config.keyframes
    if n_frames <= n:
        raise ValueError(f"frames: expected more than the n={n} start frames, got {n_frames}")
    trk = FaceTracker(device, model, seq.camera, config)
    first = [seq[k] for k in range(n)]
    lm = None if init == "haar" else start_landmarks(seq, n, landmark_noise, config.seed)
    t0 = time.perf_counter()
    ests = trk.start(np.array([f.gray for f in first]), landmarks=lm)
    start_ms = (time.perf_counter() - t0) * 1e3
    if identity is not None:
        trk.fix_identity(identity)
    truth = list(first)
    ms = []
    for k in range(n, n_frames):
        f = seq[k]
        given = visible_landmarks(f) if true_points else None
        t0 = time.perf_counter()
        est = trk.track(f.gray, features=given)
        dt = time.perf_counter() - t0
        if k == n:
            trk.scheduler.reset()  # the first tracked frame compiles the kernels
        ms.append(dt * 1e3)
        ests.append(est)
        truth.append(f)
        if progress is not None:
            progress(k, f, est, dt)
        if save and (k % 30 == 0 or k == n_frames - 1):
            _picture(save, label, k, f, est, seq.camera)
    R = np.array([e.rotation for e in ests])
    t = np.array([e.translation for e in ests])
    true = {"rotations": np.array([f.rotation for f in truth]), "translations": np.array([f.translation for f in truth]),
            "points": np.array([visible_landmarks(f) for f in truth]), "shapes": np.array([f.shape for f in truth])}  # fmt: skip
    signed = pose_errors(R, t, true["rotations"], true["translations"], signed=True)
    err = np.abs(signed)
    shape = np.array([shape_error(model, e.identity, e.expression, f.shape) for e, f in zip(ests, truth)])
    return {"errors": err, "signed_errors": signed, "shape_error": shape, "ms": np.array(ms), "start_ms": start_ms,
            "estimates": ests, "truth": true,
            "feature_px": np.array([feature_error(e.features, f) for e, f in zip(ests, truth)]),
            "lost": np.array([e.lost for e in ests]), "confidence": np.array([e.confidence for e in ests]),
            "tracker": trk}  # fmt: skip


def feature_error(features, frame) -> float:
    """Mean distance (px) of a frame's feature points (K, 2) to the true landmarks of the simulated
    ``frame`` over the points both have (visible, and not NaN: not lost); NaN where there are none."""
    d = np.linalg.norm(np.asarray(features, np.float64) - np.asarray(frame.landmarks2d, np.float64), axis=1)
    d = d[np.asarray(frame.visible, bool) & np.isfinite(d)]
    return float(d.mean()) if len(d) else float("nan")


def _picture(save, label, k, f, est, camera) -> None:
    import cv2

    from ..trackers.face.pictures import draw_estimate

    img = draw_estimate(f.gray, est, camera, truth=f.landmarks2d)
    cv2.imwrite(os.path.join(save, f"{label}frame_{k:04d}.png"), img)


def _sources_picture(save, trk) -> None:
    import cv2

    from ..trackers.face.pictures import draw_template_sources

    cv2.imwrite(os.path.join(save, "template_sources.png"), draw_template_sources(trk.views))


def _error_plot(save, records: dict, fps: float) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    from ..trackers.face.metrics import COLUMNS

    fig, axes = plt.subplots(4, 2, figsize=(10, 9), sharex=True)
    for name, rec in records.items():
        e = rec["errors"]
        x = np.arange(len(e)) / fps
        for i, c in enumerate(COLUMNS):
            ax = axes[i % 3, i // 3]
            ax.plot(x, e[:, i], lw=0.8, label=name)
            ax.set_ylabel(f"{c} error ({'mm' if i < 3 else 'deg'})")
        axes[3, 0].plot(x, rec["shape_error"], lw=0.8, label=name)
    axes[3, 0].set_ylabel("shape error (mm)")
    axes[3, 0].set_xlabel("time (s)")
    axes[3, 1].axis("off")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(save, "errors.png"), dpi=90)
    plt.close(fig)


def run(device, *, sequence=0, frames=None, seed=0, init="landmarks", landmark_noise=1.0, floor=True, generic=True,
        save=None, out=None, config: FaceConfig | None = None, ict=None) -> dict:  # fmt: skip
    """Run the face demo on ``device`` (see the module docstring); prints to ``out`` (default stdout)
    and returns the report."""
    out = sys.stdout if out is None else out
    config = FaceConfig() if config is None else config
    ict = load_ict(ict) if not hasattr(ict, "neutral_mesh") else ict
    model = FaceModel.from_ict(ict)
    if isinstance(sequence, str) and sequence.isdigit():
        sequence = int(sequence)
    seq = face_sequence(sequence, frames=frames, seed=seed, ict=ict)
    name = seq.name
    print(f"gputrack demo face: sequence {name} ({len(seq)} frames at 30 fps, a person not among the model's 26), "
          f"N = {config.particles} particles, n = {config.keyframes} key frames, device {device.spec} "
          f"({device.name})", file=out)  # fmt: skip
    if save:
        os.makedirs(save, exist_ok=True)

    def progress(k, f, est, dt):
        if k % 30 == 0:
            print(f"  frame {k:4d}  {dt * 1e3:6.1f} ms  confidence {est.confidence:.2f}"
                  f"{'  LOST' if est.lost else ''}", file=out, flush=True)  # fmt: skip

    runs = {"multilinear": (model, config, None)}
    if generic:
        runs["generic PCA"] = (PcaFaceModel.from_ict(ict), config, None)
    if floor:
        true_s = true_identity(ict, seq, model)
        runs["true identity (floor)"] = (model, dataclasses.replace(config, learn_identity=False), true_s)
    records = {}
    for label, (m, cfg, ident) in runs.items():
        print(f"\n{label} model:", file=out)
        records[label] = track_sequence(device, seq, m, cfg, init=init, landmark_noise=landmark_noise,
                                        identity=ident, progress=progress, save=save if label == "multilinear" else None,
                                        label="")  # fmt: skip
    tables = {k: table1(r["errors"]) for k, r in records.items()}
    print(f"\nTable 1: errors against the truth (sequence {name}, device {device.spec})", file=out)
    print(format_table1(tables, PAPER_TABLE1), file=out)
    lf = None
    if floor:
        n_seq = len(records["multilinear"]["errors"])
        step = 5 if n_seq >= 5 * config.keyframes else 1
        lf = landmark_floor(model, [seq[k] for k in range(0, n_seq, step)], seq.camera, config)
        among = "every frame" if step == 1 else f"every {step}th frame"
        print(f"\ndepth from perfect feature points (the bundle adjustment of the {config.keyframes} frames of "
              f"{among} with the widest spread of face directions): the size they give this person puts it "
              f"{100 * lf['relative']:+.1f} % off in depth, a z error of {lf['z_mm']:.1f} mm (the floor without "
              f"the true identity; with it, the \"true identity\" rows of Table 1)", file=out)  # fmt: skip
        roll, pitch, yaw = lf["rotation_deg"]
        print(f"rotation from the same perfect feature points: roll {roll:.2f}, pitch {pitch:.2f}, yaw {yaw:.2f} deg "
              "(mean over those frames)", file=out)  # fmt: skip
    fp = {k: float(np.nanmean(r["feature_px"])) for k, r in records.items()}
    print("feature points after eq. 14, mean distance to the true landmarks: "
          + ", ".join(f"{k} {v:.2f} px" for k, v in fp.items()), file=out)  # fmt: skip
    rec = records["multilinear"]
    se = rec["shape_error"]
    marks = [k for k in (0, 6, 30, 100, 200, len(se) - 1) if k < len(se)]
    print("\nshape error as the identity converges (mm, RMS of the K model-frame points): "
          + "  ".join(f"frame {k}: {se[k]:.2f}" for k in marks), file=out)  # fmt: skip
    trk = rec["tracker"]
    print("\nper-stage time (ms; tracked frames after the first)", file=out)
    print(trk.scheduler.table("face"), file=out)
    med = float(np.median(rec["ms"][1:])) if len(rec["ms"]) > 1 else float("nan")
    print(f"start (n = {config.keyframes} frames, {config.init_iterations} LM iterations) {rec['start_ms']:.0f} ms; "
          f"median tracked frame {med:.1f} ms; lost frames {int(rec['lost'].sum())}; detection proposals "
          f"{trk.proposals} (taken {trk.proposals_taken}); template sources {trk.template_sources}", file=out)  # fmt: skip
    if save:
        _error_plot(save, records, 30.0)
        _sources_picture(save, trk)
        print(f"pictures written to {save}", file=out)
    report = {"device": {"spec": device.spec, "name": device.name},
              "sequence": {"name": name, "frames": len(seq), "seed": seed, "init": init},
              "table1": tables, "shape_error": {int(k): float(se[k]) for k in marks},
              "landmark_floor": None if lf is None else {"relative": lf["relative"], "z_mm": lf["z_mm"],
                                                         "rotation_deg": list(lf["rotation_deg"])},
              "feature_px": fp,
              "lost": {k: int(r["lost"].sum()) for k, r in records.items()},
              "detection_proposals": {k: {"made": r["tracker"].proposals, "taken": r["tracker"].proposals_taken}
                                      for k, r in records.items()},
              "template_sources": {k: r["tracker"].template_sources for k, r in records.items()},
              "stages": trk.scheduler.report(), "median_frame_ms": med, "start_ms": rec["start_ms"]}  # fmt: skip
    return report


def landmark_floor(model, frames, camera, config: FaceConfig, *, device=None, max_iter: int = 50) -> dict:
    """The depth error left from perfect feature points: the scale a face's landmarks cannot show.

    A larger head farther away shows the same feature points; only the model's priors (the identity
    box of eq. 9 and ``config.identity_prior``) and the face's proportions fix its size. This runs
    the tracker's bundle adjustment (:func:`~gputrack.trackers.face.bundle.bundle_adjust`, n =
    ``config.keyframes``) on the true feature points (no noise, hidden ones left out) of the n
    ``frames`` with the widest spread of face directions (over the frames in order, the incremental
    adjustment's rule with ``keep_previous``: :func:`~gputrack.trackers.face.bundle.keyframe_slot`),
    from the true poses within the start's box,
    the model's mean identity and mean deformation. ``frames``: objects with ``rvec``,
    ``translation``, ``landmarks2d`` and ``visible`` (the simulator's
    :class:`~gputrack.sim.face.FaceFrame`).

    Returns {"relative": the median over the key frames of z_estimated / z_true - 1, "z_mm": |that|
    times the frames' mean true depth (the z error of Table 1 such a size error gives), "rotation_deg":
    the mean absolute roll, pitch and yaw errors over the key frames (the rotation such points leave
    with the identity they imply), "keyframes": their indices into ``frames``, "rms": the
    adjustment's reprojection RMS (px)}."""
    from ..trackers.face.bundle import START_POSE_RANGE, bundle_adjust, keyframe_slot

    n = config.keyframes
    frames = list(frames)
    if len(frames) < n:
        raise ValueError(f"frames: expected at least n={n}, got {len(frames)}")
    rv = np.array([f.rvec for f in frames], np.float64)
    keys = list(range(n))
    for i in range(n, len(frames)):
        slot = keyframe_slot(rv[keys], keys, rv[i], keep_previous=True)
        if slot >= 0:
            keys[slot] = i
    fk = [frames[k] for k in keys]
    lm = np.array([visible_landmarks(f) for f in fk])
    device = get_device("numpy") if device is None else device
    res = bundle_adjust(device, model, camera, lm, rv[keys], np.array([f.translation for f in fk]),
                        np.tile(model.expression_mean, (n, 1)), model.identity_mean, pose_range=START_POSE_RANGE,
                        identity_sigmas=config.identity_sigmas, identity_prior=config.identity_prior,
                        max_iter=max_iter)  # fmt: skip
    z = np.array([f.translation[2] for f in fk], np.float64)
    rel = float(np.median(res.tvecs[:, 2] / z - 1.0))
    depth = float(np.mean([f.translation[2] for f in frames]))
    err = pose_errors(np.array([rodrigues(r) for r in res.rvecs]), res.tvecs,
                      np.array([rodrigues(np.asarray(f.rvec, np.float64)) for f in fk]),
                      np.array([f.translation for f in fk]))  # fmt: skip
    rotation = tuple(float(v) for v in err[:, 3:].mean(axis=0))
    return {"relative": rel, "z_mm": abs(rel) * depth, "rotation_deg": rotation, "keyframes": keys, "rms": res.rms}


def true_identity(ict, seq, model) -> np.ndarray:
    """(S',) the model's coordinates of the simulated sequence's person: the least-squares identity
    of its K points in the model's A deformations (the depth floor's run holds it)."""
    lm = ict.landmarks(seq.identity[None, :], ict.motion_weights())
    return model.identity_of(lm[:, list(model.landmarks)])


def write_json(report: dict, path: str) -> None:
    with open(path, "w") as f:
        json.dump(report, f, indent=2, default=float)

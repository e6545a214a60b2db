"""The ``gputrack`` command line: ``gputrack devices [--json]``, ``gputrack doctor``, ``gputrack bench``, ``gputrack tune``,
``gputrack demo body|groups|pedestrians|face``, ``gputrack track body|groups|pedestrians|face``."""

from __future__ import annotations

import argparse
import json
import logging
import sys


# -- argument types: a bad value ends in argparse's usage line and exit status 2 ---------------------
def _int_at_least(low: int):
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            v = None
        if v is None or v < low:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}")
        return v

    return parse


def _int_in(low: int, high: int):
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            v = None
        if v is None or not low <= v <= high:
            raise argparse.ArgumentTypeError(f"expected an integer in [{low}, {high}], got {text!r}")
        return v

    return parse


def _float_above(low: float, *, inclusive: bool = False, high: float = float("inf")):
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            v = float("nan")
        if not (v >= low if inclusive else v > low) or not v <= high or v == float("inf"):
            want = f"{'>=' if inclusive else '>'} {low:g}" + (f" and <= {high:g}" if high < float("inf") else "")
            raise argparse.ArgumentTypeError(f"expected a finite number {want}, got {text!r}")
        return v

    return parse


DEVICE_HELP = "device spec (default: GPUTRACK_DEVICE, else the best available)"
NO_PREDICT_HELP = ("start each frame where the last ended (the paper); default: half the candidates also moved "
                   "by the last frame's motion")


def format_devices(infos) -> str:
    """The device table (gputrack/doctor.py, which the ``doctor`` command shares)."""
    from .doctor import format_devices as table

    return table(infos)


def _device_spec(text: str) -> str:
    """A spec of a known form (whether its device is available is found when it is opened)."""
    from .registry import parse_spec

    try:
        parse_spec(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


def _face_sequence(text: str) -> str:
    from .sim.face import SEQUENCES

    if text in SEQUENCES or (text.isdigit() and int(text) < len(SEQUENCES)):
        return text
    raise argparse.ArgumentTypeError(
        f"expected 0-{len(SEQUENCES) - 1} or one of {', '.join(SEQUENCES)}, got {text!r}"
    )


def cmd_doctor(args) -> int:
    from . import doctor

    return doctor.run(args)


def cmd_devices(args) -> int:
    from .registry import devices

    infos = devices()
    if args.json:
        print(json.dumps([d.as_dict() for d in infos], indent=2))
    else:
        print(format_devices(infos))
    return 0


def _per_op_json(path: str, op: str) -> str:
    """The file of ``op``'s results when several ops write JSON: FILE.json -> FILE.<op>.json, any
    other FILE -> FILE.<op>.json (one file per op, never the same file twice)."""
    from pathlib import Path

    p = Path(path)
    return str(p.with_suffix(f".{op}.json") if p.suffix == ".json" else p.with_name(f"{p.name}.{op}.json"))


def cmd_bench(args) -> int:
    import importlib
    import pkgutil

    from . import benchmarks
    from .benchmarks.harness import bench_main

    names = sorted(m.name for m in pkgutil.iter_modules(benchmarks.__path__) if m.name != "harness")
    ops = args.op or names
    unknown = sorted(set(ops) - set(names))
    if unknown:
        print(f"gputrack bench: unknown --op {', '.join(unknown)}; expected one of: {', '.join(names)}", file=sys.stderr)
        return 2
    status = 0
    for name in ops:
        argv = ["--min-time", str(args.min_time)]
        for spec in args.device or ["all"]:
            argv += ["--device", spec]
        if args.json:
            argv += ["--json", args.json if len(ops) == 1 else _per_op_json(args.json, name)]
        status |= bench_main(importlib.import_module(f"gputrack.benchmarks.{name}"), argv)
    return status


def cmd_demo(args) -> int:
    from .device import DeviceUnavailable
    from .registry import device

    try:
        dev = device(args.device)
    except DeviceUnavailable as e:
        args.parser.error(f"--device: {e}")
    if args.what == "face":
        from .demos import face
        from .trackers.face import FaceConfig

        report = face.run(dev, sequence=args.sequence, frames=args.frames, seed=args.seed, init=args.init,
                          generic=not args.no_generic, floor=not args.no_floor, save=args.save,
                          config=FaceConfig(particles=args.particles))  # fmt: skip
        if args.json:
            face.write_json(report, args.json)
        return 0
    if args.what == "pedestrians":
        from .demos import pedestrians

        report = pedestrians.run(dev, people=args.people, frames=args.frames, seed=args.seed, scale=args.scale,
                                 ablations=not args.no_ablations, save=args.save)  # fmt: skip
        if args.json:
            pedestrians.write_json(report, args.json)
        return 0
    if args.what == "groups":
        from .demos import groups

        report = groups.run(dev, scene_name=args.scene, seconds=args.seconds, seed=args.seed, points=args.points,
                            save=args.save)  # fmt: skip
        if args.json:
            groups.write_json(report, args.json)
        return 0
    from .demos import body

    report = body.run(dev, frames=args.frames, sequence_index=args.sequence, lm=args.lm, stages=args.stages,
                       shoulders=args.shoulders, seed=args.seed, template_every=args.template_every,
                       depth_tol=args.depth_tol, n_depth=args.depth_points, predict=not args.no_predict,
                       save=args.save)  # fmt: skip
    if args.json:
        body.write_json(report, args.json)
    return 0


#: errors of a recording, its camera or its start files: reported as one line "gputrack track X: ..."
INPUT_ERRORS = (FileNotFoundError, ValueError, TypeError)


def _fail(name: str, error) -> int:
    print(f"{name}: {error}", file=sys.stderr)
    return 1


def _track_into(args, name: str, run, done: str = "") -> int:
    """Open --device and --out, ``run(device, out) -> frames``; bad input ends in one line, not a traceback."""
    from .device import DeviceUnavailable
    from .registry import device

    try:
        dev = device(args.device)
    except DeviceUnavailable as e:
        args.parser.error(f"--device: {e}")
    try:
        out = open(args.out, "w") if args.out else sys.stdout
    except OSError as e:
        return _fail(name, f"{args.out}: cannot write the output ({e.strerror})")
    try:
        n = run(dev, out)
    except INPUT_ERRORS as e:
        return _fail(name, e)
    finally:
        if args.out:
            out.close()
    print(f"{name}: {n} frames{done}", file=sys.stderr)
    return 0


def cmd_track_pedestrians(args) -> int:
    import dataclasses

    from .trackers.pedestrians import PedestrianConfig
    from .trackers.pedestrians.recording import read_camera, track_recording

    name = "gputrack track pedestrians"
    try:
        cam, mounting = read_camera(args.camera)
        config = dataclasses.replace(PedestrianConfig(), **mounting)
    except INPUT_ERRORS as e:
        return _fail(name, e)

    def progress(k, fr):
        if args.out:
            print(f"  frame {k + 1:5d}  {len(fr.segments)} segments  pedestrians "
                  + " ".join(str(p.id) for p in fr.pedestrians), file=sys.stderr, flush=True)  # fmt: skip

    return _track_into(args, name, lambda dev, out: track_recording(
        dev, args.depth, cam, out, config=config, background=args.background, save=args.save, progress=progress))


def cmd_track_face(args) -> int:
    from .models.face import FaceModel, load_face_model
    from .trackers.face.recording import read_camera, read_landmarks, track_recording

    name = "gputrack track face"
    try:
        cam = read_camera(args.camera) if args.camera else None
        model = load_face_model(args.model) if args.model else FaceModel.from_ict()
        lm = read_landmarks(args.landmarks, model.K) if args.landmarks else None
    except INPUT_ERRORS as e:
        return _fail(name, e)
    if cam is None:
        print(f"{name}: no --camera: assuming fx = fy = the image width, the principal point at the centre",
              file=sys.stderr)  # fmt: skip

    def progress(k, est):
        if args.out and k % 30 == 0:
            print(f"  frame {k:5d}  confidence {est.confidence:.2f}{'  LOST' if est.lost else ''}", file=sys.stderr,
                  flush=True)  # fmt: skip

    return _track_into(args, name, lambda dev, out: track_recording(
        dev, args.video, out, camera=cam, landmarks=lm, model=model, save=args.save, progress=progress))


def cmd_track_body(args) -> int:
    import dataclasses

    from .trackers.body import BodyTrackerConfig
    from .trackers.body.recording import DEPTH_SCALE, read_body_model, read_camera, read_pose, track_recording

    name = "gputrack track body"
    if args.init is None and not args.rigid:
        args.parser.error("--init: expected the first frame's pose (a JSON file {\"params\": [...]}) unless --rigid")
    try:
        cam, extras = read_camera(args.camera)
        dims = read_body_model(args.model) if args.model else None
        start = read_pose(args.init, (6,) if args.rigid else (14, 20)) if args.init else None
    except INPUT_ERRORS as e:
        return _fail(name, e)
    scale = args.depth_scale or extras.get("depth_scale", DEPTH_SCALE)
    # rigid: the parameters are the frame-to-frame motion, whose last value is the constant-velocity start
    base = BodyTrackerConfig(c_depth=50.0, lam=0.5, predict=False) if args.rigid else BodyTrackerConfig()
    changes = {k: v for k, v in (("lm_iterations", args.lm), ("stages", args.stages), ("samples", args.samples),
                                 ("c_depth", args.c_depth), ("lam", args.lam), ("depth_tol", args.depth_tol),
                                 ("predict", False if args.no_predict else None))
               if v is not None}  # fmt: skip
    try:
        config = dataclasses.replace(base, **changes)
    except ValueError as e:
        args.parser.error(str(e))
    size = (extras["width"], extras["height"]) if "width" in extras and "height" in extras else None

    def progress(k, rec):
        if args.out and k % 30 == 0:
            print(f"  frame {k:5d}  confidence {rec['confidence']:.0f}" + (f"  {rec['message']}" if "message" in rec else ""),
                  file=sys.stderr, flush=True)  # fmt: skip

    return _track_into(args, name, lambda dev, out: track_recording(
        dev, args.rgb, args.depth, out, camera=cam, start=start, dimensions=dims, depth_scale=scale, config=config,
        rigid=args.rigid, start_name=args.init or "start pose", camera_size=size, save=args.save, progress=progress),
        done=f" (depth {scale:g} mm per unit)")


def cmd_track_groups(args) -> int:
    from .models import StereoCamera
    from .trackers.groups.recording import read_camera, track_recording

    name = "gputrack track groups"
    if args.camera:
        try:
            cam = read_camera(args.camera)
        except INPUT_ERRORS as e:
            return _fail(name, e)
    elif None in (args.f, args.b, args.cx, args.cy):
        print(f"{name}: expected --camera FILE or all of --f --b --cx --cy", file=sys.stderr)
        return 2
    else:
        cam = StereoCamera(f=args.f, b=args.b, cx=args.cx, cy=args.cy)

    def progress(k, fr):
        if args.out:
            print(f"  frame {k:5d}  {len(fr.labels):4d} points  groups " + " ".join(f"{g.id}:{g.n_points}" for g in fr.groups),
                  file=sys.stderr, flush=True)  # fmt: skip

    return _track_into(args, name, lambda dev, out: track_recording(
        dev, args.left, args.right, cam, out, background=args.background, background_left=args.background_left,
        progress=progress))


TRACKS = {"body": cmd_track_body, "face": cmd_track_face, "pedestrians": cmd_track_pedestrians,
          "groups": cmd_track_groups}  # fmt: skip


def cmd_track(args) -> int:
    return TRACKS[args.what](args)


def format_trials(tunable, size, trials, best, default) -> str:
    """One size of a ``gputrack tune`` sweep: each candidate's median and spread, the choice and the default."""
    from .tuning import size_bucket

    head = f"{'params':<36}{'median ms':>11}{'p10-p90 ms':>17}{'x default':>11}"
    lines = [f"{tunable.op} on {tunable.backend}, size {size} (bucket {size_bucket(size)})", head, "-" * len(head)]
    base = next((t.timing.median_s for t in trials if t.timing is not None and t.params == default), None)
    for t in trials:
        label = ", ".join(f"{k}={v}" for k, v in t.params.items())
        mark = ("  <- chosen" if t.params == best else "") + ("  (default)" if t.params == default else "")
        if t.timing is None:
            lines.append(f"{label:<36}{'failed':>11}  {t.error}{mark}")
            continue
        m = t.timing
        ratio = f"{base / m.median_s:.2f}" if base else "-"
        spread = f"{m.p10_s * 1e3:.3f}-{m.p90_s * 1e3:.3f}"
        lines.append(f"{label:<36}{m.median_s * 1e3:>11.3f}{spread:>17}{ratio:>11}{mark}")
    if best is None:
        lines.append("every candidate failed: nothing stored")
    return "\n".join(lines)


def cmd_tune(args) -> int:
    from . import tuning
    from .registry import device

    if args.min_time <= 0:
        print(f"gputrack tune: --min-time: expected seconds > 0, got {args.min_time}", file=sys.stderr)
        return 2
    dev = device(args.device)
    found = tuning.tunables(dev.backend)
    names = sorted({t.op for t in found})
    if args.op:
        unknown = sorted(set(args.op) - set(names))
        if unknown:
            expected = ", ".join(names) if names else f"none (no tunables on backend {dev.backend})"
            print(f"gputrack tune: unknown --op {', '.join(unknown)} for {dev.spec}; expected one of: {expected}",
                  file=sys.stderr)  # fmt: skip
            return 2
        found = [t for t in found if t.op in args.op]
    if not found:
        print(f"gputrack tune: nothing to tune on {dev.spec} (backend {dev.backend} has no launch parameters)")
        return 0
    cache = tuning.default_cache()  # the one the ops read: they see the new choices at once
    print(f"gputrack tune: {dev.spec} ({dev.name}); cache {cache.path}", flush=True)
    for t in found:
        n = len(t.grid()) * len(t.sizes)
        runs = f"{n} runs ({len(t.grid())} candidates x {len(t.sizes)} sizes)"
        print(f"[tune] {t.op}: {runs}", file=sys.stderr, flush=True)
        default = t.default_for(dev)

        def report(size, trials, best, t=t, default=default):
            print(format_trials(t, size, trials, best, default) + "\n", flush=True)

        tuning.tune(dev, t, cache=cache, min_time=args.min_time, report=report,
                    progress=lambda m: print(f"[tune] {m}", file=sys.stderr, flush=True))  # fmt: skip
    print(f"stored in {cache.path}; the ops use these choices on {dev.spec} from now on")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="gputrack", description="GPU-portable compute primitives for visual tracking")
    parser.add_argument("-v", "--verbose", action="store_true", help="log what gputrack does")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("devices", help="list every backend, available or not and why")
    p.add_argument("--json", action="store_true", help="print the table as JSON")
    p.set_defaults(func=cmd_devices)

    demo = sub.add_parser("demo", help="simulate a scene and track it (papers 000-003)")
    which = demo.add_subparsers(dest="what", required=True)
    p = which.add_parser("body", help="paper 000: upper-body PF + LM on simulated RGB-D")
    p.add_argument("--device", type=_device_spec, help=DEVICE_HELP)
    p.add_argument("--frames", type=_int_at_least(2), default=30, help="frames to simulate (default 30)")
    p.add_argument("--sequence", type=_int_in(0, 8), default=0, help="simulated motion sequence 0-8 (default 0)")
    p.add_argument("--lm", type=_int_at_least(0), default=10, help="LM iterations per frame (0: particle filter only)")
    p.add_argument("--stages", type=_int_at_least(1), default=3,
                   help="coarse-to-fine particle-filter stages (default 3)")  # fmt: skip
    p.add_argument("--shoulders", action="store_true", help="estimate the shoulder positions too (20 parameters)")
    p.add_argument("--template-every", type=_int_at_least(1), default=1, help="make the template every N frames")
    p.add_argument(
        "--depth-tol",
        type=_float_above(0.0, inclusive=True),
        default=0.0,
        metavar="MM",
        help="depth differences up to MM count as none (default 0; 2.5 = half the simulator's 5 mm step)",
    )
    p.add_argument("--depth-points", type=_int_at_least(1), default=128, metavar="N",
                   help="depth template points N' (default 128)")  # fmt: skip
    p.add_argument("--no-predict", action="store_true", help=NO_PREDICT_HELP)
    p.add_argument("--seed", type=_int_at_least(0), default=0)
    p.add_argument("--save", metavar="DIR", help="write pictures (frames with the model and template points, "
                   "the per-part errors over the frames)")  # fmt: skip
    p.add_argument("--json", metavar="FILE", help="write the report as JSON")
    p.set_defaults(func=cmd_demo, parser=p)
    p = which.add_parser("groups", help="paper 001: groups of people from a simulated stereo camera")
    p.add_argument("--device", type=_device_spec, help=DEVICE_HELP)
    p.add_argument("--scene", choices=["crossing", "merging", "stairs"], default="crossing",
                   help="simulated scene (default crossing)")  # fmt: skip
    p.add_argument("--seconds", type=_float_above(0.0), help="seconds of people in view (default: the scene's, 5-6 s)")
    p.add_argument("--points", action="store_true", help="feed the simulator's observation points, not images")
    p.add_argument("--seed", type=_int_at_least(0), default=0)
    p.add_argument("--save", metavar="DIR", help="write pictures (frames with groups, top view of trajectories)")
    p.add_argument("--json", metavar="FILE", help="write the report as JSON")
    p.set_defaults(func=cmd_demo, parser=p)

    p = which.add_parser("pedestrians", help="paper 002: pedestrians from a simulated level depth camera")
    p.add_argument("--device", type=_device_spec, help=DEVICE_HELP)
    p.add_argument("--people", type=_int_at_least(1), default=5, help="most people in view at once (default 5)")
    p.add_argument("--frames", type=_int_at_least(2), default=851, help="frames at 5 fps (default 851, as the paper)")
    p.add_argument("--scale", type=_float_above(0.0, high=4.0), default=1.0,
                   help="image size: 1 = 1280 x 960 (default), 0.5 = 640 x 480")  # fmt: skip
    p.add_argument("--seed", type=_int_at_least(0), default=0)
    p.add_argument("--no-ablations", action="store_true", help="skip the runs without the occlusion gain / split-merge")
    p.add_argument("--save", metavar="DIR", help="write pictures (top view of the tracks, depth with segments)")
    p.add_argument("--json", metavar="FILE", help="write the report as JSON")
    p.set_defaults(func=cmd_demo, parser=p)

    p = which.add_parser("face", help="paper 003: head pose, deformation and identity from a simulated camera")
    p.add_argument("--device", type=_device_spec, help=DEVICE_HELP)
    p.add_argument("--sequence", type=_face_sequence, default="turns",
                   help="simulated sequence: 0-4 or turns, depth, expressions, lighting, mixed (default turns)")
    p.add_argument("--frames", type=_int_in(1, 1_000_000), default=300, help="frames at 30 fps (default 300)")
    p.add_argument("--init", choices=["landmarks", "haar"], default="landmarks",
                   help="start from the first 7 frames' feature points (+1 px noise) or from a Haar face box")
    p.add_argument("--no-generic", action="store_true", help="skip the generic PCA model's run")
    p.add_argument("--no-floor", action="store_true",
                   help="skip the depth floors (the run with the true identity; the bundle adjustment on perfect "
                        "feature points)")  # fmt: skip
    p.add_argument("--particles", type=_int_in(1, 1_000_000), default=1000,
                   help="hypotheses N of the particle filter (default 1000, the paper's)")
    p.add_argument("--seed", type=_int_at_least(0), default=0)
    p.add_argument("--save", metavar="DIR", help="write pictures (frames with points and axes, errors over time)")
    p.add_argument("--json", metavar="FILE", help="write the report as JSON")
    p.set_defaults(func=cmd_demo, parser=p)

    track = sub.add_parser("track", help="track a real recording (paper 000 body, 001 groups, 002 pedestrians, 003 face)")
    which = track.add_subparsers(dest="what", required=True)
    p = which.add_parser("body", help="an RGB-D recording (ICL-NUIM / TUM RGB-D layout) -> the upper body's pose per "
                         "frame as JSON lines")  # fmt: skip
    p.add_argument("--rgb", required=True, help="RGB (or gray) images: a glob pattern or a directory")
    p.add_argument("--depth", required=True, help="depth images (16-bit PNG): a glob pattern or a directory")
    p.add_argument("--camera", required=True, metavar="JSON",
                   help='{"fx", "fy", "cx", "cy"} px (optional "width", "height", "depth_scale") or Open3D\'s '
                   '{"intrinsic_matrix": [9]}')  # fmt: skip
    p.add_argument("--init", metavar="JSON", help='the first frame\'s pose {"params": [14 or 20 numbers]} '
                   "(radians, mm; required unless --rigid)")  # fmt: skip
    p.add_argument("--model", metavar="JSON", help="the body's dimensions per part (mm; default: the average build)")
    p.add_argument("--depth-scale", type=_float_above(0.0), metavar="MM",
                   help="mm per depth unit (default: the camera file's \"depth_scale\", else 0.2: TUM RGB-D and "
                   "ICL-NUIM's 5000 units per metre; 1 for depth in mm)")  # fmt: skip
    p.add_argument("--rigid", action="store_true", help="track the camera's motion against a rigid scene instead "
                   "(template from the previous frame; --init optional, 6 numbers)")  # fmt: skip
    p.add_argument("--lm", type=_int_at_least(0), help="LM iterations per frame (default 10)")
    p.add_argument("--stages", type=_int_at_least(1), help="coarse-to-fine particle-filter stages (default 3)")
    p.add_argument("--samples", type=_int_at_least(1), help="particle-filter samples K per stage (default 1500)")
    p.add_argument("--c-depth", type=_float_above(0.0), metavar="MM",
                   help="c' of eq. 18 (default 5 mm; 50 with --rigid)")  # fmt: skip
    p.add_argument("--lam", type=_float_above(0.0, inclusive=True, high=1.0),
                   help="lambda of eq. 19, the depth term's weight (default 0.9; 0.5 with --rigid)")  # fmt: skip
    p.add_argument("--depth-tol", type=_float_above(0.0, inclusive=True), metavar="MM",
                   help="depth differences up to MM count as none (default 0)")  # fmt: skip
    p.add_argument("--no-predict", action="store_true", help=NO_PREDICT_HELP)
    p.add_argument("--device", type=_device_spec, help=DEVICE_HELP)
    p.add_argument("--out", metavar="FILE", help="write the JSON lines here (default stdout)")
    p.add_argument("--save", metavar="DIR", help="write every 10th frame with the model and the template points")
    p.set_defaults(func=cmd_track, parser=p)
    p = which.add_parser("groups", help="a rectified stereo recording -> groups per frame as JSON lines")
    p.add_argument("--left", required=True, help="left video, image directory or glob pattern")
    p.add_argument("--right", required=True, help="right video, image directory or glob pattern")
    p.add_argument("--camera", metavar="FILE", help='JSON {"f": px, "b": mm, "cx": px, "cy": px}')
    for name, unit in (("f", "focal length, px"), ("b", "baseline, mm"), ("cx", "px"), ("cy", "px")):
        p.add_argument(f"--{name}", type=float, help=f"rectified camera {name} ({unit}) instead of --camera")
    p.add_argument("--background", type=int, default=24, help="first frames that teach the background (default 24)")
    p.add_argument("--background-left", metavar="PATH", help="empty left frames for the background instead")
    p.add_argument("--device", help="device spec (default: GPUTRACK_DEVICE, else the best available)")
    p.add_argument("--out", metavar="FILE", help="write the JSON lines to FILE (default: stdout)")
    p.set_defaults(func=cmd_track)
    p = which.add_parser("pedestrians", help="16-bit depth images (mm) -> pedestrian tracks as MOTChallenge-like CSV")
    p.add_argument("--depth", required=True, help="depth PNGs in mm: a glob pattern or a directory")
    p.add_argument("--camera", required=True, metavar="FILE",
                   help='JSON {"fx", "fy", "cx", "cy"} px, optional "camera_height" mm or "ground_plane" [a, b, c, d]')
    p.add_argument("--background", metavar="PATH", help="empty depth frames (glob or directory; default: the floor)")
    p.add_argument("--device", help="device spec (default: GPUTRACK_DEVICE, else the best available)")
    p.add_argument("--save", metavar="DIR", help="write pictures every 10 frames")
    p.add_argument("--out", metavar="FILE", help="write the CSV to FILE (default: stdout)")
    p.set_defaults(func=cmd_track)

    p = which.add_parser("face", help="a video of one face -> pose, deformation and feature points as JSON lines")
    p.add_argument("--video", required=True, help="a video file, a directory of images or a glob pattern")
    p.add_argument("--camera", metavar="JSON", help="camera intrinsics {fx, fy, cx, cy} (default: fx = fy = width)")
    p.add_argument("--landmarks", metavar="JSON", help="the first frame's 10 feature points {\"landmarks\": [[u, v], ...]} "
                   "(default: a Haar face box)")  # fmt: skip
    p.add_argument("--model", metavar="NPZ", help="a face model file (default: the multilinear model of the ICT data)")
    p.add_argument("--device", help="device spec (default: GPUTRACK_DEVICE, else the best available)")
    p.add_argument("--out", metavar="FILE", help="write the JSON lines here (default stdout)")
    p.add_argument("--save", metavar="DIR", help="write every 10th frame with the points and the head's axes")
    p.set_defaults(func=cmd_track)

    p = sub.add_parser("doctor", help="check this host: probe every backend, build every kernel, self-test every device",
                       description="Probe every backend, build every OpenCL kernel on every OpenCL device and run "
                       "the numerical self-tests on every available device; exit status 1 on a problem.")  # fmt: skip
    from .doctor import add_arguments as doctor_arguments

    doctor_arguments(p)
    p.set_defaults(func=cmd_doctor)

    p = sub.add_parser("bench", help="time the ops on every device, with ratios against NumPy")
    p.add_argument("--device", action="append", help="spec, or 'all' (default; repeatable)")
    p.add_argument("--op", action="append", help="benchmark name (default: all; repeatable)")
    p.add_argument("--json", metavar="FILE", help="write results as JSON (FILE.<op>.json with several ops)")
    p.add_argument("--min-time", type=float, default=0.2, help="seconds of timed calls per figure")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("tune", help="time the kernels' launch parameters on a device and store the fastest")
    p.add_argument("--device", help="device spec (default: GPUTRACK_DEVICE, else the best available)")
    p.add_argument("--op", action="append", help="op to tune (default: every tunable op; repeatable)")
    p.add_argument("--min-time", type=float, default=0.1, help="seconds of timed calls per candidate (default 0.1)")
    p.set_defaults(func=cmd_tune)

    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(name)s: %(message)s")
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())

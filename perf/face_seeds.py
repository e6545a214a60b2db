#!/usr/bin/env python3
"""Paper 003's Table 1 over many simulated people: the face tracker (multilinear model) on every
sequence with several seeds (each seed a different person, detector noise and filter stream), one
process per run, the mean errors per sequence beside the paper's.

One run swings with its seed (a few degrees of yaw, tens of mm of depth), so a change to the
tracker is judged here over many runs: ``--compare FIELD=VALUE`` runs every case a second time with
that FaceConfig field changed and counts, per column, the runs in which the default was better.
``--floor`` runs every case once more with the person's true identity given and held (the depth
floor: the tracker as it would be if it knew the person's size), ``--generic`` once more with the
generic PCA model instead of the multilinear one (Table 1's comparison), ``--true-points`` once more
with each frame's true landmarks as the feature points instead of eq. 14's (what the rest of the
tracker leaves with perfect points).

Every default run also says where its rotation error comes from
(:func:`gputrack.trackers.face.metrics.error_parts` and ``rotation_sources``): how much of it is an
offset held through the run, how much changes slowly with the motion and how much from frame to
frame, and what the tracked points alone and the estimated shape alone leave.

    python perf/face_seeds.py --device taichi:cpu --seeds 0-5
    python perf/face_seeds.py --device opencl --seeds 0-2 --sequence turns --compare anchor_templates=false
    python perf/face_seeds.py --device opencl --seeds 0-5 --floor --generic
    python perf/face_seeds.py --device opencl --seeds 0-5 --sequence turns --true-points
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from gputrack.trackers.face.metrics import COLUMNS, PAPER_TABLE1

SEQUENCES = ("turns", "depth", "expressions", "lighting", "mixed")
#: the pseudo-overrides (not FaceConfig fields) of ``--floor``'s runs (the true identity given and held),
#: of ``--generic``'s (the generic PCA model) and of ``--true-points``' (the true landmarks as feature points)
FLOOR, GENERIC, POINTS = {"true_identity": True}, {"generic_model": True}, {"true_points": True}


def child(spec: str, sequence: str, seed: int, overrides: dict, frames=None) -> dict:
    """One run: the multilinear tracker on ``sequence`` with ``seed`` (its first ``frames`` frames, or all),
    Table 1's means and more; with :data:`FLOOR`'s key in ``overrides`` the person's true identity held,
    and the depth error that perfect feature points leave (``landmark_z``, mm:
    :func:`gputrack.demos.face.landmark_floor` over every 5th frame, as the demo); with
    :data:`GENERIC`'s the generic PCA model; with :data:`POINTS`' the true landmarks as the feature points."""
    import dataclasses

    import gputrack
    from gputrack.demos.face import landmark_floor, track_sequence, true_identity
    from gputrack.models.face import FaceModel, PcaFaceModel, load_ict
    from gputrack.sim.face import face_sequence
    from gputrack.trackers.face import FaceConfig
    from gputrack.trackers.face.metrics import error_parts, rotation_sources, table1

    ict = load_ict()
    seq = face_sequence(sequence, frames=frames, seed=seed, ict=ict)
    fields = {k: v for k, v in overrides.items() if k not in {**FLOOR, **GENERIC, **POINTS}}
    model = (PcaFaceModel if overrides.get("generic_model") else FaceModel).from_ict(ict)
    identity = None
    if overrides.get("true_identity"):
        identity = true_identity(ict, seq, model)
        fields["learn_identity"] = False
    config = dataclasses.replace(FaceConfig(), seed=seed, **fields)
    rec = track_sequence(gputrack.device(spec), seq, model, config, identity=identity,
                         true_points=bool(overrides.get("true_points")))  # fmt: skip
    t = table1(rec["errors"])
    out = {"sequence": sequence, "seed": seed, "overrides": overrides, **{c: t[c][0] for c in COLUMNS},
           "feature_px": float(np.nanmean(rec["feature_px"])), "lost": int(rec["lost"].sum()),
           "median_ms": float(np.median(rec["ms"]))}  # fmt: skip
    if not overrides:  # where the rotation error comes from (the default runs only)
        ests, true = rec["estimates"], rec["truth"]
        ok = ~rec["lost"]
        signed = rec["signed_errors"][ok, 3:]
        src = rotation_sources(seq.camera, np.array([e.features for e in ests])[ok],
                               np.array([model.shape(e.identity, e.expression) for e in ests])[ok], true["points"][ok],
                               true["shapes"][ok], true["rotations"][ok], true["translations"][ok])  # fmt: skip
        parts = {**error_parts(signed), **{k: np.nanmean(v, axis=0) for k, v in src.items()}}
        out["split"] = {k: v.tolist() for k, v in parts.items()}
    if identity is not None:
        n = len(rec["errors"])
        step = 5 if n >= 5 * config.keyframes else 1
        out["landmark_z"] = landmark_floor(model, [seq[k] for k in range(0, n, step)], seq.camera, config)["z_mm"]
    return out


def _seeds(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        try:
            a, b = int(lo), int(hi or lo)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected seeds like 0-5 or 0,3,7, got {text!r}") from None
        if a < 0 or b < a:
            raise argparse.ArgumentTypeError(f"expected seeds like 0-5 or 0,3,7, got {text!r}")
        out.extend(range(a, b + 1))
    return out


def _override(text: str) -> dict:
    """FIELD=VALUE -> {field: value}, checked against FaceConfig (VALUE a Python literal; true/false allowed)."""
    import dataclasses

    from gputrack.trackers.face import FaceConfig

    name, eq, value = text.partition("=")
    fields = {f.name for f in dataclasses.fields(FaceConfig)} - {"seed"}
    if not eq or name not in fields:
        raise argparse.ArgumentTypeError(f"expected FIELD=VALUE with FIELD one of {sorted(fields)}, got {text!r}")
    value = {"true": "True", "false": "False"}.get(value.lower(), value)
    try:
        v = ast.literal_eval(value)
    except (ValueError, SyntaxError):
        raise argparse.ArgumentTypeError(f"{name}: expected a number, bool or tuple, got {value!r}") from None
    try:
        dataclasses.replace(FaceConfig(), **{name: v})
    except (TypeError, ValueError) as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return {name: v}


def _run(spec, sequence, seed, overrides, frames) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--child", json.dumps([spec, sequence, seed, overrides, frames])]
    p = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if p.returncode != 0:
        raise RuntimeError(f"{sequence} seed {seed} {overrides}: the run failed:\n{p.stderr[-2000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def _means(rows) -> list[float]:
    return [float(np.mean([r[c] for r in rows])) for c in (*COLUMNS, "feature_px")]


def report(rows: list[dict], sequences, compare: dict | None, floor: bool = False, generic: bool = False,
           points: bool = False) -> str:  # fmt: skip
    variants = [("", {})] + (
        [("  with " + ",".join(f"{k}={v}" for k, v in compare.items()), compare)] if compare else []
    )
    variants += ([("  generic PCA", GENERIC)] if generic else []) + ([("  true identity", FLOOR)] if floor else [])
    variants += [("  true points", POINTS)] if points else []
    w = max(13, *(len(t) for t, _ in variants))
    head = f"{'sequence':<{w}} {'runs':>4} " + "".join(f"{c:>8}" for c in COLUMNS) + f"{'points px':>11}"
    lines = ["mean errors (x, y, z mm; roll, pitch, yaw deg; feature points after eq. 14, px from the truth)", head]
    groups = [(s, [s]) for s in sequences]
    if len(sequences) > 1:
        groups.append(("all", list(sequences)))
        if "mixed" in sequences and len(sequences) > 2:
            groups.append(("all but mixed", [s for s in sequences if s != "mixed"]))
    for name, seqs in groups:
        for tag, ov in variants:
            sel = [r for r in rows if r["sequence"] in seqs and r["overrides"] == ov]
            if sel:
                m = _means(sel)
                lines.append(f"{tag or name:<{w}} {len(sel):>4} "
                             + "".join(f"{v:8.2f}" for v in m[:6]) + f"{m[6]:11.2f}")  # fmt: skip
    lines.append(f"{'paper':<{w}} {'':>4} " + "".join(f"{v:8.2f}" for v in PAPER_TABLE1["paper: multilinear"]))
    if floor:
        lines.append("")
        lines.append("z (mm): the tracker's, the true identity's and perfect feature points' (the size unknown), "
                     "and the runs whose z is within 15 % of their perfect points'")  # fmt: skip
        for name, seqs in groups:
            base = {(r["sequence"], r["seed"]): r for r in rows if r["sequence"] in seqs and not r["overrides"]}
            fl = {(r["sequence"], r["seed"]): r for r in rows if r["sequence"] in seqs and r["overrides"] == FLOOR}
            keys = sorted(set(base) & set(fl))
            if keys:
                z, zt, zp = (np.mean([d[k][c] for k in keys]) for d, c in ((base, "z"), (fl, "z"), (fl, "landmark_z")))
                near = sum(base[k]["z"] <= 1.15 * fl[k]["landmark_z"] for k in keys)
                lines.append(f"{name:<{w}} {len(keys):>4}   tracker {z:6.2f}   true identity {zt:6.2f}   "
                             f"perfect points {zp:6.2f}   within 15 %: {near} of {len(keys)}")  # fmt: skip
    split = [r for r in rows if not r["overrides"] and "split" in r]
    if split:
        lines.append("")
        lines.append("where the rotation error comes from (roll, pitch, yaw deg; mean over the runs): the offset each run "
                     "holds, the part that changes slowly with the motion and the frame-to-frame jitter (error_parts); "
                     "the error of the pose fitted to the tracked points with the true shape (the points alone) and "
                     "to the true points with the estimated shape (the shape alone)")  # fmt: skip
        parts = ("offset", "slow", "jitter", "points", "shape")
        lines.append(f"{'sequence':<{w}} {'runs':>4} " + "".join(f"{p:>21}" for p in parts))
        for name, seqs in groups:
            sel = [r["split"] for r in split if r["sequence"] in seqs]
            if sel:
                cells = ("{:7.2f}{:7.2f}{:7.2f}".format(*np.mean([r[p] for r in sel], axis=0)) for p in parts)
                lines.append(f"{name:<{w}} {len(sel):>4} " + "".join(f"{c:>21}" for c in cells))
    if compare:
        lines.append("")
        lines.append("runs in which the default was better than " + ",".join(f"{k}={v}" for k, v in compare.items()))
        for name, seqs in groups:
            base = {(r["sequence"], r["seed"]): r for r in rows if r["sequence"] in seqs and not r["overrides"]}
            other = {(r["sequence"], r["seed"]): r for r in rows if r["sequence"] in seqs and r["overrides"] == compare}
            keys = sorted(set(base) & set(other))
            if keys:
                lines.append(f"{name:<{w}} {len(keys):>4} " + "".join(
                    f"{sum(base[k][c] < other[k][c] for k in keys):8d}" for c in (*COLUMNS, "feature_px")))  # fmt: skip
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("--child", help=argparse.SUPPRESS)
    p.add_argument("--device", default="taichi:cpu")
    p.add_argument("--sequence", action="append", choices=SEQUENCES, help="repeatable (default: all five)")
    p.add_argument("--seeds", type=_seeds, default=_seeds("0-2"), help="e.g. 0-5 or 0,3,7 (default 0-2)")
    p.add_argument("--compare", type=_override, action="append", help="FIELD=VALUE of FaceConfig (repeatable)")
    p.add_argument("--floor", action="store_true", help="also run every case with the person's true identity held")
    p.add_argument("--generic", action="store_true", help="also run every case with the generic PCA model")
    p.add_argument("--true-points", action="store_true",
                   help="also run every case with the true landmarks as the feature points (not eq. 14's)")
    p.add_argument("--frames", type=int, help="only each sequence's first FRAMES frames (default: all 300)")
    p.add_argument("--jobs", type=int, default=2, help="runs at a time (default 2)")
    p.add_argument("--json", help="write every run's figures to this file")
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(child(*json.loads(args.child))))
        return 0
    if args.jobs < 1:
        p.error(f"--jobs: expected at least 1, got {args.jobs}")
    if args.frames is not None and args.frames < 8:
        p.error(f"--frames: expected at least 8 (7 start frames and one tracked), got {args.frames}")
    sequences = tuple(args.sequence or SEQUENCES)
    compare = {k: v for d in args.compare or [] for k, v in d.items()} or None
    variants = (
        [{}] + ([compare] if compare else []) + ([GENERIC] if args.generic else []) + ([FLOOR] if args.floor else [])
        + ([POINTS] if args.true_points else [])
    )
    cases = [(args.device, s, seed, ov, args.frames) for seed in args.seeds for s in sequences for ov in variants]
    print(f"face_seeds: {len(cases)} runs on {args.device}, {args.jobs} at a time", flush=True)
    t0, rows = time.perf_counter(), []
    with ThreadPoolExecutor(args.jobs) as pool:
        for r in pool.map(lambda c: _run(*c), cases):
            rows.append(r)
            tag = " " + ",".join(f"{k}={v}" for k, v in r["overrides"].items()) if r["overrides"] else ""
            print(f"  [{len(rows):3d}/{len(cases)}] {r['sequence']:<11} seed {r['seed']}{tag}: z {r['z']:6.1f} mm, roll "
                  f"{r['roll']:.2f} pitch {r['pitch']:.2f} yaw {r['yaw']:.2f} deg ({time.perf_counter() - t0:.0f} s)",
                  flush=True)  # fmt: skip
    print()
    print(report(rows, sequences, compare, args.floor, args.generic, args.true_points))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": args.device, "runs": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())

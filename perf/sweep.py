#!/usr/bin/env python3
"""Scaling sweeps and the paper 000 Table 1/2 layout, per backend.

Sweeps (each point timed with the shared harness, gputrack/benchmarks/harness.py: warm-up excluded, device
synchronised, repeat count grown to --min-time, median and p10/p90, the NumPy reference in the same
run; each device in its own subprocess):

- ``K``: rgbd_cost of K = 100 .. 100 000 hypotheses (N = N' = 128, 640x480, paper 000 eq. 17-19),
  also end to end (upload of the transforms, download of the costs);
- ``N``: rgbd_cost of B = 1500 hypotheses, N = N' = 16 .. 4096 template points;
- ``T``: one fused Kalman predict+update (constant velocity, n = 6, m = 3) of T = 1e3 .. 1e6 tracks.

The NumPy reference is timed up to --reference-max-k (default 1000) and --reference-max-tracks
(default 1e5) only: above that one reference call takes seconds.

``--tables``: instead of the sweeps, run the body tracker (paper 000: PF 3 stages x K = 1500, LM 10
iterations, N = N' = 128, 640x480) on each device (numpy included), ``--frames`` frames after a
warm-up frame (which compiles the kernels) of simulated sequence 0, and print ms per frame
per stage, one column per device (the papers' Tables 1-2 layout; stages named as in
gputrack/trackers/body/tracker.py).

Usage::

    python perf/sweep.py [--device SPEC ...] [--sweep K,N,T] [--json FILE] [--plot FILE.png]
    python perf/sweep.py --tables [--device SPEC ...] [--frames 5] [--json FILE]

``--plot`` needs matplotlib (``pip install gputrack[plot]``); without it the plot is skipped
with a message and the rest still runs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

NAME = "sweep"
ROOT = Path(__file__).resolve().parent.parent
K_VALUES = (100, 300, 1000, 3000, 10_000, 30_000, 100_000)
N_VALUES = (16, 64, 256, 1024, 4096)
T_VALUES = (1_000, 10_000, 100_000, 1_000_000)
SWEEPS = ("K", "N", "T")


def add_arguments(parser):
    parser.add_argument("--sweep", default="K,N,T", help="which sweeps, comma-separated (default K,N,T)")
    parser.add_argument("--k", type=int, action="append", help=f"K values (repeatable; default {K_VALUES})")
    parser.add_argument("--n", type=int, action="append", help=f"N = N' values (repeatable; default {N_VALUES})")
    parser.add_argument("--t", type=int, action="append", help=f"T values (repeatable; default {T_VALUES})")
    parser.add_argument("--reference-max-k", type=int, default=1_000, help="largest K timed on NumPy too")
    parser.add_argument("--reference-max-tracks", type=int, default=100_000, help="largest T timed on NumPy too")
    parser.add_argument("--plot", metavar="FILE.png", help="plot time vs size per device (needs matplotlib)")


def _sweeps(args) -> list[str]:
    names = [s.strip().upper() for s in args.sweep.split(",") if s.strip()]
    bad = sorted(set(names) - set(SWEEPS))
    if bad:
        raise SystemExit(f"sweep.py: --sweep: expected some of {','.join(SWEEPS)}, got {','.join(bad)}")
    return names


def _scaled(tf, b, rng):
    """``b`` hypotheses from a particle-filter batch: repeated, with a few mm of fresh noise."""
    out = np.resize(tf, (b, *tf.shape[1:])).copy()
    out[..., :, 3] += rng.normal(0, 2, (b, tf.shape[1], 3)).astype(np.float32)
    return out


def _k_cases(device, args, ref, rng):
    """rgbd_cost of K hypotheses around 10 candidates, N = N' = 128 (its own scope: the lambdas
    below must not see the N sweep's templates)."""
    from gputrack.benchmarks.harness import Case
    from gputrack.ops.template import RgbdScene, rgbd_cost
    from gputrack.sim.problems import pf_scene

    tf0, rgb, dep, gray, depth, cam = pf_scene(rng, 1500, 128, 128)
    d_gray, d_depth = device.asarray(gray), device.asarray(depth)
    scene = RgbdScene(rgb, dep, cam).to(device)  # once per template, as a tracker does
    out = []
    for k in args.k or K_VALUES:
        tf = _scaled(tf0, k, rng)
        d_tf = device.asarray(tf)
        keep = rgbd_cost(device, d_tf, scene, d_gray, d_depth)

        def e2e(tf=tf):
            return device.to_numpy(rgbd_cost(device, tf, scene, d_gray, d_depth).total)

        out.append(
            Case(
                f"K: rgbd_cost K={k} N=N'=128",
                run=lambda d_tf=d_tf, keep=keep: rgbd_cost(device, d_tf, scene, d_gray, d_depth, out=keep),
                end_to_end=e2e,
                reference=(lambda tf=tf: rgbd_cost(ref, tf, scene, gray, depth))
                if k <= args.reference_max_k
                else None,
                params={"sweep": "K", "x": k, "K": k, "N": 128, "N'": 128, "J": 5, "H": 480, "W": 640},
            )
        )
    return out


def cases(device, args):
    """The sweep points on ``device`` (called in the device's subprocess by the harness)."""
    import gputrack
    from gputrack.benchmarks.harness import Case
    from gputrack.ops.kalman import kf_update, shared_matrix
    from gputrack.ops.template import RgbdScene, rgbd_cost
    from gputrack.sim.problems import kalman_tracks, pf_scene

    ref = gputrack.device("numpy")
    rng = np.random.default_rng(0)
    which = _sweeps(args)
    out = []
    if "K" in which:
        out += _k_cases(device, args, ref, rng)
    if "N" in which:
        for n in args.n or N_VALUES:
            tf, rgb, dep, gray, depth, cam = pf_scene(np.random.default_rng(n), 1500, n, n)
            d_tf, d_gray, d_depth = device.asarray(tf), device.asarray(gray), device.asarray(depth)
            scene = RgbdScene(rgb, dep, cam).to(device)  # once per template, as a tracker does
            keep = rgbd_cost(device, d_tf, scene, d_gray, d_depth)
            out.append(
                Case(
                    f"N: rgbd_cost K=1500 N=N'={n}",
                    run=lambda d_tf=d_tf, keep=keep, scene=scene, g=d_gray, d=d_depth: rgbd_cost(
                        device, d_tf, scene, g, d, out=keep
                    ),
                    reference=lambda tf=tf, scene=scene, gray=gray, depth=depth: rgbd_cost(
                        ref, tf, scene, gray, depth
                    ),
                    params={"sweep": "N", "x": n, "K": 1500, "N": n, "N'": n, "J": 5, "H": 480, "W": 640},
                )
            )
    if "T" in which:
        for t in args.t or T_VALUES:
            F, Q, H, R, x0, P0, z, _det = kalman_tracks(t, rng)
            Fs, Qs, Hs, Rs = (shared_matrix(device, a) for a in (F, Q, H, R))
            Fr, Qr, Hr, Rr = (shared_matrix(ref, a) for a in (F, Q, H, R))
            x, P, zd = device.asarray(x0), device.asarray(P0), device.asarray(z)
            st = device.empty((t,), np.uint8)
            xr, Pr, sr = x0.copy(), P0.copy(), np.empty(t, np.uint8)

            def step(x=x, P=P, zd=zd, st=st, Fs=Fs, Qs=Qs, Hs=Hs, Rs=Rs):
                return kf_update(device, x, P, zd, Hs, Rs, predict=(Fs, Qs), out=(x, P, st))

            def step_ref(xr=xr, Pr=Pr, z=z, sr=sr, Fr=Fr, Qr=Qr, Hr=Hr, Rr=Rr):
                return kf_update(ref, xr, Pr, z, Hr, Rr, predict=(Fr, Qr), out=(xr, Pr, sr))

            out.append(
                Case(
                    f"T: kf predict+update T={t}",
                    run=step,
                    reference=step_ref if t <= args.reference_max_tracks else None,
                    params={"sweep": "T", "x": t, "T": t, "n": 6, "m": 3},
                )
            )
    return out


# -- plot ---------------------------------------------------------------------------------------
AXES = {"K": "K (hypotheses, N = N' = 128)", "N": "N = N' (template points, K = 1500)", "T": "T (Kalman tracks)"}


def plot(doc: dict, path: str) -> bool:
    """Time vs size, one panel per sweep, one line per device (+ NumPy dashed). False without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print(f"sweep.py: matplotlib is not installed: skipping the plot {path} (pip install 'gputrack[plot]')",
              file=sys.stderr)  # fmt: skip
        return False
    rows = [r for run in doc["runs"] for r in run["results"]]
    sweeps = [s for s in SWEEPS if any(r["params"].get("sweep") == s for r in rows)]
    if not sweeps:
        print("sweep.py: nothing to plot", file=sys.stderr)
        return False
    fig, axes = plt.subplots(1, len(sweeps), figsize=(5.5 * len(sweeps), 4.2), squeeze=False)
    for ax, s in zip(axes[0], sweeps):
        mine = [r for r in rows if r["params"].get("sweep") == s]
        for spec in dict.fromkeys(r["spec"] for r in mine):
            pts = sorted((r["params"]["x"], r["device"]["median_ms"], r["device"]["p10_ms"], r["device"]["p90_ms"])
                         for r in mine if r["spec"] == spec)  # fmt: skip
            xs, med, lo, hi = (np.array(v) for v in zip(*pts))
            ax.errorbar(xs, med, yerr=[med - lo, hi - med], marker="o", capsize=2, label=spec)
        ref = {}
        for r in mine:
            if "reference" in r:
                ref.setdefault(r["params"]["x"], []).append(r["reference"]["median_ms"])
        if ref:
            xs = sorted(ref)
            ax.plot(xs, [np.median(ref[x]) for x in xs], "k--", marker="x", label="numpy (reference)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(AXES[s])
        ax.set_ylabel("ms per call (median, p10-p90)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"gputrack sweeps, commit {doc.get('commit', '?')}, {doc.get('date', '')[:10]}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"sweep.py: wrote {path}", file=sys.stderr)
    return True


# -- Tables 1/2 -----------------------------------------------------------------------------------
def tables_child(spec: str, frames: int, samples: int) -> dict:
    """Run the body tracker on ``spec``; per-stage figures of the frames after the first."""
    import gputrack
    from gputrack.benchmarks.harness import environment
    from gputrack.sim import sequence
    from gputrack.trackers.body import BodyTracker, BodyTrackerConfig

    dev = gputrack.device(spec)
    seq = sequence(0, frames=frames + 2, seed=0)  # the start pose, a warm-up frame, ``frames`` timed
    cfg = BodyTrackerConfig(lm_iterations=10, samples=samples)
    tracker = BodyTracker(dev, seq.params[0], config=cfg, profile=True)  # each stage's own time
    for i, f in enumerate(list(seq)[1:]):
        tracker.track(f.gray, f.depth)
        if i == 0:
            tracker.scheduler.reset()  # the first frame compiles the kernels
        print(f"{spec}: frame {f.index}", file=sys.stderr, flush=True)
    pipe = tracker.scheduler
    print(pipe.table(), file=sys.stderr, flush=True)
    return {
        **environment(dev),
        "config": {
            "K": cfg.samples,
            "stages": cfg.stages,
            "lm_iterations": cfg.lm_iterations,
            "N": cfg.n_rgb,
            "N'": cfg.n_depth,
            "template_every": cfg.template_every,
            "frames": len(pipe.frames),
        },
        "stages": pipe.report(),
        "frame_ms": [f.wall_s * 1e3 for f in pipe.frames],
    }


def format_tables(docs: list[dict]) -> str:
    """ms per frame per stage (rows) and device (columns), then the median frame."""
    specs = [d["device"]["spec"] for d in docs]
    names = list(dict.fromkeys(s["name"] for d in docs for s in d["stages"]))
    w = max(12, *(len(s) + 2 for s in specs))
    head = f"{'stage (ms per frame)':<24}" + "".join(f"{s:>{w}}" for s in specs)
    lines = [head, "-" * len(head)]
    for name in names:
        cells = []
        for d in docs:
            st = next((s for s in d["stages"] if s["name"] == name), None)
            cells.append(f"{st['total_ms'] / max(d['config']['frames'], 1):>{w}.3f}" if st else f"{'-':>{w}}")
        lines.append(f"{name:<24}" + "".join(cells))
    lines.append(f"{'frame (median)':<24}" + "".join(f"{np.median(d['frame_ms']):>{w}.3f}" for d in docs))
    return "\n".join(lines)


def tables_main(args) -> int:
    import gputrack

    specs = args.device or ["all"]
    if "all" in specs:
        specs = [d.spec for d in gputrack.devices() if d.available and not d.spec.startswith("opencl:")]
    docs, failed = [], []
    for spec in specs:
        print(f"[tables] {spec} ...", file=sys.stderr, flush=True)
        cmd = [sys.executable, str(Path(__file__).resolve()), "--tables-child", spec, "--frames", str(args.frames),
               "--samples", str(args.samples)]  # fmt: skip
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, check=False)
        line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("GPUTRACK_TABLES ")), None)
        if proc.returncode != 0 or line is None:
            failed.append(spec)
            print(f"[tables] {spec} failed (exit {proc.returncode})", file=sys.stderr)
            continue
        docs.append(json.loads(line.split(" ", 1)[1]))
    if docs:
        cfg = docs[0]["config"]
        n_depth = cfg["N'"]
        print(f"paper 000 Tables 1/2 layout: PF {cfg['stages']} stages x K={cfg['K']}, LM {cfg['lm_iterations']} "
              f"iterations, N={cfg['N']} N'={n_depth}, {cfg['frames']} frames after a warm-up frame; "
              f"commit {docs[0]['commit']}")  # fmt: skip
        print(format_tables(docs))
    if args.json:
        from gputrack.benchmarks.harness import environment

        text = json.dumps({"schema": "gputrack-tables/1", **environment(), "runs": docs}, indent=2)
        if args.json == "-":
            print(text)
        else:
            Path(args.json).write_text(text + "\n")
    return 1 if failed else 0


# -- command line -----------------------------------------------------------------------------------
def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    pre.add_argument("--tables", action="store_true")
    pre.add_argument("--tables-child")
    pre.add_argument("--frames", type=int, default=5)
    pre.add_argument("--samples", type=int, default=1500)
    pre.add_argument("--device", action="append")
    pre.add_argument("--json")
    pre.add_argument("--plot")
    pre.add_argument("--child")
    known, _ = pre.parse_known_args(argv)
    if known.tables_child:
        doc = tables_child(known.tables_child, known.frames, known.samples)
        sys.stdout.write("GPUTRACK_TABLES " + json.dumps(doc) + "\n")
        return 0
    if known.tables:
        return tables_main(known)
    if known.child:
        from gputrack.benchmarks.harness import bench_main

        return bench_main(sys.modules[__name__], argv)
    # the parent: the harness runs each device in a subprocess (python -m perf.sweep --child SPEC)
    from gputrack.benchmarks.harness import _strip_options, bench_main

    # the children start as ``python -m perf.sweep`` in the repository root (where perf/ is)
    for opt in ("--json", "--plot"):
        value = getattr(known, opt[2:])
        if value and value != "-":
            argv = _strip_options(argv, {opt}) + [opt, str(Path(value).resolve())]
    known = pre.parse_known_args(argv)[0]
    os.chdir(ROOT)
    json_path, tmp = known.json, None
    if known.plot and (not json_path or json_path == "-"):
        with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as tmp:
            pass
        argv = _strip_options(argv, {"--json"}) + ["--json", tmp.name]
    try:
        status = bench_main(_importable(), argv)
        if known.plot:
            path = tmp.name if tmp else json_path
            if Path(path).is_file() and Path(path).stat().st_size:
                if tmp and json_path == "-":
                    print(Path(path).read_text())
                plot(json.loads(Path(path).read_text()), known.plot)
    finally:
        if tmp:
            os.unlink(tmp.name)
    return status


def _importable():
    """This file as the module ``perf.sweep`` (the harness starts ``python -m perf.sweep`` per device)."""
    import importlib

    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    paths = os.environ.get("PYTHONPATH", "")
    if str(ROOT) not in paths.split(os.pathsep):
        os.environ["PYTHONPATH"] = str(ROOT) + (os.pathsep + paths if paths else "")
    return importlib.import_module("perf.sweep")


if __name__ == "__main__":
    sys.exit(main())

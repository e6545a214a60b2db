"""Paper 000's body tracker, per frame: PF 3 stages (K = 1500) with and without LM 10, N = N' = 128, 640x480.

The template is rendered once (``template_every`` large) so that the figure is the device work of
a steady-state frame: upload of the frame, the particle filter and the LM. Rendering and picking
the template on the host is timed as its own case ("template (host)").
"""

import sys

from ..benchmark import Case, bench_main

NAME = "body"


def add_arguments(parser):
    parser.add_argument("--sequence", type=int, default=0, help="simulated sequence (default 0)")
    parser.add_argument("--samples", type=int, default=1500, help="K, samples per PF stage (default 1500)")


def cases(device, args):
    import gputrack
    from ..sim import sequence
    from ..trackers.body import BodyTracker, TrackerConfig
    from ..trackers.body_template import sparse_template

    seq = sequence(args.sequence, frames=3, seed=0)
    frame = seq[1]
    reference = gputrack.device("numpy")
    out = []
    for lm in (0, 10):
        cfg = TrackerConfig(lm_iterations=lm, samples=args.samples, template_every=10**9)
        tracker = BodyTracker(device, seq.params[0], config=cfg)
        ref = BodyTracker(reference, seq.params[0], config=cfg)
        label = "PF 3 stages" + (f" + LM {lm}" if lm else "")
        out.append(
            Case(
                f"body frame, {label}",
                run=lambda t=tracker: t.track(frame.gray, frame.depth),
                reference=lambda t=ref: t.track(frame.gray, frame.depth),
                params={"K": args.samples, "N": 128, "N_depth": 128, "stages": 3, "lm": lm, "cascade": cfg.cascade,
                        "width": 640, "height": 480},  # fmt: skip
            )
        )
    out.append(
        Case(
            "template (host render + pick)",
            run=lambda: sparse_template(seq.chain, seq.params[0], 128, 128),
            params={"N": 128, "N_depth": 128},
        )
    )
    return out


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

"""Paper 000's body tracker, per frame: PF 3 stages (K = 1500) with and without LM 10, N = N' = 128, 640x480.

The frame as the tracker runs it by default (``profile=False``: no device waits between the stages;
the demo's stage table is made with them): the template rendered and picked at the previous
estimate on the device every frame (``template_every=1``), the particle filter and the LM; and the
same frame with the template kept (``template_every`` large: the upload of the frame, the particle
filter and the LM only). The template alone (``model_template``: render + pick on the device) is
its own case. One particle-filter stage (``pf_stage``: sample, pose, score, best 10) is timed for
the torso group (every part moves) and for the right-arm group of the cascade (the torso and left
arm do not move), inputs on the device.
"""

import sys

from .harness import Case, bench_main

NAME = "body"


def add_arguments(parser):
    parser.add_argument("--sequence", type=int, default=0, help="simulated sequence (default 0)")
    parser.add_argument("--samples", type=int, default=1500, help="K, samples per PF stage (default 1500)")
    parser.add_argument("--lm", type=int, default=10, help="LM iterations of the PF + LM frame (default 10)")
    parser.add_argument("--points", type=int, default=128, help="N = N' template points (default 128)")


def cases(device, args):
    from ..registry import device as get_device
    from ..sim import sequence
    from ..trackers.body import BodyTracker, BodyTrackerConfig
    from ..ops.model_template import model_template
    from ..trackers.body.template import sparse_template

    seq = sequence(args.sequence, frames=3, seed=0)
    frame = seq[1]
    reference = get_device("numpy")
    out = []
    n = args.points
    for lm, every in ((0, 1), (args.lm, 1), (args.lm, 10**9)):
        cfg = BodyTrackerConfig(lm_iterations=lm, samples=args.samples, template_every=every, n_rgb=n, n_depth=n)
        tracker = BodyTracker(device, seq.params[0], config=cfg)  # as deployed: no waits to time the stages
        ref = BodyTracker(reference, seq.params[0], config=cfg)
        label = "PF 3 stages" + (f" + LM {lm}" if lm else "") + (", template kept" if every > 1 else "")
        out.append(
            Case(
                f"body frame, {label}",
                run=lambda t=tracker: t.track(frame.gray, frame.depth),
                reference=lambda t=ref: t.track(frame.gray, frame.depth),
                params={"K": args.samples, "N": n, "N_depth": n, "stages": 3, "lm": lm, "cascade": cfg.cascade,
                        "template_every": every, "width": 640, "height": 480},  # fmt: skip
            )
        )
    from ..models.upper_body import pf_sigma
    from ..ops.pf import pf_stage
    from ..ops.template import RgbdScene

    rgb, dep = sparse_template(seq.chain, seq.params[0], n, n)
    scene = RgbdScene(rgb, dep, tracker.camera).to(device)  # once per template, as the tracker does
    cand = tracker.candidates.astype("float32")
    g, d = device.asarray(frame.gray), device.asarray(frame.depth)
    d_cand = device.asarray(cand)
    for name, group in zip(("torso", "right arm"), tracker._groups()):
        sigma = (pf_sigma(seq.chain) * group).astype("float32")
        out.append(
            Case(
                f"pf_stage {name} group K={args.samples}",
                run=lambda s=sigma: pf_stage(device, seq.chain, d_cand, s, args.samples, 7, scene, g, d),
                reference=lambda s=sigma: pf_stage(reference, seq.chain, cand, s, args.samples, 7, scene,
                                                   frame.gray, frame.depth),  # fmt: skip
                params={"K": args.samples, "C": 10, "N": n, "N_depth": n, "group": name},
            )
        )
    out.append(
        Case(
            "template (render + pick)",
            run=lambda: model_template(device, seq.chain, seq.params[0], n=n, n_depth=n),
            reference=lambda: model_template(reference, seq.chain, seq.params[0], n=n, n_depth=n),
            params={"N": n, "N_depth": n},
        )
    )
    return out


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

"""Sparse-template cost/residuals and NCC patches on a particle-filter-like batch.

The scene: a 640x480 gray + depth frame (depth in mm) of a body-sized surface about 2 m away;
templates of N = N' = 128 points on 5 parts; B = 1500 hypotheses spread around 10 candidate
poses (paper 000 Table 4 sized noise: a few mm, a few degrees), so that neighbouring hypotheses
read neighbouring pixels as in a real filter stage. Also: residuals for the batched LM
(B = 280 and 400 perturbed poses) and the NCC of paper 003 (B = 1000, K = 10, 16x16).
"""

import sys

import numpy as np

from .harness import Case, bench_main
from ..sim.problems import pf_scene

NAME = "template"


def add_arguments(parser):
    parser.add_argument("--batch", type=int, default=1500, help="hypotheses per rgbd_cost call (default 1500)")
    parser.add_argument("--points", type=int, default=128, help="N = N' template points (default 128)")
    parser.add_argument("--lm-batch", type=int, action="append",
                        help="B of the rgbd_residuals cases (repeatable; default 280 and 400)")  # fmt: skip
    parser.add_argument("--ncc-batch", type=int, default=1000, help="hypotheses of the patch_ncc case (default 1000)")


def cases(device, args):
    from ..registry import device as get_device
    from ..ops.particles import best_k, sample_around
    from ..ops.ncc import patch_ncc
    from ..ops.template import RgbdScene, rgbd_cost, rgbd_residuals

    ref = get_device("numpy")
    rng = np.random.default_rng(0)
    b, n = args.batch, args.points
    tf, rgb, dep, gray, depth, cam = pf_scene(rng, b, n, n)
    d_tf, d_gray, d_depth = device.asarray(tf), device.asarray(gray), device.asarray(depth)
    scene = RgbdScene(rgb, dep, cam).to(device)  # once per template, as a tracker does
    params = {"B": b, "N": n, "N'": n, "J": 5, "H": 480, "W": 640, "candidates": 10}

    def e2e_cost():
        out = rgbd_cost(device, tf, scene, d_gray, d_depth)
        return device.to_numpy(out.total)

    keep = rgbd_cost(device, d_tf, scene, d_gray, d_depth)  # result buffers reused with out=
    out = [
        Case(
            f"rgbd_cost B={b} N=N'={n} 640x480",
            run=lambda: rgbd_cost(device, d_tf, scene, d_gray, d_depth),
            reference=lambda: rgbd_cost(ref, tf, scene, gray, depth),
            end_to_end=e2e_cost,
            params=params,
        ),
        Case(
            f"rgbd_cost out= B={b} N=N'={n} 640x480",
            run=lambda: rgbd_cost(device, d_tf, scene, d_gray, d_depth, out=keep),
            reference=lambda: rgbd_cost(ref, tf, scene, gray, depth),
            params={**params, "out": True},
        ),
    ]
    for lm_b in args.lm_batch or (280, 400):
        if lm_b > b:
            raise SystemExit(f"--lm-batch: expected at most --batch={b} hypotheses, got {lm_b}")
        d_lm = device.asarray(tf[:lm_b])
        res = rgbd_residuals(device, d_lm, scene, d_gray, d_depth)
        out.append(
            Case(
                f"rgbd_residuals out= B={lm_b} N=N'={n}",
                run=lambda d_lm=d_lm, res=res: rgbd_residuals(device, d_lm, scene, d_gray, d_depth, out=res),
                reference=lambda lm_b=lm_b: rgbd_residuals(ref, tf[:lm_b], scene, gray, depth),
                params={**params, "B": lm_b, "out": True},
            )
        )
    # NCC (paper 003): 1000 hypotheses x 10 points x 16x16 templates
    k, s, nb = 10, 16, args.ncc_batch
    centres = rng.uniform([40, 40], [600, 440], (k, 2))
    pts = (centres[None] + rng.normal(0, 3, (nb, k, 2))).astype(np.float32)
    tpl = np.stack([gray[int(v) - 8 : int(v) + 8, int(u) - 8 : int(u) + 8] for u, v in centres]).astype(np.float32)
    d_pts, d_tpl = device.asarray(pts), device.asarray(tpl)
    out.append(
        Case(
            f"patch_ncc B={nb} K={k} S={s} 640x480",
            run=lambda: patch_ncc(device, d_pts, d_tpl, d_gray),
            reference=lambda: patch_ncc(ref, pts, tpl, gray),
            params={"B": nb, "K": k, "S": s},
        )
    )
    # particle helpers of one filter stage
    cand = rng.normal(size=(10, 14)).astype(np.float32)
    sigma = np.full(14, 0.05, np.float32)
    d_cand, d_sigma = device.asarray(cand), device.asarray(sigma)
    scores = rng.random(b).astype(np.float32)
    d_scores = device.asarray(scores)
    samples = sample_around(ref, cand, sigma, b, 1)
    d_samples = device.asarray(samples)
    out.append(
        Case(
            f"sample_around C=10 P=14 K={b}",
            run=lambda: sample_around(device, d_cand, d_sigma, b, 7),
            reference=lambda: sample_around(ref, cand, sigma, b, 7),
            params={"C": 10, "P": 14, "K": b},
        )
    )
    kk = min(10, b)
    out.append(
        Case(
            f"best_k k={kk} of B={b} with rows",
            run=lambda: best_k(device, d_scores, kk, rows=d_samples),
            reference=lambda: best_k(ref, scores, kk, rows=samples),
            params={"B": b, "k": kk, "P": 14},
        )
    )
    return out


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

"""Sparse-template cost/residuals and NCC patches on a particle-filter-like batch.

The scene: a 640x480 gray + depth frame (depth in mm) of a body-sized surface about 2 m away;
templates of N = N' = 128 points on 5 parts; B = 1500 hypotheses spread around 10 candidate
poses (paper 000 Table 4 sized noise: a few mm, a few degrees), so that neighbouring hypotheses
read neighbouring pixels as in a real filter stage. Also: residuals for the batched LM
(B = 280 and 400 perturbed poses) and the NCC of paper 003 (B = 1000, K = 10, 16x16).
"""

import sys

import numpy as np

from ..benchmark import Case, bench_main
from ..models.chain import rotation_zyx

NAME = "template"


def add_arguments(parser):
    parser.add_argument("--batch", type=int, default=1500, help="hypotheses per rgbd_cost call (default 1500)")
    parser.add_argument("--points", type=int, default=128, help="N = N' template points (default 128)")


def _rot(a):
    """Rz(a[2]) Ry(a[1]) Rx(a[0])."""
    return rotation_zyx(a[2], a[1], a[0])


def pf_scene(rng, b=1500, n=128, m=128, *, parts=5, candidates=10, h=480, w=640):
    """(transforms (B, J, 3, 4), rgb template, depth template, gray, depth, camera)."""
    from ..ops.template import Camera, SparseTemplate

    cam = Camera(525.0, 525.0, 319.5, 239.5)
    # part frames (camera-from-part) of a person 2 m away: torso, two upper arms, two forearms
    base = np.array([[0, 0, 2000], [-250, -150, 2000], [250, -150, 2000], [-450, -150, 1950], [450, -150, 1950]], float)
    size = np.array([[200, 300], [110, 60], [110, 60], [110, 50], [110, 50]], float)  # half extents (mm)

    def points(k):
        part = rng.integers(0, parts, k)
        xyz = np.column_stack(
            [rng.uniform(-1, 1, k) * size[part, 0], rng.uniform(-1, 1, k) * size[part, 1], rng.uniform(-20, 0, k)]
        )
        return xyz, part

    xyz, part = points(n)
    rgb = SparseTemplate(xyz, part, rng.uniform(30, 220, n))
    xyz, part = points(m)
    dep = SparseTemplate(xyz, part)
    cand = np.zeros((candidates, parts, 3, 4))
    for c in range(candidates):
        for j in range(parts):
            cand[c, j, :, :3] = _rot(rng.normal(0, np.radians(3), 3))
            cand[c, j, :, 3] = base[j] + rng.normal(0, 10, 3)
    owner = np.arange(b) * candidates // b  # the samples of a candidate are consecutive
    tf = cand[owner].copy()
    for k in range(b):
        for j in range(parts):
            tf[k, j, :, :3] = _rot(rng.normal(0, np.radians([1, 3, 1]))) @ tf[k, j, :, :3]
    tf[..., :, 3] += rng.normal(0, 5, (b, parts, 3))
    yy, xx = np.mgrid[0:h, 0:w]
    gray = 110 + 60 * np.sin(xx / 6.0) * np.cos(yy / 8.0) + rng.normal(0, 3, (h, w))
    depth = np.full((h, w), 3000.0) + rng.normal(0, 2, (h, w))
    body = (np.abs(xx - 320) < 180) & (yy > 60) & (yy < 420)
    depth[body] = 2000 + 5 * np.sin(xx[body] / 11.0)
    depth = np.round(depth / 5) * 5  # Kinect-like 5 mm steps
    depth[rng.random((h, w)) < 0.01] = 0  # dropouts
    return tf.astype(np.float32), rgb, dep, gray.astype(np.float32), depth.astype(np.float32), cam


def cases(device, args):
    from ..registry import device as get_device
    from ..ops.particles import best_k, sample_around
    from ..ops.template import patch_ncc, rgbd_cost, rgbd_residuals

    ref = get_device("numpy")
    rng = np.random.default_rng(0)
    b, n = args.batch, args.points
    tf, rgb, dep, gray, depth, cam = pf_scene(rng, b, n, n)
    d_tf, d_gray, d_depth = device.asarray(tf), device.asarray(gray), device.asarray(depth)
    rgb.to(device)
    dep.to(device)
    params = {"B": b, "N": n, "N'": n, "J": 5, "H": 480, "W": 640, "candidates": 10}

    def e2e_cost():
        out = rgbd_cost(device, tf, rgb, dep, d_gray, d_depth, cam)
        return device.to_numpy(out.total)

    keep = rgbd_cost(device, d_tf, rgb, dep, d_gray, d_depth, cam)  # result buffers reused with out=
    out = [
        Case(
            f"rgbd_cost B={b} N=N'={n} 640x480",
            run=lambda: rgbd_cost(device, d_tf, rgb, dep, d_gray, d_depth, cam),
            reference=lambda: rgbd_cost(ref, tf, rgb, dep, gray, depth, cam),
            end_to_end=e2e_cost,
            params=params,
        ),
        Case(
            f"rgbd_cost out= B={b} N=N'={n} 640x480",
            run=lambda: rgbd_cost(device, d_tf, rgb, dep, d_gray, d_depth, cam, out=keep),
            reference=lambda: rgbd_cost(ref, tf, rgb, dep, gray, depth, cam),
            params={**params, "out": True},
        ),
    ]
    for lm_b in (280, 400):
        d_lm = device.asarray(tf[:lm_b])
        res = rgbd_residuals(device, d_lm, rgb, dep, d_gray, d_depth, cam)
        out.append(
            Case(
                f"rgbd_residuals out= B={lm_b} N=N'={n}",
                run=lambda d_lm=d_lm, res=res: rgbd_residuals(device, d_lm, rgb, dep, d_gray, d_depth, cam, out=res),
                reference=lambda lm_b=lm_b: rgbd_residuals(ref, tf[:lm_b], rgb, dep, gray, depth, cam),
                params={**params, "B": lm_b, "out": True},
            )
        )
    # NCC (paper 003): 1000 hypotheses x 10 points x 16x16 templates
    k, s, nb = 10, 16, 1000
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
    out.append(
        Case(
            f"best_k k=10 of B={b} with rows",
            run=lambda: best_k(device, d_scores, 10, rows=d_samples),
            reference=lambda: best_k(ref, scores, 10, rows=samples),
            params={"B": b, "k": 10, "P": 14},
        )
    )
    return out


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

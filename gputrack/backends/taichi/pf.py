"""Taichi: one particle-filter stage (gputrack/ops/pf.py) as one kernel launch.

The kernel runs its tasks in order (Taichi finishes one before the next): evaluate each candidate
once to cache its parts (re-use mode of template.py, one serial task; the parts a stage does not
move are then read from the cache); then one parallel loop over groups of samples, each group
drawing its samples (eq. 12, the generator of gputrack/ops/particles.py), posing every part (eq.
1-11) and scoring them (eq. 17-19, the kernel body of template.py); then select the best k (one
serial task). A parallel
loop's dispatch costs ~60 us on a CPU, so sampling has no loop of its own. Scratch arrays are
kept per device; only the k rows, scores and indices are new.

A stage that moves every part (the cascade's torso group) caches the candidates too and reads
nothing of it: one compiled kernel for every stage instead of two (a warm process's first body
frame loaded ``_pf_stage`` in 1.09-1.54 s as two variants, 0.69-1.25 s as one; the torso group's
stage 2.55 / 2.44 -> 1.73 / 2.17 ms in ``perf/bench_body.py``, two noisy rounds; 2026-12-06).
"""

import numpy as np

from ...models.chain import chain_tables
from ...uploads import constant
from .kinematics import pose_f32
from .launch import launch
from .particles import best_k_body, sample_key, sample_one
from .runtime import scratch, ti
from .tasks import cpu_chunks
from .template import (
    F1,
    F2,
    F4,
    I1,
    REUSE_PF,
    _rgbd_body,
    _source_cache,
    cam_array,
    default_params,
)  # fmt: skip

U1 = ti.types.ndarray(dtype=ti.u32, ndim=1)


@ti.kernel
def _pf_stage(
    cand: F2, sig: F1, seed: U1, samples: F2, offsets: F2, tf: F4, rpts: F2, ridx: I1, dpts: F2,
    didx: I1, gray: F2, dimg: F2, cam: F1, work: F2, moved: I1, cache: F2,
    total: F1, eps_c: F1, eps_d: F1, idx: I1, val: F1, keys: U1, sel: F2,
    rparts: ti.template(), dparts: ti.template(), groups: ti.template(), L: ti.template(), chunks: ti.template(),
    chain: ti.template(),
):  # fmt: skip
    pose = ti.static((_sample_pose, (cand, sig, seed, samples, offsets, tf, chain)))  # each group's lanes first
    _source_cache(tf, rpts, ridx, rparts, dpts, didx, dparts, gray, dimg, cam, cache, chunks > 0, 0, L, pose)
    _rgbd_body(tf, rpts, ridx, rparts, dpts, didx, dparts, gray, dimg, cam, work, total, eps_c, eps_d, total,
               groups, False, L, chunks, REUSE_PF, moved, cache, moved, moved, 0, pose)  # fmt: skip
    best_k_body(total, idx, val, keys, samples, sel, True)


@ti.func
def _sample_pose(args: ti.template(), b):
    """Sample b (eq. 12, keep_candidates) and its transforms (eq. 1-11)."""
    cand, sig, seed, samples, offsets, tf, chain = ti.static(args)
    sample_one(cand, sig, samples, sample_key(seed[0], seed[1]), b, 1, False)
    pose_f32(samples, b, chain, offsets, tf)


def pf_stage(device, chain, cand, sig, n, lo, hi, rgb, depth, gray, dimg, camera, moved_parts, k, out, *,
             lam, c_rgb, c_depth, depth_tol):  # fmt: skip
    C, P = cand.shape
    J = chain.n_parts
    nl = int(default_params(device)["lanes"])
    groups = (n + nl - 1) // nl
    nr = rgb["pts"].shape[0]
    _, offsets = chain_tables(device, chain, np.float32)
    moved = constant(device, moved_parts.astype(np.int32))
    idx, val, sel = out
    arrays = (
        cand.buffer, sig.buffer, np.array([lo, hi], np.uint32), scratch(device, "pf_samples", (n, P), ti.f32),
        offsets.buffer, scratch(device, "pf_tf", (n, J, 3, 4), ti.f32), rgb["pts"].buffer,
        rgb["index"].buffer, depth["pts"].buffer, depth["index"].buffer, gray.buffer, dimg.buffer,
        cam_array(camera, lam, c_rgb, c_depth, depth_tol), scratch(device, "rgbd", (groups, 2 * nr * nl), ti.f32),
        moved.buffer,
        scratch(device, "rgbd_cache", (C, 2 * nr + 4 * J), ti.f32), scratch(device, "pf_total", (n,), ti.f32),
        scratch(device, "pf_eps_c", (n,), ti.f32), scratch(device, "pf_eps_d", (n,), ti.f32), idx.buffer,
        val.buffer, scratch(device, "keys", (k,), ti.u32), sel.buffer,
    )  # fmt: skip
    consts = (rgb["parts"], depth["parts"], groups, nl, cpu_chunks(device), chain.structure())
    launch(_pf_stage, arrays, consts, scalarize=False, ir_passes=False)
    return idx, val, sel

"""One particle-filter stage of paper 000 on the device: sample, pose, score, keep the best.

:func:`pf_stage` is the composition

    samples = sample_around(device, candidates, sigma, n, seed, keep_candidates=True)   # eq. 12
    scores = rgbd_cost(device, forward_kinematics(device, chain, samples), scene, ...).total  # eq. 17-19
    best = best_k(device, scores, k, rows=samples)

as one op, so that a backend can run it without a wait or an allocation. The numpy backend runs
the composition itself. Taichi fuses it into one kernel (a Taichi launch costs 0.03-0.2 ms on a
CPU, and a filter makes 9 stages a frame); OpenCL launches its steps in order into arrays kept
per device (a launch costs microseconds). Both add a partial evaluation that gives the same
scores to float rounding: the parts that no sampled parameter moves (sigma = 0 for every
parameter they depend on, e.g. the torso and the left arm while the right arm is sampled in
cascade order, eq. 13-16) look the same in every sample of a candidate, so their template
points are projected once per candidate instead of once per sample; the samples then re-use
those intensities (eq. 17's alpha and beta still run over all valid points) and that depth sum.
"""

from __future__ import annotations

import numpy as np

from ..device import DeviceArray, as_host_array
from ..models.chain import Chain
from ..uploads import constant
from . import backend_module
from ._args import arg, check_device
from .kinematics import forward_kinematics
from .particles import BestK, _seed, best_k, best_k_out, sample_around
from .template import frame_args, rgbd_cost

__all__ = ["pf_stage"]


def pf_stage(
    device, chain, candidates, sigma, n, seed, scene, gray, depth_image, *, k=None, out=None
) -> BestK:
    """Draw ``n`` samples around the candidates, score them with eq. 17-19, keep the best ``k``.

    chain: the :class:`gputrack.models.Chain` the parameters pose; candidates: (C, P) float32
    (NumPy or on the device), P = chain.n_params; sigma: (P,) standard deviations >= 0, a NumPy
    array (the host decides from it which parts move); n: samples (>= C; sample j belongs to
    candidate j C // n, and the first sample of each block is the candidate itself); seed: an
    integer in [0, 2**64), a new one per call; scene (a :class:`gputrack.RgbdScene` whose templates'
    parts index the chain's parts), gray, depth_image: as in :func:`gputrack.ops.template.rgbd_cost`;
    k: how many to keep (default C).

    Returns :class:`gputrack.ops.particles.BestK`: ``rows`` (k, P) float32, the next candidates,
    ``scores`` (k,) their costs (eq. 19) ascending, ``indices`` (k,) their sample indices.
    ``out``: a BestK on the device (e.g. the result of an earlier stage of the same sizes, not the
    one whose rows are ``candidates``) to write into instead of allocating.
    """
    check_device(device)
    if not isinstance(chain, Chain):
        raise TypeError(f"chain: expected a gputrack.models.Chain, got {type(chain).__name__}")
    dims = {"P": chain.n_params}
    cand = arg(device, candidates, "candidates", ("C", "P"), dims)
    if dims["C"] == 0:
        raise ValueError("candidates: expected at least one candidate, got C = 0")
    if isinstance(sigma, DeviceArray):
        raise TypeError("sigma: expected a NumPy array (it decides on the host which parts move), got a DeviceArray")
    sig = as_host_array(sigma, "sigma")
    if sig.dtype.kind not in "iuf" or sig.shape != (dims["P"],):
        raise ValueError(f"sigma: expected a real (P={dims['P']},) array, got {sig.dtype.name} {sig.shape}")
    if not np.isfinite(sig).all() or (sig < 0).any():
        raise ValueError(f"sigma: expected finite standard deviations >= 0, got {sig}")
    sig = np.ascontiguousarray(sig, np.float32)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise TypeError(f"n: expected an integer number of samples, got {type(n).__name__}")
    if not dims["C"] <= int(n) < 2**31 // (dims["P"] + dims["C"] + 1):
        raise ValueError(f"n: expected C={dims['C']} <= n and n (P + C + 1) < 2**31, got {n}")
    k = dims["C"] if k is None else k
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= int(k) <= int(n):
        raise ValueError(f"k: expected an integer in [1, n={n}], got {k!r}")
    fused = device.backend in ("taichi", "opencl")
    outs = best_k_out(device, out, int(k), dims["P"], cand) if fused or out is not None else None  # checks out
    lo, hi = _seed(seed)
    g, d = frame_args(device, scene, gray, depth_image, chain.n_parts)
    if fused:
        moved = chain.dependency_mask()[:, sig != 0].any(axis=1)  # parts that a sampled parameter poses
        rgb, dep, cam, p = scene.kernel_args(device)
        idx, val, rows = backend_module(device, "pf").pf_stage(
            device, chain, cand, constant(device, sig), int(n), lo, hi, rgb, dep, g, d, cam, moved, int(k), outs, **p
        )
        return BestK(idx, val, rows)
    samples = sample_around(device, cand, constant(device, sig), int(n), seed, keep_candidates=True)
    cost = rgbd_cost(device, forward_kinematics(device, chain, samples), scene, g, d)
    return best_k(device, cost.total, int(k), rows=samples, out=out)

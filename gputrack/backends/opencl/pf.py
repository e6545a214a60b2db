"""OpenCL: one particle-filter stage (gputrack/ops/pf.py), launched without a wait or an allocation.

Sample (eq. 12) and pose (eq. 1-11) into arrays kept per device, score (eq. 17-19) with
template.py's re-use when some parts do not move (a cascade stage, eq. 13-16: the template points
of the parts no sampled parameter moves are projected once per candidate by a first launch
instead of once per sample), and select the best k into the caller's arrays: four or five
launches in order on the device's queue (an OpenCL launch costs microseconds here, so the steps
stay separate kernels).
"""

from __future__ import annotations

import numpy as np

from ...device import per_device
from ...uploads import constant
from . import kinematics, particles, template

@per_device(maxsize=16)
def _array(device, name, shape):
    """A float32 device array kept per device, name and shape (the stages of a filter differ in
    size: a few shapes per name are kept)."""
    return device.empty(shape, np.float32)


def pf_stage(device, chain, cand, sig, n, lo, hi, rgb, depth, gray, dimg, camera, moved_parts, k, out, **consts):
    """``consts``: lam, c_rgb, c_depth, depth_tol (gputrack/ops/pf.py)."""
    C, P = cand.shape
    samples = particles.sample_around(device, cand, sig, n, lo, hi, per_candidate=False, keep_candidates=True,
                                      out=_array(device, "samples", (n, P)))  # fmt: skip
    tf = kinematics.forward_kinematics(device, chain, samples, _array(device, "tf", (n, chain.n_parts, 3, 4)))
    scores = tuple(_array(device, name, (n,)) for name in ("total", "eps_c", "eps_d"))
    reuse = None
    if not moved_parts.all():  # some parts look in every sample as in its candidate
        reuse = (constant(device, moved_parts.astype(np.int32)).buffer.data, C)
    # the stage launches with the default parameters (the tuned choice is measured on rgbd_cost alone)
    params = template.default_params(device)
    template.rgbd_cost(device, tf, rgb, depth, gray, dimg, camera, *scores, **consts, params=params, reuse=reuse)
    particles.best_k(device, scores[0], k, samples, out)
    return out

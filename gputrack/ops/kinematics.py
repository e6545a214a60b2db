"""Forward kinematics of an articulated chain for a batch of parameter vectors (paper 000, eq. 2-11).

``forward_kinematics(device, chain, params)`` -> (B, J, 3, 4) camera-from-part rigid transforms
[R | t] (the chain's root joint is camera-from-root, e.g. camera-from-torso D of eq. 4-6; a child
is camera-from-parent @ parent-from-child, eq. 2-3). One kernel launch per call; the chain is
given by two small tables (see :meth:`gputrack.models.Chain.packed`) uploaded once per device,
chain and dtype and cached (Taichi compiles the structure into its kernel and reads only the
offsets), so the kernels work for any chain, not only the upper body.

For fused kernels (sample + kinematics + score in one launch) the per-pose code is reusable:
OpenCL ``#include "gt_kinematics.clh"`` -> ``gt_fk_pose(p, table, offsets, out, J)`` with the
tables of :func:`gputrack.models.chain.chain_tables` (built with :func:`gputrack.abi.cl_defines`,
as ``Device.program`` builds); Taichi
``gputrack.backends.taichi.kinematics.pose_f32`` / ``pose_f64`` (``ti.func``) with the chain's
structure as a compile-time value (``chain.structure()``, the parts unrolled) and the offsets
of :func:`gputrack.models.chain.chain_tables`.
"""

from __future__ import annotations

import numpy as np

from ..models.chain import Chain
from . import backend_module
from ._args import FLOAT, arg, check_device, out_array

__all__ = ["forward_kinematics"]


def forward_kinematics(device, chain: Chain, params, *, out=None):
    """Camera-from-part transforms for a batch of poses.

    device: a gputrack Device. chain: a :class:`gputrack.models.Chain` with J parts and P
    parameters. params: (B, P) float32 or float64 (B >= 1; float64 only on a device with fp64),
    NumPy or on ``device``. Returns (B, J, 3, 4) of the params' dtype on ``device``:
    rows [R | t] with R a rotation and t in the chain's length unit (mm for the upper body).
    ``out``: an existing (B, J, 3, 4) array of that dtype on ``device`` to write into (saves
    the allocation in a loop); it is returned. Finite angles beyond ``gputrack.abi.ANGLE_MAX``
    (2**15 rad) are clamped to it on every backend (non-finite ones give non-finite transforms).
    """
    device = check_device(device)
    if not isinstance(chain, Chain):
        raise TypeError(f"chain: expected a gputrack.models.Chain, got {type(chain).__name__}")
    params = arg(device, params, "params", ("B", chain.n_params), dtype=FLOAT)
    if params.shape[0] == 0:
        raise ValueError(f"params: expected at least one parameter vector (B >= 1), got shape {tuple(params.shape)}")
    shape = (params.shape[0], chain.n_parts, 3, 4)
    out = out_array(device, out, "out", shape, params.dtype)
    return backend_module(device, "kinematics").forward_kinematics(device, chain, params, out)

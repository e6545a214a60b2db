"""RGB-D template residuals of a kinematic chain's parameter vectors, for the LM (paper 000 sec. 3.4).

:func:`pose_residuals` is the composition

    rgbd_residuals(device, forward_kinematics(device, chain, params), scene, ...)   # eq. 1-11, 20-21

as one op, so that a backend can run it as one launch: the residual function of a
:func:`gputrack.least_squares` fit of the chain to an RGB-D frame. With ``central=True`` it also
evaluates the block-sparse Jacobian of paper 000 Fig. 2 sparsely: in the stacked central-difference
points of ``least_squares`` (2P + 1 rows per problem: its point, then the point with parameter n
moved by +eps_n and -eps_n, eq. 24), a row of parameter n only needs the residuals of the points
whose part depends on n (its own joint's and its ancestors', ``chain.jacobian_sparsity``); the
other parts look as at the problem's point. Taichi evaluates each problem's point once for their
sums (eq. 17's alpha and beta run over every valid point), groups rows that move the same parts,
and projects and writes only those parts: for the upper body about half of the work of the full
stack (14 parameters: 57 %, 20: 48 % of the points). OpenCL runs the composition with the same
plan (kernels/gt_template.cl REUSE=3: forward kinematics, a launch caching the problems' points,
one computing the groups' residuals); the numpy backend runs the composition (every entry).
"""

from __future__ import annotations

import weakref

import numpy as np

from ..device import per_device_cache
from ..models.chain import Chain, chain_tables
from ..uploads import constant
from . import backend_module
from ._args import arg, check_device, out_array
from .kinematics import forward_kinematics
from .template import frame_args, rgbd_residuals

__all__ = ["pose_residuals"]


def pose_residuals(device, chain, params, scene, gray, depth_image, *, central=False, out=None):
    """Residuals of eq. 20-21 for n parameter vectors of ``chain``: (n, N + N') float32.

    chain: a :class:`gputrack.models.Chain`; params: (n, P) float32 (NumPy or on the device),
    P = chain.n_params; scene (a :class:`gputrack.RgbdScene`), gray, depth_image: as in
    :func:`gputrack.ops.template.rgbd_residuals` (the templates' parts index the chain's parts).
    ``out``: an (n, N + N') float32 array on the device to write into.

    ``central=True`` (a hint): ``params`` is the central-difference stack of
    :func:`gputrack.least_squares` (n a multiple of 2P + 1). In the rows of parameter n, only the
    residuals of points whose part depends on n are computed (``chain.jacobian_sparsity(parts)``
    of the templates' points, RGB then depth); the other entries of those rows are left undefined,
    which is what ``least_squares(..., jac_sparsity=chain.jacobian_sparsity(parts))`` reads. The
    problems' own rows are computed in full, and every computed entry equals the full evaluation
    to float rounding. A row that differs from its problem's point in more than its parameter
    (another layout) is computed in full, and so is every row when n is not a multiple of 2P + 1
    (a solve's last step evaluates its points only; on Taichi the stack's kernel does it).
    """
    check_device(device)
    if not isinstance(chain, Chain):
        raise TypeError(f"chain: expected a gputrack.models.Chain, got {type(chain).__name__}")
    P = chain.n_params
    params = arg(device, params, "params", ("n", P))
    n = params.shape[0]
    if n == 0:
        raise ValueError(f"params: expected at least one parameter vector (n >= 1), got shape {tuple(params.shape)}")
    g, d = frame_args(device, scene, gray, depth_image, chain.n_parts)
    out = out_array(device, out, "out", (n, scene.n))
    stride = 2 * P + 1
    stack = central and n % stride == 0  # a central-difference stack: the plan of Fig. 2
    if device.backend == "opencl" and stack:  # the composition, its residuals by the plan
        tf = forward_kinematics(device, chain, params)
        rgb, dep, cam, p = scene.kernel_args(device)
        be = backend_module(device, "template")
        plan = _device_plan(device, chain, n // stride, be.residual_lanes(device, tf, rgb, dep))
        be.rgbd_residuals(device, tf, rgb, dep, g, d, cam, out, plan=plan, **p)
        return out
    if device.backend != "taichi":
        return rgbd_residuals(device, forward_kinematics(device, chain, params), scene, g, d, out=out)
    be = backend_module(device, "pose_residuals")
    plan = None
    if stack:
        plan = _device_plan(device, chain, n // stride, be.lanes(device))
    elif central:  # the points of a solve's last step: every part of every row, by the same kernel
        plan = _full_plan(device, chain, n, be.lanes(device))
    _, offsets = chain_tables(device, chain, np.float32)
    rgb, dep, cam, p = scene.kernel_args(device)
    return be.pose_residuals(device, chain, params, offsets, rgb, dep, g, d, cam, out, plan, **p)


_PLANS: weakref.WeakKeyDictionary = per_device_cache()  # device -> {(chain, B, lanes): plan}


def _device_plan(device, chain: Chain, problems: int, lanes: int):
    """(stride, order, moved) of :func:`_plan` on ``device``, built and uploaded once per chain,
    number of problems and lanes (a solve calls the op every iteration)."""
    return _uploaded(device, (chain.key(), problems, lanes), chain, lambda: _plan(chain, problems, lanes))


def _full_plan(device, chain: Chain, n: int, lanes: int):
    """A plan that evaluates every part of the n rows (any layout), for a ``central=True`` call
    whose rows are not a central-difference stack (a solve's last step evaluates its points only):
    Taichi then runs the stack's kernel instead of compiling a second one (its first call costs a
    warm process ~0.4 s). Kept as :func:`_device_plan`'s."""

    def build():
        groups = -(-n // lanes)
        order = np.minimum(np.arange(groups * lanes), n - 1).astype(np.int32)  # the last row pads
        return order, np.ones((groups, chain.n_parts), np.int32)

    return _uploaded(device, (chain.key(), "full", n, lanes), chain, build)


def _uploaded(device, key, chain: Chain, build):
    """The plan of ``key`` on ``device``: (2P + 1, order, moved) with ``build()``'s (order, moved)
    uploaded the first time."""
    per_device = _PLANS.setdefault(device, {})
    if key not in per_device:
        order, moved = build()
        per_device[key] = (2 * chain.n_params + 1, constant(device, order), constant(device, moved))
    return per_device[key]


def _plan(chain: Chain, problems: int, lanes: int) -> tuple[np.ndarray, np.ndarray]:
    """(order (G L,) int32, moved (G, J) int32) for ``problems`` central-difference blocks: the rows
    that move the same parts (a problem's point: all of them; parameter n's two rows: the parts that
    depend on n, Fig. 2) in consecutive groups of ``lanes`` (a class padded with its last row), and
    each group's parts."""
    P, J = chain.n_params, chain.n_parts
    S = 2 * P + 1
    moves = np.ones((S, J), bool)
    moves[1:] = np.repeat(chain.dependency_mask().T, 2, axis=0)
    order, moved = [], []
    for pattern in np.unique(moves, axis=0)[::-1]:  # every part first
        s = np.flatnonzero((moves == pattern).all(axis=1))
        rows = (np.arange(problems)[:, None] * S + s[None, :]).ravel()
        rows = np.concatenate([rows, np.repeat(rows[-1], -len(rows) % lanes)])
        order.append(rows)
        moved.append(np.repeat(pattern[None].astype(np.int32), len(rows) // lanes, axis=0))
    return np.concatenate(order).astype(np.int32), np.concatenate(moved)

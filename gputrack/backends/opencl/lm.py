"""OpenCL launchers for the batched Levenberg-Marquardt (kernels/gt_lm.cl).

One launch per op call (``lm_solve`` fuses the normal equations and the Cholesky step in one
work-group per problem) and one per solver iteration (``gt_lm_update``, one work-group per problem).
"""

from __future__ import annotations

import numpy as np

from ...abi import LMLayout, LMStatus
from ...device import per_device

RUNNING = int(LMStatus.RUNNING)
_CTYPE = {"float32": "float", "float64": "double"}


def _program(device, real, rtype=None, xtype=None, jtype=None, use_jac=False, x0type=None):
    rtype = rtype or real
    xtype = xtype or real
    jtype = jtype or rtype
    x0type = x0type or real
    defines = {
        "REAL": _CTYPE[np.dtype(real).name],
        "RTYPE": _CTYPE[np.dtype(rtype).name],
        "XTYPE": _CTYPE[np.dtype(xtype).name],
        "JTYPE": _CTYPE[np.dtype(jtype).name],
        "X0TYPE": _CTYPE[np.dtype(x0type).name],
    }
    for key, dt in (
        ("REAL_IS_DOUBLE", real),
        ("RTYPE_IS_DOUBLE", rtype),
        ("XTYPE_IS_DOUBLE", xtype),
        ("JTYPE_IS_DOUBLE", jtype),
        ("X0TYPE_IS_DOUBLE", x0type),
    ):
        if np.dtype(dt) == np.float64:
            defines[key] = 1
    if use_jac:
        defines["USE_JAC"] = 1
    return device.program("gt_lm.cl", defines)


@per_device
def _kernel(device, prg, name):
    """One cl.Kernel per program and name (retrieving ``prg.name`` builds a new one each time)."""
    import pyopencl as cl

    return cl.Kernel(prg, name)


def _local_size(device, P):
    """Work-items per problem: enough to share out the P (P + 1) / 2 entries of J^T J."""
    want = 64 if P > 4 else 8
    return int(max(1, min(want, device.info.max_work_group_size or want)))


@per_device(maxsize=8)
def _work(device, shape, dtype):
    """A work array of ``shape`` and ``dtype`` kept per device (contents undefined between calls)."""
    return device.empty(shape, dtype)


def normal_equations(device, J, r, out):
    B, M, P = J.shape
    JtJ, Jtr = out
    prg = _program(device, J.dtype)
    n = B * P
    _kernel(device, prg, "gt_normal_equations")(
        device.queue,
        (n,),
        None,
        J.buffer.data,
        r.buffer.data,
        JtJ.buffer.data,
        Jtr.buffer.data,
        np.int32(B),
        np.int32(M),
        np.int32(P),
    )
    return JtJ, Jtr


def lm_step(device, JtJ, Jtr, damping, out):
    B, P = Jtr.shape
    delta, ok = out
    W = _work(device, (B, P, P), Jtr.dtype)
    prg = _program(device, Jtr.dtype)
    _kernel(device, prg, "gt_lm_step")(
        device.queue,
        (B,),
        None,
        JtJ.buffer.data,
        Jtr.buffer.data,
        damping.buffer.data,
        delta.buffer.data,
        ok.buffer.data,
        W.buffer.data,
        np.int32(B),
        np.int32(P),
    )
    return delta, ok


def lm_solve(device, J, r, damping, out):
    B, M, P = J.shape
    delta, ok = out
    W = _work(device, (B, P, P), J.dtype)
    prg = _program(device, J.dtype)
    ls = _local_size(device, P)
    _kernel(device, prg, "gt_lm_solve")(
        device.queue,
        (B * ls,),
        (ls,),
        J.buffer.data,
        r.buffer.data,
        damping.buffer.data,
        delta.buffer.data,
        ok.buffer.data,
        W.buffer.data,
        np.int32(M),
        np.int32(P),
    )
    return delta, ok


class State:
    """Arrays of one solve (gputrack.ops.lm.Layout); W is set by ``solver_workspace``."""

    def __init__(self, device, lay, S, I, Out):
        self.device, self.lay, self.S, self.I, self.Out = device, lay, S, I, Out
        self.W = None
        self.ls = _local_size(device, lay.P)


def upload_into(device, arr, host):
    """Copy ``host`` into the existing device array ``arr`` (same shape and dtype); the caller counts it."""
    arr.buffer.set(host, queue=device.queue)


def solver_state(device, lay, S, I, Out):
    return State(device, lay, S, I, Out)


def solver_workspace(state, lay, W):
    state.lay, state.W = lay, W


def solver_init(state, X0, K, X):
    dev, lay = state.device, state.lay
    B = lay.B
    prg = _program(dev, state.S.dtype, None, X.dtype, None, x0type=X0.dtype)
    _kernel(dev, prg, "gt_lm_init")(
        dev.queue,
        (B,),
        None,
        X0.buffer.data,
        K.buffer.data,
        state.S.buffer.data,
        state.I.buffer.data,
        X.buffer.data,
        np.int32(B),
        np.int32(lay.P),
        np.int32(X.shape[0] // B),
        np.int32(K.shape[0] - lay.kglob),
    )


def solver_update(state, R, X, *, first, final, jac=None):
    dev, lay = state.device, state.lay
    B = lay.B
    prg = _program(
        dev,
        state.S.dtype,
        R.dtype,
        X.dtype,
        jac.dtype if jac is not None else None,
        use_jac=jac is not None,
    )
    Jg = jac if jac is not None else R
    _kernel(dev, prg, "gt_lm_update")(
        dev.queue,
        (B * state.ls,),
        (state.ls,),
        state.S.buffer.data,
        state.I.buffer.data,
        state.W.buffer.data,
        X.buffer.data,
        R.buffer.data,
        Jg.buffer.data,
        state.Out.buffer.data,
        np.int32(R.shape[1]),
        np.int32(R.shape[0] // B),
        np.int32(X.shape[0] // B),
        np.int32(bool(first)),
        np.int32(bool(final)),
    )


def solver_active(state) -> int:
    I = state.I.numpy()
    return int(np.count_nonzero(state.lay.iblock(I)[:, LMLayout.I_STATUS] == RUNNING))


def solver_result(state):
    return state.Out.numpy()

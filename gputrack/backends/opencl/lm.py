"""OpenCL launchers for the batched Levenberg-Marquardt (kernels/gt_lm.cl).

One launch per op call (``lm_solve`` fuses the normal equations and the Cholesky step in one
work-group per problem) and one per solver iteration (``gt_lm_update``, one work-group per problem;
on GPUs its step shared out over the work-group: :func:`step_per_work_group`).
"""

from __future__ import annotations

import os
import time

import numpy as np

from ...abi import LMLayout, LMStatus
from ...device import per_device
from .program import enqueue, ndrange

RUNNING = int(LMStatus.RUNNING)
_CTYPE = {"float32": "float", "float64": "double"}


#: the largest P built as a compile-time value for the solver's Jacobian-callable variant (``LM_P``)
STATIC_P_MAX = 32
#: seconds the host polls a kernel whose points it reads next before it blocks (``_wait``)
SPIN_S = 200e-6
_yield = getattr(os, "sched_yield", lambda: None)


#: work-items per problem on GPUs where P > STATIC_P_MAX: the work-group's step updates the
#: (P - j)^2 / 2 entries of the trailing triangle at column j (P = 92: 4186 at the first)
GPU_GROUP_LARGE_P = 256


def step_per_work_group(device) -> bool:
    """Whether each iteration's step (damped Cholesky, triangular solves, predicted reduction) is
    shared out over the problem's work-group (``LM_WG_STEP``: GPUs, where one work-item's O(P^3)
    factorisation left the group idle, 2.7 ms a launch for P = 92 on an H100) rather than run by its
    first work-item (CPU devices, where a work-group is one thread's loop over its work-items)."""
    return device.info.kind != "cpu"


def _program(device, real, rtype=None, xtype=None, jtype=None, use_jac=False, x0type=None, P=0, wg_step=False):
    rtype = rtype or real
    xtype = xtype or real
    jtype = jtype or rtype
    x0type = x0type or real
    if not (use_jac and 0 < P <= STATIC_P_MAX):
        P = 0  # one program for every P where P is not built in
    return _built(device, *(np.dtype(t) for t in (real, rtype, xtype, jtype, x0type)), bool(use_jac), P, bool(wg_step))


@per_device
def _built(device, real, rtype, xtype, jtype, x0type, use_jac, P, wg_step):
    """The program of :func:`_program`'s variant, built once per device and variant (building its
    defines and looking it up took 50-150 us a call on a loaded 2-core machine, every solve)."""
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
    if wg_step:
        defines["LM_WG_STEP"] = 1
    if use_jac:
        defines["USE_JAC"] = 1
        if P:
            defines["LM_P"] = P
    return device.program("gt_lm.cl", defines)


@per_device
def _kernel(device, prg, name):
    """One cl.Kernel per program and name (retrieving ``prg.name`` builds a new one each time)."""
    import pyopencl as cl

    return cl.Kernel(prg, name)


def _local_size(device, P):
    """Work-items per problem: enough to share out the P (P + 1) / 2 entries of J^T J."""
    want = 64 if P > 4 else 8
    if P > STATIC_P_MAX and step_per_work_group(device):
        want = GPU_GROUP_LARGE_P
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
    enqueue(
        device,
        _kernel(device, prg, "gt_normal_equations"),
        *ndrange(n),
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
    enqueue(
        device,
        _kernel(device, prg, "gt_lm_step"),
        *ndrange(B),
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
    enqueue(
        device,
        _kernel(device, prg, "gt_lm_solve"),
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
        # the Jacobian-callable variant (P built in): a work-item per block of four rows of J^T J
        self.ls_jac = min(self.ls, (lay.P + 3) // 4)
        self.kernels = {}  # (residual, points, Jacobian dtypes) -> the update kernel
        self.x0type = None  # the start points' dtype (solver_init): the update's program has it too
        self.stage = {}  # role -> a buffer over a host callable's last result, or its copy in shared memory
        self.tags = {}  # id -> (shared array, its cl.SVM kernel argument)


def upload_into(device, arr, host, asynchronous=False):
    """Copy ``host`` into the existing device array ``arr`` (same shape and dtype); the caller counts
    it. ``asynchronous``: enqueued without waiting (the caller keeps ``host`` until a blocking
    download of the same in-order queue)."""
    import pyopencl as cl

    buf = arr.buffer
    cl.enqueue_copy(device.queue, buf.base_data, host, dst_offset=buf.offset, is_blocking=not asynchronous)


def download_into(device, arr, host):
    """Copy the device array ``arr`` into the NumPy array ``host`` (same shape and dtype), waiting for
    it; the caller counts it."""
    import pyopencl as cl

    buf = arr.buffer
    cl.enqueue_copy(device.queue, host, buf.base_data, src_offset=buf.offset, is_blocking=True)


def reads_host(device) -> bool:
    """Whether the solver's host callables get their points in place: on a device that shares the
    host's memory through fine-grained SVM (PoCL on a CPU), the points are NumPy arrays in shared
    virtual memory (:func:`shared_empty`) that the kernels write, and the kernels read the callables'
    results in place (:func:`_arg`). An iteration is then one command and one wait, against four
    commands (two uploads, the launch, the download of the points), each a hand-off to PoCL's worker
    threads. Elsewhere (a discrete GPU) the arrays are copied."""
    return _fine_svm(device)


@per_device
def _fine_svm(device) -> bool:
    import pyopencl as cl

    d = device.cl_device
    try:
        caps = d.svm_capabilities
    except (cl.Error, AttributeError):  # an OpenCL 1.2 device
        return False
    return bool(d.host_unified_memory) and bool(caps & cl.device_svm_capabilities.FINE_GRAIN_BUFFER)


def shared_empty(device, shape, dtype):
    """A NumPy array in fine-grained shared virtual memory (:func:`reads_host` devices): the host
    and the kernels use the same bytes, consistent at the launches and the waits."""
    import pyopencl as cl

    flags = cl.svm_mem_flags.READ_WRITE | cl.svm_mem_flags.SVM_FINE_GRAIN_BUFFER
    return cl.svm_empty(device.context, flags, shape, dtype, alignment=128)


def _arg(state, a, role):
    """What a kernel takes for an array of the solver: a DeviceArray's buffer; a NumPy array in
    shared memory as itself; any other NumPy array (a callable's result, read by the kernel) as a
    buffer over its own memory (``CL_MEM_USE_HOST_PTR``: on a device that shares the host's memory
    the kernel reads it in place, ~2 us where copying the exp fit's 410 KB Jacobian into shared
    memory took 12-31 us; held until the next call of ``role``, the update waiting for its kernel),
    or, where such a buffer cannot be made (a read-only array), copied into the shared array of
    ``role``. The points ("X", written by the kernel) must be in shared memory."""
    import pyopencl as cl

    if not isinstance(a, np.ndarray):
        return a.buffer.data
    if not isinstance(a.base, cl.SVMAllocation):
        if role == "X":
            raise TypeError("points: expected an array of the solver's shared memory (shared_empty), got a NumPy array")
        if a.flags.writeable:
            mf = cl.mem_flags
            buf = state.stage[role] = cl.Buffer(state.device.context, mf.READ_ONLY | mf.USE_HOST_PTR, hostbuf=a)
            return buf
        stage = state.stage.get(role)
        if not isinstance(stage, np.ndarray) or stage.shape != a.shape or stage.dtype != a.dtype:
            stage = state.stage[role] = shared_empty(state.device, a.shape, a.dtype)
        np.copyto(stage, a)
        a = stage
    tag = state.tags.get(id(a))
    if tag is None or tag[0] is not a:
        tag = state.tags[id(a)] = (a, cl.SVM(a))
    return tag[1]


def solver_state(device, lay, S, I, Out):
    return State(device, lay, S, I, Out)


def solver_workspace(state, lay, W):
    state.lay, state.W = lay, W


def solver_init(state, X0, K, X):
    dev, lay = state.device, state.lay
    B = lay.B
    # the program the update kernel will most likely take (residuals of the points' dtype, this X0):
    # the init kernel reads neither R nor J, and one program is one build (~0.4 s on PoCL)
    state.x0type = X0.dtype
    prg = _program(dev, state.S.dtype, X.dtype, X.dtype, None, x0type=X0.dtype)
    event = enqueue(
        dev,
        _kernel(dev, prg, "gt_lm_init"),
        *ndrange(B),
        X0.buffer.data,
        K.buffer.data,
        state.S.buffer.data,
        state.I.buffer.data,
        _arg(state, X, "X"),
        np.int32(B),
        np.int32(lay.P),
        np.int32(X.shape[0] // B),
        np.int32(K.shape[0] - lay.kglob),
    )
    if isinstance(X, np.ndarray):  # the host reads the points next
        _wait(dev, event)


def _update_kernel(state, rtype, xtype, jtype):
    """The update kernel of a variant, kept on the solve's state (building the defines and looking the
    program up took ~50-150 us a call on a loaded 2-core machine)."""
    key = (rtype, xtype, jtype)
    k = state.kernels.get(key)
    if k is None:
        prg = _program(state.device, state.S.dtype, rtype, xtype, jtype, use_jac=jtype is not None, P=state.lay.P,
                       x0type=state.x0type, wg_step=step_per_work_group(state.device))  # fmt: skip
        k = state.kernels[key] = _kernel(state.device, prg, "gt_lm_update")
    return k


def _wait(device, event) -> None:
    """Wait for the kernel (init or update) whose points the host reads next: its event polled for
    up to SPIN_S seconds, then a blocking wait. The host's callables run right after it; a blocking
    wait for a ~0.1 ms kernel put the host thread to sleep and woke it with colder caches, often on
    the other core. The exp fit's whole solve on PoCL, polled with a yield between polls, in two
    interleaved runs: 7.08 -> 6.39 ms and 5.55 -> 4.73 ms (perf/README.md). A longer kernel costs
    the poll at most SPIN_S of one core."""
    import pyopencl as cl

    complete = cl.command_execution_status.COMPLETE
    end = time.perf_counter() + SPIN_S
    while event.command_execution_status > complete and time.perf_counter() < end:
        _yield()  # a worker sharing this core runs first
    device.queue.finish()


def solver_update(state, R, X, *, first, final, jac=None):
    dev, lay = state.device, state.lay
    B = lay.B
    kernel = _update_kernel(state, R.dtype, X.dtype, jac.dtype if jac is not None else None)
    ls = state.ls if jac is None or lay.P > STATIC_P_MAX else state.ls_jac
    r_arg = _arg(state, R, "R")  # also the Jacobian's argument without one (unused)
    event = enqueue(
        dev,
        kernel,
        (B * ls,),
        (ls,),
        state.S.buffer.data,
        state.I.buffer.data,
        state.W.buffer.data,
        _arg(state, X, "X"),
        r_arg,
        _arg(state, jac, "J") if jac is not None else r_arg,
        state.Out.buffer.data,
        np.int32(R.shape[1]),
        np.int32(R.shape[0] // B),
        np.int32(X.shape[0] // B),
        np.int32(bool(first)),
        np.int32(bool(final)),
    )
    if isinstance(X, np.ndarray):  # the host reads the points next
        _wait(dev, event)


def solver_active(state) -> int:
    I = state.I.numpy()
    return int(np.count_nonzero(state.lay.iblock(I)[:, LMLayout.I_STATUS] == RUNNING))


def solver_result(state):
    return state.Out.numpy()

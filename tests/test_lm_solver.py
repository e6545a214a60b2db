"""gputrack.LeastSquaresSolver: the solver object, scale-invariant damping against scipy's MINPACK on
badly scaled problems (parameters from 1e-6 to 1e3, far starts), every backend vs the NumPy reference."""

import numpy as np
import pytest
import scipy.optimize
from tolerances import assert_matches

import gputrack
from gputrack.ops.lm import Layout, LeastSquaresSolver, least_squares
from gputrack.ops.lm import LMStatus as Status

REF = gputrack.device("numpy")
TOL = {"ftol": 1e-12, "xtol": 1e-12, "gtol": 1e-12}


def _host(f):
    """f on the host in float64, for points given as NumPy or DeviceArray (overflow at a far trial point
    gives inf or NaN residuals, which the solver rejects: no warning)."""

    def call(X):
        with np.errstate(all="ignore"):
            return f(gputrack.to_numpy(X).astype(np.float64))

    return call


def _synthetic(f, x, true):
    """Data from f at ``true`` with a deterministic 1 % ripple (the fit's cost is not 0)."""
    y = f(np.asarray(true, float)[None], x)[0]
    return y + 0.01 * np.abs(y).mean() * np.sin(1.7 * np.arange(x.size))


def _rat43(X, x):  # y = b1 / (1 + exp(b2 - b3 x))^(1 / b4): a sigmoid, NIST's Rat43 model
    b1, b2, b3, b4 = (X[:, i : i + 1] for i in range(4))
    return b1 / (1 + np.exp(b2 - b3 * x)) ** (1 / b4)


def _rat43_jac(X, x):
    b1, b2, b3, b4 = (X[:, i : i + 1] for i in range(4))
    e = np.exp(b2 - b3 * x)
    q = 1 + e
    f = b1 / q ** (1 / b4)
    return np.stack([f / b1, -f / b4 * e / q, f / b4 * x * e / q, f * np.log(q) / b4**2], axis=2)


def _gauss(X, x):  # y = (b1 / b2) exp(-((x - b3) / b2)^2 / 2): NIST's Eckerle4 model
    b1, b2, b3 = (X[:, i : i + 1] for i in range(3))
    return b1 / b2 * np.exp(-0.5 * ((x - b3) / b2) ** 2)


def _gauss_jac(X, x):
    b1, b2, b3 = (X[:, i : i + 1] for i in range(3))
    f, u = _gauss(X, x), (x - b3) / b2
    return np.stack([f / b1, f * (u**2 - 1) / b2, f * u / b2], axis=2)


def _rational(X, x):  # cubic over cubic: NIST's Thurber model
    b = [X[:, i : i + 1] for i in range(7)]
    return (b[0] + b[1] * x + b[2] * x**2 + b[3] * x**3) / (1 + b[4] * x + b[5] * x**2 + b[6] * x**3)


def _rational_jac(X, x):
    b = [X[:, i : i + 1] for i in range(7)]
    n = b[0] + b[1] * x + b[2] * x**2 + b[3] * x**3
    d = 1 + b[4] * x + b[5] * x**2 + b[6] * x**3
    one = np.ones_like(n)
    return np.stack([one / d, x / d, x**2 / d, x**3 / d, -n * x / d**2, -n * x**2 / d**2, -n * x**3 / d**2], axis=2)


def _problem(name, f, jf, x, true, x0, scale):
    """(name, residuals, jacobian, x0) of the fit of f to synthetic data, its parameters multiplied by
    ``scale`` (the solver sees p = z * scale: parameters from 1e-6 to 1e3)."""
    y, s = _synthetic(f, x, true), np.asarray(scale, float)
    return (name, lambda X: f(X / s, x) - y, lambda X: jf(X / s, x) / s, np.asarray(x0, float) * s)


RAT43 = (_rat43, _rat43_jac, np.arange(1.0, 16.0), [699.6, 5.277, 0.7596, 1.279], [100, 10, 1, 1])
GAUSS = (_gauss, _gauss_jac, np.arange(400.0, 500.1, 2.5), [1.5544, 4.0888, 451.54], [1, 10, 500])
RATIONAL = (_rational, _rational_jac, np.linspace(-3.07, 2.2, 37),
            [1288.14, 1491.08, 583.238, 75.4167, 0.966295, 0.397973, 0.0497273], [1000, 1000, 400, 40, 0.7, 0.3, 0.03])  # fmt: skip
BADLY_SCALED = [
    _problem("sigmoid", *RAT43, [1, 1e-3, 1e-6, 1]),  # 7e2 .. 7.6e-7, started 7x / 1.3x / 1.9x / 1.3x off
    _problem("gauss", *GAUSS, [1e-6, 1, 1]),  # 1.6e-6 .. 4.5e2, the peak 2.5x too wide, 48 off centre
    _problem("rational", *RATIONAL, [1, 1, 1, 1, 1, 1, 1e-4]),  # 1.3e3 .. 5e-6
]


def _minpack(r, j, x0):
    out = scipy.optimize.least_squares(lambda p: r(p[None])[0], x0, jac=lambda p: j(p[None])[0], method="lm",
                                       max_nfev=400, **TOL)  # fmt: skip
    return 2 * out.cost, out.x


@pytest.mark.parametrize("case", BADLY_SCALED, ids=[c[0] for c in BADLY_SCALED])
def test_minpack_damping_matches_scipy_minpack_where_the_identity_fails(device, case):
    """With the same tolerances, damping_scale='minpack' reaches MINPACK's (scipy, method='lm') minimum
    on every badly scaled problem; C I stops far from it on the first two. The full protocol runs on the
    fast local devices; taichi:vulkan runs the same kernels in test_scaled_modes_match_the_reference."""
    if device.spec == "taichi:vulkan":
        pytest.skip("many iterations of one small problem; the same kernels are pinned to the reference below")
    name, r, j, x0 = case
    F_scipy, x_scipy = _minpack(r, j, x0)
    runs = {}
    for mode in ("minpack", "identity"):
        runs[mode] = least_squares(_host(r), x0[None], device=device, jacobian=_host(j), damping_scale=mode,
                                   max_iter=100, **TOL)  # fmt: skip
    got = runs["minpack"]
    assert got.status[0] == Status.CONVERGED, got.messages()
    np.testing.assert_allclose(got.cost[0], F_scipy, rtol=1e-7)
    np.testing.assert_allclose(got.x[0], x_scipy, rtol=1e-4)
    if name in ("sigmoid", "gauss"):
        assert runs["identity"].cost[0] > 1.5 * F_scipy, runs["identity"].messages()


def test_minpack_damping_is_invariant_to_the_parameters_scale(device):
    """The same fit with its parameters in other units takes the same steps (damping_scale='minpack'),
    while C I takes others."""
    if device.spec == "taichi:vulkan":
        pytest.skip("many iterations of one small problem (the kernels are pinned to the reference below)")
    unit = _problem("sigmoid", *RAT43, [1, 1, 1, 1])
    scaled = BADLY_SCALED[0]
    s = np.array([1, 1e-3, 1e-6, 1])
    out = {}
    for mode in ("minpack", "identity"):
        a, b = (least_squares(_host(c[1]), c[3][None], device=device, jacobian=_host(c[2]), damping_scale=mode,
                              max_iter=40, **TOL) for c in (unit, scaled))  # fmt: skip
        out[mode] = (a, b)
    a, b = out["minpack"]
    assert a.iterations[0] == b.iterations[0]
    np.testing.assert_allclose(b.x[0] / s, a.x[0], rtol=1e-6)
    a, b = out["identity"]
    assert a.iterations[0] != b.iterations[0] or not np.allclose(b.x[0] / s, a.x[0], rtol=1e-3)


@pytest.mark.parametrize("mode", ["marquardt", "minpack"])
def test_scaled_modes_match_the_reference(device, mode):
    """Short runs of the scaled modes (central differences with absolute steps per parameter, and a
    Jacobian callable) on every backend against the NumPy reference, B = 3 problems at once."""
    name, r, j, x0 = BADLY_SCALED[2]
    X0 = x0 * np.array([[1.0] * 7, [1.1, 0.9, 1.0, 1.05, 1.0, 0.95, 1.0], [0.9, 1.1, 1.0, 1.0, 1.02, 1.0, 1.1]])
    step = 1e-6 * np.abs(x0)
    for kw in ({"step": step}, {"jacobian": _host(j)}):
        got = least_squares(_host(r), X0, device=device, damping_scale=mode, max_iter=8, **kw)
        want = least_squares(_host(r), X0, device=REF, damping_scale=mode, max_iter=8, dtype=got.dtype, **kw)
        np.testing.assert_array_equal(got.status, want.status)
        np.testing.assert_array_equal(got.iterations, want.iterations)
        # the same steps up to rounding, which an ill-conditioned fit amplifies over the iterations
        tol = 1e-4 if got.dtype == np.float64 else 1e-2
        np.testing.assert_allclose(got.x / np.abs(x0), want.x / np.abs(x0), rtol=0, atol=tol)
        np.testing.assert_allclose(got.cost, want.cost, rtol=tol)


def test_a_parameter_without_effect_gets_unit_damping(device):
    """A zero Jacobian column (parameter 1 does not enter the residuals): the scaled damping uses 1 for
    it (as MINPACK); the solve converges and leaves that parameter where it was."""

    def r(X):
        return np.stack([X[:, 0] - 2.0, 1e3 * (X[:, 2] - 1e-3), X[:, 0] * X[:, 2] - 2e-3], axis=1)

    x0 = np.array([[5.0, 0.25, 3e-3]])
    for mode in ("marquardt", "minpack"):
        res = least_squares(_host(r), x0, device=device, damping_scale=mode, max_iter=30, step=[1e-6, 1e-6, 1e-9])
        assert res.status[0] == Status.CONVERGED, res.messages()
        np.testing.assert_allclose(res.x[0], [2.0, 0.25, 1e-3], rtol=1e-5)


def test_a_start_one_rounding_inside_a_bound_starts_on_it(device):
    """A parameter held at its upper bound by the gradient: started exactly on the bound or one unit in
    the last place below it, the solve takes the same steps (the kernels hold a parameter at a bound by
    an exact comparison; without moving such a start onto the bound, the nearly collinear second
    column would be free for the first step and that step, clipped back, would move the first
    parameter elsewhere)."""
    A = np.array([[1.0, 1.0], [1.0, 1.001], [1.0, 0.999], [1.0, 1.002]])
    b = A @ np.array([1.0, 3.0])  # the unconstrained optimum: x1 = 3, beyond the bound 2

    def r(X):
        return X @ A.T - b

    upper = np.array([np.inf, 2.0])
    runs = []
    for x1 in (2.0, np.nextafter(2.0, 0.0)):
        res = least_squares(_host(r), np.array([[0.0, x1]]), device=device, upper=upper, max_iter=1,
                            damping_scale="marquardt")  # fmt: skip
        runs.append(res.x[0].astype(np.float64))
    on, inside = runs
    assert inside[1] == 2.0  # held on the bound
    np.testing.assert_allclose(inside, on, rtol=1e-6)
    free = np.linalg.lstsq(A[:, :1], b - 2.0 * A[:, 1], rcond=None)[0][0]  # the optimum with x1 = 2
    assert abs(on[0] - free) < abs(on[0] - 1.0)  # the step went towards it, not towards the free optimum


# ------------------------------------------------------------------------------------------------
# the solver object


T_EXP = np.linspace(0, 2, 24)
X0_EXP = np.array([[1.0, 0.0], [2.0, -2.0], [4.0, 1.0]])


def _expfit(X):
    return X[:, :1] * np.exp(X[:, 1:2] * T_EXP) - 2.5 * np.exp(-1.3 * T_EXP)


def _expfit_jac(X):
    """The Jacobian of ``_expfit`` at the points X (NumPy or DeviceArray), float64."""
    X = gputrack.to_numpy(X).astype(np.float64)
    e = np.exp(X[:, 1:2] * T_EXP)
    return np.stack([e, X[:, :1] * T_EXP * e], axis=2)


def test_a_solver_solves_again_and_again_on_its_own_buffers(device):
    solver = LeastSquaresSolver(device, (3, 2), max_iter=30, damping_scale="minpack")
    x0 = np.array([[1.0, 0.0], [2.0, -2.0], [4.0, 1.0]])
    once = least_squares(_host(_expfit), x0, device=device, max_iter=30, damping_scale="minpack")
    first = solver.solve(_host(_expfit), x0)
    held = {role: arr for role, (_, arr) in solver._bufs.held.items()}
    before = device.transfers.copy()
    again = solver.solve(_host(_expfit), x0)
    moved = device.transfers - before
    for res in (first, again):
        np.testing.assert_array_equal(res.x, once.x)
        np.testing.assert_array_equal(res.iterations, once.iterations)
    assert (first.status == Status.CONVERGED).all(), first.messages()
    assert {role: arr for role, (_, arr) in solver._bufs.held.items()} == held  # the same buffers
    if device.backend != "numpy":
        assert held and all(isinstance(a, gputrack.DeviceArray) for a in held.values())
        # the constants are not uploaded again: x0 (float32, exact) and the residuals (n = 3 (2P + 1)) only
        item = 8 if device.fp64 else 4
        assert moved.h2d == 3 * 2 * 4 + again.nfev * 3 * 5 * 24 * item
    solver.close()
    assert not solver._bufs.held


def test_a_solver_whose_residual_count_changes_keeps_a_bounded_pool(device):
    """A tracker's LM sees another M whenever its template's point count changes: the buffers of the
    sizes it no longer uses go back to the device's pool, which keeps at most POOL_MAX of them (the
    oldest sizes dropped, their cached host copies too), and the answers stay those of a fresh solve."""
    if device.backend == "numpy":
        pytest.skip("the numpy device has no buffer pool (NumPy arrays are made per call)")
    from gputrack.ops.lm import _Buffers

    solver = LeastSquaresSolver(device, (2, 2), max_iter=5, damping_scale="minpack")
    x0 = np.array([[1.0, 0.0], [2.0, -2.0]])
    pool = _Buffers._free.setdefault(device, {})
    first = None
    for M in range(8, 8 + 3 * (_Buffers.POOL_MAX + 8), 3):  # more sizes than the pool keeps
        t = np.linspace(0, 2, M)

        def fit(X, t=t):
            return X[:, :1] * np.exp(X[:, 1:2] * t) - 2.5 * np.exp(-1.3 * t)

        got = solver.solve(_host(fit), x0)
        want = least_squares(_host(fit), x0, device=gputrack.device("numpy"), max_iter=5, damping_scale="minpack")
        np.testing.assert_allclose(got.x, want.x, rtol=1e-4 if device.fp64 else 1e-2)
        assert sum(len(v) for v in pool.values()) <= _Buffers.POOL_MAX
        if first is None:  # the first solve's buffers, kept here to look for them at the end
            first = [arr for key, arr in solver._bufs.held.values() if key[0] != "host"]
    last = [arr for _, arr in solver._bufs.held.values()]
    first = [a for a in first if not any(a is b for b in last)]  # sized by M = 8 (the workspace)
    assert first
    pooled = [a for v in pool.values() for a in v]
    cached = [arr for arr, _ in _Buffers._sent.get(device, {}).values()]
    # dropped: neither the pool nor a cached host copy holds the first size's buffers any more
    assert not any(a is b for a in first for b in pooled + cached)
    solver.close()


def test_solver_settings_and_solve_inputs_are_checked(device):
    with pytest.raises(ValueError, match=r"^damping_scale: expected one of 'identity', 'marquardt', 'minpack', got 'jacobi'\Z"):
        LeastSquaresSolver(device, (2, 3), damping_scale="jacobi")
    with pytest.raises(ValueError, match=r"^shape: expected B >= 0 problems of P >= 1 parameters, got \(2, 0\)\Z"):
        LeastSquaresSolver(device, (2, 0))
    with pytest.raises(TypeError, match=r"^shape: expected \(B, P\) integers"):
        LeastSquaresSolver(device, (2.5, 3))
    solver = LeastSquaresSolver(device, (2, 2), max_iter=3)
    f = _host(_expfit)
    with pytest.raises(ValueError, match=r"^x0: expected shape \(B=2, P=2\), got \(3, 2\)\Z"):
        solver.solve(f, np.zeros((3, 2)))
    with pytest.raises(ValueError, match=r"^lower/upper: expected lower <= upper"):
        solver.solve(f, np.zeros((2, 2)), lower=1.0, upper=0.0)
    with pytest.raises(ValueError, match=r"^jac_sparsity: expected jacobian='central'"):
        solver.solve(f, np.zeros((2, 2)), jacobian=lambda X: np.zeros((2, 24, 2)), jac_sparsity=np.ones((24, 2), bool))

    def reenter(X):
        return solver.solve(f, np.zeros((2, 2)))

    with pytest.raises(RuntimeError, match="expected one solve at a time"):
        solver.solve(reenter, np.ones((2, 2)))
    res = solver.solve(f, np.ones((2, 2)))  # usable after the error
    assert np.isfinite(res.cost).all()


def test_host_callables_take_the_same_steps(device):
    """solve(..., host=True): the callables get NumPy points (one array for the residual and the Jacobian
    call at the same points) and return NumPy arrays; the solve is the same as with the device
    protocol, for central and forward differences and a Jacobian callable."""
    x0, jac = X0_EXP, _expfit_jac
    seen = []

    def res_host(X):
        assert type(X) is np.ndarray
        seen.append(X)
        return _expfit(X.astype(np.float64))

    def jac_host(X):
        assert X is seen[-1]  # the points of the residual call just before
        return jac(X)

    for diff, kw in (("central", {}), ("forward", {}), ("central", {"jacobian": jac})):
        solver = LeastSquaresSolver(device, (3, 2), max_iter=6, damping_scale="minpack", diff=diff)
        want = solver.solve(_host(_expfit), x0, **kw)
        if "jacobian" in kw:
            kw = {"jacobian": jac_host}
        got = solver.solve(res_host, x0, host=True, **kw)
        solver.close()
        np.testing.assert_array_equal(got.x, want.x)
        np.testing.assert_array_equal(got.cost, want.cost)
        np.testing.assert_array_equal(got.iterations, want.iterations)
        assert got.nfev == want.nfev and got.npoints == want.npoints
        rows = {"central": 5, "forward": 3}[diff] if not kw else 1
        assert seen[0].shape == (3 * rows, 2)
        seen.clear()
    with pytest.raises(ValueError, match=r"^diff: expected one of 'central', 'forward', got 'backward'\Z"):
        LeastSquaresSolver(device, (2, 2), diff="backward")


def test_the_final_update_asks_for_no_jacobian(device):
    """A solve that runs all max_iter iterations calls the Jacobian once per update that reads one:
    at the start and after each step but the last (the final update only accepts or rejects the
    last trial), in both call protocols; the steps are the reference's."""
    x0 = X0_EXP
    calls = []

    def jac(X):
        calls.append(1)
        return _expfit_jac(X)

    want = LeastSquaresSolver(REF, (3, 2), max_iter=5, early_stop=False).solve(_host(_expfit), x0, jacobian=jac)
    assert want.njev == len(calls) == 5 and want.nfev == 6
    for host in (False, True):
        calls.clear()
        got = LeastSquaresSolver(device, (3, 2), max_iter=5, early_stop=False).solve(
            _host(_expfit), x0, jacobian=jac, host=host
        )
        assert got.njev == len(calls) == 5 and got.nfev == 6, host
        assert_matches(device, got.x, want.x, got.dtype, err_msg=f"host={host}")


def test_a_profiled_solver_records_each_part_and_takes_the_same_steps(device):
    """``profile=True``: every part of a solve is a stage of ``solver.profiler`` (one frame a solve),
    with the calls a solve makes; the result is the unprofiled solver's."""
    x0, jac = X0_EXP, _expfit_jac
    plain = LeastSquaresSolver(device, (3, 2), max_iter=5, early_stop=False)
    assert plain.profiler is None
    want = plain.solve(_host(_expfit), x0, jacobian=jac)
    prof = LeastSquaresSolver(device, (3, 2), max_iter=5, early_stop=False, profile=True)
    for _ in range(2):
        got = prof.solve(_host(_expfit), x0, jacobian=jac)
    np.testing.assert_array_equal(got.x, want.x)
    calls = {r["name"]: r["calls"] for r in prof.profiler.report()}
    assert calls == {"init": 2, "residuals": 2 * 6, "jacobian": 2 * 5, "update": 2 * 6, "result": 2}
    assert len(prof.profiler.frames) == 2
    table = prof.profiler.table()
    assert all(name in table for name in calls) and "frame (median)" in table


def test_opencl_update_wait_polls_then_blocks(monkeypatch):
    """The host-mode update's wait polls the kernel's event for up to SPIN_S, then blocks on the
    queue (a kernel that takes longer is still waited for; one that is done returns at once)."""
    pytest.importorskip("pyopencl")
    import time

    import pyopencl as cl

    from gputrack.backends.opencl import lm as cl_lm

    class Event:
        def __init__(self, status):
            self.status, self.polls = status, 0

        @property
        def command_execution_status(self):
            self.polls += 1
            return self.status

    class Device:
        def __init__(self):
            self.finished = 0
            self.queue = self

        def finish(self):
            self.finished += 1

    monkeypatch.setattr(cl_lm, "SPIN_S", 0.002)
    dev, running = Device(), Event(cl.command_execution_status.RUNNING)
    t0 = time.perf_counter()
    cl_lm._wait(dev, running)
    assert time.perf_counter() - t0 >= 0.002 and running.polls > 1 and dev.finished == 1
    dev, done = Device(), Event(cl.command_execution_status.COMPLETE)
    cl_lm._wait(dev, done)
    assert done.polls == 1 and dev.finished == 1


def test_opencl_host_callables_share_memory_where_the_device_can(device, monkeypatch):
    """On an OpenCL device with fine-grained shared virtual memory (PoCL on a CPU) a host-mode solve
    hands the callables points the kernels wrote in place and the kernels read their results where
    they are (a read-only result: copied on the host into shared memory): no OpenCL copy per
    iteration, the same results as the reference."""
    if device.backend != "opencl":
        pytest.skip(f"{device.spec}: OpenCL's shared memory")
    import pyopencl as cl

    from gputrack.backends.opencl import lm as cl_lm

    if not cl_lm.reads_host(device):
        pytest.skip(f"{device.spec}: no fine-grained buffer SVM on a host-unified device (results are copied)")
    x0, jac = X0_EXP, _expfit_jac
    seen = []

    def res(X):
        seen.append(X)
        return _expfit(X)

    copies = []
    real_copy = cl.enqueue_copy
    monkeypatch.setattr(cl, "enqueue_copy", lambda *a, **k: (copies.append(1), real_copy(*a, **k))[1])
    counts = {}
    for iters in (2, 8):
        solver = LeastSquaresSolver(device, (3, 2), max_iter=iters, early_stop=False, damping_scale="minpack")
        solver.solve(res, x0, host=True, jacobian=jac)  # the constants' upload is kept from here on
        copies.clear()
        seen.clear()
        got = solver.solve(res, x0, host=True, jacobian=jac)
        counts[iters] = len(copies)
        solver.close()
        assert all(isinstance(X.base, cl.SVMAllocation) for X in seen)
        assert all(X is seen[0] for X in seen)  # one array of points, rewritten by each launch
        want = LeastSquaresSolver(REF, (3, 2), max_iter=iters, early_stop=False, damping_scale="minpack").solve(
            res, x0, jacobian=jac)  # fmt: skip
        np.testing.assert_allclose(got.x, want.x, rtol=1e-10, atol=1e-12)
        np.testing.assert_array_equal(got.iterations, want.iterations)
    assert counts[2] == counts[8] <= 2, counts  # the start points up, the results down
    # read where they are: a buffer over the callable's own array; a read-only one is copied
    state = cl_lm.State(device, Layout(3, 2, 24, False), *(device.empty((4,), np.float64) for _ in range(2)),
                        device.empty((4,), np.float64))  # fmt: skip
    r = np.arange(6.0).reshape(3, 2)
    buf = cl_lm._arg(state, r, "R")
    assert isinstance(buf, cl.Buffer) and buf.size == r.nbytes and buf.flags & cl.mem_flags.USE_HOST_PTR
    r.flags.writeable = False
    svm = cl_lm._arg(state, r, "R")
    assert isinstance(svm, cl.SVM) and isinstance(state.stage["R"].base, cl.SVMAllocation)
    np.testing.assert_array_equal(state.stage["R"], r)

    def frozen(f):
        def g(X):
            out = np.array(f(X))
            out.flags.writeable = False
            return out

        return g

    solver = LeastSquaresSolver(device, (3, 2), max_iter=8, early_stop=False, damping_scale="minpack")
    got = solver.solve(frozen(_expfit), x0, host=True, jacobian=frozen(jac))
    np.testing.assert_allclose(got.x, want.x, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(got.iterations, want.iterations)
    # points the kernel writes must be shared: a plain NumPy array would be written in a copy
    state = cl_lm.State(device, Layout(3, 2, 24, False), *(device.empty((4,), np.float64) for _ in range(2)),
                        device.empty((4,), np.float64))  # fmt: skip
    with pytest.raises(TypeError, match=r"^points: expected an array of the solver's shared memory"):
        cl_lm._arg(state, np.zeros((3, 2)), "X")

"""Batched Levenberg-Marquardt (gputrack.ops.lm) on every backend vs the NumPy reference."""

import numpy as np
import pytest
import scipy.optimize
from allocations import rejects_without_allocating
from tolerances import assert_matches

import gputrack
from gputrack.ops import lm
from gputrack.ops.lm import Layout, least_squares
from gputrack.ops.lm import LMStatus as Status

REF = gputrack.device("numpy")


def _fdt(device):
    return np.float64 if device.fp64 else np.float32


def host_residual(f, calls=None):
    """A residual function computed on the host (downloads X, returns NumPy in X's dtype)."""

    def res(X):
        Xn = gputrack.to_numpy(X)
        if calls is not None:
            calls.append(Xn.shape[0])
        return f(Xn.astype(np.float64)).astype(Xn.dtype)

    return res


def rosenbrock(X):
    return np.stack([10 * (X[:, 1] - X[:, 0] ** 2), 1 - X[:, 0]], axis=1)


def powell_singular(X):
    x1, x2, x3, x4 = X.T
    return np.stack([x1 + 10 * x2, np.sqrt(5) * (x3 - x4), (x2 - 2 * x3) ** 2, np.sqrt(10) * (x1 - x4) ** 2], axis=1)


T_BOX = 0.1 * np.arange(1, 11)


def box3d(X):
    t = T_BOX[None, :]
    x1, x2, x3 = X[:, :1], X[:, 1:2], X[:, 2:3]
    return np.exp(-t * x1) - np.exp(-t * x2) - x3 * (np.exp(-t) - np.exp(-10 * t))


T_EXP = np.linspace(0, 2, 40)
Y_EXP = 2.5 * np.exp(-1.3 * T_EXP) + 0.01 * np.random.default_rng(3).normal(size=T_EXP.size)


def expfit(X):
    return X[:, :1] * np.exp(X[:, 1:2] * T_EXP[None, :]) - Y_EXP[None, :]


def step_error_bound(JtJ, Jtr, C, dt, J=None, r=None):
    """Per problem, the error ||delta - delta*|| a step computed in ``dt`` may have (u = eps/2).

    The Cholesky solve of A = J^T J + C I is backward stable, (A + dA) delta = g with
    |dA| <= (3P+1) u |R^T||R| (Higham, Accuracy and Stability of Numerical Algorithms, Thm 10.4):
    ||delta - delta*|| <= (3P+1) u cond(A) ||delta*|| (with || |R^T||R| || ~ ||A||; the worst case's
    further factor up to P is not reached: measured <= 0.6 of this on every local backend). With
    ``J``, ``r`` (lm_solve) the normal equations are formed in dt too, each entry within M u of its
    sum of products: + M u cond(A) ||delta*|| + M u ||A^-1|| || |J|^T |r| ||.
    """
    P = JtJ.shape[-1]
    A = JtJ.astype(np.float64) + C.astype(np.float64)[:, None, None] * np.eye(P)
    want = np.linalg.solve(A, Jtr.astype(np.float64)[..., None])[..., 0]
    u = np.finfo(dt).eps / 2
    bound = (3 * P + 1) * u * np.linalg.cond(A) * np.linalg.norm(want, axis=1)
    if J is not None:
        M = J.shape[1]
        g = np.einsum("bmp,bm->bp", np.abs(J.astype(np.float64)), np.abs(r.astype(np.float64)))
        inv = 1.0 / np.linalg.eigvalsh(A)[:, 0]
        bound += M * u * (np.linalg.cond(A) * np.linalg.norm(want, axis=1) + inv * np.linalg.norm(g, axis=1))
    return want, bound


def assert_step(delta, want, bound, what=""):
    err = np.linalg.norm(gputrack.to_numpy(delta).astype(np.float64) - want, axis=1)
    assert (err <= bound).all(), (what, err, bound)


# ------------------------------------------------------------------------------------------------
# ops


# P = 40, 37: above STATIC_P_MAX (the tiles of _gram_tiles on taichi:cpu; 37: a last band past P)
@pytest.mark.parametrize("B,M,P", [(1, 1, 1), (13, 7, 5), (3, 129, 20), (2, 3, 14), (2, 45, 40), (2, 9, 37)])
def test_normal_equations_matches_reference(device, B, M, P):
    rng = np.random.default_rng(B * 100 + P)
    for dt in {np.float32, _fdt(device)}:
        J = rng.normal(size=(B, M, P)).astype(dt)
        r = rng.normal(size=(B, M)).astype(dt)
        JtJ, Jtr = lm.normal_equations(device, J, r)
        want = np.einsum("bmi,bmj->bij", J.astype(np.float64), J.astype(np.float64))
        assert_matches(device, JtJ, want, dt, scale=M)
        assert_matches(device, Jtr, np.einsum("bmi,bm->bi", J.astype(np.float64), r.astype(np.float64)), dt, scale=M)
        assert gputrack.to_numpy(JtJ).dtype == dt


@pytest.mark.parametrize("B,P", [(1, 1), (13, 5), (10, 20), (3, 40)])
def test_lm_step_and_solve_match_reference(device, B, P):
    for dt in {np.float32, _fdt(device)}:
        rng = np.random.default_rng(P)
        M = P + 7
        J = rng.normal(size=(B, M, P)).astype(dt)
        r = rng.normal(size=(B, M)).astype(dt)
        C = rng.uniform(1e-5, 1, size=B).astype(dt)
        JtJ, Jtr = lm.normal_equations(REF, J, r)
        want, bound = step_error_bound(JtJ, Jtr, C, dt)
        # the bound tells a step without the damping term from the damped one
        undamped = np.linalg.solve(JtJ.astype(np.float64), Jtr.astype(np.float64)[..., None])[..., 0]
        assert (np.linalg.norm(undamped - want, axis=1) > bound).any()
        delta, ok = lm.lm_step(device, JtJ, Jtr, C)
        assert_step(delta, want, bound, f"lm_step {dt.__name__}")
        assert (gputrack.to_numpy(ok) == 1).all()
        want2, bound2 = step_error_bound(JtJ, Jtr, C, dt, J, r)
        delta2, ok2 = lm.lm_solve(device, J, r, C)
        assert_step(delta2, want2, bound2, f"lm_solve {dt.__name__}")
        assert (gputrack.to_numpy(ok2) == 1).all()


def _linear_sine(B, M, P, seed):
    """B problems r = A_b x - y_b + 0.1 sin(3 x_0) (host residual function and its Jacobian)."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(B, M, P))
    y = rng.normal(size=(B, M))

    def res(X):
        Xn = gputrack.to_numpy(X)
        x = Xn.astype(np.float64)
        b = np.arange(len(x)) // (len(x) // B)
        return (np.einsum("bmp,bp->bm", A[b], x) - y[b] + 0.1 * np.sin(3 * x[:, :1])).astype(Xn.dtype)

    def jac(X):
        Xn = gputrack.to_numpy(X)
        J = A.copy()
        J[:, :, 0] += 0.3 * np.cos(3 * Xn[:, :1].astype(np.float64))
        return J.astype(Xn.dtype)

    return res, jac


# P above ~68 ran past lavapipe's 65535 loop passes per shader invocation: taichi:vulkan returned
# wrong steps with ok = 1 (gputrack/backends/taichi/lm.py, the parallel archs' section)
@pytest.mark.parametrize("P", [70, 92, 128])
def test_large_problems_match_reference(device, P):
    B, M = 2, P + 7
    rng = np.random.default_rng(P + 2)
    for dt in {np.float32, _fdt(device)}:
        J = rng.normal(size=(B, M, P)).astype(dt)
        r = rng.normal(size=(B, M)).astype(dt)
        C = rng.uniform(1e-3, 1, size=B).astype(dt)
        JtJ, Jtr = lm.normal_equations(REF, J, r)
        want, _ = lm.lm_step(REF, JtJ, Jtr, C)
        assert_matches(device, lm.normal_equations(device, J, r)[0], JtJ, dt, scale=M)
        for name, (delta, ok) in (("lm_step", lm.lm_step(device, JtJ, Jtr, C)),
                                  ("lm_solve", lm.lm_solve(device, J, r, C))):  # fmt: skip
            assert_matches(device, delta, want, dt, scale=1e3 if dt == np.float32 else 1e2, err_msg=name)
            assert (gputrack.to_numpy(ok) == 1).all(), name
    # the solver: central differences and a Jacobian callable, some parameters held at the box
    res, jac = _linear_sine(B, M, P, seed=P)
    x0 = np.full((B, P), 0.05)
    for kw in ({}, {"jacobian": jac}):
        got = least_squares(res, x0, device=device, lower=-0.3, upper=0.3, max_iter=6, **kw)
        ref = least_squares(res, x0, device=REF, lower=-0.3, upper=0.3, max_iter=6, dtype=got.dtype, **kw)
        assert np.isclose(np.abs(ref.x), 0.3).any()
        f32 = got.dtype == np.float32
        assert_matches(device, got.x, ref.x, got.dtype, scale=1e3 if f32 else 1e2, err_msg=str(kw))
        assert_matches(device, got.cost, ref.cost, got.dtype, scale=1e3 if f32 else 1e2, err_msg=str(kw))
        if not f32:
            np.testing.assert_array_equal(got.status, ref.status)
            np.testing.assert_array_equal(got.iterations, ref.iterations)


def test_sizes_past_the_device_loop_limit_raise(device):
    """Where the device stops a kernel's loops after a number of passes (lavapipe), sizes whose tasks
    need more raise instead of returning wrong numbers."""
    from gputrack.backends.taichi.runtime import loop_limit

    if device.backend != "taichi" or loop_limit(device) is None:
        pytest.skip("no loop limit on this device")
    P = 700
    JtJ = np.eye(P)[None]
    with pytest.raises(ValueError, match="loop passes per kernel invocation.*B=1, P=700"):
        lm.lm_step(device, JtJ, np.ones((1, P)), np.ones(1))
    res, _ = _linear_sine(1, 3, 600, seed=0)
    with pytest.raises(ValueError, match="loop passes per kernel invocation.*P=600"):
        least_squares(res, np.zeros((1, 600)), device=device, max_iter=1)


def test_ops_write_into_out(device):
    dt = _fdt(device)
    rng = np.random.default_rng(5)
    J = rng.normal(size=(3, 8, 4)).astype(dt)
    r = rng.normal(size=(3, 8)).astype(dt)
    C = np.full(3, 0.1, dt)
    want_d, _ = lm.lm_solve(REF, J, r, C)
    o = (device.empty((3, 4), dt), device.empty((3,), np.int32))
    got = lm.lm_solve(device, J, r, C, out=o)
    assert got[0] is o[0] and got[1] is o[1]
    assert_matches(device, o[0], want_d, dt, scale=10)
    ne = (device.empty((3, 4, 4), dt), device.empty((3, 4), dt))
    JtJ, Jtr = lm.normal_equations(device, J, r, out=ne)
    assert JtJ is ne[0]
    d, _ = lm.lm_step(device, JtJ, Jtr, C, out=o)
    assert_matches(device, d, want_d, dt, scale=10)
    with pytest.raises(ValueError, match=r"out delta: expected a float(32|64) array of shape \(3, 4\), got float(32|64) \(3, 5\)"):
        lm.lm_solve(device, J, r, C, out=(device.empty((3, 5), dt), o[1]))
    with pytest.raises(TypeError, match="out: expected a tuple of 2"):
        lm.lm_solve(device, J, r, C, out=o[0])


@pytest.mark.parametrize("P", [14, 20])
def test_repeated_calls_read_and_write_their_own_arrays(device, P):
    """Calls after the first with the same shapes take Taichi's direct launch path
    (gputrack/backends/taichi/launch.py): each must use the arrays it is given."""
    rng = np.random.default_rng(P + 1)
    B, M = 10, 256
    for dt in {np.float32, _fdt(device)}:
        calls = []
        for _ in range(3):
            J = rng.normal(size=(B, M, P)).astype(dt)
            r = rng.normal(size=(B, M)).astype(dt)
            C = rng.uniform(1e-3, 1, size=B).astype(dt)
            o = (device.empty((B, P), dt), device.empty((B,), np.int32))
            ne = (device.empty((B, P, P), dt), device.empty((B, P), dt))
            lm.lm_solve(device, device.asarray(J), device.asarray(r), device.asarray(C), out=o)
            lm.normal_equations(device, J, r, out=ne)
            A, g = lm.normal_equations(REF, J, r)
            calls.append((o, ne, step_error_bound(A, g, C, dt, J, r), lm.lm_solve(REF, J, r, C)[1], (A, g)))
        for o, ne, (want_d, bound), want_ok, (want_A, want_g) in calls:
            assert_step(o[0], want_d, bound, dt.__name__)
            np.testing.assert_array_equal(gputrack.to_numpy(o[1]), want_ok)
            assert_matches(device, ne[0], want_A, dt, scale=M)
            assert_matches(device, ne[1], want_g, dt, scale=M)


def test_taichi_direct_launch_takes_numpy_arrays(device):
    if device.spec != "taichi:cpu":
        pytest.skip("NumPy arrays are passed to Taichi kernels by address on taichi:cpu only")
    from gputrack.backends.taichi.arrays import COPY
    from gputrack.backends.taichi.launch import launch

    for seed, order in enumerate("CCFC"):  # the F-ordered array goes through kernel(...)
        src = np.asarray(np.random.default_rng(seed).normal(size=(5, 7)), order=order)
        dst = device.empty((5, 7), np.float64)
        launch(COPY[2], (src, dst.buffer), (True,))
        back = np.empty((5, 7), np.float64)
        launch(COPY[2], (dst.buffer, back), (True,))
        np.testing.assert_array_equal(back, src)
        np.testing.assert_array_equal(dst.numpy(), src)


def test_lm_step_flags_not_positive_definite(device):
    dt = _fdt(device)
    P = 4
    JtJ = np.stack([np.eye(P), -np.eye(P), np.zeros((P, P)), np.diag([1.0, 1.0, 0.0, 1.0])]).astype(dt)
    Jtr = np.ones((4, P), dt)
    C = np.array([0.0, 0.5, 0.0, 0.0], dt)
    delta, ok = lm.lm_step(device, JtJ, Jtr, C)
    d = gputrack.to_numpy(delta)
    assert gputrack.to_numpy(ok).tolist() == [1, 0, 0, 0]
    assert np.isfinite(d).all()
    assert (d[1:] == 0).all()
    assert_matches(device, d[0], np.ones(P), dt)
    # the same singular matrix becomes solvable with damping
    delta, ok = lm.lm_step(device, JtJ[2:], Jtr[2:], np.array([1.0, 1.0], dt))
    assert gputrack.to_numpy(ok).tolist() == [1, 1]


def test_ops_bad_input(device):
    dt = _fdt(device)
    J = np.zeros((2, 5, 3), dt)
    with pytest.raises(ValueError, match="r: expected shape"):
        lm.normal_equations(device, J, np.zeros((2, 4), dt))
    with pytest.raises(ValueError, match="J: expected shape"):
        lm.normal_equations(device, np.zeros((5, 3), dt), np.zeros((2, 5), dt))
    with pytest.raises(TypeError, match="J: expected dtype"):
        lm.normal_equations(device, J.astype(np.int32), np.zeros((2, 5), dt))
    with pytest.raises(ValueError, match="J: expected finite"):
        bad = J.copy()
        bad[0, 0, 0] = np.nan
        lm.normal_equations(device, bad, np.zeros((2, 5), dt))
    with pytest.raises(ValueError, match="non-empty"):
        lm.normal_equations(device, np.zeros((0, 5, 3), dt), np.zeros((0, 5), dt))
    with pytest.raises(ValueError, match="damping: expected values >= 0"):
        lm.lm_step(device, np.zeros((2, 3, 3), dt), np.zeros((2, 3), dt), np.array([1.0, -1.0]))
    with pytest.raises(ValueError, match="damping: expected shape"):
        lm.lm_step(device, np.zeros((2, 3, 3), dt), np.zeros((2, 3), dt), np.ones(3, dt))


def test_ops_bad_input_on_the_device(device):
    """Arrays already on the device skip the full argument check when they fit (ops/lm.py ``_arg``);
    those that do not still get its messages."""
    if device.backend == "numpy":
        pytest.skip("the numpy device's arrays are NumPy arrays (covered by test_ops_bad_input)")
    dt = _fdt(device)
    J = device.asarray(np.zeros((2, 5, 3), dt))
    C = device.asarray(np.ones(2, dt))
    with pytest.raises(ValueError, match="r: expected shape"):
        lm.lm_solve(device, J, device.asarray(np.zeros((2, 4), dt)), C)
    with pytest.raises(ValueError, match="r: expected shape"):
        lm.lm_solve(device, J, device.asarray(np.zeros((3, 5), dt)), C)
    with pytest.raises(TypeError, match="r: expected dtype"):
        lm.lm_solve(device, J, device.asarray(np.zeros((2, 5), np.int32)), C)
    with pytest.raises(ValueError, match="damping: expected shape"):
        lm.lm_solve(device, J, device.asarray(np.zeros((2, 5), dt)), device.asarray(np.ones(3, dt)))
    with pytest.raises(ValueError, match="JtJ: expected shape"):
        lm.lm_step(device, device.asarray(np.zeros((2, 3, 4), dt)), device.asarray(np.zeros((2, 3), dt)), C)
    with pytest.raises(ValueError, match="Jtr: expected shape"):
        lm.lm_step(device, device.asarray(np.zeros((2, 3, 3), dt)), device.asarray(np.zeros((2, 4), dt)), C)
    if dt == np.float64:
        with pytest.raises(TypeError, match="r: expected dtype"):
            lm.lm_solve(device, J, device.asarray(np.zeros((2, 5), np.float32)), C)
    ok = lm.lm_solve(device, J, device.asarray(np.zeros((2, 5), dt)), C)
    np.testing.assert_array_equal(gputrack.to_numpy(ok[1]), [1, 1])


# ------------------------------------------------------------------------------------------------
# solver: classic problems


def test_rosenbrock_batch_reaches_minimum_and_matches_reference(device):
    x0 = np.array([[-1.2, 1.0], [0.0, 0.0], [2.0, 2.0], [-0.5, 3.0], [1.0, 1.0]])
    res = least_squares(host_residual(rosenbrock), x0, device=device, max_iter=100)
    assert res.dtype == _fdt(device)
    np.testing.assert_allclose(res.x, 1.0, atol=1e-6)
    assert (res.cost < 1e-12).all()
    assert (res.status == Status.CONVERGED).all()
    ref = least_squares(host_residual(rosenbrock), x0, device=REF, max_iter=100)
    assert_matches(device, res.x, ref.x, np.float64, scale=1e3)
    np.testing.assert_array_equal(res.status, ref.status)
    np.testing.assert_array_equal(res.iterations, ref.iterations)


def test_powell_singular(device):
    x0 = np.array([[3.0, -1.0, 0.0, 1.0]])
    res = least_squares(host_residual(powell_singular), x0, device=device, max_iter=200)
    assert res.status[0] == Status.CONVERGED, res.messages()
    assert res.cost[0] < 1e-8
    assert np.abs(res.x).max() < 2e-2


def test_box3d(device):
    x0 = np.array([[0.0, 10.0, 20.0]])
    res = least_squares(host_residual(box3d), x0, device=device, max_iter=100)
    assert res.status[0] == Status.CONVERGED, res.messages()
    assert res.cost[0] < 1e-12
    np.testing.assert_allclose(res.x[0], [1.0, 10.0, 1.0], atol=1e-4)


def test_exponential_fit_matches_scipy(device):
    x0 = np.array([[1.0, 0.0], [4.0, -3.0], [2.0, -1.0]])
    res = least_squares(host_residual(expfit), x0, device=device, max_iter=50)
    want = scipy.optimize.least_squares(lambda p: expfit(p[None])[0], x0[0], method="lm", xtol=1e-14, ftol=1e-14).x
    assert (res.status == Status.CONVERGED).all(), res.messages()
    np.testing.assert_allclose(res.x, np.broadcast_to(want, res.x.shape), rtol=1e-6)
    np.testing.assert_allclose(res.cost, np.sum(expfit(want[None]) ** 2), rtol=1e-8)


def test_float32_fallback(device):
    x0 = np.array([[1.0, 0.0], [4.0, -3.0]])
    res = least_squares(host_residual(expfit), x0, device=device, max_iter=50, dtype=np.float32)
    assert res.dtype == np.float32 and res.x.dtype == np.float32
    want = scipy.optimize.least_squares(lambda p: expfit(p[None])[0], x0[0], method="lm").x
    np.testing.assert_allclose(res.x, np.broadcast_to(want, res.x.shape), rtol=2e-3)
    assert set(res.status.tolist()) <= {Status.CONVERGED, Status.MAX_ITER}


def test_device_without_fp64_runs_in_float32(device, monkeypatch):
    monkeypatch.setattr(type(device), "fp64", property(lambda self: False))
    calls = []

    def res(X):
        calls.append(X.dtype)
        Xn = gputrack.to_numpy(X)
        return expfit(Xn.astype(np.float64))  # float64 NumPy: converted to float32 by the solver

    out = least_squares(res, np.array([[1.0, 0.0], [4.0, -3.0]]), device=device, max_iter=50)
    assert out.dtype == np.float32 and set(calls) == {np.dtype(np.float32)}
    want = scipy.optimize.least_squares(lambda p: expfit(p[None])[0], [1.0, 0.0], method="lm").x
    np.testing.assert_allclose(out.x, np.broadcast_to(want, out.x.shape), rtol=2e-3)
    with pytest.raises(TypeError, match="points_dtype: expected float32"):
        least_squares(res, np.zeros((1, 2)), device=device, points_dtype=np.float64)


def test_points_dtype_float32(device):
    seen = []

    def res32(X):
        seen.append(X.dtype)
        Xn = gputrack.to_numpy(X)
        return expfit(Xn.astype(np.float64)).astype(np.float32)

    res = least_squares(res32, np.array([[1.0, 0.0]]), device=device, max_iter=50, points_dtype=np.float32, step=1e-3)
    assert set(seen) == {np.dtype(np.float32)}
    want = scipy.optimize.least_squares(lambda p: expfit(p[None])[0], [1.0, 0.0], method="lm").x
    np.testing.assert_allclose(res.x[0], want, rtol=1e-3)


# ------------------------------------------------------------------------------------------------
# solver: per-problem behaviour


def _mixed(X):
    """Problem 0 easy (linear), 1 hard (Powell singular), 2 diverging (leaves its domain), 3 NaN at x0."""
    out = np.zeros((X.shape[0], 4))
    B = 4
    S = X.shape[0] // B
    for b in range(B):
        Xb = X[b * S : (b + 1) * S]
        if b == 0:
            out[b * S : (b + 1) * S] = np.stack([Xb[:, 0] - 1, Xb[:, 1] + 2, Xb[:, 2] - 3, Xb[:, 3]], axis=1)
        elif b == 1:
            out[b * S : (b + 1) * S] = powell_singular(Xb)
        elif b == 2:
            # minimum at x = 3, but the model is undefined (NaN) beyond x = 2
            r = np.where(Xb[:, :1] > 2.0, np.nan, Xb[:, :1] - 3.0)
            out[b * S : (b + 1) * S] = np.concatenate([r, 0 * Xb[:, 1:]], axis=1)
        else:
            out[b * S : (b + 1) * S] = np.nan
    return out


def test_mixed_batch_gives_each_problem_its_status(device):
    x0 = np.array([[0.0, 0.0, 0.0, 0.0], [3.0, -1.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]])
    res = least_squares(host_residual(_mixed), x0, device=device, max_iter=10)
    assert res.statuses() == [Status.CONVERGED, Status.MAX_ITER, Status.MAX_ITER, Status.FAILED], res.messages()
    np.testing.assert_allclose(res.x[0], [1, -2, 3, 0], atol=1e-8)
    assert res.iterations[1] == 10
    # NaN at trial points is a rejected step (as MINPACK): problem 2 approaches its domain's edge
    assert res.x[2, 0] <= 2.0 and np.isfinite(res.cost[2]) and res.x[2, 0] > 1.0
    assert res.reason[3] == 5 and res.iterations[3] == 0  # non-finite residuals at x0
    assert res.cost[3] == np.inf
    # the hard problem runs exactly as it would alone
    alone = least_squares(host_residual(powell_singular), x0[1:2], device=device, max_iter=10)
    np.testing.assert_array_equal(res.x[1], alone.x[0])
    ref = least_squares(host_residual(_mixed), x0, device=REF, max_iter=10)
    np.testing.assert_array_equal(res.status, ref.status)
    assert_matches(device, res.x[:2], ref.x[:2], np.float64, scale=1e3)


def test_early_stop_off_gives_the_same_result(device):
    x0 = np.array([[-1.2, 1.0], [2.0, 2.0]])
    a = least_squares(host_residual(rosenbrock), x0, device=device, max_iter=60)
    b = least_squares(host_residual(rosenbrock), x0, device=device, max_iter=60, early_stop=False)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.status, b.status)
    np.testing.assert_array_equal(a.iterations, b.iterations)
    assert a.nfev < b.nfev == 61


def test_max_iter_zero_and_call_layout(device):
    calls = []
    x0 = np.array([[1.0, 2.0, 3.0]] * 2)
    res = least_squares(host_residual(box3d, calls), x0, device=device, max_iter=0)
    assert calls == [2] and (res.status == Status.MAX_ITER).all() and (res.iterations == 0).all()
    np.testing.assert_allclose(res.cost, np.sum(box3d(x0) ** 2, axis=1), rtol=1e-12)
    calls.clear()
    least_squares(host_residual(box3d, calls), x0, device=device, max_iter=3, early_stop=False)
    assert calls == [2 * 7, 2 * 7, 2 * 7, 2]  # B (2P + 1) stacked points, the last call B points


def test_stacked_points_are_central_differences(device):
    got = []

    def res(X):
        got.append(gputrack.to_numpy(X).copy())
        return np.zeros((X.shape[0], 1), dtype=X.dtype)

    x0 = np.array([[0.5, -2000.0, 0.0, 3e-6]])
    least_squares(res, x0, device=device, max_iter=0 + 1, step=None, early_stop=False)
    X = got[0]
    # steps relative to |x| (MINPACK's rule: of 1 where x = 0), so a parameter near 1e-6 gets its own
    eps = lm.DEFAULT_REL_STEP["central"][X.dtype.name] * np.array([0.5, 2000.0, 1.0, 3e-6])
    assert X.shape == (9, 4)
    np.testing.assert_array_equal(X[0], x0[0].astype(X.dtype))
    for n in range(4):
        for row, sign in ((1 + 2 * n, 1), (2 + 2 * n, -1)):
            want = x0[0].copy()
            want[n] += sign * eps[n]
            np.testing.assert_allclose(X[row], want, rtol=1e-6, atol=0)


def test_stacked_points_are_forward_differences(device):
    """jacobian='forward': P + 1 rows per problem (the point, then it moved by +eps in each parameter;
    -eps where +eps would cross the upper bound), MINPACK's relative step sqrt(eps) |x|; a solve
    with them matches the reference."""
    got = []

    def res(X):
        Xn = gputrack.to_numpy(X)
        got.append(Xn.copy())
        return box3d(Xn.astype(np.float64)).astype(Xn.dtype)

    x0 = np.array([[0.5, 8.0, 2e-6], [2.0, 0.0, 1.0]])
    upper = np.array([np.inf, 8.0, np.inf])
    least_squares(res, x0, device=device, max_iter=1, early_stop=False, jacobian="forward", upper=upper)
    X = got[0].reshape(2, 4, 3)
    rel = lm.DEFAULT_REL_STEP["forward"][X.dtype.name]
    for b in range(2):
        np.testing.assert_array_equal(X[b, 0], x0[b].astype(X.dtype))
        for n in range(3):
            want = x0[b].copy()
            a = abs(want[n]) if want[n] != 0 else 1.0
            want[n] += -rel * a if (b == 0 and n == 1) else rel * a  # at the upper bound: one step down
            np.testing.assert_allclose(X[b, 1 + n], want, rtol=1e-6, atol=0)
    x0 = np.array([[1.0, 2.0, 3.0], [0.5, 12.0, 1.5]])
    got = least_squares(host_residual(box3d), x0, device=device, max_iter=6, jacobian="forward")
    want = least_squares(host_residual(box3d), x0, device=REF, max_iter=6, jacobian="forward", dtype=got.dtype)
    np.testing.assert_array_equal(got.status, want.status)
    np.testing.assert_array_equal(got.iterations, want.iterations)
    tol = 1e-6 if got.dtype == np.float64 else 2e-3  # a nearly degenerate fit (x1 -> x2) amplifies rounding
    np.testing.assert_allclose(got.x, want.x, rtol=tol, atol=tol)
    np.testing.assert_allclose(got.cost, want.cost, rtol=tol, atol=1e-12)
    assert got.nfev == want.nfev and got.npoints == want.npoints


# ------------------------------------------------------------------------------------------------
# bounds


def test_bounds_hold_and_reach_the_constrained_minimum(device):
    x0 = np.array([[-1.2, 1.0], [0.0, 0.0], [0.4, 0.9]])
    seen = []

    def res(X):
        Xn = gputrack.to_numpy(X)
        seen.append(Xn.copy())
        return rosenbrock(Xn.astype(np.float64)).astype(Xn.dtype)

    out = least_squares(res, x0, device=device, upper=[0.5, np.inf], lower=[-2.0, -1.0], max_iter=100)
    assert (out.x[:, 0] <= 0.5).all()
    np.testing.assert_allclose(out.x, [[0.5, 0.25]] * 3, atol=1e-6)
    np.testing.assert_allclose(out.cost, 0.25, rtol=1e-8)
    assert (out.status == Status.CONVERGED).all(), out.messages()
    allpts = np.concatenate(seen)
    assert (allpts[:, 0] <= 0.5).all() and (allpts[:, 0] >= -2.0).all() and (allpts[:, 1] >= -1.0).all()


def test_fixed_parameter_and_clipped_start(device):
    x0 = np.array([[3.0, 1.0], [0.0, 0.3]])
    out = least_squares(host_residual(rosenbrock), x0, device=device, lower=[-2.0, 0.3], upper=[2.0, 0.3], max_iter=100)
    assert out.x0_clipped.tolist() == [True, False]
    np.testing.assert_array_equal(out.x[:, 1], 0.3)
    # min over x1 of 100 (0.3 - x1^2)^2 + (1 - x1)^2
    want = scipy.optimize.minimize_scalar(
        lambda a: 100 * (0.3 - a * a) ** 2 + (1 - a) ** 2, bounds=(0, 2), method="bounded", options={"xatol": 1e-12}
    ).x
    np.testing.assert_allclose(out.x[:, 0], want, atol=1e-5)


def test_bounds_bad_input(device):
    f = host_residual(rosenbrock)
    with pytest.raises(ValueError, match="expected lower <= upper"):
        least_squares(f, np.zeros((1, 2)), device=device, lower=[0, 1], upper=[1, 0])
    with pytest.raises(ValueError, match="upper: expected shape"):
        least_squares(f, np.zeros((1, 2)), device=device, upper=[1, 2, 3])
    with pytest.raises(ValueError, match="lower: expected numbers"):
        least_squares(f, np.zeros((1, 2)), device=device, lower=[np.nan, 0])


# ------------------------------------------------------------------------------------------------
# Jacobian sparsity and the rows protocol


def _chain(X):
    """A two-part chain (paper 000 Fig. 2): residuals 0-5 depend on params 0-1, residuals 6-11 on 0-3."""
    a, b, c, d = X.T
    t = np.linspace(0, 1, 6)[None, :]
    r0 = a[:, None] * np.exp(b[:, None] * t) - 2 * np.exp(-t)
    r1 = a[:, None] + c[:, None] * np.sin(d[:, None] * (t + 1)) - (2 + 0.5 * np.sin(1.5 * (t + 1)))
    return np.concatenate([r0, r1], axis=1)


CHAIN_MASK = np.zeros((12, 4), bool)
CHAIN_MASK[:6, :2] = True
CHAIN_MASK[6:, :] = True
CHAIN_MASK[6:, 1] = False  # r1 does not depend on b: the mask is exact


def test_sparse_jacobian_gives_the_dense_steps(device):
    x0 = np.array([[1.0, -0.5, 0.3, 1.2], [2.5, -1.5, 0.6, 1.6]])
    counted = {"entries": 0}

    def res_rows(X, rows):
        need = gputrack.to_numpy(rows).astype(bool)
        Xn = gputrack.to_numpy(X)
        counted["entries"] += int(need.sum())
        out = _chain(Xn.astype(np.float64))
        out[~need] = np.nan  # not needed: any value, must be ignored
        return out.astype(Xn.dtype)

    dense = least_squares(host_residual(_chain), x0, device=device, max_iter=8, early_stop=False)
    sparse = least_squares(res_rows, x0, device=device, max_iter=8, early_stop=False, jac_sparsity=CHAIN_MASK)
    assert_matches(device, sparse.x, dense.x, np.float64)
    np.testing.assert_array_equal(sparse.iterations, dense.iterations)
    assert_matches(device, sparse.cost, dense.cost, np.float64)
    # the perturbations of parameter n evaluated only the rows that depend on it
    B, M = 2, 12
    per_call = B * (M + 2 * int(CHAIN_MASK.sum()))
    assert counted["entries"] == 8 * per_call + B * M
    assert counted["entries"] < sparse.npoints * M


def test_sparse_mask_without_rows_protocol(device):
    x0 = np.array([[1.0, -0.5, 0.3, 1.2]])
    dense = least_squares(host_residual(_chain), x0, device=device, max_iter=30)
    sparse = least_squares(host_residual(_chain), x0, device=device, max_iter=30, jac_sparsity=CHAIN_MASK)
    assert_matches(device, sparse.x, dense.x, np.float64)
    with pytest.raises(ValueError, match="jac_sparsity: expected shape"):
        least_squares(host_residual(_chain), x0, device=device, jac_sparsity=CHAIN_MASK[:5])
    with pytest.raises(TypeError, match="jac_sparsity: expected a bool"):
        least_squares(host_residual(_chain), x0, device=device, jac_sparsity=CHAIN_MASK * 0.5)


# the Jacobian-callable update builds P <= STATIC_P_MAX (32) into the kernels: blocks of four
# rows and columns on OpenCL (P % 4 = 0..3), vectors of columns on taichi:cpu
@pytest.mark.parametrize("P", [1, 3, 4, 6, 9, 20, 32])
def test_jacobian_callable_matches_reference_for_each_built_p(device, P):
    B, M = 3, P + 9
    res, jac = _linear_sine(B, M, P, seed=100 + P)
    x0 = np.full((B, P), 0.05)
    for host in (False, True):
        got = least_squares(res, x0, device=device, jacobian=jac, lower=-0.3, upper=0.3, max_iter=5, host=host)
        ref = least_squares(res, x0, device=REF, jacobian=jac, lower=-0.3, upper=0.3, max_iter=5, dtype=got.dtype)
        f32 = got.dtype == np.float32
        assert_matches(device, got.x, ref.x, got.dtype, scale=1e3 if f32 else 1e2, err_msg=f"P={P} host={host}")
        assert_matches(device, got.cost, ref.cost, got.dtype, scale=1e3 if f32 else 1e2, err_msg=f"P={P} host={host}")
        if not f32:
            np.testing.assert_array_equal(got.iterations, ref.iterations)


def _unaligned(a):
    """A C-contiguous copy of ``a`` whose data start 8 bytes past a 16-byte boundary."""
    buf = np.empty(a.size + 2, a.dtype)
    start = (-buf.ctypes.data % 16) // a.itemsize + 1
    out = buf[start : start + a.size].reshape(a.shape)
    out[...] = a
    assert out.flags.c_contiguous and out.ctypes.data % 16 == 8
    return out


# taichi:cpu reads a float64 NumPy Jacobian of an even P <= 32 in pairs of columns (as vectors,
# which assume 16-byte alignment: NumPy's) and any other as scalars
@pytest.mark.parametrize("P", [6, 20])
def test_jacobian_in_pairs_and_unaligned_match_reference(device, P):
    B, M = 3, 40
    res, jac = _linear_sine(B, M, P, seed=7 + P)
    x0 = np.full((B, P), 0.05)
    want = least_squares(res, x0, device=REF, jacobian=jac, max_iter=6)
    aligned = lambda X: jac(X).astype(np.float64)
    for name, fn in (("aligned", aligned), ("unaligned", lambda X: _unaligned(aligned(X)))):
        got = least_squares(res, x0, device=device, jacobian=fn, max_iter=6, host=True)
        assert_matches(device, got.x, want.x.astype(got.dtype), got.dtype, scale=1e2, err_msg=name)
        assert_matches(device, got.cost, want.cost.astype(got.dtype), got.dtype, scale=1e2, err_msg=name)


def _block_mask(M, P):
    """(M, P) bool: rows in groups of 10, group g touching its own 5 parameters (cycling through the
    first P - 8) and the last 8 (shared, as the face bundle's frames and identity)."""
    mask = np.zeros((M, P), bool)
    for m in range(M):
        g = m // 10
        mask[m, [(5 * g + k) % (P - 8) for k in range(5)]] = True
    mask[:, P - 8 :] = True
    return mask


# P = 40, 92: above STATIC_P_MAX, where taichi:cpu skips the rows of a tile that are 0 in its blocks
@pytest.mark.parametrize("P,M", [(40, 49), (92, 155), (40, 1)])
def test_block_sparse_jacobian_matches_reference(device, P, M):
    """A Jacobian callable whose J is 0 outside blocks of rows and columns (a bundle adjustment's;
    taichi:cpu skips those rows in J^T J's tiles and factors within the rows' envelope) gives the
    reference's solve; a NaN in such a J (in a row that is 0 in the other column blocks) fails the
    problem as the reference does; a singular J^T J started at C = 0 raises the damping as the
    reference does (M > 1). M = 1: no room for taichi:cpu's row marks (the plain sums)."""
    B = 2
    rng = np.random.default_rng(300 + P + M)
    mask = _block_mask(M, P)
    A = rng.normal(size=(B, M, P)) * mask
    y = rng.normal(size=(B, M))

    def res(X):
        x = gputrack.to_numpy(X).astype(np.float64)
        b = np.arange(len(x)) // (len(x) // B)
        return np.einsum("bmp,bp->bm", A[b], x) - y[b] + 0.1 * np.sin(3 * x[:, P - 1 :])

    def jac(X):
        J = A.copy()
        J[:, :, P - 1] += 0.3 * np.cos(3 * gputrack.to_numpy(X)[:, P - 1 :].astype(np.float64))
        return J

    x0 = np.full((B, P), 0.05)
    tols = {"ftol": 0.0, "xtol": 0.0, "gtol": 0.0}
    got = least_squares(res, x0, device=device, jacobian=jac, lower=-0.3, upper=0.3, max_iter=5, **tols)
    ref = least_squares(res, x0, device=REF, jacobian=jac, lower=-0.3, upper=0.3, max_iter=5, dtype=got.dtype, **tols)
    f32 = got.dtype == np.float32
    assert_matches(device, got.x, ref.x, got.dtype, scale=1e3 if f32 else 1e2, err_msg=f"P={P} M={M}")
    assert_matches(device, got.cost, ref.cost, got.dtype, scale=1e3 if f32 else 1e2, err_msg=f"P={P} M={M}")
    if M > 1:  # one residual reaches a zero cost, where rounding decides between GTOL and MAX_ITER
        np.testing.assert_array_equal(got.status, ref.status)
        assert not mask.all()  # the case is block-sparse

    def nan_jac(X):
        J = jac(X)
        J[1, M - 1, 8] = np.nan  # problem 1: the one entry of row M - 1 in columns 8-15 (a block of 8)
        return J

    got = least_squares(res, x0, device=device, jacobian=nan_jac, max_iter=3, **tols)
    ref = least_squares(res, x0, device=REF, jacobian=nan_jac, max_iter=3, dtype=got.dtype, **tols)
    np.testing.assert_array_equal(got.status, ref.status)
    assert got.status[1] == Status.FAILED and np.isfinite(got.x).all()
    assert_matches(device, got.x, ref.x, got.dtype, scale=1e3 if f32 else 1e2, err_msg=f"P={P} M={M} NaN")

    def idle_jac(X):  # parameter 3 without effect: J^T J singular, not positive definite at C = 0
        J = jac(X)
        J[:, :, 3] = 0.0
        return J

    if M > 1:  # (one residual: J^T J of rank 1, whose damped steps rounding decides)
        got = least_squares(res, x0, device=device, jacobian=idle_jac, damping=0.0, max_iter=3, **tols)
        ref = least_squares(res, x0, device=REF, jacobian=idle_jac, damping=0.0, max_iter=3, dtype=got.dtype,
                            **tols)  # fmt: skip
        assert_matches(device, got.x, ref.x, got.dtype, scale=1e3 if f32 else 1e2, err_msg=f"P={P} M={M} singular")
        assert (got.damping > 0).all()  # raised from 0 until the factorisation succeeded


# P = 40, 92: the runtime-P update (the face bundle's P = 92); P = 20: built in, 5 work-items
@pytest.mark.parametrize("P", [3, 20, 40, 92])
def test_step_shared_out_matches_reference(device, P, monkeypatch):
    """The update with its step shared out over the problem's work-group (OpenCL on GPUs,
    ``LM_WG_STEP``, forced here on any OpenCL device) or CUDA block (taichi:cuda, ``_step_block``):
    the Cholesky column by column, the triangular solves, the predicted reduction. It gives the
    reference's solve: with a Jacobian callable and with central differences, parameters held at
    the box's bounds, and a start whose J^T J is singular (the damping raised until the
    factorisation succeeds)."""
    if device.backend == "opencl":
        from gputrack.backends.opencl import lm as ocl

        monkeypatch.setattr(ocl, "step_per_work_group", lambda dev: True)
    elif device.spec != "taichi:cuda":
        pytest.skip("the step is shared out on OpenCL devices (forced) and on taichi:cuda (block barriers)")
    B, M = 2, P + 9
    res, jac = _linear_sine(B, M, P, seed=200 + P)
    x0 = np.full((B, P), 0.05)
    # no tolerances: these problems reach their minimum within 5 iterations, where a relative
    # reduction of ~1e-8 against ftol = 1e-8 stopped the solve one iteration apart on an H100 (its
    # rounding) and on the reference
    tols = {"ftol": 0.0, "xtol": 0.0, "gtol": 0.0}
    for kw in ({"jacobian": jac}, {}):
        got = least_squares(res, x0, device=device, lower=-0.3, upper=0.3, max_iter=5, **tols, **kw)
        ref = least_squares(res, x0, device=REF, lower=-0.3, upper=0.3, max_iter=5, dtype=got.dtype, **tols, **kw)
        f32 = got.dtype == np.float32
        what = f"P={P} {'jacobian' if kw else 'central'}"
        assert_matches(device, got.x, ref.x, got.dtype, scale=1e3 if f32 else 1e2, err_msg=what)
        assert_matches(device, got.cost, ref.cost, got.dtype, scale=1e3 if f32 else 1e2, err_msg=what)
        assert ((got.x == -0.3) | (got.x == 0.3)).any(), what  # some parameters end at a bound
        np.testing.assert_array_equal(got.status, ref.status, err_msg=what)
    # J^T J of rank 1 at C = 0: not positive definite until the damping is raised
    flat = lambda X: np.repeat(gputrack.to_numpy(X)[:, :1] - 1.0, M, axis=1).astype(gputrack.to_numpy(X).dtype)
    x1 = np.zeros((B, P))
    got = least_squares(flat, x1, device=device, damping=0.0, max_iter=3)
    ref = least_squares(flat, x1, device=REF, damping=0.0, max_iter=3, dtype=got.dtype)
    assert_matches(device, got.x, ref.x, got.dtype, scale=1e3, err_msg=f"P={P} rank 1")
    np.testing.assert_array_equal(got.status, ref.status)


def test_jacobian_callable(device):
    def jac(X):
        Xn = gputrack.to_numpy(X).astype(np.float64)
        a, b = Xn[:, :1, None], Xn[:, 1:2, None]
        e = np.exp(b * T_EXP[None, :, None])
        return np.concatenate([e, a * T_EXP[None, :, None] * e], axis=2).astype(gputrack.to_numpy(X).dtype)

    x0 = np.array([[1.0, 0.0], [4.0, -3.0]])
    res = least_squares(host_residual(expfit), x0, device=device, jacobian=jac, max_iter=50)
    # a float32 Jacobian with float64 residuals is accepted (converted where it is read)
    res32 = least_squares(
        host_residual(expfit), x0, device=device, max_iter=50, jacobian=lambda X: jac(X).astype(np.float32)
    )
    np.testing.assert_allclose(res32.x, res.x, rtol=1e-4)
    central = least_squares(host_residual(expfit), x0, device=device, max_iter=50)
    np.testing.assert_allclose(res.x, central.x, rtol=1e-7)
    assert res.njev == res.nfev and res.npoints == res.nfev * 2


# ------------------------------------------------------------------------------------------------
# residual functions on the device, traffic, bad input


def test_device_residual_and_no_download_per_iteration(device):
    """A residual returning device arrays; with early_stop=False nothing but the result is downloaded."""
    moved = {"d2h": 0}

    def res(X):
        Xn = gputrack.to_numpy(X)
        moved["d2h"] += Xn.nbytes if device.backend != "numpy" else 0
        out = rosenbrock(Xn.astype(np.float64)).astype(Xn.dtype)
        return device.asarray(out)

    x0 = np.array([[-1.2, 1.0], [2.0, 2.0]])
    before = device.transfers.copy()
    out = least_squares(res, x0, device=device, max_iter=40, early_stop=False)
    moved_d2h = (device.transfers - before).d2h
    if device.backend != "numpy":
        lay = Layout(2, 2, 2)
        dt = np.dtype(out.dtype)
        assert moved_d2h == moved["d2h"] + 2 * lay.OB * dt.itemsize  # the result block only
    np.testing.assert_allclose(out.x, 1.0, atol=1e-6)


def _linear_problems(B, P, M, seed=3):
    """B linear least-squares problems r = X A_b^T - y_b with M residuals (host residual function
    that records its own traffic: X downloaded, its NumPy output uploaded by the solver)."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(B, M, P))
    y = rng.normal(size=(B, M))
    own = {"h2d": 0, "d2h": 0}

    def res(X):
        Xn = gputrack.to_numpy(X)
        n = Xn.shape[0]
        b = np.arange(n) // (n // B)
        out = (np.einsum("bmp,bp->bm", A[b], Xn.astype(np.float64)) - y[b]).astype(Xn.dtype)
        if not isinstance(X, np.ndarray):
            own["d2h"] += Xn.nbytes
            own["h2d"] += out.nbytes
        return out

    return res, own


def _moved(device, fn, own, x0, **kw):
    """Bytes the solver itself moved (the residual function's own traffic taken out)."""
    before, own0 = device.transfers.copy(), dict(own)
    out = least_squares(fn, x0, device=device, **kw)
    d = device.transfers - before
    return {"h2d": d.h2d - (own["h2d"] - own0["h2d"]), "d2h": d.d2h - (own["d2h"] - own0["d2h"])}, out


@pytest.mark.parametrize("early_stop", [False, True])
def test_a_solve_moves_its_inputs_and_results_only_independent_of_M(device, early_stop):
    B, P = 3, 5
    x0 = np.random.default_rng(0).normal(size=(B, P))  # not exact in float32
    x0_32 = x0.astype(np.float32).astype(np.float64)  # exact in float32: uploaded as float32
    moved = {}
    for M in (256, 1280):
        fn, own = _linear_problems(B, P, M)
        kw = {"max_iter": 4, "early_stop": early_stop}
        _moved(device, fn, own, x0, damping=1e-3, **kw)  # other constants in the pooled buffer
        first, out = _moved(device, fn, own, x0, **kw)
        again, out2 = _moved(device, fn, own, x0, **kw)  # same constants: not uploaded again
        as32, out32 = _moved(device, fn, own, x0_32, **kw)
        np.testing.assert_array_equal(out.x, out2.x)
        if device.backend == "numpy":
            assert first == again == as32 == {"h2d": 0, "d2h": 0}
            continue
        dt = np.dtype(out.dtype)
        lay = Layout(B, P, M)

        def down(res):  # the results, and with early_stop one int-block download per iteration that did
            checks = 0  # not end the loop (each solve's own count: x0_32 may converge sooner)
            if early_stop:
                checks = res.nfev if res.nfev - 1 < kw["max_iter"] else res.nfev - 1
            return B * lay.OB * dt.itemsize + checks * lay.i_size() * 4

        assert first == {"h2d": B * P * dt.itemsize + lay.k_size() * dt.itemsize, "d2h": down(out)}
        assert again == {"h2d": B * P * dt.itemsize, "d2h": down(out2)}
        assert as32 == {"h2d": B * P * 4, "d2h": down(out32)}
        moved[M] = (first, again, as32)
    if device.backend != "numpy" and not early_stop:
        assert moved[256] == moved[1280]


def test_the_mask_is_part_of_the_cached_constants(device):
    B, P, M = 2, 3, 13
    fn, own = _linear_problems(B, P, M)
    mask = np.ones((M, P), bool)
    mask[::2, 0] = False
    x0 = np.full((B, P), 0.5)
    kw = {"max_iter": 3, "early_stop": False}
    _moved(device, fn, own, x0, **kw)  # other constants (no mask: another K size)
    first, out = _moved(device, fn, own, x0, jac_sparsity=mask, **kw)
    again, _ = _moved(device, fn, own, x0, jac_sparsity=mask, **kw)
    mask2 = mask.copy()
    mask2[1, 1] = False
    changed, _ = _moved(device, fn, own, x0, jac_sparsity=mask2, **kw)
    if device.backend == "numpy":
        assert first == again == changed == {"h2d": 0, "d2h": 0}
        return
    dt = np.dtype(out.dtype)
    k = Layout(B, P, M, has_mask=True).k_size() * dt.itemsize
    assert k == (B * (2 * P + 1) + P + 8 + M * P) * dt.itemsize
    x = B * P * 4  # 0.5 is exact in float32
    assert (first["h2d"], again["h2d"], changed["h2d"]) == (x + k, x, x + k)

    # a residual function taking the row masks: they are cached with the constants
    def res_rows(X, rows):
        return fn(X)

    _moved(device, res_rows, own, x0, jac_sparsity=mask2, **kw)  # other row masks in the buffers
    first, _ = _moved(device, res_rows, own, x0, jac_sparsity=mask, **kw)
    again, out = _moved(device, res_rows, own, x0, jac_sparsity=mask, **kw)
    need = B * (2 * P + 1) * M  # uint8; the (B, M) all-ones mask of the last call is unchanged
    assert (first["h2d"], again["h2d"]) == (x + k + need, x)
    assert again["d2h"] == B * (P + 5) * dt.itemsize


def test_x0_on_the_device(device):
    x0 = np.array([[-1.2, 1.0], [2.0, 2.0]])
    a = least_squares(host_residual(rosenbrock), device.asarray(x0), device=device, max_iter=30)
    b = least_squares(host_residual(rosenbrock), x0, device=device, max_iter=30)
    np.testing.assert_array_equal(a.x, b.x)
    if device.backend != "numpy":
        other = gputrack.device("numpy")
        with pytest.raises(ValueError, match="x0: expected an array on numpy"):
            least_squares(host_residual(rosenbrock), device.asarray(x0), device=other)


def test_nested_and_repeated_solves_reuse_buffers_safely(device):
    x0 = np.array([[-1.2, 1.0], [2.0, 2.0]])
    alone = least_squares(host_residual(rosenbrock), x0, device=device, max_iter=40)
    inner_results = []

    def res(X):
        # a solve of the same shapes inside the residual function must not disturb the outer one
        inner_results.append(least_squares(host_residual(rosenbrock), x0, device=device, max_iter=2).x)
        return host_residual(rosenbrock)(X)

    outer = least_squares(res, x0, device=device, max_iter=40)
    np.testing.assert_array_equal(outer.x, alone.x)
    assert all(np.array_equal(r, inner_results[0]) for r in inner_results)
    again = least_squares(host_residual(rosenbrock), x0, device=device, max_iter=40)
    np.testing.assert_array_equal(again.x, alone.x)


def test_solver_bad_input(device):
    f = host_residual(rosenbrock)
    with pytest.raises(ValueError, match="x0: expected finite"):
        least_squares(f, np.array([[np.nan, 1.0]]), device=device)
    with pytest.raises(ValueError, match=r"x0: expected shape \(B, P\)"):
        least_squares(f, np.zeros(2), device=device)
    with pytest.raises(TypeError, match="x0: expected a float"):
        least_squares(f, np.array([["a", "b"]]), device=device)
    with pytest.raises(ValueError, match="residuals: expected a result of shape"):
        least_squares(lambda X: np.zeros((3, 2)), np.zeros((1, 2)), device=device)
    with pytest.raises(TypeError, match="residuals: expected a float32 or float64"):
        least_squares(lambda X: np.zeros((X.shape[0], 2), np.int32), np.zeros((1, 2)), device=device)
    with pytest.raises(ValueError, match="jacobian: expected 'central', 'forward' or a callable"):
        least_squares(f, np.zeros((1, 2)), device=device, jacobian="backward")
    with pytest.raises(ValueError, match="damping: expected"):
        least_squares(f, np.zeros((1, 2)), device=device, damping=-1)
    with pytest.raises(ValueError, match="step: expected"):
        least_squares(f, np.zeros((1, 2)), device=device, step=[1e-3, 0])
    with pytest.raises(ValueError, match="max_iter: expected"):
        least_squares(f, np.zeros((1, 2)), device=device, max_iter=-1)
    with pytest.raises(ValueError, match="ftol: expected"):
        least_squares(f, np.zeros((1, 2)), device=device, ftol=np.nan)
    with pytest.raises(TypeError, match="dtype: expected"):
        least_squares(f, np.zeros((1, 2)), device=device, dtype=np.int32)

    # the output shape changing after the first call
    n_calls = []

    def shrinking(X):
        n_calls.append(1)
        Xn = gputrack.to_numpy(X)
        out = rosenbrock(Xn.astype(np.float64)).astype(Xn.dtype)
        return out if len(n_calls) == 1 else np.concatenate([out, out[:, :1]], axis=1)

    with pytest.raises(ValueError, match="residuals: expected a result of shape"):
        least_squares(shrinking, np.zeros((1, 2)), device=device, max_iter=3)


def test_real_numbers_only(device):
    """A complex or object damping (or bound, step, tolerance) is refused, not silently cast (the
    imaginary part was dropped)."""
    dt = _fdt(device)
    JtJ, Jtr = np.tile(np.eye(3, dtype=dt), (2, 1, 1)), np.ones((2, 3), dt)
    for bad, name in ((np.array([1 + 1j, 1]), "complex128"), (np.array([1.0, None], dtype=object), "object")):
        want = rf"^damping: expected real numbers, got dtype {name}\Z"
        with pytest.raises(TypeError, match=want):
            lm.lm_step(device, JtJ, Jtr, bad)
        with pytest.raises(TypeError, match=want):
            lm.lm_solve(device, np.ones((2, 4, 3), dt), np.ones((2, 4), dt), bad)
    f = host_residual(rosenbrock)
    with pytest.raises(TypeError, match=r"^damping: expected real numbers, got dtype complex128\Z"):
        least_squares(f, np.zeros((1, 2)), device=device, damping=1e-3 + 1j)
    with pytest.raises(TypeError, match=r"^lower: expected real numbers, got dtype complex128\Z"):
        least_squares(f, np.zeros((1, 2)), device=device, lower=[0j, 0])
    with pytest.raises(TypeError, match=r"^step: expected real numbers, got dtype object\Z"):
        least_squares(f, np.zeros((1, 2)), device=device, step=np.array([1e-3, None], dtype=object))
    with pytest.raises(TypeError, match=r"^ftol: expected a real number, got complex\Z"):
        least_squares(f, np.zeros((1, 2)), device=device, ftol=1e-8j)


def test_shapes_are_checked_before_any_value_is_read(device):
    """Broadcast views of 2**32 rows of the wrong shape are rejected without being copied or scanned;
    a solve too large for the device is refused before its points are checked."""
    f = host_residual(rosenbrock)
    rows = np.broadcast_to(np.zeros(1), (2**32, 2))
    rejects_without_allocating(ValueError, r"^lower: expected shape \(P=2,\) or \(B=1, P=2\), got shape \(4294967296, 2\)\Z",
                               lambda: least_squares(f, np.zeros((1, 2)), device=device, lower=rows))  # fmt: skip
    rejects_without_allocating(ValueError, r"^damping: expected a finite number >= 0 or \(B=4294967296,\) of them, got shape \(5,\)\Z",
                               lambda: least_squares(f, rows, device=device, damping=np.ones(5)))  # fmt: skip
    rejects_without_allocating(MemoryError, r"^expected an array of at most .* got float(32|64) \(21474836480, 2\)",
                               lambda: least_squares(f, rows, device=device))  # fmt: skip
    JtJ = np.broadcast_to(np.eye(2), (2**32, 2, 2))
    rejects_without_allocating(ValueError, r"^Jtr: expected shape \(B=4294967296, P=2\), got \(5, 2\)\Z",
                               lambda: lm.lm_step(device, JtJ, np.ones((5, 2)), 1.0))  # fmt: skip
    rejects_without_allocating(ValueError, r"^damping: expected shape \(B=5\), got \(4294967296,\)\Z",
                               lambda: lm.lm_step(device, np.ones((5, 2, 2)), np.ones((5, 2)), rows[:, 0]))  # fmt: skip


def test_empty_batch_and_underdetermined(device):
    called = []
    out = least_squares(lambda X: called.append(1), np.zeros((0, 3)), device=device)
    assert out.x.shape == (0, 3) and not called and out.nfev == 0
    # M = 1 < P = 3: the damped step still reduces the cost to zero
    res = least_squares(
        host_residual(lambda X: X.sum(axis=1, keepdims=True) - 1), np.zeros((2, 3)), device=device, max_iter=20
    )
    np.testing.assert_allclose(res.x.sum(axis=1), 1.0, atol=1e-8)
    assert (res.status == Status.CONVERGED).all()


def test_selftest(device):
    from gputrack.selftest import check_lm

    check_lm(device)

"""Batched Levenberg-Marquardt: B = 10 problems, P = 14 and 20 params, M = 256 and 1280 residuals.

Cases per (P, M), each timed on the device with the NumPy reference in the same run:

- ``lm_solve``: normal equations + damped Cholesky step (the public fused op, J given as
  (B, M, P) on the device, outputs preallocated with ``out=``); peer: the same in batched NumPy
  (einsum + np.linalg.solve).
- ``lm init``: the solver's per-solve initialisation launch (state from x0 and the constants,
  the first 2P + 1 points per problem), inputs on the device.
- ``lm iteration``: the solver's fused per-iteration launch (Jacobian from the stacked residuals,
  J^T J, J^T r, acceptance, damping, damped Cholesky step, next points, result block), residuals
  on the device.
- ``least_squares 10 it RGB-D``: a whole 10-iteration solve (``early_stop=False``: exactly 11
  residual calls) whose residuals are paper 000's RGB-D template residuals (eq. 20-21) of the
  upper-body model with its block-sparse Jacobian (Fig. 2), as the body tracker runs it:
  ``pose_residuals(..., central=True)`` (forward kinematics + residuals, only the entries of
  ``jac_sparsity = chain.jacobian_sparsity(parts)`` in the perturbed rows), float32 points,
  N = N' = M / 2, the output array of the last call reused, on a synthetic 640x480 frame; peer:
  ``scipy.optimize.least_squares`` (trf, 3-point Jacobian, 10 iterations' worth of evaluations)
  looping over the 10 problems with the NumPy residuals.
- ``solver exp ... analytic J`` / ``... central`` / ``... forward``: a whole 10-iteration solve of B = 10
  fits of a sum of P / 2 exponentials to M = 256 samples (``sim.problems``-free: the model is written
  below), on a held :class:`gputrack.LeastSquaresSolver` (``early_stop=False``,
  ``damping_scale="minpack"``, ``diff`` central or forward), the residuals (and the analytic
  Jacobian) a vectorised NumPy callable of all B problems' points (``solve(..., host=True)``); peers:
  scipy's MINPACK (``least_squares(method="lm")``, the same callables per problem, 11 evaluations at
  trial points with the Jacobian and with forward differences, ``minpack_max_nfev``) in a loop over the
  10 problems; its residual calls per problem and the costs each reaches (the solver's over MINPACK's,
  max and median over the problems) are in the case's params. A second MINPACK column runs each
  problem to the solver's final cost (within 0.1 %): the fewest ``max_nfev`` that reaches it, searched
  before the timing (the budgets and the residual calls are in the params).
- ``... central, device residuals`` / ``... forward, device residuals``: the same solves with the
  residuals computed by a device kernel (gputrack/benchmarks/expfit_taichi.py,
  kernels/gt_bench_expfit.cl; DeviceArray points in and out), and ``exp residuals n=410 ... device
  kernel``: that kernel alone against the NumPy callable at the 410 stacked points of a
  central-difference iteration (float64 devices).
"""

import sys

import numpy as np

from ..sim.problems import lm_body_scene
from .harness import Case, bench_main

NAME = "lm"
B = 10


def add_arguments(parser):
    parser.add_argument("--params", type=int, action="append", help="P (14 or 20, repeatable; default both)")
    parser.add_argument("--residuals", type=int, action="append", help="M (even, repeatable; default 256 and 1280)")
    parser.add_argument("--iterations", type=int, default=10, help="LM iterations of the whole solve (default 10)")
    parser.add_argument("--no-scipy", action="store_true", help="skip the scipy.optimize.least_squares peer")
    parser.add_argument("--only-exp", action="store_true", help="only the exponential-fit solves (solver vs MINPACK)")


def _rgbd_residual_fn(device, chain, rgb, dep, gray, depth, cam):
    from ..ops.pose_residuals import pose_residuals
    from ..ops.template import RgbdScene

    scene = RgbdScene(rgb, dep, cam).to(device)  # once per template, as the tracker does
    g = device.asarray(gray)
    d = device.asarray(depth)
    buffers = {}  # per number of points: the residuals of the last call, reused

    def residuals(X):
        n = X.shape[0]
        r = pose_residuals(device, chain, X, scene, g, d, central=True, out=buffers.get(n))
        if device.backend != "numpy":  # the reference's results are NumPy arrays the caller may keep
            buffers[n] = r
        return r

    return residuals


T_EXP = np.linspace(0.0, 1.0, 256)


def exp_fits(B, P, M, rng):
    """B fits of y = sum_k a_k exp(b_k t) (P / 2 terms) to M samples: (residuals, jacobian, x0, one,
    one_jac): the first two vectorised NumPy callables over stacked points (row i belongs to problem
    i // (n / B)), the start points 20-50 % off the truth, and the same residuals and Jacobian of
    problem b at one point p (``one(p, b)``, for a solver called per problem).

    Each pair shares its exponentials: the Jacobian callable reuses those of the residual call just
    before it when the points are the same (both solvers evaluate the Jacobian at the point of their
    last residual call), as a hand-written model would; a residual call always computes them."""
    t = np.linspace(0.0, 1.0, M)
    tc = t[None, :, None]
    K = P // 2
    true = np.empty((B, P))
    true[:, 0::2] = rng.uniform(0.5, 2.0, (B, K))
    true[:, 1::2] = -np.linspace(0.5, 5.0, K) * rng.uniform(0.9, 1.1, (B, K))
    y = np.einsum("bkm->bm", true[:, 0::2, None] * np.exp(true[:, 1::2, None] * t))
    y += 0.01 * rng.normal(size=y.shape)
    x0 = true * rng.uniform(0.5, 0.8, true.shape)
    memo = {}

    def exps(Xn, key, reuse):
        """exp(b_k t) of every row of Xn, (n, M, K); the last one per key is kept (and with ``reuse``
        returned for the same points)."""
        last = memo.get(key)
        if reuse and last is not None and last[0].shape == Xn.shape and np.array_equal(last[0], Xn):
            return last[1]
        with np.errstate(over="ignore", invalid="ignore"):  # a far trial point: rejected by the solver
            e = np.exp(Xn[:, None, 1::2] * tc)
        memo[key] = (Xn.copy(), e)
        return e

    def rows(X):
        Xn = np.asarray(X.numpy() if hasattr(X, "numpy") else X, np.float64)
        return Xn, np.arange(Xn.shape[0]) // (Xn.shape[0] // B)

    def residuals(X):
        Xn, b = rows(X)
        with np.errstate(over="ignore", invalid="ignore"):
            return np.matmul(exps(Xn, "all", False), Xn[:, 0::2, None])[..., 0] - y[b]

    def jacobian(X):
        Xn, _ = rows(X)
        e = exps(Xn, "all", True)  # (n, M, K)
        J = np.empty((Xn.shape[0], M, K, 2))  # columns a_k, b_k interleaved
        J[..., 0] = e
        with np.errstate(over="ignore", invalid="ignore"):
            np.multiply(e, tc * Xn[:, None, 0::2], out=J[..., 1])
        return J.reshape(Xn.shape[0], M, P)

    def one(p, b):
        with np.errstate(over="ignore", invalid="ignore"):
            return exps(p[None], b, False)[0] @ p[0::2] - y[b]

    def one_jac(p, b):
        e = exps(p[None], b, True)[0]  # (M, K)
        J = np.empty((M, K, 2))
        J[..., 0] = e
        with np.errstate(over="ignore", invalid="ignore"):
            np.multiply(e, t[:, None] * p[0::2], out=J[..., 1])
        return J.reshape(M, P)

    residuals.data = (t, y)  # for the device version (``device_residuals``)
    return residuals, jacobian, x0, one, one_jac


def device_residuals(device, B, t, y):
    """The residuals of ``exp_fits`` as a device kernel (gputrack/benchmarks/expfit_taichi.py,
    kernels/gt_bench_expfit.cl): ``residuals(X)`` takes the solver's DeviceArray points and returns a
    DeviceArray (one output array per number of points, reused); float64 devices only."""
    td, yd = device.asarray(t), device.asarray(y)
    M = t.size
    outs = {}
    if device.backend == "taichi":
        from .expfit_taichi import expfit

        def launch(X, R, nper):
            expfit(X.buffer, td.buffer, yd.buffer, R.buffer, nper)

    else:
        import pyopencl as cl

        from ..backends.opencl.program import enqueue, ndrange

        kernel = cl.Kernel(device.program("gt_bench_expfit.cl"), "gt_bench_expfit")

        lanes = 8  # GT_EXPFIT_LANES of gt_bench_expfit.cl (its double8): one work-item per (group, point)

        def launch(X, R, nper):
            # one row of points per work-group column: the kernel skips only the padding past M
            enqueue(device, kernel, *ndrange((M + lanes - 1) // lanes, X.shape[0], group=(8, 1)), X.buffer.data,
                    td.buffer.data, yd.buffer.data, R.buffer.data, np.int32(X.shape[1]), np.int32(M),
                    np.int32(nper))  # fmt: skip

    def residuals(X):
        n = X.shape[0]
        R = outs.get(n)
        if R is None:
            R = outs[n] = device.empty((n, M), np.float64)
        launch(X, R, n // B)
        return R

    return residuals


def exp_cases(device, args, B=10, P=20, M=256, iterations=10):
    """The whole-solve comparison with scipy's MINPACK (see the module docstring)."""
    from ..ops.lm import LeastSquaresSolver
    from ..registry import device as get_device

    ref = get_device("numpy")
    rng = np.random.default_rng(1)
    res, jac, x0, one, one_j = exp_fits(B, P, M, rng)
    on_device = device.fp64 and device.backend in ("taichi", "opencl")
    dres = device_residuals(device, B, *res.data) if on_device else None
    out = []
    kinds = [("analytic J", "central", res), ("central", "central", res), ("forward", "forward", res)]
    if dres is not None:
        kinds += [("central, device residuals", "central", dres), ("forward, device residuals", "forward", dres)]
    for kind, diff, fn in kinds:
        solvers = {d: LeastSquaresSolver(d, (B, P), max_iter=iterations, early_stop=False, damping_scale="minpack",
                                         diff=diff, **TOL) for d in (device, ref)}  # fmt: skip
        kw = {"jacobian": jac} if kind == "analytic J" else {}
        host = fn is res  # NumPy callables: NumPy points (``host=True``)
        peers = {}
        if not args.no_scipy:
            import scipy.optimize

            jacobian = kind == "analytic J"
            calls = {}  # residual calls per problem of each peer's last run

            def minpack(budgets, label, problems=range(B), jacobian=jacobian, calls=calls):
                """MINPACK on each of ``problems`` with ``budgets[b]`` as ``max_nfev``: the final costs."""
                costs, n = [], [0]

                def counted(p, b):
                    n[0] += 1
                    return one(p, b)

                for b in problems:
                    o = scipy.optimize.least_squares(counted, x0[b], jac=one_j if jacobian else "2-point", args=(b,),
                                                     method="lm", max_nfev=int(budgets[b]), **TOL)  # fmt: skip
                    costs.append(2 * o.cost)
                calls[label] = n[0] / len(problems)
                return np.array(costs)

            same = [iterations + 1 if jacobian else minpack_max_nfev(iterations, P)] * B
            peers["scipy MINPACK lm x10"] = lambda same=same, minpack=minpack: minpack(same, "same")
        run = (lambda s=solvers[device], kw=kw, fn=fn, host=host: s.solve(fn, x0, host=host, **kw))
        name = f"solver exp B={B} M={M} P={P} {iterations} it {kind}"
        params = {"B": B, "M": M, "P": P, "iterations": iterations, "jacobian": kind, "damping_scale": "minpack",
                  "residuals": "device kernel" if fn is dres else "vectorised NumPy callable (host=True)"}
        if not args.no_scipy:
            mine, theirs = run().cost, peers["scipy MINPACK lm x10"]()
            params["cost / MINPACK's cost, max"] = float(np.max(mine / theirs))
            params["cost / MINPACK's cost, median"] = float(np.median(mine / theirs))
            params["MINPACK's residual calls per problem"] = calls["same"]
            reach = [_budget_to_cost(lambda nf, b=b: minpack([nf] * B, "search", [b])[0], mine[b], 10 * same[b])
                     for b in range(B)]  # fmt: skip
            peers["scipy MINPACK lm x10 to the solver's cost"] = lambda reach=reach, minpack=minpack: minpack(reach, "reach")
            peers["scipy MINPACK lm x10 to the solver's cost"]()
            params["MINPACK's max_nfev to the solver's cost, per problem"] = [int(v) for v in reach]
            params["MINPACK's residual calls per problem to the solver's cost"] = calls["reach"]
        out.append(Case(
            name,
            run=run,
            reference=lambda s=solvers[ref], kw=kw: s.solve(res, x0, **kw),
            peers=peers,
            params=params,
        ))  # fmt: skip
    if dres is not None:
        # the residual call alone, at the 410 stacked points of a central-difference iteration
        Xh = np.repeat(x0, 2 * P + 1, axis=0)
        Xd = device.asarray(Xh)
        out.append(Case(
            f"exp residuals n={B * (2 * P + 1)} M={M} device kernel",
            run=lambda: dres(Xd),
            reference=lambda: res(Xh),
            params={"n": B * (2 * P + 1), "M": M, "P": P, "reference": "the NumPy callable"},
        ))  # fmt: skip
    return out


TOL = {"ftol": 1e-10, "xtol": 1e-10, "gtol": 1e-10}


def _budget_to_cost(cost_at, target: float, cap: int) -> int:
    """The fewest ``max_nfev`` with which ``cost_at(max_nfev)`` (MINPACK's final cost on one problem, not
    rising with its budget: a longer run extends the same iterations) is within 0.1 % of ``target``;
    ``cap`` if even that budget does not reach it."""
    lo, hi, limit = 1, cap, target * 1.001
    if cost_at(hi) > limit:
        return cap
    while lo < hi:
        mid = (lo + hi) // 2
        if cost_at(mid) <= limit:
            hi = mid
        else:
            lo = mid + 1
    return lo


def minpack_max_nfev(iterations: int, P: int) -> int:
    """scipy's ``max_nfev`` for ``iterations`` LM iterations of ``least_squares(method="lm")`` without a
    Jacobian callable, the budget the solver's ``max_iter`` gives: up to scipy 1.15 it counts the P
    evaluations of each forward-difference Jacobian as well, from 1.16 on only the evaluations at the
    trial points (as with a Jacobian callable; measured with scipy 1.17: ``max_nfev`` = 231 made 3892
    residual calls for one of these fits, 11 made 132)."""
    import scipy

    major, minor = (int(v) for v in scipy.__version__.split(".")[:2])
    return iterations + 1 if (major, minor) >= (1, 16) else (iterations + 1) * (P + 1)


def cases(device, args):
    from ..registry import device as get_device

    if args.only_exp:
        return exp_cases(device, args)
    from ..ops import lm
    from ..ops.lm import Layout, _constants, least_squares

    ref = get_device("numpy")
    dt = np.float64 if device.fp64 else np.float32
    out = []
    rng = np.random.default_rng(0)
    for P in args.params or [14, 20]:
        for M in args.residuals or [256, 1280]:
            params = {"B": B, "P": P, "M": M, "dtype": np.dtype(dt).name}
            # 1. the fused op
            J = rng.normal(size=(B, M, P)).astype(dt)
            r = rng.normal(size=(B, M)).astype(dt)
            C = np.full(B, 1e-5, dt)
            Jd, rd, Cd = device.asarray(J), device.asarray(r), device.asarray(C)

            def numpy_batched(J=J, r=r, C=C, P=P):
                A = np.einsum("bmi,bmj->bij", J, J) + C[:, None, None] * np.eye(P)
                return np.linalg.solve(A, np.einsum("bmi,bm->bi", J, r)[..., None])[..., 0]

            res_d = (device.empty((B, P), dt), device.empty((B,), np.int32))
            res_r = (np.empty((B, P), dt), np.empty(B, np.int32))
            out.append(
                Case(
                    f"lm_solve B={B} M={M} P={P}",
                    run=lambda Jd=Jd, rd=rd, Cd=Cd, o=res_d: lm.lm_solve(device, Jd, rd, Cd, out=o),
                    reference=lambda J=J, r=r, C=C, o=res_r: lm.lm_solve(ref, J, r, C, out=o),
                    peers={"numpy batched": numpy_batched},
                    params=params,
                )
            )
            # 2. the solver's per-iteration launch, residuals already on the device
            lay = Layout(B, P, M)
            x0 = rng.normal(size=(B, P)).astype(dt)
            lo, hi, h = np.full((B, P), -np.inf), np.full((B, P), np.inf), np.zeros(P)
            K = _constants(lay, lo, hi, h, np.full(B, 1e-5), (1e-8, 1e-8, 1e-8), np.dtype(dt))
            R = rng.normal(size=(B * (2 * P + 1), M)).astype(np.float32)
            be, be_ref = lm.backend_module(device, "lm"), lm.backend_module(ref, "lm")

            def state(dev, be, empty, lay=lay):
                st = be.solver_state(
                    dev, lay, empty((lay.s_size(),), dt), empty((lay.i_size(),), np.int32), empty((B, lay.OB), dt)
                )
                be.solver_workspace(st, lay, empty((lay.w_size(),), dt))
                return st

            st, st_ref = state(device, be, device.empty), state(ref, be_ref, np.empty)
            Kd, X0d, Rd = device.asarray(K), device.asarray(x0), device.asarray(R)
            Xd, Xr = device.empty((B * (2 * P + 1), P), dt), np.empty((B * (2 * P + 1), P), dt)
            be.solver_init(st, X0d, Kd, Xd)
            be_ref.solver_init(st_ref, x0, K, Xr)
            if M == (args.residuals or [256])[0]:
                out.append(
                    Case(
                        f"lm init B={B} P={P}",
                        run=lambda st=st, X0d=X0d, Kd=Kd, Xd=Xd, be=be: be.solver_init(st, X0d, Kd, Xd),
                        reference=lambda st=st_ref, x0=x0, K=K, Xr=Xr, be=be_ref: be.solver_init(st, x0, K, Xr),
                        params={"B": B, "P": P, "dtype": np.dtype(dt).name},
                    )
                )
            out.append(
                Case(
                    f"lm iteration B={B} M={M} P={P}",
                    run=lambda st=st, Rd=Rd, Xd=Xd, be=be: be.solver_update(st, Rd, Xd, first=True, final=False),
                    reference=lambda st=st_ref, R=R, Xr=Xr, be=be_ref: be.solver_update(
                        st, R, Xr, first=True, final=False
                    ),
                    params={**params, "residual dtype": "float32"},
                )
            )
            # 3. a whole solve with the RGB-D template residuals
            if M % 2:
                continue
            chain, rgb, dep, gray, depth, cam, x0 = lm_body_scene(P, M, rng, B)
            fn = _rgbd_residual_fn(device, chain, rgb, dep, gray, depth, cam)
            fn_ref = _rgbd_residual_fn(ref, chain, rgb, dep, gray, depth, cam)
            sparsity = chain.jacobian_sparsity(np.concatenate([rgb.part, dep.part]))  # Fig. 2
            kw = {"max_iter": args.iterations, "points_dtype": np.float32, "early_stop": False,
                  "jac_sparsity": sparsity}  # fmt: skip
            peers = {}
            if not args.no_scipy:
                import scipy.optimize

                def one(p, fn_ref=fn_ref):
                    return fn_ref(p[None, :].astype(np.float32))[0].astype(np.float64)

                def scipy_loop(x0=x0, P=P, one=one):
                    for b in range(B):
                        scipy.optimize.least_squares(
                            one, x0[b], method="trf", jac="3-point", max_nfev=args.iterations + 1
                        )

                peers["scipy least_squares x10"] = scipy_loop
            out.append(
                Case(
                    f"least_squares {args.iterations} it RGB-D B={B} M={M} P={P}",
                    run=lambda fn=fn, x0=x0, kw=kw: least_squares(fn, x0, device=device, **kw),
                    reference=lambda fn=fn_ref, x0=x0, kw=kw: least_squares(fn, x0, device=ref, **kw),
                    peers=peers,
                    params={
                        **params,
                        "N": M // 2,
                        "N'": M // 2,
                        "iterations": args.iterations,
                        "points dtype": "float32",
                        "jacobian": "block-sparse (Fig. 2)",
                    },
                )
            )
    return out + exp_cases(device, args)


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

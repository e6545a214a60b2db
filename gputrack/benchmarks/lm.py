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
"""

import sys

import numpy as np

from .harness import Case, bench_main
from ..sim.problems import lm_body_scene

NAME = "lm"
B = 10


def add_arguments(parser):
    parser.add_argument("--params", type=int, action="append", help="P (14 or 20, repeatable; default both)")
    parser.add_argument("--residuals", type=int, action="append", help="M (even, repeatable; default 256 and 1280)")
    parser.add_argument("--iterations", type=int, default=10, help="LM iterations of the whole solve (default 10)")
    parser.add_argument("--no-scipy", action="store_true", help="skip the scipy.optimize.least_squares peer")


def _rgbd_residual_fn(device, chain, rgb, dep, gray, depth, cam):
    from ..ops.pose_residuals import pose_residuals

    g = device.asarray(gray)
    d = device.asarray(depth)
    buffers = {}  # per number of points: the residuals of the last call, reused

    def residuals(X):
        n = X.shape[0]
        r = pose_residuals(device, chain, X, rgb, dep, g, d, cam, central=True, out=buffers.get(n))
        if device.backend != "numpy":  # the reference's results are NumPy arrays the caller may keep
            buffers[n] = r
        return r

    return residuals


def cases(device, args):
    from ..registry import device as get_device
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
    return out


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))

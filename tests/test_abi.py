"""gputrack/abi.py is the one source of the status codes and packed layouts: every backend's
kernels write the codes and slots that Python reads."""

import re
from pathlib import Path

import numpy as np
import pytest

import gputrack
from gputrack.abi import KalmanStatus, LMLayout, LMReason, LMStatus, cl_defines
from gputrack.ops import backend_module
from gputrack.ops.kalman import ekf_update_stereo, kf_update
from gputrack.ops.lm import Layout, _constants

ROOT = Path(__file__).resolve().parents[1]
REF = gputrack.device("numpy")


def test_the_ops_re_export_the_abi_enums():
    from gputrack.ops import kalman, lm

    assert gputrack.KalmanStatus is kalman.KalmanStatus is KalmanStatus
    assert gputrack.LMStatus is lm.LMStatus is LMStatus
    assert set(lm.REASONS) == set(LMReason)


def test_kalman_kernels_write_every_status_code(device):
    """One batch whose tracks end UPDATED, SKIPPED (NaN observation, mask), NOT_PD (an indefinite
    R) and, for the stereo EKF, BAD_DEPTH (state behind the camera), on every backend."""
    T = 5
    x = np.zeros((T, 6), np.float32)
    x[:, 4] = 5.0
    x[4, 4] = -1.0  # behind the camera
    P = np.tile(np.eye(6, dtype=np.float32), (T, 1, 1))
    H = np.zeros((3, 6), np.float32)
    H[0, 0] = H[1, 2] = H[2, 4] = 1
    R = np.tile(np.eye(3, dtype=np.float32), (T, 1, 1))
    R[2] = -10 * np.eye(3)  # S = H P H^T + R not positive definite
    z = np.ones((T, 3), np.float32)
    z[1, 0] = np.nan
    mask = np.array([1, 1, 1, 0, 1], np.uint8)
    got = gputrack.to_numpy(kf_update(device, x, P, z, H, R, mask=mask).status)
    want = [KalmanStatus.UPDATED, KalmanStatus.SKIPPED, KalmanStatus.NOT_PD, KalmanStatus.SKIPPED,
            KalmanStatus.UPDATED]  # fmt: skip
    np.testing.assert_array_equal(got, np.array(want, np.uint8))
    zs = np.stack([np.full(T, 10.0), np.full(T, 5.0), np.full(T, 20.0)], 1).astype(np.float32)
    st = gputrack.to_numpy(ekf_update_stereo(device, x, P, zs, R, f=400.0, b=0.1).status)
    assert st[4] == KalmanStatus.BAD_DEPTH and st[2] == KalmanStatus.NOT_PD and st[0] == KalmanStatus.UPDATED
    assert {int(s) for s in KalmanStatus} == set(np.concatenate([got, st]).tolist())


def _rosenbrock(X):
    X = np.asarray(X, np.float64)
    return np.stack([10 * (X[:, 1] - X[:, 0] ** 2), 1 - X[:, 0]], 1)


def _packed_states(device, steps=4):
    """The LM solver's packed arrays (S, I, Out) after init and after each of ``steps`` updates,
    driving the backend's solver functions as gputrack.ops.lm does (central differences)."""
    be = backend_module(device, "lm")
    B, P, M = 3, 2, 2
    dt = np.dtype(np.float32)
    lay = Layout(B, P, M)
    lo, hi = np.full((B, P), -5.0), np.full((B, P), [5.0, 0.5])  # x2 <= 0.5: a bound is active
    K = _constants(lay, lo, hi, np.zeros(P), np.full(B, 1e-3), (1e-10, 1e-10, 1e-10), dt)
    X0 = np.array([[-1.2, 1.0], [2.0, 2.0], [0.5, 0.25]], np.float32)
    X0[1] = np.minimum(X0[1], hi[1])

    def on(a):
        return a if device.backend == "numpy" else device.asarray(a)

    def empty(shape, dtype):
        return np.empty(shape, dtype) if device.backend == "numpy" else device.empty(shape, dtype)

    S, I, Out = empty((lay.s_size(),), dt), empty((lay.i_size(),), np.int32), empty((B, lay.OB), dt)
    X = empty((B * (2 * P + 1), P), dt)
    state = be.solver_state(device, lay, S, I, Out)
    be.solver_init(state, on(X0), on(K), X)
    be.solver_workspace(state, lay, empty((lay.w_size(),), dt))
    got = [(gputrack.to_numpy(S).copy(), gputrack.to_numpy(I).copy(), None)]
    for it in range(steps):
        R = on(_rosenbrock(gputrack.to_numpy(X)).astype(dt))
        be.solver_update(state, R, X, first=it == 0, final=it == steps - 1)
        got.append((gputrack.to_numpy(S).copy(), gputrack.to_numpy(I).copy(), gputrack.to_numpy(Out).copy()))
    return lay, got


def test_lm_kernels_pack_their_state_as_the_layout_says(device):
    """Every slot of the packed state (S, I, Out) that a backend's kernels write equals the NumPy
    reference's, which reads them through Layout's named views: after init (copies: exact) and
    after each update (status, iterations, reason and flags exact; values to float32 rounding)."""
    lay, want = _packed_states(REF)
    _, got = _packed_states(device)
    for step, ((S, I, Out), (Sw, Iw, Ow)) in enumerate(zip(got, want)):
        np.testing.assert_array_equal(I, Iw, err_msg=f"I after step {step}")
        if step == 0:
            np.testing.assert_array_equal(S, Sw, err_msg="S after init")
            continue
        np.testing.assert_allclose(S, Sw, rtol=2e-4, atol=1e-5, err_msg=f"S after step {step}")
        np.testing.assert_allclose(Out, Ow, rtol=2e-4, atol=1e-5, err_msg=f"Out after step {step}")
        ib = lay.iblock(I)
        P = lay.P
        np.testing.assert_array_equal(Out[:, P + LMLayout.O_STATUS], ib[:, LMLayout.I_STATUS])
        np.testing.assert_array_equal(Out[:, P + LMLayout.O_ITER], ib[:, LMLayout.I_ITER])
        np.testing.assert_array_equal(Out[:, P + LMLayout.O_REASON], ib[:, LMLayout.I_REASON])
    final = lay.iblock(got[-1][1])
    assert set(final[:, LMLayout.I_STATUS]) <= {int(s) for s in LMStatus} - {LMStatus.RUNNING}
    assert (final[:, LMLayout.I_REASON] != LMReason.RUNNING).all()


def test_opencl_builds_get_every_abi_define(device):
    if device.backend != "opencl":
        pytest.skip("OpenCL build options")
    import pyopencl as cl

    for source, defines in (("gt_lm.cl", {}), ("gt_kalman.cl", {}), ("gt_template.cl", {"LANES": 1})):
        prg = device.program(source, defines)
        options = prg.get_build_info(device.cl_device, cl.program_build_info.OPTIONS).split()
        for name, value in cl_defines().items():
            assert f"-D{name}={value}" in options, (source, name)


def test_kernel_sources_hold_no_copy_of_the_abi_and_use_only_its_names():
    defines = cl_defines()
    sources = {p.name: p.read_text() for p in (ROOT / "kernels").glob("*.cl*")}
    used = set()
    for name, text in sources.items():
        assert not re.search(r"#\s*define\s+GT_(KF|LM)_", text), f"{name} defines an ABI name itself"
        used |= set(re.findall(r"\bGT_(?:KF|LM)_[A-Z0-9_]+\b", text))
    assert used and used <= set(defines), sorted(used - set(defines))
    for name, text in (("gt_kalman.cl", sources["gt_kalman.cl"]), ("gt_lm.cl", sources["gt_lm.cl"])):
        assert "#ifndef GT_ABI" in text and "#error" in text, name
    # the old hand-written codes are gone
    assert not re.search(r"#define\s+(RUNNING|CONVERGED|FAILED|R_FTOL|GT_UPDATED)\b", "".join(sources.values()))


def test_an_opencl_build_without_the_abi_defines_fails(device):
    if device.backend != "opencl":
        pytest.skip("OpenCL builds")
    import pyopencl as cl

    from gputrack.backends.opencl.program import kernel_dir

    src = (kernel_dir() / "gt_lm.cl").read_text()
    with pytest.raises(cl.RuntimeError, match="ABI defines"):
        cl.Program(device.context, src).build(options=[f"-I{kernel_dir()}"])

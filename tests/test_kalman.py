"""Batched Kalman filters (papers 001 and 002): predict, update, stereo EKF, gating.

Every backend is compared with the NumPy reference on the same inputs; the reference itself is
pinned to a textbook per-track loop (np.linalg, one filter at a time, float64).
"""

import numpy as np
import pytest
from allocations import rejects_without_allocating
from tolerances import assert_matches

import gputrack
from gputrack.ops.kalman import (
    MAX_N,
    KalmanState,
    KalmanStatus,
    constant_velocity,
    ekf_update_stereo,
    kf_predict,
    kf_update,
    mahalanobis,
    shared_matrix,
)

REF = gputrack.device("numpy")


def spd(rng, T, n, scale=1.0, floor=0.3):
    A = rng.standard_normal((T, n, n))
    return scale * (A @ A.transpose(0, 2, 1) / n + floor * np.eye(n))


def problem(rng, T, n, m, dtype=np.float32, per_track=False):
    F = np.eye(n) + 0.3 * rng.standard_normal((T, n, n) if per_track else (n, n))
    Q = spd(rng, T, n, 0.1) if per_track else spd(rng, 1, n, 0.1)[0]
    H = rng.standard_normal((T, m, n) if per_track else (m, n))
    R = spd(rng, T, m, 0.5) if per_track else spd(rng, 1, m, 0.5)[0]
    x = rng.standard_normal((T, n))
    P = spd(rng, T, n)
    z = rng.standard_normal((T, m)) * 2
    c = lambda a: np.ascontiguousarray(a, dtype=dtype)
    return c(x), c(P), c(F), c(Q), c(z), c(H), c(R)


def get(a):
    return gputrack.to_numpy(a)


# -- textbook per-track filter (the independent check of the reference) ---------------------
def textbook_predict(x, P, F, Q):
    return F @ x, F @ P @ F.T + Q


def textbook_update(x, P, z, H, R, s=1.0):
    S = H @ P @ H.T + R
    K = s * (P @ H.T @ np.linalg.inv(S))
    A = np.eye(len(x)) - K @ H
    return x + K @ (z - H @ x), A @ P @ A.T + K @ R @ K.T


def per_track(A, t):
    return A[t] if A.ndim == 3 else A


def stereo_h(x, f, b, cx, cy):
    return np.array([f * x[0] / x[4] + cx, f * x[2] / x[4] + cy, f * b / x[4]])


def numeric_jacobian(x, f, b, cx, cy, eps=1e-6):
    J = np.zeros((3, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps * max(1.0, abs(x[k]))
        J[:, k] = (stereo_h(x + d, f, b, cx, cy) - stereo_h(x - d, f, b, cx, cy)) / (2 * d[k])
    return J


# -- the reference against the textbook loop ------------------------------------------------
@pytest.mark.parametrize("per", [False, True])
def test_reference_matches_textbook_loop(per):
    rng = np.random.default_rng(1)
    T, n, m = 13, 6, 3
    x, P, F, Q, z, H, R = problem(rng, T, n, m, np.float64, per)
    s = rng.uniform(0, 1.5, T)
    xp, Pp = kf_predict(REF, x, P, F, Q)
    st = kf_update(REF, x, P, z, H, R, gain_scale=s, predict=(F, Q))
    d2 = mahalanobis(REF, x, P, H, R, z[:5])
    for t in range(T):
        xe, Pe = textbook_predict(x[t], P[t], per_track(F, t), per_track(Q, t))
        np.testing.assert_allclose(xp[t], xe, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(Pp[t], Pe, rtol=1e-12, atol=1e-12)
        xu, Pu = textbook_update(xe, Pe, z[t], per_track(H, t), per_track(R, t), s[t])
        np.testing.assert_allclose(st.x[t], xu, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(st.P[t], Pu, rtol=1e-9, atol=1e-9)
        Ht, Rt = per_track(H, t), per_track(R, t)
        S = Ht @ P[t] @ Ht.T + Rt
        for d in range(5):
            r = z[d] - Ht @ x[t]
            np.testing.assert_allclose(d2[t, d], r @ np.linalg.solve(S, r), rtol=1e-9)
    assert (st.status == KalmanStatus.UPDATED).all()


def test_reference_stereo_matches_textbook_ekf():
    rng = np.random.default_rng(2)
    T = 9
    f, b, cx, cy = 500.0, 0.12, 320.0, 240.0
    x = np.column_stack([rng.normal(0, 1, T), rng.normal(0, 0.3, T), rng.normal(0, 1, T), rng.normal(0, 0.3, T),
                         rng.uniform(0.5, 40, T), rng.normal(0, 0.3, T)])  # fmt: skip
    P = spd(rng, T, 6, 0.05)
    R = np.diag([2.0, 2.0, 0.5])
    z = np.array([stereo_h(xi, f, b, cx, cy) for xi in x]) + rng.normal(0, 1, (T, 3))
    st = ekf_update_stereo(REF, x, P, z, R, f=f, b=b, cx=cx, cy=cy)
    for t in range(T):
        J = numeric_jacobian(x[t], f, b, cx, cy)
        S = J @ P[t] @ J.T + R
        K = P[t] @ J.T @ np.linalg.inv(S)
        A = np.eye(6) - K @ J
        np.testing.assert_allclose(st.x[t], x[t] + K @ (z[t] - stereo_h(x[t], f, b, cx, cy)), rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(st.P[t], A @ P[t] @ A.T + K @ R @ K.T, rtol=1e-6, atol=1e-9)


# -- every backend against the reference ----------------------------------------------------
@pytest.mark.parametrize("T", [1, 13, 129])
@pytest.mark.parametrize("per", [False, True])
def test_predict_matches_reference(device, T, per):
    rng = np.random.default_rng(T)
    x, P, F, Q, *_ = problem(rng, T, 6, 3, per_track=per)
    xp, Pp = kf_predict(device, x, P, F, Q)
    xr, Pr = kf_predict(REF, x, P, F, Q)
    assert_matches(device, xp, xr)
    assert_matches(device, Pp, Pr, scale=10)  # sums of 36 products
    Pg = get(Pp)
    assert np.array_equal(Pg, Pg.transpose(0, 2, 1))  # exactly symmetric


@pytest.mark.parametrize("n,m,T", [(6, 3, 1), (6, 3, 129), (4, 2, 13), (1, 1, 127)])
def test_update_matches_reference(device, n, m, T):
    rng = np.random.default_rng(n * 100 + T)
    x, P, _, _, z, H, R = problem(rng, T, n, m)
    st = kf_update(device, x, P, z, H, R)
    ref = kf_update(REF, x, P, z, H, R)
    assert isinstance(st, KalmanState)
    assert_matches(device, st.x, ref.x, scale=20)
    assert_matches(device, st.P, ref.P, scale=20)
    assert np.array_equal(get(st.status), ref.status)
    assert (ref.status == KalmanStatus.UPDATED).all()
    Pg = get(st.P)
    assert np.array_equal(Pg, Pg.transpose(0, 2, 1))
    assert (np.linalg.eigvalsh(Pg.astype(np.float64)) > 0).all()


def test_update_per_track_matrices_and_options(device):
    rng = np.random.default_rng(7)
    T, n, m = 129, 6, 3
    x, P, F, Q, z, H, R = problem(rng, T, n, m, per_track=True)
    mask = rng.random(T) > 0.25
    gain = rng.uniform(0, 1.5, T).astype(np.float32)
    z[5, 1] = np.nan  # missing observation
    st = kf_update(device, x, P, z, H, R, mask=mask, gain_scale=gain, predict=(F, Q))
    ref = kf_update(REF, x, P, z, H, R, mask=mask, gain_scale=gain, predict=(F, Q))
    assert_matches(device, st.x, ref.x, scale=20)
    assert_matches(device, st.P, ref.P, scale=20)
    assert np.array_equal(get(st.status), ref.status)
    assert ref.status[5] == KalmanStatus.SKIPPED
    assert (ref.status[~mask] == KalmanStatus.SKIPPED).all()
    assert (ref.status == KalmanStatus.UPDATED).sum() > T // 2


def test_fused_predict_update_equals_two_calls(device):
    rng = np.random.default_rng(8)
    T = 129
    F, Q = constant_velocity(3, 0.2, 0.5)
    x, P, _, _, z, _, R = problem(rng, T, 6, 3)
    H = np.zeros((3, 6), np.float32)
    H[0, 0] = H[1, 2] = H[2, 4] = 1  # a selection matrix: the kernels skip its zeros
    mask = np.arange(T) % 4 != 0
    fused = kf_update(device, x, P, z, H, R, mask=mask, predict=(F, Q))
    xp, Pp = kf_predict(device, x, P, F, Q)
    two = kf_update(device, xp, Pp, z, H, R, mask=mask)
    assert_matches(device, fused.x, get(two.x), scale=5)
    assert_matches(device, fused.P, get(two.P), scale=5)
    # masked tracks are predicted only (paper 001: fewer than 2 observations)
    assert_matches(device, get(fused.x)[~mask], get(xp)[~mask])
    assert_matches(device, get(fused.P)[~mask], get(Pp)[~mask])
    assert_matches(device, fused.x, kf_update(REF, x, P, z, H, R, mask=mask, predict=(F, Q)).x, scale=5)


def test_masked_and_missing_tracks_are_untouched(device):
    rng = np.random.default_rng(9)
    T = 13
    x, P, _, _, z, H, R = problem(rng, T, 6, 3)
    P[3] += 0.01 * rng.standard_normal((6, 6)).astype(np.float32)  # not symmetric: still returned as is
    mask = np.ones(T, bool)
    mask[[0, 3, 12]] = False
    z[7] = np.nan
    z[8, 2] = np.nan
    st = kf_update(device, x, P, z, H, R, mask=mask)
    skipped = ~mask
    skipped[[7, 8]] = True
    xs, Ps, ss = get(st.x), get(st.P), get(st.status)
    assert np.array_equal(xs[skipped], x[skipped])
    assert np.array_equal(Ps[skipped], P[skipped])
    assert (ss[skipped] == KalmanStatus.SKIPPED).all()
    assert (ss[~skipped] == KalmanStatus.UPDATED).all()
    assert not np.allclose(xs[~skipped], x[~skipped])


def test_gain_scale_zero_is_predict_only_and_one_is_plain_update(device):
    rng = np.random.default_rng(10)
    T = 13
    F, Q = constant_velocity(3, 0.5, 0.2)
    x, P, _, _, z, H, R = problem(rng, T, 6, 3)
    xp, Pp = kf_predict(device, x, P, F, Q)
    zero = kf_update(device, x, P, z, H, R, gain_scale=np.zeros(T), predict=(F, Q))
    assert_matches(device, zero.x, get(xp))
    assert_matches(device, zero.P, get(Pp))
    one = kf_update(device, x, P, z, H, R, gain_scale=np.ones(T), predict=(F, Q))
    plain = kf_update(device, x, P, z, H, R, predict=(F, Q))
    assert_matches(device, one.x, get(plain.x))
    assert_matches(device, one.P, get(plain.P))
    # a smaller gain trusts the observation less: the innovation shrinks less
    half = kf_update(device, x, P, z, H, R, gain_scale=np.full(T, 0.5), predict=(F, Q))
    r_half = np.linalg.norm(z - get(half.x) @ H.T, axis=1)
    r_one = np.linalg.norm(z - get(one.x) @ H.T, axis=1)
    assert (r_half > r_one).all()
    # the scaled gain's covariance is the Joseph-form one: between the prior and the optimal one
    tr = lambda A: np.trace(get(A), axis1=1, axis2=2)
    assert (tr(one.P) < tr(half.P)).all() and (tr(half.P) < tr(Pp)).all()


@pytest.mark.parametrize("where", ["near", "far"])
def test_stereo_ekf_matches_reference(device, where):
    rng = np.random.default_rng(11 if where == "near" else 12)
    T = 129
    f, b, cx, cy = 480.0, 0.12, 320.0, 240.0
    zr = (0.4, 1.5) if where == "near" else (20.0, 60.0)
    x = np.column_stack([rng.normal(0, 1, T), rng.normal(0, 0.3, T), rng.normal(0, 1, T), rng.normal(0, 0.3, T),
                         rng.uniform(*zr, T), rng.normal(0, 0.3, T)]).astype(np.float32)  # fmt: skip
    P = spd(rng, T, 6, 0.05 if where == "near" else 1.0).astype(np.float32)
    R = np.diag([4.0, 4.0, 0.25]).astype(np.float32)
    z = (np.array([stereo_h(xi, f, b, cx, cy) for xi in x]) + rng.normal(0, 2, (T, 3))).astype(np.float32)
    x[5, 4] = -0.5  # behind the camera
    x[6, 4] = 0.0
    F, Q = constant_velocity(3, 1 / 48, 1.0)
    gain = rng.uniform(0.2, 1.0, T).astype(np.float32)
    for kw in ({}, {"predict": (F, Q), "gain_scale": gain, "mask": np.arange(T) != 9}):
        st = ekf_update_stereo(device, x, P, z, R, f=f, b=b, cx=cx, cy=cy, **kw)
        ref = ekf_update_stereo(REF, x, P, z, R, f=f, b=b, cx=cx, cy=cy, **kw)
        assert_matches(device, st.x, ref.x, scale=50)
        assert_matches(device, st.P, ref.P, scale=50)
        ss = get(st.status)
        assert np.array_equal(ss, ref.status)
        assert ss[5] == KalmanStatus.BAD_DEPTH and ss[6] == KalmanStatus.BAD_DEPTH
        assert np.isfinite(get(st.x)).all() and np.isfinite(get(st.P)).all()
    assert np.array_equal(get(st.x)[5], get(kf_predict(device, x, P, F, Q)[0])[5])
    assert ss[9] == KalmanStatus.SKIPPED
    assert (ss[10:] == KalmanStatus.UPDATED).all()


def test_not_positive_definite_and_nonsymmetric_input(device):
    rng = np.random.default_rng(13)
    T = 13
    x, P, _, _, z, H, R = problem(rng, T, 6, 3)
    Rt = np.broadcast_to(R, (T, 3, 3)).copy()
    Rt[4] = -50 * np.eye(3, dtype=np.float32)  # S = H P H^T + R not positive definite
    st = kf_update(device, x, P, z, H, Rt)
    ss = get(st.status)
    assert ss[4] == KalmanStatus.NOT_PD
    assert np.array_equal(get(st.x)[4], x[4]) and np.array_equal(get(st.P)[4], P[4])
    assert (np.delete(ss, 4) == KalmanStatus.UPDATED).all()
    d2 = get(mahalanobis(device, x, P, H, Rt, z[:3]))
    assert np.isinf(d2[4]).all() and np.isfinite(np.delete(d2, 4, axis=0)).all()
    # P and R are symmetrised: adding an antisymmetric part changes nothing (up to rounding)
    Wp = rng.standard_normal((T, 6, 6)).astype(np.float32)
    Wr = rng.standard_normal((3, 3)).astype(np.float32)
    skewed = kf_update(device, x, P + 0.1 * (Wp - Wp.transpose(0, 2, 1)), z, H, R + 0.1 * (Wr - Wr.T))
    plain = kf_update(device, x, P, z, H, R)
    assert_matches(device, skewed.x, get(plain.x), scale=20)
    assert_matches(device, skewed.P, get(plain.P), scale=20)


def test_ill_conditioned_regression(device):
    # A tight observation of a very uncertain state: P eigenvalues 1e4 .. 1e-4, R = 1e-6 I. The
    # standard form P - K H P loses symmetry and definiteness in float32; Joseph form must not.
    rng = np.random.default_rng(14)
    T, n, m = 129, 6, 3
    U, _ = np.linalg.qr(rng.standard_normal((T, n, n)))
    ev = np.logspace(4, -4, n)
    P = (U * ev[None, None, :]) @ U.transpose(0, 2, 1)
    P = (0.5 * (P + P.transpose(0, 2, 1))).astype(np.float32)
    x = rng.standard_normal((T, n)).astype(np.float32)
    H = np.zeros((m, n), np.float32)
    H[0, 0] = H[1, 2] = H[2, 4] = 1
    R = (1e-6 * np.eye(m)).astype(np.float32)
    z = rng.standard_normal((T, m)).astype(np.float32)
    st = kf_update(device, x, P, z, H, R)
    Pg = get(st.P).astype(np.float64)
    assert (get(st.status) == KalmanStatus.UPDATED).all()
    assert np.array_equal(Pg, Pg.transpose(0, 2, 1))
    # float32 rounding of the prior alone is eps * 1e4 ~ 1e-3; the standard form ends near -80
    scale = np.finfo(np.float32).eps * ev[0]
    assert np.linalg.eigvalsh(Pg).min() > -10 * scale
    # the observed components are pinned to the observation within its noise
    assert np.abs(get(st.x)[:, [0, 2, 4]] - z).max() < 0.2  # vs O(1) without the update
    # and the float32 result stays close to the float64 textbook one (the standard form is ~35 off)
    for t in range(0, T, 16):
        xe, Pe = textbook_update(x[t].astype(np.float64), P[t].astype(np.float64), z[t], H, R.astype(np.float64))
        assert np.abs(Pg[t] - Pe).max() < 100 * scale
        assert np.abs(get(st.x)[t] - xe).max() < 0.01 * np.sqrt(ev[0])  # 1% of the prior spread


@pytest.mark.parametrize("T,D", [(1, 1), (13, 17), (129, 100)])
def test_mahalanobis_matches_reference(device, T, D):
    rng = np.random.default_rng(T + D)
    x, P, _, _, _, H, R = problem(rng, T, 6, 3)
    det = (rng.standard_normal((D, 3)) * 2).astype(np.float32)
    d2 = mahalanobis(device, x, P, H, R, det)
    assert tuple(d2.shape) == (T, D)
    assert_matches(device, d2, mahalanobis(REF, x, P, H, R, det), scale=20)
    _, _, _, _, _, Ht, Rt = problem(rng, T, 6, 3, per_track=True)
    assert_matches(device, mahalanobis(device, x, P, Ht, Rt, det), mahalanobis(REF, x, P, Ht, Rt, det), scale=20)


def test_out_writes_in_place(device):
    rng = np.random.default_rng(15)
    T = 129
    F, Q = constant_velocity(3, 0.5, 0.2)
    x, P, _, _, z, H, R = problem(rng, T, 6, 3)
    want = kf_update(REF, x, P, z, H, R, predict=(F, Q))
    xd, Pd = device.asarray(x.copy()), device.asarray(P.copy())
    sd = device.empty((T,), np.uint8)
    got = kf_update(device, xd, Pd, z, H, R, predict=(F, Q), out=(xd, Pd, sd))
    assert got.x is xd and got.P is Pd and got.status is sd
    assert_matches(device, xd, want.x, scale=5)
    assert_matches(device, Pd, want.P, scale=5)
    xp, Pp = kf_predict(device, xd, Pd, F, Q, out=(xd, Pd))
    assert xp is xd and Pp is Pd
    assert_matches(device, Pd, kf_predict(REF, want.x, want.P, F, Q)[1], scale=10)


def _frames_problem(T, dtype):
    """Constant-velocity tracks with a selection H and a diagonal R (the kernels skip their zeros),
    a missing observation, and two tracks whose innovation covariance is not positive definite."""
    rng = np.random.default_rng(T)
    F, Q = constant_velocity(3, 0.1, 0.5, dtype=dtype)
    x, P, _, _, z, _, _ = problem(rng, T, 6, 3, dtype)
    H = np.zeros((3, 6), dtype)
    H[0, 0] = H[1, 2] = H[2, 4] = 1
    R = np.diag([0.2, 0.3, 0.4]).astype(dtype)
    P[[1, T - 1]] = -10 * np.eye(6, dtype=dtype)  # S = H P' H^T + R not positive definite
    z[min(2, T - 1), 1] = np.nan
    mask = np.arange(T) % 5 != 3
    gain = np.linspace(0, 1.5, T).astype(dtype)
    return x, P, z, F, Q, H, R, mask, gain


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("T", [13, 1535])
@pytest.mark.parametrize("options", [False, True])
def test_steady_state_frames_match_reference(device, dtype, T, options):
    # a tracker's frames: device-resident state updated in place with the same arrays every frame
    # (the ops' and launchers' steady-state fast paths), new observation arrays on some frames
    if dtype == np.float64 and not device.fp64:
        pytest.skip(f"{device.spec} has no float64")
    x, P, z, F, Q, H, R, mask, gain = _frames_problem(T, dtype)
    Fs, Qs, Hs, Rs = (shared_matrix(device, a, dtype) for a in (F, Q, H, R))
    xd, Pd, zd = device.asarray(x), device.asarray(P), device.asarray(z)
    sd = device.empty((T,), np.uint8)
    opts = {"mask": device.asarray(mask.astype(np.uint8)), "gain_scale": device.asarray(gain)} if options else {}
    ref_opts = {"mask": mask, "gain_scale": gain} if options else {}
    xr, Pr, sr = x.copy(), P.copy(), np.empty(T, np.uint8)
    for frame in range(4):
        if frame == 2:  # a new observation array with the same signature
            z = (z + 0.5).astype(dtype)
            zd = device.asarray(z)
        got = kf_update(device, xd, Pd, zd, Hs, Rs, predict=(Fs, Qs), out=(xd, Pd, sd), **opts)
        kf_update(REF, xr, Pr, z, H, R, predict=(F, Q), out=(xr, Pr, sr), **ref_opts)
        assert got.x is xd and got.P is Pd and got.status is sd
        assert np.array_equal(get(sd), sr), f"frame {frame}"
        assert_matches(device, xd, xr, dtype, scale=20, err_msg=f"frame {frame}")
        assert_matches(device, Pd, Pr, dtype, scale=20, err_msg=f"frame {frame}")
    assert sr[1] == sr[T - 1] == KalmanStatus.NOT_PD and sr[min(2, T - 1)] == KalmanStatus.SKIPPED
    assert (sr == KalmanStatus.UPDATED).sum() > T // 2
    if options:
        assert (sr[3::5] == KalmanStatus.SKIPPED).all()
    # new state arrays (the old ones freed) with the same signature
    del xd, Pd
    xd, Pd = device.asarray(xr), device.asarray(Pr)
    kf_update(device, xd, Pd, zd, Hs, Rs, predict=(Fs, Qs), out=(xd, Pd, sd), **opts)
    kf_update(REF, xr, Pr, z, H, R, predict=(F, Q), out=(xr, Pr, sr), **ref_opts)
    assert np.array_equal(get(sd), sr)
    assert_matches(device, Pd, Pr, dtype, scale=20)


@pytest.mark.parametrize("T", [13, 1535])
def test_steady_state_predict_stereo_and_gating_match_reference(device, T):
    x, P, _, F, Q, H, R, _, _ = _frames_problem(T, np.float32)
    x[:, 4] = np.abs(x[:, 4]) + 2.0
    x[0, 4] = -1.0  # behind the camera: BAD_DEPTH
    f, b = 480.0, 0.12
    zs = np.stack([f * x[:, 0] / x[:, 4], f * x[:, 2] / x[:, 4], f * b / x[:, 4]], 1).astype(np.float32) + 0.3
    det = np.random.default_rng(T).normal(0, 2, (17, 3)).astype(np.float32)
    Fs, Qs, Hs, Rs = (shared_matrix(device, a) for a in (F, Q, H, R))
    xd, Pd, zsd, detd = device.asarray(x), device.asarray(P), device.asarray(zs), device.asarray(det)
    sd, d2 = device.empty((T,), np.uint8), device.empty((T, 17), np.float32)
    xr, Pr, sr = x.copy(), P.copy(), np.empty(T, np.uint8)
    for frame in range(3):
        kf_predict(device, xd, Pd, Fs, Qs, out=(xd, Pd))
        kf_predict(REF, xr, Pr, F, Q, out=(xr, Pr))
        assert_matches(device, Pd, Pr, scale=20, err_msg=f"frame {frame}")
        ekf_update_stereo(device, xd, Pd, zsd, Rs, f=f, b=b, predict=(Fs, Qs), out=(xd, Pd, sd))
        ekf_update_stereo(REF, xr, Pr, zs, R, f=f, b=b, predict=(F, Q), out=(xr, Pr, sr))
        assert np.array_equal(get(sd), sr), f"frame {frame}"
        assert_matches(device, xd, xr, scale=50, err_msg=f"frame {frame}")
        assert_matches(device, Pd, Pr, scale=50, err_msg=f"frame {frame}")
        got = mahalanobis(device, xd, Pd, Hs, Rs, detd, out=d2)
        assert got is d2
        assert_matches(device, d2, mahalanobis(REF, xr, Pr, H, R, det), scale=50, err_msg=f"frame {frame}")
    assert sr[0] == KalmanStatus.BAD_DEPTH and sr[1] == KalmanStatus.NOT_PD
    assert np.isinf(get(d2)[1]).all()


def test_bad_input_after_steady_state_calls(device):
    # a remembered call does not let a later bad one through
    x, P, z, _, _, H, R, _, _ = _frames_problem(13, np.float32)
    Hs, Rs = shared_matrix(device, H), shared_matrix(device, R)
    xd, Pd, zd = device.asarray(x), device.asarray(P), device.asarray(z)
    sd = device.empty((13,), np.uint8)
    for _ in range(2):
        kf_update(device, xd, Pd, zd, Hs, Rs, out=(xd, Pd, sd))
    with pytest.raises(ValueError, match=r"out status: expected a uint8 array of shape \(13,\), got float32"):
        kf_update(device, xd, Pd, zd, Hs, Rs, out=(xd, Pd, device.empty((13,), np.float32)))
    with pytest.raises(ValueError, match="z: expected shape"):
        kf_update(device, xd, Pd, device.asarray(z[:5]), Hs, Rs, out=(xd, Pd, sd))
    with pytest.raises(ValueError, match="z: expected finite values or NaN"):
        kf_update(device, xd, Pd, np.full((13, 3), np.inf, np.float32), Hs, Rs, out=(xd, Pd, sd))
    if device.backend != "numpy":  # NumPy inputs are converted; device arrays must match
        with pytest.raises(TypeError, match="P: expected dtype"):
            kf_update(device, xd, device.asarray(P.astype(np.float64)), zd, Hs, Rs, out=(xd, Pd, sd))


def test_float64(device):
    if not device.fp64:
        pytest.skip(f"{device.spec} has no float64")
    rng = np.random.default_rng(16)
    x, P, F, Q, z, H, R = problem(rng, 13, 6, 3, np.float64)
    st = kf_update(device, x, P, z, H, R, predict=(F, Q), gain_scale=np.full(13, 0.7))
    ref = kf_update(REF, x, P, z, H, R, predict=(F, Q), gain_scale=np.full(13, 0.7))
    assert get(st.x).dtype == np.float64
    assert_matches(device, st.x, ref.x, np.float64, scale=10)
    assert_matches(device, st.P, ref.P, np.float64, scale=10)
    d2 = mahalanobis(device, x, P, H, R, z)
    assert_matches(device, d2, mahalanobis(REF, x, P, H, R, z), np.float64, scale=10)


def test_empty_batches(device):
    F, Q = constant_velocity()
    H = np.eye(3, 6, dtype=np.float32)
    R = np.eye(3, dtype=np.float32)
    x0, P0 = np.zeros((0, 6), np.float32), np.zeros((0, 6, 6), np.float32)
    xp, Pp = kf_predict(device, x0, P0, F, Q)
    assert tuple(xp.shape) == (0, 6) and tuple(Pp.shape) == (0, 6, 6)
    st = kf_update(device, x0, P0, np.zeros((0, 3), np.float32), H, R, predict=(F, Q))
    assert tuple(st.status.shape) == (0,) and get(st.x).shape == (0, 6)
    st = ekf_update_stereo(device, x0, P0, np.zeros((0, 3), np.float32), R, f=400, b=0.1)
    assert get(st.P).shape == (0, 6, 6)
    assert get(mahalanobis(device, x0, P0, H, R, np.ones((5, 3), np.float32))).shape == (0, 5)
    x1, P1 = np.zeros((4, 6), np.float32), np.tile(np.eye(6, dtype=np.float32), (4, 1, 1))
    assert get(mahalanobis(device, x1, P1, H, R, np.zeros((0, 3), np.float32))).shape == (4, 0)


def test_bad_input(device):
    rng = np.random.default_rng(17)
    x, P, F, Q, z, H, R = problem(rng, 5, 6, 3)
    with pytest.raises(ValueError, match="P: expected shape"):
        kf_predict(device, x, P[:, :5, :5], F, Q)
    with pytest.raises(ValueError, match="F: expected shape"):
        kf_predict(device, x, P, F[:5], Q)
    with pytest.raises(ValueError, match="Q: expected shape"):
        kf_predict(device, x, P, F, np.zeros((4, 6, 6), np.float32))
    with pytest.raises(ValueError, match="H: expected shape"):
        kf_update(device, x, P, z, H[:, :5], R)
    with pytest.raises(ValueError, match="z: expected shape"):
        kf_update(device, x, P, z[:4], H, R)
    with pytest.raises(ValueError, match="R: expected shape"):
        kf_update(device, x, P, z, H, np.eye(2))
    with pytest.raises(TypeError, match="x: expected dtype"):
        kf_predict(device, x.astype(np.int32), P, F, Q)
    with pytest.raises(ValueError, match="P: expected finite"):
        kf_predict(device, x, np.full_like(P, np.nan), F, Q)
    bad = z.copy()
    bad[1, 1] = np.inf
    with pytest.raises(ValueError, match="z: expected finite values or NaN"):
        kf_update(device, x, P, bad, H, R)
    with pytest.raises(ValueError, match="gain_scale: expected values >= 0"):
        kf_update(device, x, P, z, H, R, gain_scale=-np.ones(5))
    with pytest.raises(ValueError, match="mask: expected shape"):
        kf_update(device, x, P, z, H, R, mask=np.ones(4, bool))
    with pytest.raises(TypeError, match="predict: expected a pair"):
        kf_update(device, x, P, z, H, R, predict=F)
    with pytest.raises(ValueError, match="state size n"):
        kf_predict(device, np.zeros((2, MAX_N + 1), np.float32), np.zeros((2, MAX_N + 1, MAX_N + 1), np.float32), 1, 1)
    with pytest.raises(ValueError, match=r"x: expected shape \(T=5, 6\)"):
        ekf_update_stereo(device, x[:, :4], P[:, :4, :4], z, R, f=400, b=0.1)
    with pytest.raises(ValueError, match="f: expected a number > 0, got 0"):
        ekf_update_stereo(device, x, P, z, R, f=0, b=0.1)
    with pytest.raises(ValueError, match="cx: expected a finite number, got nan"):
        ekf_update_stereo(device, x, P, z, R, f=400, b=0.1, cx=float("nan"))
    with pytest.raises(TypeError, match="b: expected a real number, got str"):
        ekf_update_stereo(device, x, P, z, R, f=400, b="0.1")
    with pytest.raises(ValueError, match="z: expected finite"):
        mahalanobis(device, x, P, H, R, np.full((2, 3), np.nan, np.float32))
    with pytest.raises(TypeError, match="expected a gputrack.Device"):
        kf_predict("numpy", x, P, F, Q)
    want = r"out x: expected a float(32|64) array of shape \(5, 6\), got float(32|64) \(4, 6\)"
    with pytest.raises(ValueError, match=want):
        kf_update(
            device, x, P, z, H, R, out=(device.empty((4, 6)), device.empty((5, 6, 6)), device.empty((5,), np.uint8))
        )
    if device.backend != "numpy":
        with pytest.raises(TypeError, match="out x: expected a writable array on"):
            kf_update(device, x, P, z, H, R, out=(x.copy(), P.copy(), np.zeros(5, np.uint8)))
        with pytest.raises(TypeError, match="float64 or float32|expected dtype float32"):
            kf_predict(device, x, device.asarray(P.astype(np.float64)) if device.fp64 else P.astype(np.int32), F, Q)


def test_shapes_are_checked_before_any_value_is_read(device):
    """A wrong shape is rejected before anything is scanned, copied or uploaded: a wrong (1e5, 6) F
    took 3.2 s (its zero pattern was computed first), a (2**32, 6) broadcast view never returned,
    and broadcast x, z and detections of 2**32 rows were copied before the shapes were compared."""
    rng = np.random.default_rng(3)
    x, P, F, Q, z, H, R = problem(rng, 5, 6, 2)
    rows = 2**32

    def view(*shape):
        return np.broadcast_to(np.ones(1, np.float32), shape)

    wrong = np.ones((100_000, 6), np.float32)
    rejects_without_allocating(ValueError, r"^F: expected shape \(n=6, n=6\), got \(100000, 6\)\Z",
                               lambda: kf_predict(device, x, P, wrong, Q))  # fmt: skip
    rejects_without_allocating(ValueError, r"^F: expected shape \(n=6, n=6\), got \(4294967296, 6\)\Z",
                               lambda: kf_predict(device, x, P, view(rows, 6), Q))  # fmt: skip
    rejects_without_allocating(ValueError, r"^Q: expected shape \(n=6, n=6\), got \(4294967296, 6\)\Z",
                               lambda: kf_update(device, x, P, z, H, R, predict=(F, view(rows, 6))))  # fmt: skip
    rejects_without_allocating(ValueError, r"^P: expected shape \(T=4294967296, n=6, n=6\), got \(5, 6, 6\)\Z",
                               lambda: kf_update(device, view(rows, 6), P, z, H, R))  # fmt: skip
    rejects_without_allocating(ValueError, r"^z: expected shape \(T=5, m\), got \(4294967296, 2\)\Z",
                               lambda: kf_update(device, x, P, view(rows, 2), H, R))  # fmt: skip
    rejects_without_allocating(ValueError, r"^mask: expected shape \(T=5\), got \(4294967296,\)\Z",
                               lambda: kf_update(device, x, P, z, H, R, mask=view(rows)))  # fmt: skip
    rejects_without_allocating(ValueError, r"^P: expected shape \(T=4294967296, n=6, n=6\), got \(5, 6, 6\)\Z",
                               lambda: mahalanobis(device, view(rows, 6), P, H, R, z))  # fmt: skip
    rejects_without_allocating(ValueError, r"^H: expected shape \(m=3, n=6\), got \(2, 6\)\Z",
                               lambda: mahalanobis(device, x, P, H, R, view(rows, 3)))  # fmt: skip


def test_a_distance_table_too_large_for_the_device_is_a_memory_error(device):
    """2**17 tracks x 2**20 detections: a 512 GiB result (a SIGSEGV on taichi:cpu before)."""
    T, D = 2**17, 2**20
    x, P = np.zeros((T, 2), np.float32), np.broadcast_to(np.eye(2, dtype=np.float32), (T, 2, 2))
    I2 = np.eye(2, dtype=np.float32)
    with pytest.raises(MemoryError, match=r"got float32 \(131072, 1048576\): .*549755813888 bytes \(512 GiB\)"):
        mahalanobis(device, x, P, I2, I2, np.zeros((D, 2), np.float32))


def test_constant_velocity():
    F, Q = constant_velocity(3, 0.5, 2.0)
    assert F.dtype == np.float32 and F.shape == (6, 6)
    want_F = np.eye(6)
    want_F[0, 1] = want_F[2, 3] = want_F[4, 5] = 0.5  # eq. 3 block [[1, dt], [0, 1]]
    np.testing.assert_array_equal(F, want_F.astype(np.float32))
    G = np.array([0.125, 0.5])
    np.testing.assert_allclose(Q[:2, :2], 2.0 * np.outer(G, G), rtol=1e-6)
    assert (Q[:2, 2:] == 0).all()
    F2, Q2 = constant_velocity(2, 1.0, [1.0, 4.0], dtype=np.float64)
    assert F2.shape == (4, 4) and Q2.dtype == np.float64
    np.testing.assert_allclose(Q2[2:, 2:], 4.0 * np.outer([0.5, 1.0], [0.5, 1.0]))
    with pytest.raises(ValueError, match="dt: expected a positive"):
        constant_velocity(3, 0.0)
    with pytest.raises(ValueError, match="q: expected a scalar or 3 values"):
        constant_velocity(3, 1.0, [1.0, 2.0])
    with pytest.raises(ValueError, match="dim: expected a positive integer"):
        constant_velocity(0)


def test_selftest(device):
    from gputrack.selftest import check_kalman

    check_kalman(device)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("lanes", [1, 4, 8])
def test_opencl_kernel_variants(device, lanes, dtype, monkeypatch):
    """The OpenCL kernels built for one track per work-item (GPUs) and for 4 or 8 tracks in vector
    lanes (CPUs): filter and gating, float32 and float64."""
    if device.backend != "opencl":
        pytest.skip("OpenCL kernel variants")
    if dtype == np.float64 and not device.fp64:
        pytest.skip(f"{device.spec} has no float64")
    from gputrack.backends.opencl import kalman as ocl

    monkeypatch.setattr(ocl, "lanes", lambda dev: lanes)
    rng = np.random.default_rng(18)
    T = 13  # not a multiple of 4 or 8: the last work-item has idle lanes
    F, Q = constant_velocity(3, 0.5, 0.2, dtype=dtype)
    x, P, _, _, z, H, R = problem(rng, T, 6, 3, dtype)
    x[:, 4] += 4
    z[2, 0] = np.nan
    mask = np.arange(T) != 5
    gain = rng.uniform(0, 1.5, T).astype(dtype)
    Rt = np.broadcast_to(R, (T, 3, 3)).copy()
    Rt[7] = -50 * np.eye(3, dtype=dtype)
    got = kf_update(device, x, P, z, H, Rt, mask=mask, gain_scale=gain, predict=(F, Q))
    want = kf_update(REF, x, P, z, H, Rt, mask=mask, gain_scale=gain, predict=(F, Q))
    assert_matches(device, got.x, want.x, dtype, scale=20)
    assert_matches(device, got.P, want.P, dtype, scale=20)
    assert np.array_equal(get(got.status), want.status)
    assert set(want.status.tolist()) == {0, 1, 2}
    xs = x.copy()
    xs[3, 4] = -1.0
    zs = np.stack([400 * xs[:, 0] / np.abs(xs[:, 4]), 400 * xs[:, 2] / np.abs(xs[:, 4]), 40 / np.abs(xs[:, 4])], 1)
    zs = zs.astype(dtype)
    got = ekf_update_stereo(device, xs, P, zs, R, f=400, b=0.1, mask=mask)
    want = ekf_update_stereo(REF, xs, P, zs, R, f=400, b=0.1, mask=mask)
    assert_matches(device, got.x, want.x, dtype, scale=50)
    assert_matches(device, got.P, want.P, dtype, scale=50)
    assert np.array_equal(get(got.status), want.status)
    assert want.status[3] == KalmanStatus.BAD_DEPTH and want.status[5] == KalmanStatus.SKIPPED
    xp, Pp = kf_predict(device, x, P, F, Q)
    xr, Pr = kf_predict(REF, x, P, F, Q)
    assert_matches(device, xp, xr, dtype)
    assert_matches(device, Pp, Pr, dtype, scale=10)
    det = (rng.standard_normal((5, 3)) * 2).astype(dtype)
    d2 = get(mahalanobis(device, x, P, H, Rt, det))
    assert_matches(device, d2, mahalanobis(REF, x, P, H, Rt, det), dtype, scale=20)
    assert np.isinf(d2[7]).all()

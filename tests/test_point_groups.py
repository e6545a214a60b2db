"""gputrack.ops.point_groups.assign_points on every device against the NumPy reference (paper 001
eq. 7-11), hand-checked cases, and bad input."""

import numpy as np
import pytest
from tolerances import assert_matches

import gputrack
from gputrack.backends.reference import point_groups as ref
from gputrack.ops.point_groups import assign_points

POS, VEL = [0, 2, 4], [1, 3, 5]


def _groups(rng, T, spread=300.0):
    """T groups on a 3 m grid with random spreads (positions mm, velocities mm/frame)."""
    means = np.zeros((T, 6), np.float32)
    means[:, POS] = np.stack([np.arange(T) % 7 * 3000.0, np.arange(T) // 7 * 3000.0, 5000 + rng.uniform(-500, 500, T)], 1)
    means[:, VEL] = rng.uniform(-30, 30, (T, 3))
    A = rng.standard_normal((T, 6, 6)) * 0.3 + np.eye(6)
    S = A @ np.swapaxes(A, 1, 2)
    S[:, POS] *= spread
    S[:, :, POS] *= spread
    S[:, VEL] *= 5.0
    S[:, :, VEL] *= 5.0
    return means, S.astype(np.float32)


def _points(rng, means, N, scale=900.0):
    owner = rng.integers(0, len(means), N)
    y = means[owner][:, POS] + rng.standard_normal((N, 3)) * scale
    lam = means[owner][:, VEL] + rng.standard_normal((N, 3)) * 8.0
    return y.astype(np.float32), lam.astype(np.float32)


def _reference(y, lam, means, S, gamma, active=None, n=None):
    N, T = len(y), len(means)
    out = (np.empty(N, np.int32), np.empty(T, np.int32), np.empty((T, 6), np.float32), np.empty((T, 6, 6), np.float32))
    return ref.assign_points(None, y, lam, means, S, active, gamma, N if n is None else n, out)


@pytest.mark.parametrize("N,T", [(1, 1), (13, 3), (1535, 17), (129, 40)])
def test_assign_points_matches_reference(device, N, T):
    rng = np.random.default_rng(N * 100 + T)
    means, S = _groups(rng, T)
    y, lam = _points(rng, means, N)
    y[::11] = np.nan  # "no point" rows
    got = assign_points(device, y, lam, means, S, 9.0)
    want = _reference(y, lam, means, S, 9.0)
    labels = gputrack.to_numpy(got.labels)
    np.testing.assert_array_equal(labels, want[0])
    assert (labels[::11] == -1).all()
    assert 0 < (labels >= 0).sum() < N or N == 1
    np.testing.assert_array_equal(gputrack.to_numpy(got.counts), want[1])
    assert_matches(device, got.mean, want[2], scale=50)  # sums of up to N float32 terms
    cov = gputrack.to_numpy(got.cov)
    floor = (1e-6 * np.nanmax(np.abs(y))) ** 2  # a float32 rounding of the mean, squared
    np.testing.assert_allclose(cov, want[3], rtol=2e-4, atol=2e-3 * np.abs(want[3]).max() + floor)


def test_gate_and_tie_break_by_hand(device):
    """Two groups at the same place with the same spread: the velocity term decides (eq. 9-11)."""
    means = np.zeros((3, 6), np.float32)
    means[:, 4] = 5000.0
    means[0, VEL] = [20, 0, 0]
    means[1, VEL] = [-20, 0, 0]
    means[2, POS] = [9000, 0, 5000]  # far away: never gated
    S = np.tile(np.diag([1e4, 4, 1e4, 4, 1e4, 4]).astype(np.float32), (3, 1, 1))
    y = np.array([[0, 0, 5000], [10, 0, 5000], [500, 0, 5000], [0, 0, 5000]], np.float32)  # point 2: d2 = 25 > 9
    lam = np.array([[18, 0, 0], [-19, 0, 0], [0, 0, 0], [0, 0, 0]], np.float32)  # point 3: a tie -> slot 0
    got = assign_points(device, y, lam, means, S, 9.0)
    np.testing.assert_array_equal(gputrack.to_numpy(got.labels), [0, 1, -1, 0])
    np.testing.assert_array_equal(gputrack.to_numpy(got.counts), [2, 1, 0])
    mean = gputrack.to_numpy(got.mean)
    np.testing.assert_allclose(mean[0], [0, 9, 0, 0, 5000, 0], atol=1e-3)
    np.testing.assert_allclose(mean[2], means[2])  # no point: the group's own mean, zero covariance
    cov = gputrack.to_numpy(got.cov)
    np.testing.assert_allclose(cov[0][1, 1], 81.0, rtol=1e-5)  # velocities 18 and 0 about 9
    assert not cov[2].any() and not cov[1].any()


def test_active_slots_n_points_and_degenerate_spreads(device):
    rng = np.random.default_rng(5)
    means, S = _groups(rng, 4)
    y, lam = _points(rng, means, 200)
    S[2] = 0.0  # not positive definite: gates nothing
    S[3][np.ix_(VEL, VEL)] = 0.0  # velocity block singular: position only
    active = np.array([1, 0, 1, 1], np.uint8)
    got = assign_points(device, y, lam, means, S, 16.0, active=active, n_points=150)
    want = _reference(y, lam, means, S, 16.0, active, 150)
    labels = gputrack.to_numpy(got.labels)
    np.testing.assert_array_equal(labels, want[0])
    assert (labels[150:] == -1).all() and not np.isin(labels, [1, 2]).any() and (labels == 3).any()
    np.testing.assert_array_equal(gputrack.to_numpy(got.counts), want[1])
    # no group at all, and out= reuse
    none = assign_points(device, y, lam, np.zeros((0, 6), np.float32), np.zeros((0, 6, 6), np.float32), 9.0)
    assert (gputrack.to_numpy(none.labels) == -1).all()
    again = assign_points(device, y, lam, means, S, 16.0, active=active, n_points=150, out=got)
    assert again.labels is got.labels
    np.testing.assert_array_equal(gputrack.to_numpy(again.labels), want[0])


def test_bad_input(device):
    y = np.zeros((4, 3), np.float32)
    m = np.zeros((2, 6), np.float32)
    S = np.tile(np.eye(6, dtype=np.float32), (2, 1, 1))
    with pytest.raises(ValueError, match=r"points: expected shape \(N=4, 3\), got \(4, 2\)"):
        assign_points(device, y[:, :2], y, m, S, 9.0)
    with pytest.raises(ValueError, match=r"velocities: expected shape \(N=4, 3\), got \(3, 3\)"):
        assign_points(device, y, y[:3], m, S, 9.0)
    with pytest.raises(ValueError, match=r"spreads: expected shape \(T=2, 6, 6\), got \(3, 6, 6\)"):
        assign_points(device, y, y, m, np.tile(S[:1], (3, 1, 1)), 9.0)
    with pytest.raises(ValueError, match="gamma: expected a positive finite gate, got -1"):
        assign_points(device, y, y, m, S, -1)
    with pytest.raises(TypeError, match="gamma: expected a positive number"):
        assign_points(device, y, y, m, S, "9")
    with pytest.raises(ValueError, match=r"points: expected finite values or NaN rows \(no point\), got inf"):
        assign_points(device, np.full((4, 3), np.inf, np.float32), y, m, S, 9.0)
    with pytest.raises(ValueError, match="means: expected finite values"):
        assign_points(device, y, y, np.full((2, 6), np.nan, np.float32), S, 9.0)
    with pytest.raises(ValueError, match=r"n_points: expected an integer in \[0, 4\]"):
        assign_points(device, y, y, m, S, 9.0, n_points=5)
    with pytest.raises(TypeError, match="points: expected dtype float32, got complex128"):
        assign_points(device, y.astype(complex), y, m, S, 9.0)


# -- group_frame: a whole frame of the group table ------------------------------------------------

from gputrack.ops import constant_velocity
from gputrack.ops.point_groups import COLUMNS, group_constants, group_frame


def _constants(offset=120.0):
    F, Q = constant_velocity(3, 1.0, 1.0)
    return group_constants(F, Q, (16.0, 16.0, 0.04), f=513.5, b=120.0, cx=320.0, cy=240.0, gamma=11.34, alpha_s=0.9,
                           min_points=2, min_spread=(150.0, 3.0), surface_offset=offset, merge_gamma=11.34)  # fmt: skip


def _table(rng, T, live):
    """T slots, the first ``live`` of them live groups on a 3 m grid (a few pairs close enough to be
    merge candidates), slot 1 free."""
    means, S = _groups(rng, T)
    t = np.zeros((T, COLUMNS), np.float32)
    t[:, :6] = means
    t[1:3, 0] = t[0, 0] + np.array([400.0, 700.0])[: T - 1]  # near slot 0: merge candidates
    t[1:3, 2:5] = t[0, 2:5]
    t[:, 6:42] = (np.eye(6) * rng.uniform(50, 150, (T, 1, 1))).reshape(T, 36)
    t[:, 42:78] = S.reshape(T, 36)
    t[:live, 78] = 1
    t[1:2, 78] = 0
    return t


def _frame_points(rng, t, N, rows):
    y, lam = _points(rng, t[:, :6], N, scale=150.0)
    pts, vel = np.full((rows, 3), np.nan, np.float32), np.full((rows, 3), np.nan, np.float32)
    pts[:N], vel[:N] = y, lam
    pts[5:N:26, 2] = np.nan  # "no point" rows: a NaN position
    vel[18:N:26, 0] = np.nan  # or a NaN velocity
    return pts, vel


def _frame_against_reference(device, rng, T, live, N, offset=120.0):
    """One group_frame of T slots (``live`` of them live) and N points on ``device`` and on the
    reference: the labels equal, counts, seen and candidates equal, x, P, Sigma and the means
    close. Returns the device's (table, labels) and the reference's table."""
    t = _table(rng, T, live)
    rows = max(16, 1 << (N - 1).bit_length())
    pts, vel = _frame_points(rng, t, N, rows)
    c = _constants(offset)
    want_t, want_l = t.copy(), np.zeros(rows, np.int32)
    ref.group_frame(None, want_t, pts, vel, c, N, want_l)
    td = t.copy() if device.backend == "numpy" else device.asarray(t)
    got_t, got_l = group_frame(device, td, pts, vel, c, n_points=N)
    got_t, got_l = gputrack.to_numpy(got_t), gputrack.to_numpy(got_l)
    np.testing.assert_array_equal(got_l, want_l)
    for cols in ((79, 80), (86, 92)):  # counts; seen and the merge candidates
        np.testing.assert_array_equal(got_t[:, cols[0]:cols[1]], want_t[:, cols[0]:cols[1]])
    for a, b, scale in ((0, 6, 1e4), (6, 42, 1e3), (42, 78, 1e6), (80, 86, 1e4)):  # x, P, Sigma, mean
        np.testing.assert_allclose(got_t[:, a:b], want_t[:, a:b], rtol=2e-4, atol=1e-6 * scale)
    assert np.isfinite(got_t[:, :92]).all()
    return got_t, got_l, want_t


@pytest.mark.parametrize("N,T,live", [(1, 1, 1), (13, 3, 3), (1535, 17, 12), (129, 40, 40)])
def test_group_frame_matches_reference(device, N, T, live):
    rng = np.random.default_rng(7 * N + T)
    _, got_l, want_t = _frame_against_reference(device, rng, T, live, N, 120.0 if N != 13 else 0.0)
    assert (got_l[5:N:26] == -1).all() and (got_l[18:N:26] == -1).all() and (got_l[N:] == -1).all()
    assert (got_l >= 0).any()
    if live >= 3:
        assert want_t[0, 87] >= 1  # slots 0 and 2 overlap (slot 1 is free)


@pytest.mark.parametrize("serial_points", [0, 1 << 20])
def test_taichi_cpu_group_frame_threads_agree(device, serial_points, monkeypatch):
    """taichi:cpu runs the per-group loops on one thread up to SERIAL_POINTS points, on the pool
    beyond: both forms give the reference's answer."""
    if device.spec != "taichi:cpu":
        pytest.skip("the one-thread per-group loops are taichi:cpu's")
    from gputrack.backends.taichi import point_groups as tpg

    monkeypatch.setattr(tpg, "SERIAL_POINTS", serial_points)
    _, got_l, _ = _frame_against_reference(device, np.random.default_rng(11), 17, 12, 1535)
    assert (got_l >= 0).any()


def test_group_frame_predicts_a_group_without_points(device):
    t = _table(np.random.default_rng(3), 4, 4)
    pts = np.full((16, 3), np.nan, np.float32)
    c = _constants()
    td = t.copy() if device.backend == "numpy" else device.asarray(t)
    got_t, got_l = group_frame(device, td, pts, pts, c, n_points=0)
    got_t = gputrack.to_numpy(got_t)
    F = c[:36].reshape(6, 6)
    np.testing.assert_allclose(got_t[:, :6], t[:, :6] @ F.T, rtol=1e-6, atol=1e-4)
    assert (got_t[:, 79] == 0).all() and (got_t[:, 86] == 0).all()  # no points: nobody seen
    np.testing.assert_array_equal(got_t[:, 42:78], t[:, 42:78])  # spreads kept
    assert (gputrack.to_numpy(got_l) == -1).all()


def test_group_frame_bad_input(device):
    t = _table(np.random.default_rng(4), 4, 4)
    pts = np.zeros((16, 3), np.float32)
    c = _constants()
    with pytest.raises(ValueError, match="table"):
        group_frame(device, t[:, :90], pts, pts, c)
    with pytest.raises(ValueError, match="points"):
        group_frame(device, t, np.zeros((16, 6), np.float32), pts, c)
    with pytest.raises(ValueError, match="velocities"):
        group_frame(device, t, pts, pts[:15], c)
    bad = pts.copy()
    bad[2, 1] = np.inf
    with pytest.raises(ValueError, match="finite values or NaN rows"):
        group_frame(device, t, bad, pts, c)
    with pytest.raises(ValueError, match="velocities: expected finite values or NaN rows"):
        group_frame(device, t, pts, bad, c)
    with pytest.raises(ValueError, match="n_points"):
        group_frame(device, t, pts, pts, c, n_points=17)
    with pytest.raises(ValueError, match="constants"):
        group_frame(device, t, pts, pts, c[:80])
    with pytest.raises(ValueError, match="finite constants"):
        group_constants(np.eye(6), np.eye(6) * np.nan, (1, 1, 1), f=1, b=1, cx=0, cy=0, gamma=1, alpha_s=0.5,
                        min_points=2, min_spread=(1, 1), surface_offset=0, merge_gamma=1)  # fmt: skip

"""gputrack.ops.gating.gate_pairs on every device against the NumPy reference, and bad input."""

import numpy as np
import pytest

import gputrack
from gputrack.backends.reference.kalman import mahalanobis as dense_reference
from gputrack.ops.gating import gate_pairs

from tolerances import tolerance


def _problem(rng, T, D, n=4, m=2, spread=10.0):
    x = rng.uniform(0, spread, (T, n)).astype(np.float32)
    A = rng.standard_normal((T, n, n)).astype(np.float32)
    P = (0.2 * A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(n)).astype(np.float32)
    H = np.zeros((m, n), np.float32)
    H[np.arange(m), 2 * np.arange(m) % n] = 1
    R = (0.05 * np.eye(m) + 0.01).astype(np.float32)
    z = rng.uniform(0, spread, (D, m)).astype(np.float32)
    return x, P, H, R, z[np.argsort(z[:, 0], kind="stable")]


def _host(g):
    return [gputrack.to_numpy(a) for a in g]


@pytest.mark.parametrize("T,D,m", [(1, 1, 2), (13, 127, 2), (129, 40, 3), (300, 1, 1), (7, 0, 2)])
@pytest.mark.parametrize("sorted_z", [False, True])
def test_gate_pairs_matches_the_dense_distances(device, T, D, m, sorted_z):
    rng = np.random.default_rng(T * 1000 + D)
    x, P, H, R, z = _problem(rng, T, D, m=m, spread=10.0 if m < 3 else 4.0)
    P[T // 2] = -np.eye(4)  # a track whose S is not positive definite gates nothing
    active = (rng.random(T) < 0.8).astype(np.uint8)
    thr = 9.0
    g = _host(gate_pairs(device, x, P, H, R, z, thr, active=active, max_pairs=3, sorted_z=sorted_z))
    full = dense_reference(None, x, P, H, R, z) if D else np.zeros((T, 0), np.float32)
    rtol, atol = tolerance(device, scale=10)
    inside = (full < np.float32(thr)) & active.astype(bool)[:, None]
    borderline = np.abs(full - thr) <= 1e-4 * thr
    assert not borderline.any(), "the problem should have no distance at the threshold"
    np.testing.assert_array_equal(g[0], inside.sum(1))
    for t in range(T):
        want = np.flatnonzero(inside[t])[:3]
        k = len(want)
        np.testing.assert_array_equal(g[1][t, :k], want, err_msg=f"track {t}")
        np.testing.assert_allclose(g[2][t, :k], full[t, want], rtol=rtol, atol=atol)
    Ps = 0.5 * (P + np.swapaxes(P, 1, 2))
    np.testing.assert_allclose(g[3], np.einsum("ak,tkl,al->t", H, Ps, H), rtol=rtol, atol=atol)
    assert g[0][T // 2] == 0
    assert (g[0] > 3).any() or T * D < 400, "the test should hold tracks with more pairs than max_pairs"


def test_gate_pairs_sorted_sweep_in_a_crowd(device):
    # many tracks and detections, small gates: the sweep and the full scan find the same pairs
    rng = np.random.default_rng(7)
    x, P, H, R, z = _problem(rng, 600, 500, spread=100.0)
    P *= 0.05
    a = _host(gate_pairs(device, x, P, H, R, z, 13.8, max_pairs=8, sorted_z=True))
    b = _host(gate_pairs(device, x, P, H, R, z, 13.8, max_pairs=8, sorted_z=False))
    assert a[0].sum() > 50
    np.testing.assert_array_equal(a[0], b[0])
    keep = np.arange(8)[None, :] < a[0][:, None]
    np.testing.assert_array_equal(a[1][keep], b[1][keep])
    np.testing.assert_array_equal(a[2][keep], b[2][keep])


def test_gate_pairs_outputs_and_bad_input(device):
    rng = np.random.default_rng(1)
    x, P, H, R, z = _problem(rng, 5, 6)
    out = tuple(device.empty(s, d) for s, d in (((5,), np.int32), ((5, 2), np.int32), ((5, 2), np.float32),
                                                ((5,), np.float32)))  # fmt: skip
    g = gate_pairs(device, x, P, H, R, z, 9.0, out=out)
    assert all(a is b for a, b in zip(g, out))
    with pytest.raises(ValueError, match=r"z: expected rows sorted by z\[:, 0\]"):
        gate_pairs(device, x, P, H, R, z[::-1], 9.0, sorted_z=True)
    with pytest.raises(ValueError, match="threshold: expected a number > 0, got 0.0"):
        gate_pairs(device, x, P, H, R, z, 0.0)
    with pytest.raises(ValueError, match="threshold: expected a finite number, got inf"):
        gate_pairs(device, x, P, H, R, z, float("inf"))
    with pytest.raises(TypeError, match="threshold: expected a real number"):
        gate_pairs(device, x, P, H, R, z, "9")
    with pytest.raises(ValueError, match="z: expected finite values"):
        gate_pairs(device, x, P, H, R, np.where(z > 5, np.nan, z), 9.0)
    with pytest.raises(ValueError, match=r"z: expected shape \(D, m=2\), got \(6, 3\)|H: expected shape"):
        gate_pairs(device, x, P, H, R, np.zeros((6, 3), np.float32), 9.0)
    with pytest.raises(ValueError, match=r"active: expected shape \(T=5\), got \(4,\)"):
        gate_pairs(device, x, P, H, R, z, 9.0, active=np.ones(4, np.uint8))
    with pytest.raises(ValueError, match="max_pairs: expected a positive integer"):
        gate_pairs(device, x, P, H, R, z, 9.0, max_pairs=0)
    with pytest.raises(ValueError, match=r"P: expected shape \(T=5, n=4, n=4\)"):
        gate_pairs(device, x, P[:4], H, R, z, 9.0)
    with pytest.raises(ValueError, match=r"H: expected a shared matrix"):
        gate_pairs(device, x, P, np.tile(H, (5, 1, 1)), R, z, 9.0)


def test_gate_pairs_reads_only_the_first_n_z_detections(device):
    # a padded buffer of detections: rows after n_z are never gated, whatever they hold
    rng = np.random.default_rng(4)
    x, P, H, R, z = _problem(rng, 30, 20)
    padded = np.concatenate([z, np.tile(x[:1, [0, 2]], (12, 1))]).astype(np.float32)  # on top of track 0
    for sorted_z in (False, True):
        a = _host(gate_pairs(device, x, P, H, R, padded, 9.0, sorted_z=sorted_z, n_z=20))
        b = _host(gate_pairs(device, x, P, H, R, z, 9.0, sorted_z=sorted_z))
        np.testing.assert_array_equal(a[0], b[0])
        keep = np.arange(16)[None, :] < np.minimum(a[0], 16)[:, None]
        np.testing.assert_array_equal(a[1][keep], b[1][keep])
    with pytest.raises(ValueError, match=r"n_z: expected an integer in \[0, 32\]"):
        gate_pairs(device, x, P, H, R, padded, 9.0, n_z=33)
    g = _host(gate_pairs(device, x, P, H, R, padded, 9.0, n_z=0))
    assert (g[0] == 0).all()

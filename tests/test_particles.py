"""Particle-filter helpers: counter-based sampling around candidates (paper 000 eq. 12) and best-k."""

import numpy as np
import pytest
from allocations import rejects_without_allocating
from tolerances import assert_matches, fuses

import gputrack
from gputrack.backends.reference.particles import sortable_key
from gputrack.ops.particles import best_k, sample_around

REF = gputrack.device("numpy")


def test_reference_distribution():
    """The generator's deviates are standard normal: moments and a histogram."""
    cand = np.zeros((1, 5), np.float32)
    s = sample_around(REF, cand, np.ones(5, np.float32), 200_000, 42)
    z = s.ravel().astype(np.float64)
    assert abs(z.mean()) < 5 / np.sqrt(z.size)
    assert abs(z.var() - 1) < 0.01
    assert abs(np.mean(z**3)) < 0.02 and abs(np.mean(z**4) - 3) < 0.05
    hist, edges = np.histogram(z, bins=[-np.inf, -2, -1, 0, 1, 2, np.inf])
    from math import erf, sqrt

    cdf = [0.0] + [0.5 * (1 + erf(e / sqrt(2))) for e in edges[1:-1]] + [1.0]
    expect = np.diff(cdf) * z.size
    assert np.all(np.abs(hist - expect) < 5 * np.sqrt(expect))
    # neighbouring parameters and neighbouring samples are uncorrelated
    s2 = s.astype(np.float64)
    assert abs(np.corrcoef(s2[:, 0], s2[:, 1])[0, 1]) < 0.01
    assert abs(np.corrcoef(s2[:-1, 0], s2[1:, 0])[0, 1]) < 0.01


@pytest.mark.parametrize("c,p,n", [(1, 1, 1), (10, 14, 1500), (3, 20, 13), (7, 6, 129), (10, 14, 1535)])
def test_sample_around_matches_reference(device, c, p, n):
    rng = np.random.default_rng(c * 1000 + p + n)
    cand = rng.normal(0, 3, (c, p)).astype(np.float32)
    sigma = rng.uniform(0.01, 2, p).astype(np.float32)
    got = sample_around(device, cand, sigma, n, 987654321987654321)
    want = sample_around(REF, cand, sigma, n, 987654321987654321)
    assert got.shape == (n, p)
    # the same generator: equal to libm rounding (log, cos) scaled by sigma
    assert_matches(device, got, want, scale=10.0)
    sig_c = rng.uniform(0.01, 2, (c, p)).astype(np.float32)
    got = sample_around(device, cand, sig_c, n, 5, keep_candidates=True)
    want = sample_around(REF, cand, sig_c, n, 5, keep_candidates=True)
    assert_matches(device, got, want, scale=10.0)


def test_sample_around_distribution_and_layout(device):
    c, p, n = 10, 14, 15000
    rng = np.random.default_rng(0)
    cand = rng.normal(0, 10, (c, p)).astype(np.float32)
    sigma = np.linspace(0.1, 3, p).astype(np.float32)
    s = gputrack.to_numpy(sample_around(device, cand, sigma, n, 1234))
    owner = np.arange(n) * c // n
    dev = (s - cand[owner]) / sigma
    assert np.abs(dev.mean(axis=0)).max() < 6 / np.sqrt(n)
    np.testing.assert_allclose(dev.std(axis=0), 1.0, atol=0.03)
    # same seed: same samples; another seed: other samples
    again = gputrack.to_numpy(sample_around(device, cand, sigma, n, 1234))
    np.testing.assert_array_equal(s, again)
    other = gputrack.to_numpy(sample_around(device, cand, sigma, n, 1235))
    assert np.mean(np.isclose(s, other)) < 0.01
    # keep_candidates: the first sample of each block is its candidate, exactly
    kept = gputrack.to_numpy(sample_around(device, cand, sigma, n, 1234, keep_candidates=True))
    first = np.searchsorted(owner, np.arange(c))
    np.testing.assert_array_equal(kept[first], cand)
    rest = np.setdiff1d(np.arange(n), first)
    if fuses(device):  # the two variants may contract mu + sigma z differently (tests/tolerances.py):
        # a few roundings (z's own formula, the product, the sum) of the largest term
        rounding = 4 * np.spacing(np.abs(cand).max(axis=0) + 6 * sigma)
        assert (np.abs(kept[rest] - s[rest]) <= rounding).all()
    else:
        np.testing.assert_array_equal(kept[rest], s[rest])
    # zero sigma: every sample is its candidate
    z = gputrack.to_numpy(sample_around(device, cand, np.zeros(p, np.float32), 37, 9))
    np.testing.assert_array_equal(z, cand[np.arange(37) * c // 37])


@pytest.mark.parametrize("b,k", [(1, 1), (13, 1), (13, 13), (1500, 10), (1535, 129)])
def test_best_k_matches_reference(device, b, k):
    rng = np.random.default_rng(b + k)
    scores = rng.normal(size=b).astype(np.float32)
    if b > 10:
        scores[3] = scores[7] = scores[8]  # ties: lower index first
        scores[5] = np.nan
        scores[6] = np.inf
        scores[9] = -np.inf
    rows = rng.normal(size=(b, 14)).astype(np.float32)
    got = best_k(device, scores, k, rows=rows)
    order = np.argsort(sortable_key(scores), kind="stable")[:k]
    np.testing.assert_array_equal(gputrack.to_numpy(got.indices), order)
    np.testing.assert_array_equal(gputrack.to_numpy(got.scores), scores[order])
    np.testing.assert_array_equal(gputrack.to_numpy(got.rows), rows[order])
    plain = best_k(device, scores, k)
    assert plain.rows is None
    np.testing.assert_array_equal(gputrack.to_numpy(plain.indices), order)


def test_best_k_writes_into_out(device):
    rng = np.random.default_rng(5)
    scores = rng.normal(size=200).astype(np.float32)
    rows = rng.normal(size=(200, 6)).astype(np.float32)
    fresh = best_k(device, scores, 7, rows=rows)
    out = best_k(device, scores[::-1].copy(), 7, rows=rows)
    got = best_k(device, scores, 7, rows=rows, out=out)
    for name in ("indices", "scores", "rows"):
        assert getattr(got, name) is getattr(out, name)
        np.testing.assert_array_equal(gputrack.to_numpy(getattr(got, name)), gputrack.to_numpy(getattr(fresh, name)))
    plain = best_k(device, scores, 7, out=gputrack.BestK(out.indices, out.scores))
    np.testing.assert_array_equal(gputrack.to_numpy(plain.indices), gputrack.to_numpy(fresh.indices))
    with pytest.raises(ValueError, match=r"out.rows: expected a float32 array of shape \(7, 5\)"):
        best_k(device, scores, 7, rows=rows[:, :5], out=out)
    if device.backend != "numpy":
        with pytest.raises(TypeError, match="out.scores: expected a writable array on"):
            best_k(device, scores, 7, out=gputrack.BestK(out.indices, gputrack.to_numpy(out.scores)))


def test_best_k_ordering_rules(device):
    scores = np.array([3.0, np.nan, -0.0, 1.0, np.inf, -np.inf, 1.0, -2.5], np.float32)
    got = gputrack.to_numpy(best_k(device, scores, 8).indices)
    np.testing.assert_array_equal(got, [5, 7, 2, 3, 6, 0, 4, 1])  # NaN after +inf, ties by index


def test_best_k_on_device_data_makes_no_transfer(device):
    if device.backend == "numpy":
        pytest.skip("the numpy device has no transfers")
    rng = np.random.default_rng(2)
    cand = device.asarray(rng.normal(size=(10, 14)).astype(np.float32))
    sigma = device.asarray(np.ones(14, np.float32))
    scores = device.asarray(rng.normal(size=1500).astype(np.float32))
    before = device.transfers.copy()
    samples = sample_around(device, cand, sigma, 1500, 3)
    best = best_k(device, scores, 10, rows=samples)
    moved = device.transfers - before
    assert (moved.h2d, moved.d2h) == (0, 0)
    assert best.rows.shape == (10, 14)


def test_bad_input(device):
    cand = np.zeros((3, 4), np.float32)
    sig = np.ones(4, np.float32)
    with pytest.raises(ValueError, match=r"sigma: expected shape \(P=4\), got \(5,\)"):
        sample_around(device, cand, np.ones(5, np.float32), 10, 1)
    with pytest.raises(ValueError, match=r"sigma: expected shape \(C=3, P=4\)"):
        sample_around(device, cand, np.ones((2, 4), np.float32), 10, 1)
    with pytest.raises(ValueError, match="sigma: expected standard deviations >= 0"):
        sample_around(device, cand, -sig, 10, 1)
    with pytest.raises(ValueError, match="candidates: expected finite values"):
        c = cand.copy()
        c[1, 2] = np.nan
        sample_around(device, c, sig, 10, 1)
    with pytest.raises(TypeError, match="candidates: expected dtype float32, got float64"):
        sample_around(device, cand.astype(np.float64), sig, 10, 1)
    with pytest.raises(ValueError, match="at least one candidate"):
        sample_around(device, cand[:0], sig, 10, 1)
    with pytest.raises(ValueError, match="n: expected at least one sample, got 0"):
        sample_around(device, cand, sig, 0, 1)
    with pytest.raises(TypeError, match="n: expected an integer"):
        sample_around(device, cand, sig, 10.0, 1)
    with pytest.raises(ValueError, match=r"seed: expected an integer in \[0, 2\*\*64\)"):
        sample_around(device, cand, sig, 10, -1)
    with pytest.raises(TypeError, match="seed: expected an integer"):
        sample_around(device, cand, sig, 10, 1.5)
    scores = np.zeros(20, np.float32)
    with pytest.raises(ValueError, match=r"k: expected 1 <= k <= B=20, got 21"):
        best_k(device, scores, 21)
    with pytest.raises(ValueError, match=r"k: expected 1 <= k <= B=20, got 0"):
        best_k(device, scores, 0)
    with pytest.raises(ValueError, match=r"scores: expected shape \(B\), got \(20, 1\)"):
        best_k(device, np.zeros((20, 1), np.float32), 3)
    with pytest.raises(ValueError, match=r"rows: expected shape \(B=20, P\)"):
        best_k(device, scores, 3, rows=np.zeros((19, 2), np.float32))
    with pytest.raises(TypeError, match="scores: expected dtype float32"):
        best_k(device, scores.astype(np.int32), 3)
    # shapes first: broadcast views of 2**32 rows are rejected without being copied or scanned
    rows = np.broadcast_to(np.zeros(1, np.float32), (2**32, 3))
    rejects_without_allocating(ValueError, r"^rows: expected shape \(B=20, P\), got \(4294967296, 3\)\Z",
                               lambda: best_k(device, scores, 3, rows=rows))  # fmt: skip
    many = np.broadcast_to(np.zeros(1, np.float32), (2**32,))
    rejects_without_allocating(ValueError, r"^rows: expected shape \(B=4294967296, P\), got \(20, 3\)\Z",
                               lambda: best_k(device, many, 3, rows=np.zeros((20, 3), np.float32)))  # fmt: skip

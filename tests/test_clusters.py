"""gputrack.ops.clusters (radius_components, dbscan) on every device against the NumPy reference
(labels are integers: compared exactly), the reference and the devices against scikit-learn's
DBSCAN, the documented border-point rule, and bad input."""

import numpy as np
import pytest
from tolerances import fuses

import gputrack
from gputrack.ops.clusters import compact_labels, dbscan, radius_components

REF = gputrack.device("numpy")


def _labels(x):
    return np.asarray(gputrack.to_numpy(x))


def _cloud(N, dim, seed, *, nan_rows=True, duplicates=True):
    """Points in a unit box (clumpy: half of them near a few centres), some NaN rows, some
    duplicated points."""
    rng = np.random.default_rng(seed)
    p = rng.random((N, dim))
    if N >= 4:
        centres = rng.random((3, dim))
        half = N // 2
        p[:half] = centres[rng.integers(0, 3, half)] + 0.03 * rng.standard_normal((half, dim))
    p = p.astype(np.float32)
    if duplicates and N >= 8:
        p[N // 3] = p[N // 4]
        p[N - 1] = p[0]
    if nan_rows and N >= 8:
        p[N // 5] = np.nan
        p[N // 2, 0] = np.nan  # one NaN coordinate: not a point either
    return p


SIZES = [0, 1, 13, 127, 1535]


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("N", SIZES)
def test_radius_components_matches_reference(device, N, dim):
    p = _cloud(N, dim, N + dim)
    r = 0.05 if dim == 2 else 0.1
    want = radius_components(REF, p, r)
    got = _labels(radius_components(device, p, r))
    assert got.dtype == np.int32 and got.shape == (N,)
    np.testing.assert_array_equal(got, want)
    if N >= 8:
        assert want[N // 5] == -1 and want[N // 2] == -1  # NaN rows
        assert want[N // 3] == want[N // 4] and want[N - 1] == want[0] == 0  # duplicates linked
        assert 1 < np.unique(want[want >= 0]).size < N  # neither one component nor all singletons
    valid = want >= 0
    assert (want[valid] <= np.flatnonzero(valid)).all()  # a label is the smallest index of its component


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("N", SIZES)
def test_dbscan_matches_reference(device, N, dim):
    p = _cloud(N, dim, 7 * N + dim)
    eps = 0.05 if dim == 2 else 0.1
    for min_samples in (1, 4, 12):
        want = dbscan(REF, p, eps, min_samples)
        got = _labels(dbscan(device, p, eps, min_samples))
        np.testing.assert_array_equal(got, want, err_msg=f"min_samples={min_samples}")
    if N >= 127:  # the cloud has clusters and noise at min_samples = 12
        assert (want == -1).sum() > 10 and np.unique(want[want >= 0]).size >= 2


def test_reference_matches_brute_force():
    """The reference against the definition: all pairs, float32 distances, a union-find."""
    p = _cloud(300, 3, 5)
    r2 = np.float32(0.1) * np.float32(0.1)
    d = p[:, None, :] - p[None, :, :]
    d2 = (d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]) + d[..., 2] * d[..., 2]
    adj = d2 <= r2
    parent = list(range(300))

    def find(x):
        while parent[x] != x:
            x = parent[x]
        return x

    for i, j in zip(*np.nonzero(adj)):
        a, b = find(i), find(j)
        if a != b:
            parent[max(a, b)] = min(a, b)
    valid = ~np.isnan(p).any(axis=1)
    want = np.array([find(i) if valid[i] else -1 for i in range(300)], np.int32)
    np.testing.assert_array_equal(radius_components(REF, p, 0.1), want)


@pytest.mark.parametrize("order", ["sorted", "shuffled", "reversed"])
def test_long_chain_is_one_component(device, order):
    """A path graph of 2500 points (spacing 0.8 r; more points than taichi:cpu runs on one thread):
    the labels must travel 2499 hops."""
    N = 2500
    x = np.arange(N, dtype=np.float32) * np.float32(0.8)
    p = np.stack([x, np.full(N, 5.0, np.float32)], 1)  # 2D only: one more kernel variant to compile
    if order == "shuffled":
        p = p[np.random.default_rng(1).permutation(N)]
    elif order == "reversed":
        p = p[::-1].copy()
    np.testing.assert_array_equal(_labels(radius_components(device, p, 1.0)), np.zeros(N, np.int32))
    # dbscan with min_samples 3: the two ends are border points of the one cluster
    got = _labels(dbscan(device, p, 1.0, 3))
    np.testing.assert_array_equal(got, dbscan(REF, p, 1.0, 3))
    assert np.unique(got).size == 1 and got.min() >= 0
    # cut the chain in the middle (a gap of 2 r): two components
    q = np.stack([x + np.float32(2.0) * (np.arange(N) >= N // 2), np.zeros(N, np.float32)], 1).astype(np.float32)
    got = _labels(radius_components(device, q, 1.0))
    np.testing.assert_array_equal(got, np.where(np.arange(N) < N // 2, 0, N // 2).astype(np.int32))


def test_one_cluster_and_all_noise(device):
    p = _cloud(127, 2, 3, nan_rows=False)
    np.testing.assert_array_equal(_labels(radius_components(device, p, 10.0)), np.zeros(127, np.int32))
    np.testing.assert_array_equal(_labels(dbscan(device, p, 10.0, 127)), np.zeros(127, np.int32))
    np.testing.assert_array_equal(_labels(dbscan(device, p, 10.0, 128)), np.full(127, -1, np.int32))  # no core
    single = _labels(radius_components(device, p, 1e-6))  # only the two duplicated pairs are linked
    np.testing.assert_array_equal(single, radius_components(REF, p, 1e-6))
    assert np.unique(single).size == 125
    nan = np.full((13, 3), np.nan, np.float32)
    np.testing.assert_array_equal(_labels(radius_components(device, nan, 1.0)), np.full(13, -1, np.int32))
    np.testing.assert_array_equal(_labels(dbscan(device, nan, 1.0, 1)), np.full(13, -1, np.int32))


def _ties(n, seed=0):
    """n pairs of 2D points (10 apart) at distance exactly on the radius 1 in float32, where a fused
    multiply-add would round d2 to the other side of r2 = 1 (some linked, some not)."""
    f32 = np.float32
    rng = np.random.default_rng(seed)
    rows = []
    while len(rows) < 2 * n:
        x0 = f32(10.0 * len(rows))
        q0 = f32(x0 + f32(rng.uniform(0.3, 0.9)))
        d0 = f32(q0 - x0)
        v = f32(np.sqrt(1.0 - np.float64(d0) ** 2))
        for d1 in (np.nextafter(v, f32(0)), v, np.nextafter(v, f32(2))):
            plain = f32(f32(d0 * d0) + f32(d1 * d1))
            fused = f32(np.float64(d1) * d1 + np.float64(f32(d0 * d0)))
            if plain != fused and f32(1.0) in (plain, fused):
                rows += [[x0, 0.0], [q0, d1]]
                break
    return np.array(rows, f32)


def test_exact_ties_at_the_radius(device):
    """Pairs on the radius to the last bit: linked exactly when the unfused float32 d2 <= r2."""
    p = _ties(20)
    d = p[1::2] - p[0::2]
    f32, one = np.float32, np.float32(1.0)
    linked = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] <= one
    assert 0 < linked.sum() < 20
    expect = lambda link: np.where(np.repeat(link, 2), np.repeat(np.arange(0, 40, 2), 2), np.arange(40)).astype(np.int32)  # noqa: E731
    np.testing.assert_array_equal(radius_components(REF, p, 1.0), expect(linked))
    got, core = _labels(radius_components(device, p, 1.0)), _labels(dbscan(device, p, 1.0, 2))
    if fuses(device):  # d2 is one fma on such a device (tests/tolerances.py): the fused rounding decides
        d64 = d.astype(np.float64)
        fused = [(d64[:, a] * d64[:, a] + (d[:, b] * d[:, b]).astype(np.float64)).astype(f32) <= one for a, b in ((0, 1), (1, 0))]
        linked = next((f for f in fused if np.array_equal(got, expect(f))), fused[0])
    np.testing.assert_array_equal(got, expect(linked))
    np.testing.assert_array_equal(core, np.where(np.repeat(linked, 2), expect(linked), -1))


@pytest.mark.parametrize("offset,r", [(4e6, 0.3), (3e7, 3.0)])
def test_far_from_the_origin(device, offset, r):
    """Coordinates so large that float32 cell indices round (the grid's cells then hold points
    farther apart than r, found and linked pair by pair): still the reference's labels."""
    p = (offset + np.random.default_rng(2).uniform(0, 30 * r, (500, 2))).astype(np.float32)
    want = radius_components(REF, p, r)
    assert 50 < np.unique(want).size < 400
    np.testing.assert_array_equal(_labels(radius_components(device, p, r)), want)
    np.testing.assert_array_equal(_labels(dbscan(device, p, r, 3)), dbscan(REF, p, r, 3))


def test_n_points_device_inputs_and_out(device):
    p = _cloud(127, 3, 11)
    padded = np.concatenate([p, np.random.default_rng(0).random((40, 3)).astype(np.float32)])
    want = np.concatenate([radius_components(REF, p, 0.1), np.full(40, -1, np.int32)])
    dev_pts = device.asarray(padded) if device.backend != "numpy" else padded
    out = device.empty((167,), np.int32)
    got = radius_components(device, dev_pts, 0.1, n_points=127, out=out)
    assert got is out
    np.testing.assert_array_equal(_labels(got), want)
    want = np.concatenate([dbscan(REF, p, 0.1, 4), np.full(40, -1, np.int32)])
    np.testing.assert_array_equal(_labels(dbscan(device, dev_pts, 0.1, 4, n_points=127, out=out)), want)
    np.testing.assert_array_equal(_labels(dbscan(device, dev_pts, 0.1, 4, n_points=0, out=out)), -1)
    # a smaller frame in the same buffers after a larger one
    want = np.concatenate([radius_components(REF, p[:13], 0.1), np.full(154, -1, np.int32)])
    np.testing.assert_array_equal(_labels(radius_components(device, dev_pts, 0.1, n_points=13)), want)


def _sklearn(p, eps, min_samples):
    sklearn_cluster = pytest.importorskip("sklearn.cluster")
    return sklearn_cluster.DBSCAN(eps=eps, min_samples=min_samples).fit(p).labels_.astype(np.int32)


@pytest.mark.parametrize("dim,seed", [(2, 0), (2, 1), (3, 2)])
def test_dbscan_equals_sklearn_on_blobs(device, dim, seed):
    datasets = pytest.importorskip("sklearn.datasets")
    n = 1024 if dim == 2 else 600
    p, _ = datasets.make_blobs(n_samples=n, n_features=dim, centers=5, cluster_std=0.5, random_state=seed)
    p = p.astype(np.float32)
    for eps, ms in ((0.3, 5), (0.5, 10)):
        want = _sklearn(p, eps, ms)
        got = compact_labels(dbscan(device, p, eps, ms))
        np.testing.assert_array_equal(got, want, err_msg=f"eps={eps} min_samples={ms}")
        assert np.unique(want[want >= 0]).size >= 3 and (want == -1).any()


def _ambiguous(first):
    """Border point x (index 0, 3 neighbours: not core at min_samples 4) reached by two clusters:
    A (its nearest core point a1 at 0.9) and B (b1 at 0.95). ``first`` names the cluster whose
    core points come first in the array (the smaller label)."""
    x = [[0.0, 0.0]]
    b = [[-0.95, 0.0], [-1.5, 0.0], [-1.5, 0.3], [-1.5, -0.3], [-1.8, 0.0]]
    a = [[0.9, 0.0], [1.5, 0.0], [1.5, 0.3], [1.5, -0.3], [1.8, 0.0]]
    return np.array(x + (b + a if first == "B" else a + b), np.float32)


@pytest.mark.parametrize("first", ["A", "B"])
def test_dbscan_ambiguous_border_point(device, first):
    p = _ambiguous(first)
    got = _labels(dbscan(device, p, 1.0, 4))
    np.testing.assert_array_equal(got, dbscan(REF, p, 1.0, 4))
    assert got[1] == 1 and got[6] == 6  # the two clusters, labelled by their smallest core index
    assert got[0] == 1  # the documented rule: the smaller label, whichever core point is nearer
    np.testing.assert_array_equal(compact_labels(got), _sklearn(p, 1.0, 4))  # and scikit-learn's choice
    assert compact_labels(got)[0] == 0


def test_compact_labels():
    np.testing.assert_array_equal(compact_labels(np.array([5, -1, 2, 5, 9, 2], np.int32)), [1, -1, 0, 1, 2, 0])
    assert compact_labels(np.zeros(0, np.int32)).shape == (0,)
    with pytest.raises(ValueError, match="labels: expected a 1-D integer array"):
        compact_labels(np.zeros(3, np.float32))


def test_bad_input(device):
    p = _cloud(13, 2, 0)
    with pytest.raises(ValueError, match=r"points: expected shape \(N, 2\) or \(N, 3\), got \(13,\)"):
        radius_components(device, p[:, 0].copy(), 1.0)
    with pytest.raises(ValueError, match=r"points: expected shape \(N, 2\) or \(N, 3\), got \(13, 4\)"):
        dbscan(device, np.zeros((13, 4), np.float32), 1.0, 2)
    with pytest.raises(ValueError, match=r"points: expected shape"):
        dbscan(device, np.zeros((2, 13, 2), np.float32), 1.0, 2)
    with pytest.raises(TypeError, match="points: expected dtype float32, got float64"):
        radius_components(device, p.astype(np.float64), 1.0)
    with pytest.raises(TypeError, match="points: expected dtype float32, got int64"):
        radius_components(device, np.zeros((3, 2), np.int64), 1.0)
    inf = p.copy()
    inf[3, 1] = np.inf
    with pytest.raises(ValueError, match="points: expected finite coordinates or NaN rows"):
        dbscan(device, inf, 1.0, 2)
    for bad, want in ((0.0, "a number > 0, got 0.0"), (-1.0, "a number > 0, got -1.0"), (float("nan"), "a finite number"),
                      (float("inf"), "a finite number"), (1e-30, "a positive finite distance \\(float32 square"),
                      (1e30, "a positive finite distance \\(float32 square")):  # fmt: skip
        with pytest.raises(ValueError, match=f"eps: expected {want}"):
            dbscan(device, p, bad, 2)
        with pytest.raises(ValueError, match=f"radius: expected {want}"):
            radius_components(device, p, bad)
    with pytest.raises(TypeError, match="radius: expected a real number, got str"):
        radius_components(device, p, "1")
    for bad in (0, -3, 1.5, True, None):
        with pytest.raises(ValueError, match="min_samples: expected an integer >= 1"):
            dbscan(device, p, 1.0, bad)
    for bad in (-1, 14, 2.0, True):
        with pytest.raises(ValueError, match=r"n_points: expected an integer in \[0, 13\]"):
            radius_components(device, p, 1.0, n_points=bad)
    with pytest.raises(ValueError, match=r"out: expected a int32 array of shape \(13,\)"):
        radius_components(device, p, 1.0, out=device.empty((12,), np.int32))
    with pytest.raises(ValueError, match=r"out: expected a int32 array of shape \(13,\)"):
        dbscan(device, p, 1.0, 2, out=device.empty((13,), np.float32))
    with pytest.raises(TypeError, match="expected a gputrack.Device"):
        radius_components("numpy", p, 1.0)


def test_selftest(device):
    from gputrack.selftest import check_clusters

    check_clusters(device)


def test_benchmark_cases_run(device):
    """gputrack/benchmarks/clusters.py at small sizes: its cases check the device's labels against
    the reference when they are built, and every callable runs."""
    import argparse

    from gputrack.benchmarks import clusters as bench

    args = argparse.Namespace(dbscan_points=300, components_points=600)
    cases = bench.cases(device, args)
    assert [c.name for c in cases] == ["dbscan N=300 2D", "radius_components N=600 3D"]
    for case in cases:
        np.testing.assert_array_equal(_labels(case.run()), _labels(case.reference()))
        np.testing.assert_array_equal(_labels(case.end_to_end()), _labels(case.reference()))
        assert case.params["dim"] in (2, 3)

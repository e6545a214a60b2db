"""The host helpers of the group tracker's rules, against independent computations: the
eigenvalue filter of the split rule, the components of the merge and start rules, and the host
pre-test that spares the device call of eq. 12."""

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from gputrack.trackers.groups import rules
from gputrack.trackers.groups.tracker import _may_link, _union


def test_may_exceed_is_false_exactly_where_every_eigenvalue_is_below_c():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(5000, 3, 3))
    S = A @ np.swapaxes(A, 1, 2) * rng.uniform(0.1, 3.0, (5000, 1, 1))
    top = np.linalg.eigvalsh(S)[:, -1]
    for c in (0.5, 3.0, 10.0):
        got = rules.may_exceed(S, c)
        assert np.array_equal(got, top >= c)
        assert 0 < got.sum() < len(S)  # both answers occur
    S[0, 1, 1] = np.nan  # a spread that is not finite is never examined
    assert not rules.may_exceed(S[:1], 0.0)[0]


def _same_partition(a, b) -> bool:
    return len(set(zip(a.tolist(), b.tolist()))) == len(set(a.tolist())) == len(set(b.tolist()))


@pytest.mark.parametrize("seed", range(5))
def test_union_labels_the_components_scipy_finds(seed):
    rng = np.random.default_rng(seed)
    k = int(rng.integers(1, 300))
    pairs = rng.integers(0, k, (int(rng.integers(0, 2 * k)), 2))
    got = _union(k, pairs)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(k, k))
    want = connected_components(g, directed=False)[1]
    assert _same_partition(got, want)
    assert all(got[i] == np.flatnonzero(got == got[i])[0] for i in range(k))  # each node's smallest index


def test_union_of_a_long_chain_is_one_component():
    k = 256
    chain = np.stack([np.arange(k - 1), np.arange(1, k)], 1)[::-1]
    assert np.array_equal(_union(k, chain), np.zeros(k, np.int64))


@pytest.mark.parametrize("seed", range(6))
def test_may_link_is_false_only_without_a_component_of_need_points(seed):
    rng = np.random.default_rng(seed)
    pts = rng.normal(0, 2500.0 + 1000.0 * seed, (int(rng.integers(10, 200)), 3))
    need = 8
    d2 = ((pts[:, None] - pts[None]) ** 2).sum(-1)
    i, j = np.nonzero(np.triu(d2 <= 1000.0**2, 1))
    sizes = np.bincount(_union(len(pts), np.stack([i, j], 1)))
    assert _may_link(pts.astype(np.float32), 1000.0, need) == (sizes.max() >= need)


def test_may_link_assumes_a_component_for_many_points():
    far = np.arange(300, dtype=np.float32)[:, None] * np.float32(1e4) * np.ones(3, np.float32)
    assert _may_link(far, 1000.0, 8)  # no pair is linked, but 300 points are left to the device

"""gputrack.ops.rows.scatter_rows on every device against NumPy fancy indexing, and bad input."""

import numpy as np
import pytest

import gputrack
from gputrack.ops.rows import scatter_rows


def _dev(device, a):
    return device.asarray(a) if device.backend != "numpy" else a.copy()


@pytest.mark.parametrize("shape,dtype", [((13, 6), np.float32), ((129, 4, 4), np.float32), ((7,), np.uint8),
                                         ((5, 3), np.int32), ((1, 2), np.float32), ((9, 3), np.uint8)])  # fmt: skip
def test_scatter_rows_matches_numpy(device, shape, dtype):
    rng = np.random.default_rng(shape[0])
    base = (rng.standard_normal(shape) * 50).astype(dtype)
    k = max(shape[0] // 2, 1)
    idx = rng.permutation(shape[0])[:k].astype(np.int32)
    src = (rng.standard_normal((k, *shape[1:])) * 50).astype(dtype)
    want = base.copy()
    want[idx] = src
    dst = _dev(device, base)
    out = scatter_rows(device, dst, idx, src)
    assert out is dst
    np.testing.assert_array_equal(gputrack.to_numpy(out), want)  # bit for bit
    # with a device index and source
    dst = _dev(device, base)
    scatter_rows(device, dst, _dev(device, idx), _dev(device, src))
    np.testing.assert_array_equal(gputrack.to_numpy(dst), want)


def test_scatter_rows_one_row_for_every_index(device):
    base = np.zeros((6, 3, 3), np.float32)
    one = np.arange(9, dtype=np.float32).reshape(1, 3, 3)
    dst = _dev(device, base)
    scatter_rows(device, dst, [4, 0, 2], one)
    want = base.copy()
    want[[4, 0, 2]] = one
    np.testing.assert_array_equal(gputrack.to_numpy(dst), want)


def test_scatter_rows_empty_and_bad_input(device):
    dst = _dev(device, np.zeros((4, 2), np.float32))
    assert scatter_rows(device, dst, np.zeros(0, np.int32), np.zeros((0, 2), np.float32)) is dst
    with pytest.raises(ValueError, match=r"index: expected row indices in \[0, 4\), got 4"):
        scatter_rows(device, dst, [1, 4], np.zeros((2, 2), np.float32))
    with pytest.raises(ValueError, match="index: expected distinct row indices"):
        scatter_rows(device, dst, [1, 1], np.zeros((2, 2), np.float32))
    with pytest.raises(TypeError, match="index: expected integer row indices"):
        scatter_rows(device, dst, [1.0], np.zeros((1, 2), np.float32))
    with pytest.raises(ValueError, match=r"src: expected shape \(1, 2\), got \(1, 3\)"):
        scatter_rows(device, dst, [1], np.zeros((1, 3), np.float32))
    with pytest.raises(ValueError, match=r"src: expected shape \(K=2, 2\), got \(3, 2\)"):
        scatter_rows(device, dst, [1, 2], np.zeros((3, 2), np.float32))
    with pytest.raises(TypeError, match="src: expected dtype float32, got float64"):
        scatter_rows(device, dst, [1], np.zeros((1, 2), np.float64))
    with pytest.raises(ValueError, match="src: expected finite values"):
        scatter_rows(device, dst, [1], np.full((1, 2), np.nan, np.float32))
    with pytest.raises(TypeError, match="dst: expected"):
        scatter_rows(device, [[0.0, 0.0]], [0], np.zeros((1, 2), np.float32))
    np.testing.assert_array_equal(gputrack.to_numpy(dst), 0)  # bad input wrote nothing


def test_scatter_rows_uses_only_the_first_n_rows(device):
    base = np.zeros((8, 2), np.float32)
    src = np.arange(10, dtype=np.float32).reshape(5, 2)
    dst = _dev(device, base)
    scatter_rows(device, dst, np.array([6, 1, 7, 7, 7], np.int32), src, n_rows=2)  # the padding is not read
    want = base.copy()
    want[[6, 1]] = src[:2]
    np.testing.assert_array_equal(gputrack.to_numpy(dst), want)
    scatter_rows(device, dst, _dev(device, np.array([3, 4, 0, 0, 0], np.int32)), _dev(device, src), n_rows=2)
    want[[3, 4]] = src[:2]
    np.testing.assert_array_equal(gputrack.to_numpy(dst), want)
    with pytest.raises(ValueError, match=r"n_rows: expected an integer in \[0, 5\]"):
        scatter_rows(device, dst, np.arange(5, dtype=np.int32), src, n_rows=6)

"""Zero-mean NCC patches (paper 003 eq. 13): every backend against the NumPy reference, the
conventions (exact patch, negative, flat, off the image) and bad input."""

import numpy as np
import pytest
from tolerances import assert_matches

import gputrack
from gputrack.ops.ncc import patch_ncc, patch_ncc_per_point

REF = gputrack.device("numpy")


def ncc_scene(rng, b, k, s, h=40, w=56):
    img = (
        100 + 50 * np.sin(np.arange(w)[None, :] / 2.3) * np.cos(np.arange(h)[:, None] / 3.7) + rng.normal(0, 5, (h, w))
    ).astype(np.float32)
    pts = (
        np.column_stack([rng.uniform(-3, w + 2, b * k), rng.uniform(-3, h + 2, b * k)])
        .reshape(b, k, 2)
        .astype(np.float32)
    )
    tpl = rng.uniform(0, 255, (k, s, s)).astype(np.float32)
    return pts, tpl, img


@pytest.mark.parametrize("b,k,s", [(1, 1, 1), (1, 1, 2), (13, 10, 16), (129, 3, 5), (1000, 10, 16)])
def test_patch_ncc_matches_reference(device, b, k, s):
    rng = np.random.default_rng(b * 100 + k + s)
    pts, tpl, img = ncc_scene(rng, b, k, s)
    # some templates copied from the image at integer points, so that scores near 1 appear
    for kk in range(0, k, 2):
        y0, x0 = 5 + kk, 7 + 2 * kk
        tpl[kk] = img[y0 : y0 + s, x0 : x0 + s]
        pts[0, kk] = (x0 + (s - 1) / 2, y0 + (s - 1) / 2)
    want_pp = patch_ncc_per_point(REF, pts, tpl, img)
    got_pp = patch_ncc_per_point(device, pts, tpl, img)
    assert_matches(device, got_pp, want_pp, scale=10.0)  # sqrt of float32 sums of S^2 terms
    want = patch_ncc(REF, pts, tpl, img)
    assert_matches(device, patch_ncc(device, pts, tpl, img), want, scale=10.0 * k)
    np.testing.assert_allclose(want, want_pp.astype(np.float64).sum(axis=1), rtol=1e-5, atol=1e-5)
    assert (np.abs(want_pp) <= 1).all()
    if s > 1:
        np.testing.assert_allclose(want_pp[0, ::2], 1.0, atol=1e-5)


def test_patch_ncc_conventions(device):
    h, w = 30, 40
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 1, (h, w)).astype(np.float32)
    img[:, 30:] = 0.25  # a flat region
    exact = img[10:15, 4:9]
    tpl = np.stack([exact, 1 - exact, rng.uniform(0, 1, (5, 5)).astype(np.float32)])
    pts = np.array(
        [
            [[6, 12], [6, 12], [2, 2]],  # the exact patch; its negative; inside, touching the border
            [[34, 12], [34, 12], [34, 12]],  # a flat image patch
            [[1.9, 12], [w - 3 + 0.01, 12], [6, h - 2.5]],  # partly off the image
        ],
        np.float32,
    )
    got = gputrack.to_numpy(patch_ncc_per_point(device, pts, tpl, img))
    np.testing.assert_allclose(got[0, :2], [1.0, -1.0], atol=1e-5)
    assert abs(got[0, 2]) > 1e-3
    np.testing.assert_array_equal(got[1:], 0.0)
    total = gputrack.to_numpy(patch_ncc(device, pts, tpl, img))
    np.testing.assert_allclose(total, got.sum(axis=1), rtol=1e-5, atol=1e-5)
    flat_tpl = np.stack([exact, np.full((5, 5), 3.0, np.float32), tpl[2]])
    got = gputrack.to_numpy(patch_ncc_per_point(device, pts[:1], flat_tpl, img))
    np.testing.assert_allclose(got[0, :2], [1.0, 0.0], atol=1e-5)


def test_bad_input(device):
    rng = np.random.default_rng(0)
    pts, tpl, img = ncc_scene(rng, 3, 2, 4)
    with pytest.raises(ValueError, match=r"templates: expected shape \(K=2, S, S\)"):
        patch_ncc(device, pts, tpl[:1], img)
    with pytest.raises(ValueError, match=r"templates: expected shape \(K=2, S=4, S=4\)"):
        patch_ncc(device, pts, tpl[:, :, :3], img)
    with pytest.raises(ValueError, match="points2d: expected finite values"):
        p = pts.copy()
        p[0, 0, 0] = np.nan
        patch_ncc(device, p, tpl, img)
    with pytest.raises(ValueError, match="at least one hypothesis and one point"):
        patch_ncc(device, pts[:0], tpl, img)
    with pytest.raises(TypeError, match="image: expected dtype float32"):
        patch_ncc_per_point(device, pts, tpl, img.astype(np.float64))

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


@pytest.mark.parametrize(
    "b,k,s", [(1, 1, 1), (1, 1, 2), (13, 10, 16), (129, 3, 5), (1000, 10, 16), (37, 4, 4), (21, 3, 8), (17, 3, 12)]
)
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


def test_extreme_finite_values_are_clamped_alike_on_every_backend(device):
    """Pixels and template values beyond +-INTENSITY_MAX (2**48) are clamped to it on every backend
    and in the reference (gputrack/ops/ncc.py): an image of +-3e38 scores as one of +-2**48, not 0
    or NaN; values up to the limit score as the unscaled input (NCC is scale invariant); a template
    scaled past the limit is clamped to one value and scores as flat (0)."""
    from gputrack.abi import INTENSITY_MAX

    lim = np.float32(INTENSITY_MAX)
    rng = np.random.default_rng(21)
    h, w, s = 20, 24, 5
    img = rng.uniform(0, 1, (h, w)).astype(np.float32)
    tpl = rng.uniform(0, 1, (3, s, s)).astype(np.float32)
    tpl[0] = img[3:8, 4:9]
    pts = np.array([[[6, 5], [10, 10], [12, 8]], [[15.5, 9.25], [3, 13], [19, 15]]], np.float32)
    signs = np.where(img > 0.5, 3e38, -3e38).astype(np.float32)
    plain = patch_ncc_per_point(REF, pts, tpl, img)
    cases = {
        "image of +-3e38": (signs, tpl),
        "image x 3e38": ((img * 3e38).astype(np.float32), tpl),
        "image x 2**47": ((img * 2.0**47).astype(np.float32), tpl),
        "template x 1e30": (img, (tpl * 1e30).astype(np.float32)),
        "template x -2**47": (img, (tpl * -(2.0**47)).astype(np.float32)),
        "both x 2**47": ((img * 2.0**47).astype(np.float32), (tpl * 2.0**47).astype(np.float32)),
    }
    for name, (im, tp) in cases.items():
        want = patch_ncc_per_point(REF, pts, tp, im)
        assert np.isfinite(want).all(), name
        # the reference's answer is the clamped input's
        clamped = patch_ncc_per_point(REF, pts, np.clip(tp, -lim, lim), np.clip(im, -lim, lim))
        np.testing.assert_array_equal(want, clamped, err_msg=name)
        assert_matches(device, patch_ncc_per_point(device, pts, tp, im), want, scale=10.0, err_msg=name)
        assert_matches(device, patch_ncc(device, pts, tp, im), want.astype(np.float64).sum(axis=1), scale=30.0,
                       err_msg=name)  # fmt: skip
    # within the limit the score is the unscaled input's; past it the values are clamped
    np.testing.assert_allclose(patch_ncc_per_point(REF, pts, tpl, cases["image x 2**47"][0]), plain, atol=1e-5)
    np.testing.assert_allclose(patch_ncc_per_point(REF, pts, cases["both x 2**47"][1], cases["both x 2**47"][0]),
                               plain, atol=1e-5)  # fmt: skip
    np.testing.assert_allclose(patch_ncc_per_point(REF, pts, cases["template x -2**47"][1], img), -plain, atol=1e-5)
    assert np.abs(patch_ncc_per_point(REF, pts, tpl, signs)).max() > 0.1  # a real score, not 0
    np.testing.assert_array_equal(patch_ncc_per_point(REF, pts, cases["template x 1e30"][1], img), 0.0)


@pytest.mark.parametrize("s", [4, 8, 12, 16])
def test_extreme_values_are_clamped_alike_at_vector_widths(device, s):
    """The clamp to +-INTENSITY_MAX at the patch sizes a backend may vectorise (S a multiple of 4 or
    8, as kernels/gt_ncc.cl does): pixels and template values of +-3e38 or scaled past the limit
    score as the reference's clamped input."""
    rng = np.random.default_rng(s)
    pts, tpl, img = ncc_scene(rng, 19, 3, s)
    tpl[0] = img[4 : 4 + s, 6 : 6 + s]
    pts[0, 0] = (6 + (s - 1) / 2, 4 + (s - 1) / 2)
    signs = np.where(img > 100, 3e38, -3e38).astype(np.float32)
    cases = {
        "image of +-3e38": (signs, tpl),
        "image x 1e36": ((img * 1e36).astype(np.float32), tpl),
        "template x -1e30": (img, (tpl * -1e30).astype(np.float32)),
        "both x 2**40": ((img * 2.0**40).astype(np.float32), (tpl * 2.0**40).astype(np.float32)),
    }
    for name, (im, tp) in cases.items():
        want = patch_ncc_per_point(REF, pts, tp, im)
        assert np.isfinite(want).all(), name
        assert_matches(device, patch_ncc_per_point(device, pts, tp, im), want, scale=10.0, err_msg=name)
        assert_matches(device, patch_ncc(device, pts, tp, im), want.astype(np.float64).sum(axis=1), scale=30.0,
                       err_msg=name)  # fmt: skip
    assert np.abs(patch_ncc_per_point(REF, pts, tpl, signs)).max() > 0.1  # a real score, not 0

"""Feature-point re-localisation on the device (gputrack.ops.face_relocate, paper 003 eq. 14): every
device against the float64 reference, the behaviour of eq. 14 (the appearance, the prediction, a flat
image, a change of light), the patches it returns, bad input."""

import cv2
import numpy as np
import pytest

import gputrack
from gputrack.ops.face_relocate import relocate_points, sample_patches

REF = gputrack.device("numpy")


def scene(seed=1, shape=(120, 160)):
    """A smooth random texture, 10 true points (one 3 px from the left edge: its patches are clipped),
    their 16 x 16 patches and start points 1.5 px (std) off."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, shape).astype(np.float32), (0, 0), 2.0)
    true = rng.uniform(30, min(shape) - 30, (10, 2))
    true[0] = [3.2, 60.4]
    tpl = sample_patches(img, true, 16).astype(np.float32)
    start = (true + rng.normal(0, 1.5, true.shape)).astype(np.float32)
    return img, true, tpl, start


def _on(device, *arrays):
    return [a if device.backend == "numpy" else device.asarray(np.ascontiguousarray(a, np.float32)) for a in arrays]


@pytest.mark.parametrize(("contrast", "shading"), [(0.0, False), (30.0, False), (30.0, True)])
@pytest.mark.parametrize("iterations", [2, 5])
def test_devices_match_the_reference(device, contrast, shading, iterations):
    """Points and patches against the float64 reference: before convergence (2 iterations, where every
    point still moves) and at the tracker's 5, the previous patches of another light than the first
    (with ``shading``, shaded across too)."""
    img, _, tpl, start = scene()
    prev = (1.3 * tpl + 5.0).astype(np.float32)
    if shading:
        prev += np.linspace(-20.0, 20.0, 16, dtype=np.float32)[None, None, :] + np.linspace(0, 8, 16)[None, :, None]
        prev = prev.astype(np.float32)
    want_m, want_p, want_c = relocate_points(REF, img, start, prev, tpl, iterations=iterations, contrast=contrast,
                                             shading=shading)  # fmt: skip
    got = relocate_points(device, *_on(device, img, start, prev, tpl), iterations=iterations, contrast=contrast,
                          shading=shading)  # fmt: skip
    got_m, got_p, got_c = (gputrack.to_numpy(a) for a in got)
    assert got_m.shape == (10, 2) and got_m.dtype == np.float32 and got_p.shape == (10, 16, 16)
    assert got_c.shape == (10,) and got_c.dtype == np.float32
    assert np.abs(want_m - start).max() > 1.0  # the points moved
    np.testing.assert_allclose(got_m, want_m, atol=2e-3)  # float32 sums of 256 terms
    np.testing.assert_allclose(got_p, want_p, atol=2e-3)
    np.testing.assert_allclose(want_p, sample_patches(img, want_m, 16), atol=1e-3)  # the image's patches there
    np.testing.assert_allclose(got_c, want_c, atol=2e-4)
    np.testing.assert_allclose(want_c, _plane_ncc(want_p, tpl), atol=1e-6)


def _plane_ncc(patches, templates):
    """The match written out: each patch's least-squares plane a + b x + c y (np.linalg.lstsq) off, then
    the NCC of the residuals."""
    S = patches.shape[-1]
    y, x = np.mgrid[0:S, 0:S]
    A = np.column_stack([np.ones(S * S), x.ravel(), y.ravel()])
    out = []
    for p, t in zip(np.asarray(patches, np.float64), np.asarray(templates, np.float64)):
        rp = p.ravel() - A @ np.linalg.lstsq(A, p.ravel(), rcond=None)[0]
        rt = t.ravel() - A @ np.linalg.lstsq(A, t.ravel(), rcond=None)[0]
        out.append(rp @ rt / np.sqrt((rp @ rp) * (rt @ rt)))
    return np.array(out)


def test_the_match_is_the_ncc_without_the_light_plane(device):
    """match: 1 for a point back on its own patch under another gain, offset and light from one side;
    low for a point whose template is another place's; 0 for a flat image. eps = 0, the appearance alone."""
    img, true, tpl, start = scene()
    x = np.arange(img.shape[1], dtype=np.float32)[None, :]
    side = (1.6 * img - 40.0 + 2.0 * x).astype(np.float32)  # 32 gray levels across a patch
    prev = sample_patches(side, true, 16).astype(np.float32)
    m, _, c = relocate_points(device, *_on(device, side, start, prev, tpl), eps=0.0, iterations=10, contrast=30.0,
                              shading=True)  # fmt: skip
    c = gputrack.to_numpy(c)
    assert np.abs(gputrack.to_numpy(m)[1:] - true[1:]).max() < 0.01
    assert (c[1:] > 0.999).all()  # the inner points (the edge's patch is clipped)
    other = np.roll(tpl, 1, axis=0)  # each point's template cut at another point
    c = gputrack.to_numpy(relocate_points(device, *_on(device, img, true.astype(np.float32), other, other),
                                          iterations=0)[2])  # fmt: skip
    np.testing.assert_allclose(c, _plane_ncc(sample_patches(img, true, 16), other), atol=2e-4)
    assert c.max() < 0.7 and np.abs(c).mean() < 0.4  # measured: 0.39 and 0.30 (the right template: 1)
    flat = np.full(img.shape, 7.0, np.float32)
    c = gputrack.to_numpy(relocate_points(device, *_on(device, flat, start, tpl, tpl))[2])
    np.testing.assert_array_equal(c, np.zeros(10, np.float32))


def test_out_arrays_are_written(device):
    img, _, tpl, start = scene()
    args = _on(device, img, start, tpl, tpl)
    out = relocate_points(device, *args)
    again = relocate_points(device, *args, out=out)
    assert len(again) == 3 and all(a is b for a, b in zip(again, out))


def test_relocation_follows_the_appearance_and_the_prediction(device):
    img, true, tpl, start = scene()
    args = _on(device, img, start, tpl, tpl)
    m = gputrack.to_numpy(relocate_points(device, *args, eps=0.0, iterations=10)[0])  # appearance only
    np.testing.assert_allclose(m, true, atol=0.05)
    m = gputrack.to_numpy(relocate_points(device, *args, eps=1e9, iterations=10)[0])  # the prior dominates
    np.testing.assert_allclose(m, start, atol=1e-3)
    flat = np.full(img.shape, 7.0, np.float32)  # no gradient: the 2 x 2 systems are eps I, the points stay
    m = gputrack.to_numpy(relocate_points(device, *_on(device, flat, start, tpl, tpl))[0])
    np.testing.assert_allclose(m, start)
    m = gputrack.to_numpy(relocate_points(device, *args, iterations=0)[0])  # no step at all
    np.testing.assert_array_equal(m, start)


def test_relocation_with_contrast_ignores_a_change_of_light(device):
    """The frame's light changed since the templates: gain 1.6 and offset -40. With ``contrast``
    (patches normalised to zero mean and that standard deviation) the points go back onto the true
    ones as on the unchanged image; with the paper's raw intensities they are pulled far off. A ramp
    across the image on top (6 gray levels across a patch: no gain and offset of a patch) leaves
    a small error. eps = 0: the appearance alone."""
    img, true, tpl, start = scene()
    lit = (1.6 * img - 40.0).astype(np.float32)
    ramp = (lit + np.linspace(0.0, 60.0, img.shape[1], dtype=np.float32)[None, :]).astype(np.float32)

    def err(image, contrast):
        m = relocate_points(device, *_on(device, image, start, tpl, tpl), eps=0.0, iterations=10, contrast=contrast)[0]
        return np.abs(gputrack.to_numpy(m)[1:] - true[1:]).max()  # the inner points (the edge's patch is clipped)

    assert err(img, 30.0) < 0.05 and err(lit, 30.0) < 0.05
    assert err(lit, 0.0) > 3.0  # raw intensities: pulled off
    assert err(ramp, 30.0) < 0.2 and err(ramp, 0.0) > 3.0


def test_relocation_with_shading_ignores_light_from_one_side(device):
    """Light from one side since the first frame: the frame (and the previous one, whose patches are cut at
    the true points) brightened across the image, by 6 and by 30 gray levels across a patch's width, on
    top of a gain and offset. With ``shading`` (the comparison with the first frame's templates takes
    each patch's ramp off as well as its mean and contrast) the points stay on the true ones as in the
    unchanged image; normalised without it, the templates pull them off, further the stronger the ramp.
    eps = 0."""
    img, true, tpl, start = scene()
    x = np.arange(img.shape[1], dtype=np.float32)[None, :]

    def err(image, shading):
        prev = sample_patches(image, true, 16).astype(np.float32)
        m = relocate_points(device, *_on(device, image, start, prev, tpl), eps=0.0, iterations=10, contrast=30.0,
                            shading=shading)[0]  # fmt: skip
        return np.abs(gputrack.to_numpy(m)[1:] - true[1:]).max()  # the inner points (the edge's patch is clipped)

    assert err(img, True) < 0.01
    for per_patch, off in ((6.0, 0.015), (30.0, 0.08)):  # measured: 0.0013 / 0.026 and 0.0015 / 0.13 px
        side = (1.6 * img - 40.0 + per_patch / 16.0 * x).astype(np.float32)
        assert err(side, True) < 0.01 and err(side, False) > off


def test_bad_input_is_a_clear_error(device):
    img, _, tpl, start = scene()
    with pytest.raises(ValueError, match=r"^first: expected shape \(K=10, S=16, S=16\), got \(10, 8, 8\)"):
        relocate_points(device, img, start, tpl, tpl[:, :8, :8])
    with pytest.raises(ValueError, match=r"^predicted: expected shape \(K=10, 2\), got \(9, 2\)"):
        relocate_points(device, img, start[:9], tpl, tpl)
    with pytest.raises(ValueError, match="predicted: expected finite values"):
        relocate_points(device, img, np.full((10, 2), np.nan, np.float32), tpl, tpl)
    with pytest.raises(ValueError, match=r"^contrast: expected a number >= 0.0, got -1.0"):
        relocate_points(device, img, start, tpl, tpl, contrast=-1.0)
    with pytest.raises(ValueError, match=r"^shading: expected contrast > 0 .*, got contrast 0"):
        relocate_points(device, img, start, tpl, tpl, shading=True)
    with pytest.raises(TypeError, match=r"^shading: expected a bool, got str"):
        relocate_points(device, img, start, tpl, tpl, contrast=30.0, shading="yes")
    with pytest.raises(ValueError, match=r"^max_step: expected a number > 0, got 0"):
        relocate_points(device, img, start, tpl, tpl, max_step=0)
    with pytest.raises(ValueError, match=r"^iterations: expected an int >= 0, got 2.5"):
        relocate_points(device, img, start, tpl, tpl, iterations=2.5)
    with pytest.raises(ValueError, match=r"^image: expected an image of at least 2 x 2 pixels, got shape \(1, 160\)"):
        relocate_points(device, img[:1], start, tpl, tpl)
    if device.backend != "numpy":
        with pytest.raises(TypeError, match="image: expected dtype float32, got float64"):
            relocate_points(device, img.astype(np.float64), start, tpl, tpl)


def test_patches_are_bilinear_with_the_border_pixel_outside():
    """sample_patches against bilinear interpolation written out, with every sample coordinate
    clipped into the image (the border pixel outside), for points inside, on and far past the edges."""
    rng = np.random.default_rng(2)
    img = rng.uniform(0, 255, (30, 40)).astype(np.float32)
    pts = np.array([[12.3, 7.8], [0.0, 0.0], [-2.6, 14.2], [38.9, 29.4], [1e7, -1e7], [20.5, 15.5]])
    S = 6
    off = np.arange(S) - (S - 1) / 2.0
    want = np.empty((len(pts), S, S))
    for k, (u, v) in enumerate(pts):
        for i in range(S):
            for j in range(S):
                x, y = np.clip(u + off[j], 0, 39), np.clip(v + off[i], 0, 29)
                x0, y0 = min(int(x), 38), min(int(y), 28)
                fx, fy = x - x0, y - y0
                want[k, i, j] = ((1 - fy) * ((1 - fx) * img[y0, x0] + fx * img[y0, x0 + 1])
                                 + fy * ((1 - fx) * img[y0 + 1, x0] + fx * img[y0 + 1, x0 + 1]))  # fmt: skip
    got = sample_patches(img, pts, S)
    assert got.shape == (len(pts), S, S) and got.dtype == np.float64
    np.testing.assert_allclose(got, want, atol=1e-9)
    np.testing.assert_allclose(sample_patches(img.astype(np.uint8), pts, S),
                               sample_patches(img.astype(np.uint8).astype(np.float32), pts, S), atol=1e-3)  # fmt: skip
    with pytest.raises(ValueError, match="finite"):
        sample_patches(img, [[np.nan, 3.0]], S)


def test_patches_from_a_stack_of_images_are_each_images_own():
    """sample_patches with ``index``: from a stack (n, H, W), patch k is image index[k]'s, the same
    values as cut from that image alone (warped or not, at the borders too); a bad index or a single
    image with an index raises."""
    rng = np.random.default_rng(7)
    stack = rng.uniform(0, 255, (3, 30, 40))
    pts = np.array([[12.3, 7.8], [0.0, 0.0], [-2.6, 14.2], [38.9, 29.4], [20.5, 15.5]])
    index = np.array([2, 0, 1, 2, 1])
    warp = np.tile(np.array([[0.9, -0.2], [0.2, 0.9]]), (len(pts), 1, 1))
    for w in (None, warp):
        got = sample_patches(stack, pts, 6, w, index)
        for k, i in enumerate(index):
            np.testing.assert_array_equal(got[k], sample_patches(stack[i], pts[k : k + 1], 6, None if w is None else w[k : k + 1])[0])
    with pytest.raises(ValueError, match=r"index: expected 5 ints in \[0, 3\)"):
        sample_patches(stack, pts, 6, None, np.array([0, 1, 2, 3, 0]))
    with pytest.raises(ValueError, match=r"index: expected 5 ints"):
        sample_patches(stack, pts, 6, None, np.zeros(4, int))
    with pytest.raises(ValueError, match=r"image: expected a stack of images \(n, H, W\)"):
        sample_patches(stack[0], pts, 6, None, index)


def test_warped_patches_sample_the_image_through_the_warp():
    """sample_patches with a warp (K, 2, 2): pixel (i, j) of patch k samples the image at
    points[k] + warp[k] @ (j - c, i - c), bilinear as the plain patches; the identity warp gives them,
    a quarter turn gives them turned and a scale of 2 every second pixel of a patch twice the size."""
    rng = np.random.default_rng(5)
    img = rng.uniform(0, 255, (40, 50))
    pts = np.array([[20.0, 18.0], [25.5, 20.5], [-3.0, 45.0]])
    S = 6
    plain = sample_patches(img, pts, S)
    np.testing.assert_allclose(sample_patches(img, pts, S, np.tile(np.eye(2), (3, 1, 1))), plain, atol=1e-12)
    quarter = np.array([[0.0, -1.0], [1.0, 0.0]])  # offset (x, y) -> (-y, x)
    got = sample_patches(img, pts, S, np.tile(quarter, (3, 1, 1)))
    np.testing.assert_allclose(got, np.rot90(plain, k=1, axes=(1, 2)), atol=1e-9)
    twice = sample_patches(img, pts[:1], S, 2.0 * np.eye(2)[None])
    np.testing.assert_allclose(twice, sample_patches(img, pts[:1], 2 * S - 1)[:, ::2, ::2], atol=1e-9)
    shear = np.array([[[1.0, 0.3], [0.0, 1.0]]])
    off = np.arange(S) - (S - 1) / 2.0
    u, v = pts[1]
    for i in range(S):
        for j in range(S):
            x, y = u + off[j] + 0.3 * off[i], v + off[i]
            x0, y0 = int(np.floor(x)), int(np.floor(y))
            fx, fy = x - x0, y - y0
            want = ((1 - fy) * ((1 - fx) * img[y0, x0] + fx * img[y0, x0 + 1])
                    + fy * ((1 - fx) * img[y0 + 1, x0] + fx * img[y0 + 1, x0 + 1]))  # fmt: skip
            assert abs(sample_patches(img, pts[1:2], S, shear)[0, i, j] - want) < 1e-9
    with pytest.raises(ValueError, match=r"warp: expected \(3, 2, 2\) finite matrices, got shape \(2, 2\)"):
        sample_patches(img, pts, S, np.eye(2))
    with pytest.raises(ValueError, match="warp: expected"):
        sample_patches(img, pts, S, np.full((3, 2, 2), np.nan))

"""gputrack.ops.stereo.stereo_match on every device: against the NumPy reference (exact winners,
subpixel values to float32 tolerance), the masked-matching guarantee, known shifts, bad input."""

import numpy as np
import pytest
from tolerances import assert_matches

import gputrack
from gputrack.ops import stereo_match
from gputrack.ops.stereo import mask_runs

REF = gputrack.device("numpy")


def random_pair(H, W, shift, rng, *, dy=0, noise=3):
    """uint8 random texture; right = left shifted by ``shift`` px (and ``dy`` rows), plus noise."""
    base = rng.integers(0, 256, (H + 8, W + shift + 8)).astype(np.int32)
    left = base[:H, :W] + rng.integers(-noise, noise + 1, (H, W))
    right = base[dy:dy + H, shift:shift + W]  # left(x) = right(x - shift)
    return np.clip(left, 0, 255).astype(np.uint8), right.astype(np.uint8)


def smooth_pair(H, W, shift, rng):
    """float32 band-limited texture (a sum of sinusoids) in [0, 1], the right image sampled at
    x + shift: the true disparity is ``shift`` everywhere, fractions included."""
    k = 40
    fx, fy = rng.uniform(0.05, 0.6, k), rng.uniform(0.05, 0.6, k)
    ph, amp = rng.uniform(0, 2 * np.pi, (2, k)), rng.uniform(0.5, 1, k)
    yy, xx = np.mgrid[:H, :W].astype(np.float64)

    def image(x):
        return sum(amp[i] * np.sin(fx[i] * x + ph[0, i]) * np.sin(fy[i] * yy + ph[1, i]) for i in range(k))

    left, right = image(xx), image(xx + shift)
    lo, hi = min(left.min(), right.min()), max(left.max(), right.max())
    return ((left - lo) / (hi - lo)).astype(np.float32), ((right - lo) / (hi - lo)).astype(np.float32)


def blob_mask(H, W, rng, n=3):
    yy, xx = np.mgrid[:H, :W]
    mask = np.zeros((H, W), bool)
    for _ in range(n):
        cx, cy, ax, ay = rng.uniform(0, W), rng.uniform(0, H), rng.uniform(3, W / 4), rng.uniform(3, H / 3)
        mask |= ((xx - cx) / ax) ** 2 + ((yy - cy) / ay) ** 2 < 1
    return mask


def assert_same_disparity(device, got, want):
    got = gputrack.to_numpy(got)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))  # the same pixels have a value
    assert_matches(device, got, want)  # NaN == NaN; values to float32 tolerance


@pytest.mark.parametrize(
    "H,W,D,block,dtype,shift",
    [(13, 29, 5, 3, np.uint8, 2), (61, 127, 16, 9, np.uint8, 7), (40, 90, 24, 5, np.float32, 11)],
)
def test_matches_reference(device, H, W, D, block, dtype, shift):
    rng = np.random.default_rng(H)
    left, right = random_pair(H, W, shift, rng)
    if dtype == np.float32:
        left, right = left.astype(np.float32) / 255, right.astype(np.float32) / 255
    for mask in (None, rng.random((H, W)) < 0.3, blob_mask(H, W, rng)):
        want = stereo_match(REF, left, right, mask=mask, max_disparity=D, block=block)
        got = stereo_match(device, left, right, mask=mask, max_disparity=D, block=block)
        assert_same_disparity(device, got, want)
    # not vacuous: the reference finds the shift at most pixels that can have one (3 x 3 windows
    # of this texture's saturated gradients are too ambiguous for that: compared, not judged)
    r = block // 2
    inner = stereo_match(REF, left, right, max_disparity=D, block=block)[r:H - r, r + D - 1:W - r]
    if block >= 5:
        assert np.isfinite(inner).mean() > 0.8
        assert np.abs(np.nanmedian(inner) - shift) < 0.2


@pytest.mark.parametrize("per_pixel", [False, True])
def test_both_cost_layouts_match_reference(device, per_pixel, monkeypatch):
    """Both layouts of the costs on whatever device runs them: per tile of runs carrying the column
    sums (CPU devices and archs, lavapipe) and per pixel and disparity group summing each window
    (GPUs: OpenCL in work-groups of GPU_GROUP, taichi:cuda, Vulkan on a GPU), uint8 and float32
    lanes, masked and not."""
    if device.backend == "numpy":
        pytest.skip("the reference has one layout")
    monkeypatch.setattr(gputrack.ops.backend_module(device, "stereo"), "per_pixel", lambda dev: per_pixel)
    rng = np.random.default_rng(21)
    for H, W, D, block, dtype, shift in ((61, 127, 16, 9, np.uint8, 7), (40, 90, 24, 5, np.float32, 11),
                                         (33, 150, 40, 7, np.uint8, 19)):  # fmt: skip
        left, right = random_pair(H, W, shift, rng)
        if dtype == np.float32:
            left, right = left.astype(np.float32) / 255, right.astype(np.float32) / 255
        for mask in (None, blob_mask(H, W, rng)):
            want = stereo_match(REF, left, right, mask=mask, max_disparity=D, block=block)
            got = stereo_match(device, left, right, mask=mask, max_disparity=D, block=block)
            assert_same_disparity(device, got, want)
            assert np.isfinite(want).sum() > 200  # not vacuous: many winners compared


def test_masked_result_is_the_unmasked_result_inside_the_mask(device):
    """The guarantee: at a mask pixel, exactly the unmasked result (the left-right check reads
    outside the mask as it must); NaN everywhere else. Bool, uint8 and device masks alike."""
    rng = np.random.default_rng(5)
    H, W = 37, 101
    left, right = random_pair(H, W, 9, rng)
    right[:, 50:65] = rng.integers(0, 256, (H, 15))  # an occluded band: its pixels fail the checks
    left[:, 80:] = right[:, 80:] = 128  # a flat band: ties, rejected
    full = gputrack.to_numpy(stereo_match(device, left, right, max_disparity=20, block=7))
    assert 0.05 < np.isnan(full[3:-3, 22:-3]).mean() < 0.9  # both outcomes occur inside the valid area
    mask = blob_mask(H, W, rng, n=4)
    mask[5, :] = True  # a whole row, and single pixels
    mask[rng.integers(0, H, 30), rng.integers(0, W, 30)] = True
    want = np.where(mask, full, np.nan)
    dev_mask = mask.astype(np.uint8) if device.backend == "numpy" else device.asarray(mask.astype(np.uint8))
    for m in (mask, mask.astype(np.uint8), dev_mask):
        got = gputrack.to_numpy(stereo_match(device, left, right, mask=m, max_disparity=20, block=7))
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        np.testing.assert_array_equal(got[mask], want[mask])  # bit for bit: the same costs and checks


def test_empty_mask_and_out(device):
    rng = np.random.default_rng(2)
    left, right = random_pair(21, 50, 4, rng)
    out = device.empty((21, 50), np.float32) if device.backend != "numpy" else np.zeros((21, 50), np.float32)
    got = stereo_match(device, left, right, mask=np.zeros((21, 50), bool), max_disparity=8, block=5, out=out)
    assert got is out
    assert np.isnan(gputrack.to_numpy(got)).all()
    got = stereo_match(device, left, right, max_disparity=8, block=5, out=out)  # the same buffer, reused
    assert got is out
    assert_same_disparity(device, got, stereo_match(REF, left, right, max_disparity=8, block=5))
    # no pixel can have a value: every window or candidate leaves the image
    assert np.isnan(gputrack.to_numpy(stereo_match(device, left, right, max_disparity=50, block=5))).all()


def test_known_fractional_shift_is_recovered(device):
    """A band-limited pair shifted by integer + fraction: the parabola vertex is within 0.25 px
    (median; SAD's parabola leans towards the integers, so not every pixel is)."""
    rng = np.random.default_rng(3)
    for shift in (6.4, 9.75):
        left, right = smooth_pair(40, 90, shift, rng)
        d = gputrack.to_numpy(stereo_match(device, left, right, max_disparity=16, block=9))
        err = np.abs(d - shift)[np.isfinite(d)]
        assert np.isfinite(d).mean() > 0.55  # the whole valid area (32 x 67 of 40 x 90 pixels)
        assert np.median(err) < 0.25 and np.mean(err < 0.25) > 0.85
        assert err.max() < 0.5  # the right integer everywhere
        assert abs(err.mean()) < 0.2


def test_unrectified_pair_is_mostly_nan(device):
    """Rows shifted by 2 between the images (a rectification error): the checks reject most
    pixels (about 12 % keep a value, against about 63 % of the same pair rectified)."""
    rng = np.random.default_rng(4)
    left, right = random_pair(48, 96, 6, rng, dy=2)
    d = gputrack.to_numpy(stereo_match(device, left, right, max_disparity=16, block=9))
    assert np.isfinite(d).mean() < 0.25
    left, right = random_pair(48, 96, 6, rng)
    d = gputrack.to_numpy(stereo_match(device, left, right, max_disparity=16, block=9))
    assert np.isfinite(d).mean() > 0.55


def test_bad_input(device):
    rng = np.random.default_rng(1)
    left, right = random_pair(20, 40, 3, rng)
    f = left.astype(np.float32) / 255

    def call(a=left, b=right, **kw):
        kw.setdefault("max_disparity", 8)
        kw.setdefault("block", 5)
        return stereo_match(device, a, b, **kw)

    with pytest.raises(ValueError, match=r"right: expected shape \(H=20, W=40\), got \(20, 41\)"):
        call(b=np.zeros((20, 41), np.uint8))
    with pytest.raises(TypeError, match="right: expected the dtype of left \\(uint8\\), got float32"):
        call(b=f)
    with pytest.raises(TypeError, match="left: expected a uint8 or float32 gray image, got dtype float64"):
        call(a=left.astype(np.float64))
    with pytest.raises(ValueError, match=r"left: expected a gray image of shape \(H, W\), got shape \(20, 40, 3\)"):
        call(a=np.zeros((20, 40, 3), np.uint8))
    bad = f.copy()
    bad[3, 4] = np.nan
    with pytest.raises(ValueError, match=r"left: expected finite float32 intensities in \[0, 1\], got nan at index \(3, 4\)"):
        call(a=bad, b=f)
    with pytest.raises(ValueError, match=r"right: expected finite float32 intensities in \[0, 1\], got 2.0"):
        call(a=f, b=f * 0 + 2)
    with pytest.raises(ValueError, match=r"block: expected an odd integer in \[3, 20\], got 4"):
        call(block=4)
    with pytest.raises(ValueError, match=r"block: expected an odd integer in \[3, 20\], got 21"):
        call(block=21)
    with pytest.raises(TypeError, match="block: expected an integer, got float 5.0"):
        call(block=5.0)
    with pytest.raises(ValueError, match=r"max_disparity: expected an integer in \[1, 40\], got 0"):
        call(max_disparity=0)
    with pytest.raises(ValueError, match=r"max_disparity: expected an integer in \[1, 40\], got 41"):
        call(max_disparity=41)
    with pytest.raises(ValueError, match=r"uniqueness: expected an integer in \[0, 100\], got -1"):
        call(uniqueness=-1)
    with pytest.raises(ValueError, match=r"mask: expected shape \(H=20, W=40\), got \(40, 20\)"):
        call(mask=np.ones((40, 20), bool))
    with pytest.raises(TypeError, match="mask: expected a bool or uint8 array, got dtype float32"):
        call(mask=np.ones((20, 40), np.float32))
    with pytest.raises(ValueError, match="left: expected an image of at least 3 x 3 pixels, got 2 x 40"):
        call(a=left[:2], b=right[:2])
    with pytest.raises(ValueError, match=r"out: expected a float32 array of shape \(20, 40\)"):
        call(out=device.empty((20, 41), np.float32))
    with pytest.raises(TypeError, match="expected a gputrack.Device"):
        stereo_match("numpy", left, right)


def test_mask_runs_cover_exactly_the_pixels_that_can_have_a_value():
    rng = np.random.default_rng(0)
    H, W, D, block = 30, 70, 12, 5
    mask = rng.random((H, W)) < 0.4
    runs = mask_runs(mask, H, W, D, block)
    covered = np.zeros((H, W), bool)
    for y, x0, x1, off, roff in runs:
        assert not covered[y, x0:x1 + 1].any()
        covered[y, x0:x1 + 1] = True
        assert mask[y, x0] and mask[y, x1]
    r = block // 2
    can = np.zeros((H, W), bool)
    can[r:H - r, r + D - 1:W - r] = True
    np.testing.assert_array_equal(covered, mask & can)
    lengths = runs[:, 2] - runs[:, 1] + 1
    np.testing.assert_array_equal(runs[:, 3], np.cumsum(lengths) - lengths)
    np.testing.assert_array_equal(runs[:, 4], np.cumsum(lengths + D - 1) - (lengths + D - 1))
    assert mask_runs(np.zeros((H, W), bool), H, W, D, block).shape == (0, 5)
    assert len(mask_runs(None, H, W, D, block)) == H - 2 * r


def test_selftest(device):
    from gputrack.selftest import check_stereo

    check_stereo(device)


def test_scores_count_bad_pixels_and_density():
    from gputrack.benchmarks.stereo import scores

    truth = np.array([[10.0, 20.0, np.inf, 30.0], [5.0, 6.0, 7.0, 8.0]], np.float32)
    disp = np.array([[10.5, 21.5, 3.0, np.nan], [8.0, 6.0, np.nan, 8.9]], np.float32)
    s = scores(disp, truth)  # 5 of the 7 known pixels have a value; errors 0.5, 1.5, 3, 0, 0.9
    assert s["density"] == pytest.approx(5 / 7)
    assert s["bad1"] == pytest.approx(2 / 5) and s["bad2"] == pytest.approx(1 / 5)


def test_bench_script_smoke(tmp_path):
    """perf/bench_stereo.py as users run it, on numpy at a small size (no accuracy table: the
    full motorcycle pair takes seconds): the harness's JSON with both cases and the peer."""
    pytest.importorskip("skimage")
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    # the script imports this checkout's gputrack (not whichever one the environment installed)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    out = tmp_path / "stereo.json"
    cmd = [sys.executable, str(root / "perf" / "bench_stereo.py"), "--device", "numpy", "--size", "160x48",
           "--min-time", "0.001", "--no-accuracy", "--json", str(out)]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path, check=False, env=env)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(out.read_text())
    assert doc["schema"] == "gputrack-bench/1" and doc["bench"] == "stereo" and "commit" in doc
    (run,) = doc["runs"]
    assert run["device"]["spec"] == "numpy"
    cases = [r["case"] for r in run["results"]]
    assert cases == ["stereo_match 160x48 mask 15.0 %", "stereo_match 160x48 full"]
    for r in run["results"]:
        assert r["params"]["max_disparity"] == 64 and "cv2.StereoBM full" in r["peers"]


def test_run_tiles_partition_the_runs():
    from gputrack.ops.stereo import run_tiles

    rng = np.random.default_rng(6)
    H, W, D, block = 70, 150, 10, 5
    mask = blob_mask(H, W, rng, n=5) | (rng.random((H, W)) < 0.02)
    runs = mask_runs(mask, H, W, D, block)
    tiles, order, run_tile = run_tiles(runs, D, block, rows=16)
    np.testing.assert_array_equal(np.sort(order), np.arange(len(runs)))  # every run in one tile
    r = block // 2
    for t, (y0, y1, xa, xb, i0, i1, off, w) in enumerate(tiles):
        assert (run_tile[order[i0:i1]] == t).all()
        mine = runs[order[i0:i1]]
        assert (np.diff(mine[:, 0]) >= 0).all() and y0 == mine[0, 0] and y1 == mine[-1, 0]  # by row
        assert len(set((mine[:, 0] - r) // 16)) == 1  # one band
        assert xa == mine[:, 1].min() and xb == mine[:, 2].max() and w == xb - xa + D + 2 * r
    np.testing.assert_array_equal(tiles[:, 6], np.cumsum(tiles[:, 7]) - tiles[:, 7])
    # tiles of one band do not touch: their ranges [xa - D + 1 - r, xb + r] are disjoint
    band = (tiles[:, 0] - r) // 16
    for b in np.unique(band):
        t = tiles[band == b]
        lo, hi = np.sort(t[:, 2] - D + 1 - r), np.sort(t[:, 3] + r)
        assert (lo[1:] > hi[:-1]).all()
    assert len(tiles) > len(np.unique(band))  # the blobs give several tiles in some band

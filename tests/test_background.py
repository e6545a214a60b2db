"""gputrack.ops.background (papers 001 and 002: per-pixel median, running average, foreground mask)
on every device against the NumPy reference, the reference against numpy.nanmedian and hand
values, bad input, and real Kinect depth frames."""

import warnings

import numpy as np
import pytest
from tolerances import assert_matches

import gputrack
from gputrack.ops.background import MAX_FRAMES, background_median, foreground_mask, update_background
from gputrack.shared_data import shared_data

REF = gputrack.device("numpy")
KINECT = shared_data("pcl_kinect_frames")


def _frames(rng, F, H, W, dtype, missing):
    """Frames with dropouts: NaN (float32) or the missing value, some pixels never valid."""
    if dtype == np.float32:
        x = rng.uniform(0, 50, (F, H, W)).astype(np.float32)
        x[rng.random(x.shape) < 0.2] = np.nan
        x[:, 0, 0] = np.nan  # a pixel with no valid sample
    else:
        hi = 6 if dtype == np.uint8 else 3000
        x = rng.integers(0, hi, (F, H, W)).astype(dtype)  # repeated values: ties in the sort
    if missing is not None:
        x[rng.random(x.shape) < 0.2] = missing
        x[:, -1, -1] = missing  # all missing
    return x


def _nanmedian(x, missing):
    x = x.astype(np.float32)
    if missing is not None:
        x[x == missing] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices
        return np.nanmedian(x, axis=0)


CASES = [
    (1, 1, 1, np.float32, None),
    (4, 13, 29, np.float32, None),
    (5, 13, 29, np.uint16, 0),
    (6, 127, 129, np.uint8, None),
    (7, 127, 129, np.float32, 0.0),
    (30, 12, 30, np.uint16, 0),  # even width: uploaded as uint32 words (odd: as bytes)
    (MAX_FRAMES, 3, 5, np.float32, None),
]


@pytest.mark.parametrize("F,H,W,dtype,missing", CASES)
def test_median_reference_is_nanmedian(F, H, W, dtype, missing):
    x = _frames(np.random.default_rng(F * H), F, H, W, dtype, missing)
    got = background_median(REF, x, missing=missing)
    assert got.dtype == np.float32 and got.shape == (H, W)
    np.testing.assert_array_equal(got, _nanmedian(x, missing))  # NaN where no valid sample
    if dtype == np.float32:
        assert np.isnan(got[0, 0])
    if missing is not None:
        assert np.isnan(got[-1, -1])


def test_median_even_and_odd_counts_by_hand():
    x = np.array([[[1.0, 5.0, np.nan]], [[4.0, 0.0, np.nan]], [[2.0, 7.0, 3.0]], [[np.nan, 2.0, 0.0]]], np.float32)
    np.testing.assert_array_equal(background_median(REF, x)[0], [2.0, 3.5, 1.5])  # odd; (2 + 5) / 2; (0 + 3) / 2
    np.testing.assert_array_equal(background_median(REF, x, missing=0)[0], [2.0, 5.0, 3.0])


@pytest.mark.parametrize("F,H,W,dtype,missing", CASES)
def test_median_matches_reference(device, F, H, W, dtype, missing):
    x = _frames(np.random.default_rng(F * H), F, H, W, dtype, missing)
    want = background_median(REF, x, missing=missing)
    got = gputrack.to_numpy(background_median(device, x, missing=missing))
    np.testing.assert_array_equal(got, want)  # the same float32 operations: bit for bit


def test_median_device_inputs_and_out(device):
    x = _frames(np.random.default_rng(3), 8, 13, 29, np.float32, None)
    out = device.empty((13, 29), np.float32) if device.backend != "numpy" else np.empty((13, 29), np.float32)
    got = background_median(device, device.asarray(x) if device.backend != "numpy" else x, out=out)
    assert got is out
    np.testing.assert_array_equal(gputrack.to_numpy(got), background_median(REF, x))
    u8 = _frames(np.random.default_rng(4), 3, 13, 29, np.uint8, 0)
    got = background_median(device, device.asarray(u8) if device.backend != "numpy" else u8, missing=0)
    np.testing.assert_array_equal(gputrack.to_numpy(got), background_median(REF, u8, missing=0))


def _bg(rng, H, W):
    bg = rng.uniform(0, 50, (H, W)).astype(np.float32)
    bg[rng.random((H, W)) < 0.1] = np.nan  # no background yet
    return bg


@pytest.mark.parametrize("H,W,dtype", [(1, 1, np.float32), (13, 29, np.uint16), (12, 30, np.uint16),
                                       (127, 129, np.uint8), (127, 129, np.float32)])  # fmt: skip
def test_update_matches_reference(device, H, W, dtype):
    rng = np.random.default_rng(H + W)
    bg = _bg(rng, H, W)
    frame = _frames(rng, 1, H, W, dtype, 0 if dtype != np.float32 else None)[0]
    mask = (rng.random((H, W)) < 0.3).astype(np.uint8)
    for kw in ({"rate": 0.05}, {"rate": 0.3, "mask": mask}, {"rate": 1.0, "mask": mask, "missing": 0}):
        want = update_background(REF, bg, frame, **kw)
        got = update_background(device, bg, frame, **kw)
        assert_matches(device, got, want)
        np.testing.assert_array_equal(np.isnan(gputrack.to_numpy(got)), np.isnan(want))


def test_update_semantics_and_in_place(device):
    bg = np.array([[10.0, 10.0, np.nan, 10.0, np.inf]], np.float32)
    frame = np.array([[20.0, 20.0, 20.0, np.nan, 20.0]], np.float32)
    mask = np.array([[0, 1, 0, 0, 0]], bool)
    want = np.array([[12.5, 10.0, 20.0, 10.0, 20.0]], np.float32)  # eq.: 0.75 * 10 + 0.25 * 20; masked; none yet
    dbg = device.asarray(bg) if device.backend != "numpy" else bg.copy()
    got = update_background(device, dbg, frame, rate=0.25, mask=mask, out=dbg)
    assert got is dbg
    np.testing.assert_allclose(gputrack.to_numpy(dbg), want, rtol=1e-6)
    same = update_background(device, bg, frame, rate=0.0)  # rate 0: only pixels without a background change
    np.testing.assert_array_equal(gputrack.to_numpy(same), [[10.0, 10.0, 20.0, 10.0, 20.0]])


def test_foreground_mask_by_hand(device):
    bg = np.array([[1000.0, 1000.0, 1000.0, np.nan, 0.0, 1000.0, np.inf]], np.float32)
    frame = np.array([[900, 1100, 950, 500, 500, 0, 800]], np.uint16)
    both = gputrack.to_numpy(foreground_mask(device, frame, bg, 100.0, missing=0))
    np.testing.assert_array_equal(both, [[1, 1, 0, 0, 0, 0, 1]])  # >= threshold; NaN, missing: never
    nearer = gputrack.to_numpy(foreground_mask(device, frame, bg, 100.0, missing=0, nearer=True))
    np.testing.assert_array_equal(nearer, [[1, 0, 0, 0, 0, 0, 1]])  # only in front of the background
    assert both.dtype == np.uint8
    every = gputrack.to_numpy(foreground_mask(device, frame, bg, 0.0))  # no missing value: 0 is a reading
    np.testing.assert_array_equal(every, [[1, 1, 1, 0, 1, 1, 1]])


@pytest.mark.parametrize("H,W,dtype", [(1, 1, np.uint16), (13, 29, np.float32), (127, 129, np.uint16),
                                       (128, 130, np.uint16), (127, 129, np.uint8)])  # fmt: skip
def test_foreground_mask_matches_reference(device, H, W, dtype):
    rng = np.random.default_rng(H * W)
    bg = _bg(rng, H, W) * (100 if dtype == np.uint16 else 1)
    frame = _frames(rng, 1, H, W, dtype, 0 if dtype != np.float32 else None)[0]
    for nearer in (False, True):
        for missing in (None, 0):
            want = foreground_mask(REF, frame, bg, 7.0, missing=missing, nearer=nearer)
            got = foreground_mask(device, frame, bg, 7.0, missing=missing, nearer=nearer)
            np.testing.assert_array_equal(gputrack.to_numpy(got), want)
    out = device.empty((H, W), np.uint8) if device.backend != "numpy" else np.empty((H, W), np.uint8)
    assert foreground_mask(device, frame, bg, 7.0, out=out) is out


def test_bad_input(device):
    f3 = np.zeros((3, 4, 5), np.float32)
    bg = np.zeros((4, 5), np.float32)
    with pytest.raises(ValueError, match=r"frames: expected shape \(F, H, W\), got \(4, 5\)"):
        background_median(device, bg)
    with pytest.raises(ValueError, match=r"frames: expected at least one frame \(F >= 1\), got shape \(0, 4, 5\)"):
        background_median(device, np.zeros((0, 4, 5), np.uint16))
    with pytest.raises(ValueError, match=f"frames: expected at most {MAX_FRAMES} frames, got F = {MAX_FRAMES + 1}"):
        background_median(device, np.zeros((MAX_FRAMES + 1, 2, 2), np.uint8))
    with pytest.raises(TypeError, match="frames: expected dtype uint8, uint16 or float32, got float64"):
        background_median(device, f3.astype(np.float64))
    with pytest.raises(TypeError, match="frames: expected dtype uint8, uint16 or float32, got int32"):
        background_median(device, f3.astype(np.int32))
    with pytest.raises(ValueError, match="frames: expected finite values or NaN"):
        background_median(device, np.full((2, 2, 2), np.inf, np.float32))
    with pytest.raises(ValueError, match="missing: expected a finite number, got nan"):
        background_median(device, f3, missing=np.nan)
    with pytest.raises(ValueError, match=r"frame: expected shape \(H=4, W=5\), got \(4, 6\)"):
        foreground_mask(device, np.zeros((4, 6), np.uint16), bg, 100.0)
    with pytest.raises(ValueError, match=r"frame: expected shape \(H=4, W=5\), got \(3, 4, 5\)"):
        foreground_mask(device, f3, bg, 100.0)
    with pytest.raises(TypeError, match="background: expected dtype float32, got uint16"):
        foreground_mask(device, bg, bg.astype(np.uint16), 100.0)
    with pytest.raises(ValueError, match="background: expected finite values, NaN or \\+inf, got -inf"):
        foreground_mask(device, bg, np.full((4, 5), -np.inf, np.float32), 100.0)
    with pytest.raises(ValueError, match=r"threshold: expected a number >= 0.0, got -1.0"):
        foreground_mask(device, bg, bg, -1.0)
    with pytest.raises(TypeError, match="threshold: expected a real number, got str"):
        foreground_mask(device, bg, bg, "100")
    with pytest.raises(ValueError, match=r"out: expected a uint8 array of shape \(4, 5\)"):
        foreground_mask(device, bg, bg, 1.0, out=device.empty((4, 5), np.float32))
    for rate in (-0.1, 1.5):
        with pytest.raises(ValueError, match=rf"rate: expected a number in \[0.0, 1.0\], got {rate}"):
            update_background(device, bg, bg, rate=rate)
    with pytest.raises(ValueError, match="rate: expected a finite number, got nan"):
        update_background(device, bg, bg, rate=float("nan"))
    with pytest.raises(TypeError, match="mask: expected dtype uint8, got float32"):
        update_background(device, bg, bg, rate=0.5, mask=bg)
    with pytest.raises(ValueError, match=r"mask: expected shape \(H=4, W=5\), got \(5, 4\)"):
        update_background(device, bg, bg, rate=0.5, mask=np.zeros((5, 4), np.uint8))
    with pytest.raises(TypeError, match="expected a gputrack.Device"):
        foreground_mask("numpy", bg, bg, 1.0)


def _kinect_depth():
    import cv2

    files = sorted(KINECT.glob("*_depth.tiff"))
    return np.stack([cv2.imread(str(f), cv2.IMREAD_UNCHANGED) for f in files])


@pytest.mark.skipif(not KINECT.is_dir(), reason=f"real Kinect frames not found at {KINECT}")
def test_kinect_depth_background_and_mask(device):
    depth = _kinect_depth()  # (3, 480, 640) uint16 mm, 0 = no reading
    assert depth.dtype == np.uint16 and depth.shape[1:] == (480, 640)
    want = background_median(REF, depth, missing=0)
    np.testing.assert_array_equal(want, _nanmedian(depth, 0))
    got = background_median(device, depth, missing=0)
    np.testing.assert_array_equal(gputrack.to_numpy(got), want)
    none = (depth == 0).all(axis=0)
    assert none.any() and np.isnan(want[none]).all() and not np.isnan(want[~none]).any()
    # a person 300 mm in front of the background where frame 0 reads: exactly there, nearer only
    frame = depth[0].copy()
    frame[200:300, 250:350] = np.where(frame[200:300, 250:350] > 0, frame[200:300, 250:350] - 300, 0)
    mask_ref = foreground_mask(REF, frame, want, 100.0, missing=0, nearer=True)
    mask = gputrack.to_numpy(foreground_mask(device, frame, want, 100.0, missing=0, nearer=True))
    np.testing.assert_array_equal(mask, mask_ref)
    inside = np.zeros(frame.shape, bool)
    inside[200:300, 250:350] = True
    assert mask[inside & (frame > 0) & ~np.isnan(want) & (want - frame >= 100)].all()
    assert mask[inside].mean() > 0.8 and mask[~inside].mean() < 0.01  # the frames differ little elsewhere


def test_selftest(device):
    from gputrack.selftest import CHECKS, check_background

    assert ("background", check_background) in CHECKS
    check_background(device)

"""gputrack.ops.depth_points (paper 002 sec. 4.1: foreground points of a depth frame, randomly
downsampled) on every device against the NumPy reference, the reference against an independent
back-projection (gputrack.models.DepthCamera) and the sampling's promises, floor_background,
bad input, and real Kinect frames against the PCL point cloud made from them."""

from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
from tolerances import assert_matches

import gputrack
from gputrack.models.camera import Camera, DepthCamera
from gputrack.ops.background import foreground_mask
from gputrack.ops.depth_points import depth_points, floor_background
from gputrack.shared_data import shared_data

REF = gputrack.device("numpy")
CAM = Camera(525.0, 525.0, 320.0, 240.0)
KINECT = shared_data("pcl_kinect_frames")


def _scene(rng, H, W, dtype=np.uint16):
    """A background 1-6 m with holes, a frame with people 0.5 m in front of it, dropouts (0 / NaN)
    and readings beyond 5 m."""
    bg = rng.uniform(1000, 6500, (H, W)).astype(np.float32)
    bg[rng.random((H, W)) < 0.05] = np.nan
    z = np.nan_to_num(bg, nan=3000.0)
    z = np.where(rng.random((H, W)) < 0.4, z - 500, z + rng.normal(0, 20, (H, W)))
    z[rng.random((H, W)) < 0.05] = 0
    if dtype == np.float32:
        z = z.astype(np.float32)
        z[rng.random((H, W)) < 0.05] = np.nan
    return z.astype(dtype), bg


def _pixels(points, cam=CAM):
    """(row, column) of each finite point, projected back (the points are pixel centres)."""
    p = points[~np.isnan(points[:, 2])].astype(np.float64)
    u = np.rint(p[:, 0] * cam.fx / p[:, 2] + cam.cx).astype(int)
    v = np.rint(p[:, 1] * cam.fy / p[:, 2] + cam.cy).astype(int)
    return v, u


def _foreground(depth, bg, threshold=100.0, max_range=5000.0, nearer=False):
    """The foreground pixels by the definition: the mask op with missing 0, within range."""
    z = depth.astype(np.float32)
    m = foreground_mask(REF, depth, bg, threshold, missing=0, nearer=nearer).astype(bool)
    with np.errstate(invalid="ignore"):
        return m & (z > 0) & (z <= max_range)


@pytest.mark.parametrize("H,W,n", [(1, 1, 4), (13, 29, 16), (12, 30, 16), (127, 129, 1024), (127, 129, 300),
                                   (127, 129, 50), (127, 129, 7)])  # fmt: skip
@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_matches_reference(device, H, W, n, dtype):
    depth, bg = _scene(np.random.default_rng(H * W + n), H, W, dtype)
    for seed, counter, nearer in ((0, 0, False), (2**32 - 1, 12345, True)):
        want, count = depth_points(REF, depth, bg, CAM, n_points=n, seed=seed, counter=counter, nearer=nearer)
        got, got_count = depth_points(device, depth, bg, CAM, n_points=n, seed=seed, counter=counter, nearer=nearer)
        assert got_count == count == int(_foreground(depth, bg, nearer=nearer).sum())
        np.testing.assert_array_equal(np.isnan(gputrack.to_numpy(got)), np.isnan(want))
        assert_matches(device, got, want)  # the same points in the same order on every backend


def test_reference_is_a_uniform_subset_of_the_back_projected_foreground():
    depth, bg = _scene(np.random.default_rng(1), 127, 129)
    fg = _foreground(depth, bg)
    cam = DepthCamera(CAM.fx, CAM.fy, CAM.cx, CAM.cy, depth_scale=1.0, min_depth=0.0, max_depth=1e9)
    every = cam.points(np.where(fg, depth, 0))  # (N, 3) float64, row-major
    pts, count = depth_points(REF, depth, bg, cam, n_points=1024, seed=7)
    assert pts.shape == (1024, 3) and pts.dtype == np.float32 and count == len(every) > 4000
    v, u = _pixels(pts)
    assert fg[v, u].all() and len(set(zip(v, u))) == 1024  # foreground pixels, without replacement
    np.testing.assert_allclose(pts, _at(every, fg, v, u), rtol=1e-6, atol=1e-3)
    # uniform: over 200 counters each foreground pixel is drawn about 200 * 1024 / N times
    hits = np.zeros(fg.shape)
    for counter in range(200):
        hv, hu = _pixels(depth_points(REF, depth, bg, CAM, n_points=1024, counter=counter)[0])
        hits[hv, hu] += 1
    expect = 200 * 1024 / count
    assert abs(hits[fg].mean() - expect) < 1e-9 and hits[~fg].sum() == 0
    assert hits[fg].std() < 1.3 * np.sqrt(expect * (1 - 1024 / count))  # binomial spread
    left = fg[:, :64].sum() / count
    assert abs(hits[:, :64].sum() / (200 * 1024) - left) < 0.01


def _at(every, fg, v, u):
    """The rows of ``every`` (the foreground's points in row-major order) at pixels (v, u)."""
    order = np.cumsum(fg.ravel()) - 1
    return every[order[v * fg.shape[1] + u]]


def test_prefix_order_and_counters(device):
    depth, bg = _scene(np.random.default_rng(2), 13, 29)
    a, count = depth_points(device, depth, bg, CAM, n_points=64, seed=3, counter=1)
    b, _ = depth_points(device, depth, bg, CAM, n_points=64, seed=3, counter=1)
    c, _ = depth_points(device, depth, bg, CAM, n_points=64, seed=3, counter=2)
    d, _ = depth_points(device, depth, bg, CAM, n_points=64, seed=4, counter=1)
    few, _ = depth_points(device, depth, bg, CAM, n_points=16, seed=3, counter=1)
    a, b, c, d, few = (gputrack.to_numpy(x) for x in (a, b, c, d, few))
    assert count > 64
    np.testing.assert_array_equal(a, b)  # same (seed, counter): same points
    assert set(zip(*_pixels(a))) != set(zip(*_pixels(c)))  # another counter: another subset
    assert set(zip(*_pixels(a))) != set(zip(*_pixels(d)))  # another seed too
    np.testing.assert_array_equal(few, a[:16])  # ascending key: the first m rows are the m-subset


def test_fewer_points_than_asked(device):
    depth, bg = _scene(np.random.default_rng(3), 13, 29)
    fg = _foreground(depth, bg)
    pts, count = depth_points(device, depth, bg, CAM, n_points=1024)
    pts = gputrack.to_numpy(pts)
    assert count == fg.sum() < 1024  # paper 002: fewer than 1024 points, no pedestrian
    assert not np.isnan(pts[:count]).any() and np.isnan(pts[count:]).all()
    v, u = _pixels(pts)
    assert sorted(zip(v, u)) == sorted(zip(*np.nonzero(fg)))  # every foreground point
    empty, none = depth_points(device, depth, np.full_like(bg, np.nan), CAM, n_points=5)
    assert none == 0 and np.isnan(gputrack.to_numpy(empty)).all()
    one, n1 = depth_points(device, np.array([[1500]], np.uint16), np.array([[np.inf]], np.float32), CAM, n_points=3)
    assert n1 == 1
    np.testing.assert_allclose(gputrack.to_numpy(one)[0], [-320 * 1500 / 525, -240 * 1500 / 525, 1500], rtol=1e-6)


def test_range_threshold_and_out(device):
    depth = np.array([[1000, 4000, 6000, 0, 1000]], np.uint16)
    bg = np.array([[2000, 5000, 9000, 5000, 1050]], np.float32)
    out = device.empty((4, 3), np.float32) if device.backend != "numpy" else np.empty((4, 3), np.float32)
    pts, count = depth_points(device, depth, bg, CAM, n_points=4, out=out)
    assert pts is out and count == 2  # beyond 5 m, no reading, 50 mm off: not foreground
    v, u = _pixels(gputrack.to_numpy(pts))
    assert sorted(u) == [0, 1]
    assert depth_points(device, depth, bg, CAM, n_points=4, max_range=np.inf)[1] == 3
    assert depth_points(device, depth, bg, CAM, n_points=4, threshold=40.0)[1] == 3
    assert depth_points(device, depth, bg - 3000, CAM, n_points=4, nearer=True, threshold=0.0)[1] == 0


def test_floor_background():
    cam = DepthCamera(525.0, 525.0, 320.0, 240.0)
    floor = floor_background(cam, 1000.0, (480, 640))
    assert floor.shape == (480, 640) and floor.dtype == np.float32
    assert np.isinf(floor[:241]).all() and np.isfinite(floor[241:]).all()  # at and above the horizon: no floor
    v = np.arange(241, 480)
    np.testing.assert_allclose(floor[241:, 0], 1000.0 * 525.0 / (v - 240.0), rtol=1e-6)
    # back-projected, every floor pixel lies on the plane 1 m below the camera (y down)
    h = DepthCamera(525.0, 525.0, 320.0, 240.0, depth_scale=1.0, min_depth=0.0, max_depth=1e9)
    np.testing.assert_allclose(h.points(np.where(np.isfinite(floor), floor, 0))[:, 1], 1000.0, rtol=1e-5)
    # pitched down 30 degrees: the points' height along the vertical is the camera's height
    pitch = np.radians(30.0)
    tilted = floor_background(cam, 1500.0, (48, 64), pitch=pitch)
    pts = h.points(np.where(np.isfinite(tilted), tilted, 0))
    np.testing.assert_allclose(pts @ [0.0, np.cos(pitch), np.sin(pitch)], 1500.0, rtol=1e-5)
    with pytest.raises(ValueError, match="height: expected a height above the floor > 0, got -1.0"):
        floor_background(cam, -1.0, (4, 4))
    with pytest.raises(ValueError, match=r"shape: expected \(H, W\) with H, W >= 1, got \(4, 0\)"):
        floor_background(cam, 1.0, (4, 0))
    with pytest.raises(TypeError, match="camera: expected a gputrack.models.Camera or DepthCamera, got tuple"):
        floor_background((525.0, 525.0, 320.0, 240.0), 1.0, (4, 4))


def test_people_on_the_floor(device):
    """A level camera 1 m up: the floor is background, a box standing on it is foreground."""
    H, W = 48, 64
    cam = Camera(52.5, 52.5, 32.0, 24.0)
    floor = floor_background(cam, 1000.0, (H, W))
    depth = np.where(np.isfinite(floor), np.minimum(floor, 6000.0), 0).astype(np.float32)
    depth[10:40, 20:30] = 2000.0  # a person 2 m away
    pts, count = depth_points(device, depth, floor, cam, n_points=1024, nearer=True)
    assert count == 300
    v, u = _pixels(gputrack.to_numpy(pts), cam)
    assert sorted(zip(v, u)) == [(r, c) for r in range(10, 40) for c in range(20, 30)]


def test_bad_input(device):
    depth = np.zeros((4, 5), np.uint16)
    bg = np.zeros((4, 5), np.float32)
    for n in (0, -1):
        with pytest.raises(ValueError, match=f"n_points: expected n_points >= 1, got {n}"):
            depth_points(device, depth, bg, CAM, n_points=n)
    with pytest.raises(TypeError, match="n_points: expected an integer, got float"):
        depth_points(device, depth, bg, CAM, n_points=10.0)
    with pytest.raises(ValueError, match=r"seed: expected an integer in \[0, 2\*\*32\), got -1"):
        depth_points(device, depth, bg, CAM, seed=-1)
    with pytest.raises(ValueError, match=r"counter: expected an integer in \[0, 2\*\*32\), got 4294967296"):
        depth_points(device, depth, bg, CAM, counter=2**32)
    with pytest.raises(TypeError, match="seed: expected an integer"):
        depth_points(device, depth, bg, CAM, seed=True)
    with pytest.raises(ValueError, match="threshold: expected a number >= 0.0, got -100.0"):
        depth_points(device, depth, bg, CAM, threshold=-100.0)
    with pytest.raises(ValueError, match="max_range: expected a number > 0, got 0.0"):
        depth_points(device, depth, bg, CAM, max_range=0.0)
    with pytest.raises(TypeError, match="camera: expected a gputrack.models.Camera or DepthCamera, got dict"):
        depth_points(device, depth, bg, {"fx": 525.0})
    with pytest.raises(ValueError, match=r"depth: expected shape \(H=4, W=5\), got \(5, 4\)"):
        depth_points(device, depth.T, bg, CAM)
    with pytest.raises(TypeError, match="depth: expected dtype uint8, uint16 or float32, got int16"):
        depth_points(device, depth.astype(np.int16), bg, CAM)
    with pytest.raises(TypeError, match="background: expected dtype float32, got float64"):
        depth_points(device, depth, bg.astype(np.float64), CAM)
    with pytest.raises(ValueError, match=r"out: expected a float32 array of shape \(8, 3\)"):
        depth_points(device, depth, bg, CAM, n_points=8, out=device.empty((9, 3), np.float32))
    if device.spec == "taichi:vulkan" and device.info.kind != "gpu":  # lavapipe's loop-pass limit
        tall = np.zeros((13108, 2), np.uint16)  # step 2's serial task: 5 passes a row, 65540 > 65535
        with pytest.raises(ValueError, match="depth: at most 13107 rows and 21845 columns on taichi:vulkan"):
            depth_points(device, tall, np.zeros(tall.shape, np.float32), CAM)


@lru_cache(maxsize=1)
def _pcd_xyz(path: Path) -> np.ndarray:
    """x, y, z (480, 640, 3) float32 of an organised PCD ``binary_compressed`` (LZF) file."""
    raw = path.read_bytes()
    tag = b"DATA binary_compressed\n"
    at = raw.index(tag) + len(tag)
    csize, usize = (int(s) for s in np.frombuffer(raw[at : at + 8], np.uint32))
    src, out, i, o = raw[at + 8 : at + 8 + csize], bytearray(usize), 0, 0
    while i < len(src):  # LZF: literal runs and back references
        ctrl = src[i]
        i += 1
        if ctrl < 32:
            out[o : o + ctrl + 1] = src[i : i + ctrl + 1]
            i += ctrl + 1
            o += ctrl + 1
            continue
        n, ref = ctrl >> 5, o - ((ctrl & 0x1F) << 8) - 1
        if n == 7:
            n += src[i]
            i += 1
        ref -= src[i]
        i += 1
        n += 2
        if ref + n <= o:
            out[o : o + n] = out[ref : ref + n]
        else:
            for k in range(n):
                out[o + k] = out[ref + k]
        o += n
    count = 480 * 640
    return np.frombuffer(bytes(out), np.float32, 3 * count).reshape(3, count).T.reshape(480, 640, 3)


@pytest.mark.skipif(not KINECT.is_dir(), reason=f"real Kinect frames not found at {KINECT}")
def test_kinect_frame_reproduces_the_pcl_cloud(device):
    import cv2

    pcd = next(KINECT.glob("*.pcd"))
    depth = cv2.imread(str(pcd.with_name(pcd.stem + "_depth.tiff")), cv2.IMREAD_UNCHANGED)
    xyz = _pcd_xyz(pcd)  # metres, NaN where no reading
    far = np.full(depth.shape, np.inf, np.float32)  # nothing in range: every reading is foreground
    n = int((depth > 0).sum())
    pts, count = depth_points(device, depth, far, CAM, n_points=n, max_range=np.inf)
    pts = gputrack.to_numpy(pts)
    assert count == n == int(np.isfinite(xyz[..., 2]).sum())  # the same NaN mask as PCL's
    v, u = _pixels(pts)
    assert len(set(zip(v, u))) == n
    np.testing.assert_allclose(pts / 1000.0, xyz[v, u], rtol=0, atol=3e-7)  # PCL's cloud, in metres
    # the paper's downsampling on the real frame: 1024 of them, the same on every device
    sub, _ = depth_points(device, depth, far, CAM, n_points=1024, max_range=np.inf, counter=9)
    want, _ = depth_points(REF, depth, far, CAM, n_points=1024, max_range=np.inf, counter=9)
    assert_matches(device, sub, want)

"""Paper 002's pipeline on real and recorded data: the PCL five-people cloud (floor-plane
background, a camera that is neither level nor 1 m up), the PCD reader's LZF, and the two
commands (``gputrack demo pedestrians``, ``gputrack track pedestrians``) on tiny inputs."""

import json

import numpy as np
import pytest

from gputrack.benchmarks.pedestrians import crowd_depth
from gputrack.cli import main
from gputrack.models import Camera
from gputrack.shared_data import shared_data
from gputrack.trackers.pedestrians import PedestrianConfig, PedestrianTracker
from gputrack.trackers.pedestrians.pcd import depth_from_cloud, lzf_decompress, read_pcd

DATA = shared_data("pcl_people", "five_people.pcd")
#: PCL's people test: ground plane (metres; d scaled to mm below) and Kinect intrinsics
PLANE = (-0.0103586, 0.997011, 0.0765573, -1266.14)
KINECT = Camera(525.0, 525.0, 319.5, 239.5)


def test_lzf_literals_and_overlapping_back_references():
    # "abc" literal (ctrl 2), then a back-reference of length 7 at distance 3 (ctrl (5 << 5) | 0, 2):
    # "abcabcabca"; then a long reference (len 7 + 2 + 2 = 11) at distance 1: eleven "a"
    data = bytes([2]) + b"abc" + bytes([5 << 5, 2]) + bytes([7 << 5, 2, 0])
    assert lzf_decompress(data, 21) == b"abcabcabca" + b"a" * 11
    with pytest.raises(ValueError, match="LZF"):
        lzf_decompress(bytes([1 << 5, 9]), 4)  # a reference before the start
    with pytest.raises(ValueError, match="expected 5 bytes"):
        lzf_decompress(bytes([0]) + b"x", 5)


@pytest.fixture(scope="session")  # built once, not again per device
def five_people():
    if not DATA.exists():
        pytest.skip(f"{DATA} is absent (the shared test data lives beside the repository or in $GPUTRACK_DATA, not in it)")
    cloud = read_pcd(str(DATA))
    assert cloud["x"].shape == (480, 640) and cloud["x"].dtype == np.float32
    return cloud


def test_pcd_reader_matches_the_pinhole_model(five_people):
    """The organised cloud is the back-projection of its own z with fx = fy = 525, cx = 319.5,
    cy = 239.5 (so the depth image we make of it is the sensor's)."""
    z = five_people["z"]
    v, u = np.nonzero(np.isfinite(z))
    np.testing.assert_allclose(five_people["x"][v, u], (u - 319.5) * z[v, u] / 525.0, atol=1e-4)
    np.testing.assert_allclose(five_people["y"][v, u], (v - 239.5) * z[v, u] / 525.0, atol=1e-4)


def test_five_people_with_the_floor_plane_background(device, five_people):
    """PCL's test expects five people. With the floor plane as the background every static thing
    above the floor is foreground too (160k of the 240k readings); the paper's 1024 points are
    drawn among the readings above the sensor's horizon only (the floor mode's rule), which puts
    100-350 of them on each person. Two people stand a few cm apart, so DBSCAN needs a radius
    tighter than the default (60 mm), and a static thing at 4.7 m that reaches 1.7 m in a few
    points needs min_segment_points 25: then five segments for every seed (0-9 were checked; the
    defaults give 3-6), each a person 1.3-2.3 m tall (PCL's bounds)."""
    depth = depth_from_cloud(five_people)
    for seed in (0, 1, 2):
        cfg = PedestrianConfig(ground_plane=PLANE, eps=60.0, min_segment_points=25, seed=seed)
        trk = PedestrianTracker(device, camera=KINECT, config=cfg)
        trk.floor_background(depth.shape)
        fr = trk.track(depth)
        assert len(fr.segments) == 5, seed
        n = trk.front.plane
        tops = [-(n[:3] @ s.lo + n[3]) for s in fr.segments]  # highest point: min y, camera y down
        bottoms = [-(n[:3] @ s.hi + n[3]) for s in fr.segments]
        assert all(1200 <= b <= 1350 for b in bottoms), bottoms  # cut at the sensor's height, 1.27 m
        assert all(1300 <= t <= 2300 for t in tops), tops
        xs = sorted(float(s.position[0]) for s in fr.segments)
        assert min(np.diff(xs)) > 200  # five different places
        assert [p.status for p in fr.pedestrians] == ["new"] * 5


# -- the commands -------------------------------------------------------------------------------------
def test_demo_command_on_a_tiny_sequence(tmp_path, capsys):
    assert main(["demo", "pedestrians", "--frames", "12", "--people", "2", "--scale", "0.25", "--device", "numpy",
                 "--no-ablations", "--save", str(tmp_path), "--json", str(tmp_path / "r.json")]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "Table 2" in out and "Table 3" in out and "Table 4" in out and "frame   11" in out
    assert "associate" in out  # the stage table
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["sequence"]["frames"] == 12 and 0 <= rep["metrics"]["full"]["detection"]["precision"] <= 1
    assert (tmp_path / "depth_0000.png").exists() and (tmp_path / "top_0011.png").exists()


def _recording(tmp_path):
    import cv2

    cam = Camera(160 / (2 * np.tan(np.radians(29.5))), 120 / (2 * np.tan(np.radians(23.0))), 79.5, 59.5)
    (tmp_path / "bg").mkdir()
    (tmp_path / "depth").mkdir()
    for k in range(3):
        cv2.imwrite(str(tmp_path / "bg" / f"{k:03d}.png"), crowd_depth(cam, (120, 160), np.zeros((0, 2))))
    truth = []
    for k in range(6):
        xz = [[-800.0 + 150 * k, 2500.0], [900.0 - 100 * k, 3800.0]]
        truth.append(xz)
        cv2.imwrite(str(tmp_path / "depth" / f"{k:03d}.png"), crowd_depth(cam, (120, 160), xz))
    (tmp_path / "cam.json").write_text(json.dumps({"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}))
    return truth


def test_track_command_writes_csv_tracks(tmp_path):
    truth = _recording(tmp_path)
    out = tmp_path / "tracks.csv"
    with pytest.warns(UserWarning, match="fewer than the paper's 30"):
        assert main(["track", "pedestrians", "--depth", str(tmp_path / "depth" / "*.png"), "--camera",
                     str(tmp_path / "cam.json"), "--background", str(tmp_path / "bg"), "--device", "numpy",
                     "--out", str(out), "--save", str(tmp_path / "pics")]) == 0  # fmt: skip
    rows = np.loadtxt(out, delimiter=",", ndmin=2)
    assert rows.shape[1] == 10 and set(rows[:, 0].astype(int)) == set(range(1, 7))
    assert set(rows[:, 1].astype(int)) == {0, 1}  # two people, two ids, all along
    for f, xz in enumerate(truth, start=1):
        got = rows[rows[:, 0] == f]
        for x, z in xz:  # each person has a track within 300 mm on the ground (the board's front)
            assert np.min(np.hypot(got[:, 7] - x, got[:, 9] - z)) < 300
    assert (tmp_path / "pics" / "depth_00000.png").exists()
    # without --background: the floor plane of a level camera 1 m up (the default mounting)
    out2 = tmp_path / "floor.csv"
    assert main(["track", "pedestrians", "--depth", str(tmp_path / "depth"), "--camera", str(tmp_path / "cam.json"),
                 "--device", "numpy", "--out", str(out2)]) == 0  # fmt: skip
    assert set(np.loadtxt(out2, delimiter=",", ndmin=2)[:, 1].astype(int)) == {0, 1}


def test_track_command_reports_bad_input(tmp_path, capsys):
    _recording(tmp_path)
    (tmp_path / "bad.json").write_text(json.dumps({"fx": 100.0}))
    assert main(["track", "pedestrians", "--depth", str(tmp_path / "depth"), "--camera", str(tmp_path / "bad.json"),
                 "--device", "numpy"]) == 1  # fmt: skip
    assert "missing fy, cx, cy" in capsys.readouterr().err
    assert main(["track", "pedestrians", "--depth", str(tmp_path / "nothing*.png"), "--camera",
                 str(tmp_path / "cam.json"), "--device", "numpy"]) == 1  # fmt: skip
    assert "found nothing" in capsys.readouterr().err
    import cv2

    cv2.imwrite(str(tmp_path / "depth" / "999.png"), np.zeros((120, 160, 3), np.uint8))
    assert main(["track", "pedestrians", "--depth", str(tmp_path / "depth"), "--camera", str(tmp_path / "cam.json"),
                 "--device", "numpy", "--out", str(tmp_path / "x.csv")]) == 1  # fmt: skip
    assert "16-bit single-channel" in capsys.readouterr().err


def test_benchmark_cases_run_and_match_the_reference(device):
    """perf/bench_pedestrians.py's cases at a tiny size: the tracker's frame runs, the device DBSCAN
    gives the reference's labels and the NumPy + scikit-learn peer finds the same people."""
    import argparse

    from gputrack.benchmarks import pedestrians as bench

    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args(["--people", "5", "--frames", "2", "--scale", "0.25"])
    frame, clusters = bench.cases(device, args)
    fr = frame.run()
    assert len(fr.segments) >= 1 and fr.pedestrians
    got, want = clusters.run(), clusters.reference()
    got = got if device.backend == "numpy" else got.numpy()
    np.testing.assert_array_equal(got, want)
    peer = frame.peers["numpy front end + sklearn"]()
    assert abs(len(peer) - len(fr.segments)) <= 1

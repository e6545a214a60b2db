"""``gputrack track body``: a simulated recording written as PNGs + JSON and tracked from the command
line, the rigid path, the frame pairing, and bad input (missing or unreadable frames, mixed sizes,
depth in metres, a model file without a part, a bad start pose)."""

import json
import shutil

import numpy as np
import pytest

from gputrack.cli import main
from gputrack.models import DEFAULT_CAMERA, upper_body
from gputrack.sim import sequence
from gputrack.trackers.body.metrics import arm_axis_errors
from gputrack.trackers.body.recording import body_model_json, pair_frames, read_body_model, read_depth

cv2 = pytest.importorskip("cv2")

FAST = ["--device", "numpy", "--samples", "60", "--stages", "1", "--lm", "2"]


@pytest.fixture(scope="module")
def frame():
    seq = sequence("arm_swing", frames=1, seed=3)
    return seq, seq[0]


def write_recording(root, frames, *, depth_unit=0.2, start=None, model=True, camera=None):
    """RGB PNGs (colour, 8-bit) and 16-bit depth PNGs in ``depth_unit`` mm as TUM RGB-D lays them out, a
    camera file, a pose file and a model file; returns the paths as a dict."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    for k, f in enumerate(frames):
        g = np.clip(np.round(f.gray * 255.0), 0, 255).astype(np.uint8)
        cv2.imwrite(str(root / "rgb" / f"{k:05d}.png"), cv2.cvtColor(g, cv2.COLOR_GRAY2BGR))
        cv2.imwrite(str(root / "depth" / f"{k:05d}.png"), np.round(f.depth / depth_unit).astype(np.uint16))
    cam = DEFAULT_CAMERA
    (root / "camera.json").write_text(json.dumps(camera or {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}))
    p0 = frames[0].params if start is None else start
    (root / "pose.json").write_text(json.dumps({"params": [float(v) for v in p0]}))
    (root / "model.json").write_text(json.dumps(body_model_json() if model is True else model))
    return paths_of(root)


def paths_of(root):
    return {"rgb": str(root / "rgb" / "*.png"), "depth": str(root / "depth"), "camera": str(root / "camera.json"),
            "init": str(root / "pose.json"), "model": str(root / "model.json")}  # fmt: skip


@pytest.fixture(scope="module")
def recording(frame, tmp_path_factory):
    """Two frames (the same simulated one twice), written once; tests copy it and change what they test."""
    root = tmp_path_factory.mktemp("recording") / "rec"
    write_recording(root, [frame[1]] * 2)
    return root


def copy_of(recording, tmp_path):
    root = tmp_path / "rec"
    shutil.copytree(recording, root)
    return root, paths_of(root)


def argv(paths, *extra, model=True):
    out = ["track", "body", "--rgb", paths["rgb"], "--depth", paths["depth"], "--camera", paths["camera"],
           "--init", paths["init"]]  # fmt: skip
    return out + (["--model", paths["model"]] if model else []) + list(extra)


def test_track_body_on_a_written_recording(frame, recording, tmp_path, capsys):
    """A simulated frame as TUM-style PNGs (depth 0.2 mm per unit, the default), tracked from a start 15 mm
    and 4 deg off, then a frame without depth: the first pose moves to the truth; the second keeps it with
    confidence 0 (never NaN); the first frame's picture is written."""
    seq, f = frame
    root, paths = copy_of(recording, tmp_path)
    cv2.imwrite(str(root / "depth" / "00001.png"), np.zeros(f.depth.shape, np.uint16))
    start = f.params.copy()
    start[3] += 15.0
    start[6] += np.radians(4.0)
    start[13] -= np.radians(4.0)
    (root / "pose.json").write_text(json.dumps({"params": start.tolist()}))
    out = tmp_path / "poses.jsonl"
    assert main(argv(paths, *FAST, "--out", str(out), "--save", str(tmp_path / "pics"))) == 0
    assert "2 frames (depth 0.2 mm per unit)" in capsys.readouterr().err
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(lines) == 3 and lines[-1] == {"frames": 2, "names": list(upper_body().param_names), "kept": 1,
                                              "left_out": 0}  # fmt: skip
    assert [(r["frame"], r["rgb"], r["depth"]) for r in lines[:2]] == [
        (k, f"{k:05d}.png", f"{k:05d}.png") for k in (0, 1)
    ]
    est = np.array([r["params"] for r in lines[:2]])
    assert est.shape == (2, 14) and np.isfinite(est).all()
    assert [r["confidence"] for r in lines[:2]] == [1.0, 0.0] and np.isfinite(lines[0]["cost"])
    assert lines[1]["cost"] is None and "no valid depth" in lines[1]["message"]
    np.testing.assert_array_equal(est[1], est[0])
    before = arm_axis_errors(seq.chain, start, f.params)
    after = arm_axis_errors(seq.chain, est[0], f.params)
    assert before.max() > 3.9 and after.max() < 2.5, (before, after)
    assert np.abs(est[0, 3:6] - f.params[3:6]).max() < 5.0, est[0, 3:6] - f.params[3:6]
    pic = cv2.imread(str(tmp_path / "pics" / "frame_00000.png"))
    raw = cv2.imread(str(root / "rgb" / "00000.png"))
    assert pic is not None and pic.shape == raw.shape and (pic != raw).any(axis=2).mean() > 0.01


def test_track_body_rigid_path_and_mixed_sizes(recording, tmp_path, capsys, monkeypatch):
    """--rigid reaches the frame-template path (frame 0: the identity, no pose file needed), with the
    rigid settings (its parameters are the frame-to-frame motion: no constant-velocity start on top);
    a later frame of another size stops the run with the file named, after the lines so far."""
    from gputrack.trackers.body import tracker as tracker_module

    configs = []
    real_init = tracker_module.BodyTracker.__init__

    def init(self, *a, **kw):
        configs.append(kw["config"])
        real_init(self, *a, **kw)

    monkeypatch.setattr(tracker_module.BodyTracker, "__init__", init)
    root, paths = copy_of(recording, tmp_path)
    cv2.imwrite(str(root / "depth" / "00001.png"), np.full((240, 320), 9000, np.uint16))
    out = tmp_path / "motion.jsonl"
    args = ["track", "body", "--rigid", "--rgb", paths["rgb"], "--depth", paths["depth"], "--camera", paths["camera"],
            "--out", str(out), *FAST]  # fmt: skip
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "depth/00001.png: expected a 640 x 480 image" in err and "got 320 x 240" in err, err
    first = json.loads(out.read_text().splitlines()[0])
    assert first["params"] == [0.0] * 6 and first["pose"] == np.eye(4).tolist()
    assert len(configs) == 1 and configs[0].predict is False and (configs[0].c_depth, configs[0].lam) == (50.0, 0.5)


def test_pairing_by_number_and_by_time(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    for k in range(11):  # numbers sort as numbers: 0, 1, 2, ..., 10 (not 0, 1, 10, 2)
        (a / f"{k}.png").touch()
        (b / f"{k}.png").touch()
    pairs, left = pair_frames(str(a), str(b / "*.png"))
    assert [p[0].rsplit("/", 1)[1] for p in pairs] == [f"{k}.png" for k in range(11)] and left == 0
    assert all(p[0].rsplit("/", 1)[1] == p[1].rsplit("/", 1)[1] for p in pairs)
    # TUM RGB-D: time-stamped names, more RGB than depth images: nearest in time within 0.02 s
    c, d = tmp_path / "c", tmp_path / "d"
    c.mkdir(), d.mkdir()
    for t in ("100.000", "100.033", "100.066", "100.100"):
        (c / f"{t}.png").touch()
    for t in ("100.005", "100.070", "100.098"):
        (d / f"{t}.png").touch()
    pairs, left = pair_frames(str(c), str(d))
    got = [(p[0].rsplit("/", 1)[1], p[1].rsplit("/", 1)[1]) for p in pairs]
    assert got == [("100.000.png", "100.005.png"), ("100.066.png", "100.070.png"), ("100.100.png", "100.098.png")]
    assert left == 1


@pytest.mark.parametrize("case, message", [
    ("rgb missing", "missing the RGB image of frame 1"),
    ("gap", "rgb/00002.png: missing RGB frame 1 (expected frame numbers in steps of 1, got 0 then 2)"),
    ("rgb unreadable", "rgb/00000.png: expected an image OpenCV can read, got an unreadable file"),
    ("depth unreadable", "depth/00000.png: expected a depth image OpenCV can read, got an unreadable file"),
    ("depth 8-bit", "depth/00000.png: expected a 16-bit depth image (or 32-bit float), got uint8"),
    ("depth size", "depth/00000.png: expected a 640 x 480 image"),
    ("camera size", "rgb/00000.png: expected a 320 x 240 image"),
    ("metres", "depth/00000.png: the depth looks like metres, not units of 0.2 mm"),
    ("mm as default", None),
    ("no frames", "expected RGB images (a directory or a glob pattern), found nothing"),
    ("model part", "model.json: expected the parts torso, shoulder, upper_arm, forearm, missing forearm"),
    ("model field", "model.json: expected \"upper_arm\" with length, radius (mm), missing radius"),
    ("model value", "model.json: expected \"torso\".half_width > 0 (mm), got -5"),
    ("pose length", "pose.json: expected \"params\" as a list of 14 or 20 numbers, got shape (13,)"),
    ("pose nan", "pose.json: expected finite \"params\", got NaN or inf at index 2"),
    ("pose metres", "pose.json: expected the torso in front of the camera, in mm (tz_O >= 100), got 2 (metres?)"),
    ("pose out of view", "pose.json: expected a pose with the torso in view"),
    ("camera keys", "camera.json: expected the keys fx, fy, cx, cy (px) or \"intrinsic_matrix\", missing cy"),
])  # fmt: skip
def test_bad_recordings_name_the_file_and_what_was_expected(case, message, frame, recording, tmp_path, capsys):
    """Each is found before any frame is tracked: exit status 1 and one line naming the file."""
    _, f = frame
    root, paths = copy_of(recording, tmp_path)
    p0 = f.params.copy()
    if case == "metres":  # the depth written in metres
        cv2.imwrite(str(root / "depth" / "00000.png"), np.round(f.depth / 1000.0).astype(np.uint16))
    if case == "mm as default":
        # depth in mm read as 0.2 mm units is within range: nothing to detect; --depth-scale 1 reads it
        cv2.imwrite(str(root / "depth" / "00000.png"), np.round(f.depth).astype(np.uint16))
        d = read_depth(str(root / "depth" / "00000.png"), 1.0)
        np.testing.assert_allclose(d[f.depth > 0], np.round(f.depth[f.depth > 0]), atol=0.5)
        return
    if case.startswith("model"):
        model = body_model_json()
        if case == "model part":
            del model["forearm"]
        elif case == "model field":
            del model["upper_arm"]["radius"]
        else:
            model["torso"]["half_width"] = -5
        (root / "model.json").write_text(json.dumps(model))
    if case.startswith("pose"):
        if case == "pose length":
            p0 = p0[:13]
        elif case == "pose nan":
            p0[2] = np.nan
        elif case == "pose metres":
            p0[3:6] = (0.0, 0.0, 2.0)
        else:
            p0[3] = 5000.0
        (root / "pose.json").write_text(json.dumps({"params": p0.tolist()}))
    c = DEFAULT_CAMERA
    if case == "camera keys":
        (root / "camera.json").write_text(json.dumps({"fx": 525.0, "fy": 525.0, "cx": 319.5}))
    elif case == "camera size":
        (root / "camera.json").write_text(json.dumps({"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": 320,
                                                      "height": 240}))  # fmt: skip
    if case == "rgb missing":
        (root / "rgb" / "00001.png").unlink()
    elif case == "gap":  # frames 0, 2, 3 in both folders
        for k in (2, 3):
            for sub in ("rgb", "depth"):
                shutil.copy(root / sub / "00001.png", root / sub / f"{k:05d}.png")
        (root / "rgb" / "00001.png").unlink()
        (root / "depth" / "00001.png").unlink()
    elif case == "rgb unreadable":
        (root / "rgb" / "00000.png").write_bytes(b"not a png")
    elif case == "depth unreadable":
        (root / "depth" / "00000.png").write_bytes(b"\x89PNG broken")
    elif case == "depth 8-bit":
        cv2.imwrite(str(root / "depth" / "00000.png"), np.full((480, 640), 100, np.uint8))
    elif case == "depth size":
        cv2.imwrite(str(root / "depth" / "00000.png"), np.full((480, 320), 9000, np.uint16))
    elif case == "no frames":
        paths["rgb"] = str(root / "rgb" / "*.jpg")
    assert main(argv(paths, *FAST)) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gputrack track body: ") and message in err[0], err


def test_metres_are_found_in_float_depth_too(tmp_path):
    """A 32-bit float depth image in metres (values 1-3) is named as metres; --depth-scale 1000 reads it."""
    from gputrack.trackers.body.recording import check_depth_unit

    name = str(tmp_path / "d.tiff")
    cv2.imwrite(name, np.full((4, 5), 2.25, np.float32))
    raw = read_depth(name, 1.0)
    with pytest.raises(ValueError, match=r"d.tiff: the depth looks like metres, not units of 1 mm \(median 2.25 units"):
        check_depth_unit(name, float(np.median(raw)), 1.0)
    check_depth_unit(name, float(np.median(raw)), 1000.0)  # 2250 mm: fine
    with pytest.raises(
        ValueError,
        match=r"expected a median depth within 50-30000 mm, got 2.25 units x 100000 mm = 2.25e\+05 mm: check --depth-scale",
    ):
        check_depth_unit(name, 2.25, 1e5)


def test_model_file_round_trip_and_missing_file(tmp_path):
    p = tmp_path / "m.json"
    p.write_text(json.dumps(body_model_json({"forearm_length": 250.0})))
    dims = read_body_model(str(p))
    assert dims["forearm_length"] == 250.0 and dims["shoulder"] == (195.0, -215.0, 0.0)
    upper_body(dimensions=dims)  # builds
    with pytest.raises(FileNotFoundError, match=r"nope.json: cannot read the body model file"):
        read_body_model(str(tmp_path / "nope.json"))


def test_track_body_needs_a_start_pose_unless_rigid(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["track", "body", "--rgb", "x", "--depth", "y", "--camera", "c.json"])
    assert e.value.code == 2
    assert "--init: expected the first frame's pose" in capsys.readouterr().err


@pytest.mark.parametrize("extra, message", [
    (["--samples", "5"], "candidates: expected at most samples=5, got 10"),
    (["--lam", "2"], "argument --lam: expected a finite number >= 0 and <= 1, got '2'"),
    (["--depth-scale", "0"], "argument --depth-scale: expected a finite number > 0, got '0'"),
    (["--device", "opencl:no-such-device"], "--device: opencl:no-such-device is not available: "),
])  # fmt: skip
def test_bad_track_body_options_end_in_a_usage_line(extra, message, recording, capsys):
    paths = paths_of(recording)
    with pytest.raises(SystemExit) as e:
        main(argv(paths, *extra))
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: gputrack track body") and f"gputrack track body: error: {message}" in err, err

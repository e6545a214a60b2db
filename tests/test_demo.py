"""``gputrack demo body``: the main job's command line, report and Table 7 start."""

import json

import numpy as np
import pytest

from gputrack.cli import main
from gputrack.sim import shoulders_off
from gputrack.models import upper_body


def test_demo_body_reports_the_tables(device, tmp_path, capsys):
    out = tmp_path / "report.json"
    argv = ["demo", "body", "--device", device.spec, "--frames", "3", "--sequence", "8", "--shoulders",
            "--stages", "1", "--lm", "3", "--depth-tol", "2.5", "--depth-points", "64", "--json", str(out)]  # fmt: skip
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "N'=64 depth points, depth tolerance 2.5 mm" in text and "Table 7 layout" in text
    report = json.loads(out.read_text())
    assert report["config"]["depth_tol"] == 2.5 and report["config"]["n_depth"] == 64
    assert [f["frame"] for f in report["frames"]] == [1, 2]
    assert all(f["confidence"] == 1.0 and np.isfinite(f["arm_errors_deg"]).all() for f in report["frames"])
    sh = np.array([report["shoulder_error_mm"]["right"], report["shoulder_error_mm"]["left"]])
    # started 30 mm off per shoulder; two frames of PF 1 + LM 3 bring them well inside that
    assert np.isfinite(sh).all() and (np.linalg.norm(sh, axis=1) < 30.0).all(), sh
    names = {s["name"] for s in report["stages"]}
    assert {"LM", "upload inputs", "template"} <= names and any(n.startswith("PF stage 1") for n in names), names


def test_shoulders_off_moves_each_shoulder_30mm():
    p = upper_body(shoulders=True).rest_params()
    a, b = shoulders_off(p, 0), shoulders_off(p, 1)
    np.testing.assert_array_equal(a[:14], p[:14])
    np.testing.assert_allclose(np.linalg.norm((a - p)[14:].reshape(2, 3), axis=1), 30.0)
    assert not np.allclose(a, b)  # seeded: another seed, another direction
    np.testing.assert_array_equal(a, shoulders_off(p, 0))
    with pytest.raises(ValueError, match=r"params: expected a 20-parameter pose"):
        shoulders_off(p[:14], 0)


@pytest.mark.parametrize("argv, message", [
    (["body", "--frames", "1"], "argument --frames: expected an integer >= 2, got '1'"),
    (["body", "--sequence", "9"], "argument --sequence: expected an integer in [0, 8], got '9'"),
    (["body", "--stages", "0"], "argument --stages: expected an integer >= 1, got '0'"),
    (["body", "--depth-tol", "nan"], "argument --depth-tol: expected a finite number >= 0, got 'nan'"),
    (["body", "--device", "nope"], "argument --device: unknown device spec 'nope'; expected one of: "),
    (["body", "--device", "opencl:no-such-device"], "--device: opencl:no-such-device is not available: "),
    (["groups", "--seconds", "0"], "argument --seconds: expected a finite number > 0, got '0'"),
    (["pedestrians", "--scale", "5"], "argument --scale: expected a finite number > 0 and <= 4, got '5'"),
    (["face", "--sequence", "9"], "argument --sequence: expected 0-4 or one of turns, depth, expressions, lighting, mixed, got '9'"),
    (["face", "--frames", "0"], "argument --frames: expected an integer in [1, 1000000], got '0'"),
])  # fmt: skip
def test_bad_demo_arguments_end_in_a_usage_line(argv, message, capsys):
    """argparse's usage line and exit status 2, not a traceback, for a bad demo argument."""
    what, rest = argv[0], argv[1:]
    if "--device" not in rest:
        rest += ["--device", "numpy"]
    with pytest.raises(SystemExit) as e:
        main(["demo", what, *rest])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(f"usage: gputrack demo {what}") and f"gputrack demo {what}: error: {message}" in err, err

import numpy as np
import pytest

import gputrack


def test_stage_counts_bytes_and_time(device):
    pipe = gputrack.Pipeline(device)
    x = np.random.default_rng(1).random((127, 3), dtype=np.float32)
    frames = []
    for _ in range(3):
        with pipe.frame() as f:
            with pipe.stage("upload"):
                d = device.asarray(x)
            with pipe.stage("work"):
                out = device.empty((127, 3), np.float32)
            with pipe.stage("download"):
                back = gputrack.to_numpy(d)
        frames.append(f)
        np.testing.assert_array_equal(back, x)
        assert out.shape == (127, 3)
    moved = 0 if device.backend == "numpy" else x.nbytes
    for f in frames:
        assert f.h2d == moved and f.d2h == moved
        assert f.stages["work"][1:] == (0, 0)
        assert f.wall_s >= sum(s[0] for s in f.stages.values()) * 0.5
    stats = {r["name"]: r for r in pipe.report()}
    assert stats["upload"]["calls"] == 3 and stats["upload"]["h2d_bytes"] == 3 * moved
    assert stats["download"]["d2h_bytes"] == 3 * moved and stats["download"]["h2d_bytes"] == 0
    assert all(r["median_ms"] >= 0 for r in stats.values())
    table = pipe.table()
    assert "upload" in table and "download" in table and device.spec in table


def test_pipeline_rejects_bad_use(device):
    with pytest.raises(TypeError, match="expected a gputrack.Device"):
        gputrack.Pipeline("numpy")
    pipe = gputrack.Pipeline(device)
    with pytest.raises(ValueError, match="non-empty stage name"):
        with pipe.stage(""):
            pass
    with pytest.raises(RuntimeError, match="frame inside a frame"):
        with pipe.frame():
            with pipe.frame():
                pass

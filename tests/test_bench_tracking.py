"""gputrack/benchmarks/tracking.py: the cases build and run (no timing assertions)."""

import argparse

import numpy as np
import pytest

from gputrack.benchmarks import tracking


def _args(*argv):
    parser = argparse.ArgumentParser()
    tracking.add_arguments(parser)
    return parser.parse_args(list(argv))


def test_tracking_cases_run(device):
    args = _args("--tracks", "40", "--frames", "6", "--no-stonesoup", "--no-kdtree")
    (case,) = tracking.cases(device, args)
    assert case.params["T"] == 40 and case.peers == {}
    frames = [case.run() for _ in range(3)]
    ref = [case.reference() for _ in range(3)]
    # the device and the NumPy reference track the same scene alike (same tracks started)
    assert [f.started.tolist() for f in frames] == [f.started.tolist() for f in ref]
    with pytest.raises(RuntimeError, match="run with a larger --frames"):
        for _ in range(3):
            case.run()


def test_stonesoup_peers_track_the_same_scene():
    pytest.importorskip("stonesoup")
    scene, x0, P0 = tracking.crowd(30, 4, 0.1)
    for kdtree in (False, True):
        step = tracking.stonesoup_cycle(scene, x0, P0, kdtree=kdtree)
        for _ in range(3):
            _, tracks = step()
        # the 30 initial tracks are kept (and near the truth)
        states = np.array([t.state_vector.ravel() for t in tracks])
        truth = scene[3].states
        d = np.linalg.norm(states[:, None, 0::2] - truth[None, :, 0::2], axis=2).min(axis=0)
        assert len(tracks) >= 30 and np.mean(d < 0.5) > 0.9

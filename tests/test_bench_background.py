"""gputrack/benchmarks/background.py: the cases build and run at a small size (no timing)."""

import argparse

import numpy as np

import gputrack
from gputrack.benchmarks import background


def _args(*argv):
    parser = argparse.ArgumentParser()
    background.add_arguments(parser)
    return parser.parse_args(list(argv))


def test_background_cases_run(device):
    cases = background.cases(device, _args("--size", "128x96", "--frames", "4"))
    assert [c.name.split()[0] for c in cases] == ["background_median", "foreground_mask", "depth_points"]
    for case in cases:
        got, want = case.run(), case.reference()
        for peer in case.peers.values():
            peer()
        if case.end_to_end is not None:
            case.end_to_end()
        if isinstance(got, tuple):  # depth_points: (points, count)
            assert got[1] == want[1] == case.params["foreground"] > 1024
            got, want = got[0], want[0]
        assert gputrack.to_numpy(got).shape == np.shape(want)

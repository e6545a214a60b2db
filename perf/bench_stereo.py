#!/usr/bin/env python3
"""stereo_match on every device, VGA with a ~15 % foreground mask and on the whole image, with
cv2.StereoBM as a peer; then the accuracy table on the Middlebury motorcycle pair against
cv2.StereoBM and cv2.StereoSGBM (see gputrack/benchmarks/stereo.py). With ``--json FILE`` the
accuracy goes into the file's document as ``"accuracy"``."""

import argparse
import json
import sys
from pathlib import Path

from gputrack.benchmarks import stereo
from gputrack.benchmarks.harness import bench_main, environment


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--json")
    parser.add_argument("--no-accuracy", action="store_true")
    parser.add_argument("--accuracy-only", action="store_true")
    opts, _ = parser.parse_known_args(argv)
    rc = 0
    if not opts.accuracy_only:
        rc = bench_main(stereo, argv)
    if opts.no_accuracy:
        return rc
    rows = stereo.accuracy()
    print("\nAccuracy: Middlebury motorcycle (scikit-image), 741 x 500, max_disparity 64")
    print(stereo.format_accuracy(rows))
    if opts.json and opts.json != "-":
        path = Path(opts.json)
        doc = json.loads(path.read_text()) if path.exists() and not opts.accuracy_only else environment()
        doc["accuracy"] = rows
        path.write_text(json.dumps(doc, indent=2) + "\n")
    return rc


if __name__ == "__main__":
    sys.exit(main())

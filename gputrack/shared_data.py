"""Where the public data sets live: ``$GPUTRACK_DATA`` when set, else ``shared/data`` beside the
repository (a source checkout's layout). The face model's default and the tests' real-data
cases read them through :func:`shared_data`; each caller says what is missing if a path is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["shared_data"]


def shared_data(*parts: str) -> Path:
    """The path of ``parts`` under the data folder (existing or not)."""
    base = os.environ.get("GPUTRACK_DATA")
    root = Path(base) if base else Path(__file__).resolve().parents[2] / "shared" / "data"
    return root.joinpath(*parts)

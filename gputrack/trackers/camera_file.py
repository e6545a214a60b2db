"""Camera files of the ``gputrack track`` commands: a JSON object with the intrinsics a tracker needs."""

from __future__ import annotations

import json

__all__ = ["read_camera_json"]


def read_camera_json(path: str, keys: tuple, what: str = "camera file") -> dict:
    """The JSON object in ``path`` (a ``what``, for the messages), checked to hold every name in ``keys``. Raises
    FileNotFoundError (unreadable) or ValueError (not JSON, not an object, a key missing), naming
    the file and what was expected."""
    want = ", ".join(keys)
    try:
        with open(path) as fh:
            data = json.load(fh)
    except OSError as e:
        raise FileNotFoundError(f"{path}: cannot read the {what} ({e.strerror})") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: expected JSON with {want}, got invalid JSON ({e.msg})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object with {want}, got {type(data).__name__}")
    missing = [k for k in keys if k not in data]
    if missing:
        raise ValueError(f"{path}: expected the keys {want}, missing {', '.join(missing)}")
    return data

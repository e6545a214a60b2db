"""Launch parameters worth tuning: their declarations and the per-device cache the launchers read.

A backend declares each kernel launch parameter set worth tuning (work-group size, hypotheses
per work-item, ...) as a :class:`Tunable` beside the launcher that reads it: plain data (the
op, the backend, the candidate values, the default, representative problem sizes and the kernel
sources). ``gputrack tune`` (:mod:`gputrack.tuning`) times every candidate on a device and
stores the fastest per problem-size bucket in a JSON file per user (``$GPUTRACK_TUNING_CACHE``,
else ``$XDG_CACHE_HOME/gputrack/tuning.json``, else ``~/.cache/gputrack/tuning.json``), keyed by
device name and driver version. The launchers read it with :func:`choose`; an entry that is
corrupt, names unknown values, or was measured on other kernel sources (stale) is ignored with a
warning and the default is used.

This module imports nothing else from gputrack, so that any backend may use it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import threading
import warnings
import weakref
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger("gputrack")

CACHE_VERSION = 1


@dataclasses.dataclass(frozen=True)
class Tunable:
    """Launch parameters of one op on one backend.

    ``candidates`` maps a parameter name to the values to try; ``default`` gives the values used
    without a cache entry: a dict, or a callable ``default(device) -> dict`` (read at every call,
    so it may depend on the device kind); ``sizes`` are representative problem sizes (dicts),
    the sizes ``gputrack tune`` times (the problem it runs for each is the tuner's:
    :data:`gputrack.tuning.PROBLEMS`). ``sources`` are the files whose contents key the cache (an
    edit makes entries stale): paths (``str`` or ``os.PathLike``, e.g. a Taichi kernel module, or
    :func:`gputrack.backends.opencl.program.source` for a file in kernels/).
    """

    op: str
    backend: str
    candidates: dict
    default: dict | Callable
    sizes: tuple
    sources: tuple = ()
    _fingerprint: list = dataclasses.field(default_factory=list, init=False, compare=False, hash=False, repr=False)

    def grid(self) -> list[dict]:
        """Every combination of candidate values."""
        combos = [{}]
        for name, values in self.candidates.items():
            combos = [{**c, name: v} for c in combos for v in values]
        return combos

    def cover(self) -> list[dict]:
        """A few combinations that try every candidate value of every parameter at least once
        (value i of each parameter together, cycling the shorter lists): a check of each value that
        costs max(len(values)) builds and launches instead of the grid's product."""
        n = max(len(v) for v in self.candidates.values())
        return [{name: values[i % len(values)] for name, values in self.candidates.items()} for i in range(n)]

    def default_for(self, device) -> dict:
        """The parameters used on ``device`` without a cache entry."""
        return dict(self.default(device) if callable(self.default) else self.default)

    def fingerprint(self) -> str:
        """Hash of the kernel sources and the candidate grid; a change makes cache entries stale.

        Computed once per process (the launchers ask for it at call time)."""
        if self._fingerprint:
            return self._fingerprint[0]
        h = hashlib.sha256(json.dumps(self.candidates, sort_keys=True).encode())
        for source in self.sources:
            p = Path(os.fspath(source))
            if p.is_file():
                h.update(p.read_bytes())
        self._fingerprint.append(h.hexdigest()[:16])
        return self._fingerprint[0]


def size_bucket(size: dict) -> str:
    """Problem sizes rounded up to powers of two, as a stable key, e.g. 'B=2048,N=128'."""
    parts = []
    for k in sorted(size):
        v = int(size[k])
        parts.append(f"{k}={1 << max(v - 1, 0).bit_length()}")
    return ",".join(parts)


def cache_path() -> Path:
    env = os.environ.get("GPUTRACK_TUNING_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "gputrack" / "tuning.json"


_device_keys = weakref.WeakKeyDictionary()


def device_key(device) -> str:
    """Device name and driver version: a new driver gets new measurements (cached per device)."""
    try:
        return _device_keys[device]
    except (KeyError, TypeError):
        pass
    driver = device.info.driver
    if not driver and device.backend == "taichi":
        from importlib.metadata import version

        driver = f"taichi {version('taichi')}"
    key = f"{device.spec}|{device.name}|{driver}"
    try:
        _device_keys[device] = key
    except TypeError:  # not weak-referenceable: computed each time
        pass
    return key


class TuningCache:
    """The JSON file of tuning choices: {version, devices: {device_key: {op: {bucket: entry}}}}."""

    def __init__(self, path: Path | None = None):
        self.path = Path(path) if path else cache_path()
        self._lock = threading.Lock()
        self._data: dict | None = None
        # (device key, op, fingerprint, *size items) -> params or None: what get() answered, so
        # that a launcher asking at every call costs a dict lookup (and a bad entry warns once per size)
        self._memo: dict = {}

    def _load(self) -> dict:
        if self._data is not None:
            return self._data
        data = {"version": CACHE_VERSION, "devices": {}}
        if self.path.is_file():
            try:
                loaded = json.loads(self.path.read_text())
                if (
                    not isinstance(loaded, dict)
                    or loaded.get("version") != CACHE_VERSION
                    or not isinstance(loaded.get("devices"), dict)
                ):
                    raise ValueError(f"expected a version {CACHE_VERSION} tuning cache")
                data = loaded
            except (OSError, ValueError) as e:
                warnings.warn(f"ignoring the tuning cache {self.path}: {e}", RuntimeWarning, stacklevel=3)
        self._data = data
        return data

    def get(self, device, tunable: Tunable, size: dict) -> dict | None:
        """The stored parameters for this device, op and size bucket, or None (with a warning if unusable)."""
        memo_key = (device_key(device), tunable.op, tunable.fingerprint(), *size.items())
        try:
            found = self._memo[memo_key]
        except (KeyError, TypeError):
            found = self._lookup(device, tunable, (*memo_key[:3], size_bucket(size)))
            if len(self._memo) > 4096:  # many distinct sizes: start over rather than grow
                self._memo.clear()
            try:
                self._memo[memo_key] = found
            except TypeError:  # unhashable size values: not memoised
                pass
        return dict(found) if found is not None else None

    def _lookup(self, device, tunable: Tunable, key) -> dict | None:
        dkey, op, fingerprint, bucket = key
        with self._lock:
            entry = self._load()["devices"].get(dkey, {}).get(op, {}).get(bucket)
        if entry is None:
            return None
        try:
            params = entry["params"]
            if entry.get("fingerprint") != fingerprint:
                raise ValueError("it was measured on other kernel sources (stale)")
            if set(params) != set(tunable.candidates):
                raise ValueError(f"expected parameters {sorted(tunable.candidates)}, got {sorted(params)}")
            for name, value in params.items():
                if value not in tunable.candidates[name]:
                    raise ValueError(f"{name}={value!r} is not one of {tunable.candidates[name]}")
            return dict(params)
        except (AttributeError, KeyError, TypeError, ValueError) as e:
            warnings.warn(f"ignoring tuning entry for {op} on {device.spec}: {e}", RuntimeWarning, stacklevel=4)
            return None

    def put(self, device, tunable: Tunable, size: dict, params: dict, timings_ms: dict | None = None) -> None:
        with self._lock:
            self._memo.clear()
            data = self._load()
            ops = data["devices"].setdefault(device_key(device), {})
            ops.setdefault(tunable.op, {})[size_bucket(size)] = {
                "params": params,
                "fingerprint": tunable.fingerprint(),
                "size": size,
                "timings_ms": timings_ms or {},
            }

    def save(self) -> None:
        with self._lock:
            data = self._load()
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_suffix(".tmp")
            tmp.write_text(json.dumps(data, indent=1, sort_keys=True))
            tmp.replace(self.path)


_cache: TuningCache | None = None
_cache_env: tuple | None = None


def default_cache() -> TuningCache:
    """The cache at :func:`cache_path` (re-opened when the environment names another file)."""
    global _cache, _cache_env
    env = (os.environ.get("GPUTRACK_TUNING_CACHE"), os.environ.get("XDG_CACHE_HOME"))
    if _cache is None or env != _cache_env:
        _cache, _cache_env = TuningCache(), env
    return _cache


def choose(device, tunable: Tunable, size: dict) -> dict:
    """The parameters a launcher should use: the cached choice for this size bucket, else the default."""
    return default_cache().get(device, tunable, size) or tunable.default_for(device)

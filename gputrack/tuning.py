"""Per-device tuning cache: launch parameters chosen by ``gputrack tune``, used by the ops.

Kernel launch parameters (work-group size, hypotheses per work-item, ...) that are worth tuning
are declared by the op that uses them as a :class:`Tunable`: the candidate values, the default,
the problem sizes to try and a factory that builds a runnable problem. ``gputrack tune`` times
every candidate on a device and stores the fastest per problem-size bucket in a JSON file per
user (``$GPUTRACK_TUNING_CACHE``, else ``$XDG_CACHE_HOME/gputrack/tuning.json``, else
``~/.cache/gputrack/tuning.json``), keyed by device name and driver version. The ops read it with
:func:`choose`; an entry that is corrupt, names unknown values, or was measured on other kernel
sources (stale) is ignored with a warning and the default is used.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import threading
import warnings
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger("gputrack")

CACHE_VERSION = 1


@dataclasses.dataclass(frozen=True)
class Tunable:
    """Launch parameters of one op on one backend.

    ``candidates`` maps a parameter name to the values to try, ``default`` gives the value used
    without a cache entry; ``sizes`` are representative problem sizes (dicts) and
    ``problem(device, size, params)`` returns a zero-argument callable that runs the op once.
    ``sources`` are the kernel files whose contents key the cache (an edit makes entries stale).
    """

    op: str
    backend: str
    candidates: dict
    default: dict
    sizes: tuple
    problem: Callable
    sources: tuple = ()

    def grid(self) -> list[dict]:
        """Every combination of candidate values."""
        combos = [{}]
        for name, values in self.candidates.items():
            combos = [{**c, name: v} for c in combos for v in values]
        return combos

    def fingerprint(self) -> str:
        """Hash of the kernel sources and the candidate grid; a change makes cache entries stale."""
        h = hashlib.sha256(json.dumps(self.candidates, sort_keys=True).encode())
        if self.sources:
            from .backends.opencl.program import kernel_dir

            for name in self.sources:
                p = kernel_dir() / name
                if p.is_file():
                    h.update(p.read_bytes())
        return h.hexdigest()[:16]


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


def device_key(device) -> str:
    """Device name and driver version: a new driver gets new measurements."""
    driver = device.info.driver
    if not driver and device.backend == "taichi":
        from importlib.metadata import version

        driver = f"taichi {version('taichi')}"
    return f"{device.spec}|{device.name}|{driver}"


class TuningCache:
    """The JSON file of tuning choices: {version, devices: {device_key: {op: {bucket: entry}}}}."""

    def __init__(self, path: Path | None = None):
        self.path = Path(path) if path else cache_path()
        self._lock = threading.Lock()
        self._data: dict | None = None

    def _load(self) -> dict:
        if self._data is not None:
            return self._data
        data = {"version": CACHE_VERSION, "devices": {}}
        if self.path.is_file():
            try:
                loaded = json.loads(self.path.read_text())
                if not isinstance(loaded, dict) or loaded.get("version") != CACHE_VERSION or not isinstance(loaded.get("devices"), dict):
                    raise ValueError(f"expected a version {CACHE_VERSION} tuning cache")
                data = loaded
            except (OSError, ValueError) as e:
                warnings.warn(f"ignoring the tuning cache {self.path}: {e}", RuntimeWarning, stacklevel=3)
        self._data = data
        return data

    def get(self, device, tunable: Tunable, size: dict) -> dict | None:
        """The stored parameters for this device, op and size bucket, or None (with a warning if unusable)."""
        with self._lock:
            entry = self._load()["devices"].get(device_key(device), {}).get(tunable.op, {}).get(size_bucket(size))
        if entry is None:
            return None
        try:
            params = entry["params"]
            if entry.get("fingerprint") != tunable.fingerprint():
                raise ValueError("it was measured on other kernel sources (stale)")
            if set(params) != set(tunable.candidates):
                raise ValueError(f"expected parameters {sorted(tunable.candidates)}, got {sorted(params)}")
            for name, value in params.items():
                if value not in tunable.candidates[name]:
                    raise ValueError(f"{name}={value!r} is not one of {tunable.candidates[name]}")
            return dict(params)
        except (KeyError, TypeError, ValueError) as e:
            warnings.warn(f"ignoring tuning entry for {tunable.op} on {device.spec}: {e}", RuntimeWarning, stacklevel=3)
            return None

    def put(self, device, tunable: Tunable, size: dict, params: dict, timings_ms: dict | None = None) -> None:
        with self._lock:
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


def _default_cache() -> TuningCache:
    global _cache
    if _cache is None or _cache.path != cache_path():
        _cache = TuningCache()
    return _cache


def choose(device, tunable: Tunable, size: dict) -> dict:
    """The parameters an op should launch with: the cached choice, else the default."""
    return _default_cache().get(device, tunable, size) or dict(tunable.default)


def tune(device, tunable: Tunable, *, cache: TuningCache | None = None, min_time: float = 0.1, progress=None) -> dict:
    """Time every candidate for every size on ``device``; store and return {bucket: best params}."""
    from .benchmark import time_call

    cache = cache or _default_cache()
    chosen = {}
    for size in tunable.sizes:
        timings = {}
        for params in tunable.grid():
            fn = tunable.problem(device, size, params)
            t = time_call(fn, device.synchronize, min_time=min_time)
            timings[json.dumps(params, sort_keys=True)] = t.median_s * 1e3
            if progress:
                progress(f"{tunable.op} {size_bucket(size)} {params}: {t.median_s * 1e3:.3f} ms")
        best = json.loads(min(timings, key=timings.get))
        cache.put(device, tunable, size, best, timings)
        chosen[size_bucket(size)] = best
    cache.save()
    return chosen

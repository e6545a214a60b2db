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
import importlib
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

#: modules that declare tunables (a ``TUNABLES`` dict of :class:`Tunable`), searched by :func:`tunables`
TUNABLE_MODULES = ("gputrack.ops.template", "gputrack.ops.kalman")


@dataclasses.dataclass(frozen=True)
class Tunable:
    """Launch parameters of one op on one backend.

    ``candidates`` maps a parameter name to the values to try; ``default`` gives the values used
    without a cache entry: a dict, or a callable ``default(device) -> dict`` (read at every call,
    so it may depend on the device kind); ``sizes`` are representative problem sizes (dicts) and
    ``problem(device, size, params)`` returns a zero-argument callable that runs the op once with
    ``params``. ``sources`` are the kernel files whose contents key the cache (an edit makes
    entries stale): names in kernels/, or absolute paths (e.g. a Taichi kernel module).
    """

    op: str
    backend: str
    candidates: dict
    default: dict | Callable
    sizes: tuple
    problem: Callable
    sources: tuple = ()
    _fingerprint: list = dataclasses.field(default_factory=list, compare=False, hash=False, repr=False)

    def grid(self) -> list[dict]:
        """Every combination of candidate values."""
        combos = [{}]
        for name, values in self.candidates.items():
            combos = [{**c, name: v} for c in combos for v in values]
        return combos

    def default_for(self, device) -> dict:
        """The parameters used on ``device`` without a cache entry."""
        return dict(self.default(device) if callable(self.default) else self.default)

    def fingerprint(self) -> str:
        """Hash of the kernel sources and the candidate grid; a change makes cache entries stale.

        Computed once per process (the ops ask for it at call time)."""
        if self._fingerprint:
            return self._fingerprint[0]
        h = hashlib.sha256(json.dumps(self.candidates, sort_keys=True).encode())
        if self.sources:
            from .backends.opencl.program import kernel_dir

            for name in self.sources:
                p = Path(name) if os.path.isabs(name) else kernel_dir() / name
                if p.is_file():
                    h.update(p.read_bytes())
        self._fingerprint.append(h.hexdigest()[:16])
        return self._fingerprint[0]


def tunables(backend: str | None = None, op: str | None = None) -> list[Tunable]:
    """Every declared tunable (of ``backend`` / for ``op`` when given), from :data:`TUNABLE_MODULES`."""
    found = []
    for name in TUNABLE_MODULES:
        for t in importlib.import_module(name).TUNABLES.values():
            if (backend is None or t.backend == backend) and (op is None or t.op == op):
                found.append(t)
    return found


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
        # that an op asking at every call costs a dict lookup (and a bad entry warns once per size)
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
    """The parameters an op should launch with: the cached choice for this size bucket, else the default."""
    return default_cache().get(device, tunable, size) or tunable.default_for(device)


@dataclasses.dataclass
class Trial:
    """One candidate's timing in :func:`tune` (``timing`` None and ``error`` set when it failed)."""

    params: dict
    timing: object = None
    error: str | None = None


#: a candidate replaces the default only when its confirmed median is this much lower
MIN_GAIN = 0.03


def _confirm(device, tunable, size, ok, min_time, progress) -> dict:
    """Re-time the three fastest candidates and the default (a busy machine makes single medians
    noisy) and return the fastest; the default stays unless the winner beats it by MIN_GAIN."""
    from .benchmark import time_call

    default = tunable.default_for(device)
    ranked = sorted(ok, key=lambda t: t.timing.median_s)
    finalists = [t.params for t in ranked[:3]]
    if default not in finalists and any(t.params == default for t in ok):
        finalists.append(default)
    if len(finalists) == 1:
        return finalists[0]
    again = {}
    for params in finalists:
        t = time_call(tunable.problem(device, size, params), device.synchronize, min_time=min_time)
        first = next(x.timing.median_s for x in ok if x.params == params)
        again[json.dumps(params, sort_keys=True)] = min(first, t.median_s)
        if progress:
            progress(f"{tunable.op} on {device.spec} {size_bucket(size)} {params}: {t.median_s * 1e3:.3f} ms (confirm)")
    best = json.loads(min(again, key=again.get))
    dkey = json.dumps(default, sort_keys=True)
    if dkey in again and again[json.dumps(best, sort_keys=True)] > (1.0 - MIN_GAIN) * again[dkey]:
        return default
    return best


def tune(
    device,
    tunable: Tunable,
    *,
    cache: TuningCache | None = None,
    min_time: float = 0.1,
    progress=None,
    report=None,
) -> dict:
    """Time every candidate for every size on ``device``; store and return {bucket: best params}.

    ``progress(message)`` is called after each candidate; ``report(size, trials, best)`` after
    each size with the :class:`Trial` list. The three fastest and the default are timed a second
    time (each keeps the lower of its two medians) and the default is kept unless the fastest
    beats it by :data:`MIN_GAIN`. A candidate that fails to build or launch (e.g. a
    work-group size the device does not support) is skipped; a size where every candidate fails
    stores nothing.
    """
    from .benchmark import time_call

    cache = cache or default_cache()
    chosen = {}
    for size in tunable.sizes:
        trials = []
        for params in tunable.grid():
            try:
                fn = tunable.problem(device, size, params)
                trial = Trial(params, time_call(fn, device.synchronize, min_time=min_time))
                msg = f"{trial.timing.median_s * 1e3:.3f} ms"
            except Exception as e:  # noqa: BLE001 - a candidate the device cannot run
                trial = Trial(params, error=f"{type(e).__name__}: {e}".splitlines()[0][:200])
                msg = f"failed ({trial.error})"
            trials.append(trial)
            if progress:
                progress(f"{tunable.op} on {device.spec} {size_bucket(size)} {params}: {msg}")
        ok = [t for t in trials if t.timing is not None]
        best = _confirm(device, tunable, size, ok, min_time, progress) if ok else None
        if best is not None:
            timings = {json.dumps(t.params, sort_keys=True): t.timing.median_s * 1e3 for t in ok}
            cache.put(device, tunable, size, best, timings)
            chosen[size_bucket(size)] = best
        if report:
            report(size, trials, best)
    cache.save()
    return chosen

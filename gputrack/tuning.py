"""``gputrack tune``: time the declared launch parameters on a device and store the fastest.

The launch parameters worth tuning are declared by the backends beside their launchers (a
``TUNABLES`` dict of :class:`gputrack.tuning_cache.Tunable` in each module of
:data:`TUNABLE_MODULES`); the launchers read the choices with
:func:`gputrack.tuning_cache.choose`. This module is the sweep: for each tunable it builds a
runnable problem of each representative size (:data:`PROBLEMS`, from the scenes of
:mod:`gputrack.sim.problems`), times every candidate (:func:`tune`) and stores the fastest in the
cache. The cache's names are re-exported here (``gputrack.tuning.choose`` etc.).
"""

from __future__ import annotations

import dataclasses
import importlib
import json
from collections.abc import Callable

import numpy as np

from .tuning_cache import (
    CACHE_VERSION,
    Tunable,
    TuningCache,
    cache_path,
    choose,
    default_cache,
    device_key,
    size_bucket,
)

__all__ = [
    "CACHE_VERSION",
    "MIN_GAIN",
    "PROBLEMS",
    "TUNABLE_MODULES",
    "Trial",
    "Tunable",
    "TuningCache",
    "cache_path",
    "choose",
    "default_cache",
    "device_key",
    "problem_for",
    "size_bucket",
    "tunables",
    "tune",
]

#: backend -> the modules that declare its tunables (a ``TUNABLES`` dict {op: Tunable}), beside the
#: launchers that read them
TUNABLE_MODULES = {
    "taichi": ("gputrack.backends.taichi.template",),
    "opencl": ("gputrack.backends.opencl.template", "gputrack.backends.opencl.kalman"),
}


def tunables(backend: str | None = None, op: str | None = None) -> list[Tunable]:
    """Every declared tunable (of ``backend`` / for ``op`` when given), from :data:`TUNABLE_MODULES`
    (only the modules of ``backend`` are imported when it is given)."""
    found = []
    for name, modules in TUNABLE_MODULES.items():
        if backend is not None and name != backend:
            continue
        for module in modules:
            for t in importlib.import_module(module).TUNABLES.values():
                if op is None or t.op == op:
                    found.append(t)
    return found


# -- the problems the sweep times ----------------------------------------------------------------
def _rgbd_problem(op):
    def problem(device, size, params):
        """One ``op`` call on a particle-filter-like scene of ``size`` (:func:`~gputrack.sim.problems.pf_scene`),
        launched with ``params``."""
        from .ops import backend_module
        from .ops.template import RgbdScene
        from .sim.problems import pf_scene

        rng = np.random.default_rng(0)
        tf, rgb, dep, gray, depth, cam = pf_scene(rng, size["B"], size["N"], size["N"])
        tf_d, g, d = device.asarray(tf), device.asarray(gray), device.asarray(depth)
        scene = RgbdScene(rgb, dep, cam)  # the ops' defaults: lam 0.9, c_rgb 0.5/N, c_depth 5, depth_tol 0
        r, dd, c, consts = scene.kernel_args(device)
        p = {**consts, "params": dict(params)}
        mod = backend_module(device, "template")
        if op == "rgbd_cost":
            outs = tuple(device.empty((size["B"],), np.float32) for _ in range(3))
            return lambda: mod.rgbd_cost(device, tf_d, r, dd, g, d, c, *outs, **p)
        res = device.empty((size["B"], scene.n), np.float32)
        return lambda: mod.rgbd_residuals(device, tf_d, r, dd, g, d, c, res, **p)

    return problem


def _kalman_problem(device, size, params):
    """One fused constant-velocity predict+update (n = 6, m = 3) of size["T"] tracks
    (:func:`~gputrack.sim.problems.kalman_tracks`), in place, launched with ``params``."""
    from .ops import backend_module
    from .ops.kalman import _patterns, shared_matrix
    from .sim.problems import kalman_tracks

    F, Q, H, R, x0, P0, z, _det = kalman_tracks(int(size["T"]), np.random.default_rng(0))
    Fs, Qs, Hs, Rs = (shared_matrix(device, a) for a in (F, Q, H, R))
    x, P, zd = device.asarray(x0), device.asarray(P0), device.asarray(z)
    st = device.empty((x0.shape[0],), np.uint8)
    be = backend_module(device, "kalman")
    dims = {"T": x0.shape[0], "n": 6, "m": 3}
    pats = _patterns((Fs, Qs), Hs, Rs, dims)
    return lambda: be.kf_update(device, x, P, zd, Hs.array, Rs.array, None, None, Fs.array, Qs.array,
                                (x, P, st), pats, params=dict(params))  # fmt: skip


#: op -> problem(device, size, params): a zero-argument callable that runs the op once with
#: ``params`` on a problem of ``size`` (one of the tunable's ``sizes``)
PROBLEMS: dict[str, Callable] = {
    "rgbd_cost": _rgbd_problem("rgbd_cost"),
    "rgbd_residuals": _rgbd_problem("rgbd_residuals"),
    "kalman": _kalman_problem,
}


def problem_for(tunable: Tunable) -> Callable:
    """The problem builder the sweep times ``tunable`` on (:data:`PROBLEMS`)."""
    try:
        return PROBLEMS[tunable.op]
    except KeyError:
        raise ValueError(
            f"tunable {tunable.op!r} on {tunable.backend}: expected an op with a problem in gputrack.tuning.PROBLEMS "
            f"({', '.join(sorted(PROBLEMS))}), got none"
        ) from None


# -- the sweep -----------------------------------------------------------------------------------
@dataclasses.dataclass
class Trial:
    """One candidate's timing in :func:`tune` (``timing`` None and ``error`` set when it failed)."""

    params: dict
    timing: object = None
    error: str | None = None


#: a candidate replaces the default only when its confirmed median is this much lower
MIN_GAIN = 0.03


def _confirm(device, tunable, problem, size, ok, min_time, progress) -> dict:
    """Re-time the three fastest candidates and the default (a busy machine makes single medians
    noisy) and return the fastest; the default stays unless the winner beats it by MIN_GAIN."""
    from .benchmarks.harness import time_call

    default = tunable.default_for(device)
    ranked = sorted(ok, key=lambda t: t.timing.median_s)
    finalists = [t.params for t in ranked[:3]]
    if default not in finalists and any(t.params == default for t in ok):
        finalists.append(default)
    if len(finalists) == 1:
        return finalists[0]
    again = {}
    for params in finalists:
        t = time_call(problem(device, size, params), device.synchronize, min_time=min_time)
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
    problem: Callable | None = None,
    cache: TuningCache | None = None,
    min_time: float = 0.1,
    progress=None,
    report=None,
) -> dict:
    """Time every candidate for every size on ``device``; store and return {bucket: best params}.

    ``problem(device, size, params)`` returns a zero-argument callable that runs the op once
    with ``params`` (default: :data:`PROBLEMS` of the tunable's op). ``progress(message)`` is
    called after each candidate; ``report(size, trials, best)`` after
    each size with the :class:`Trial` list. The three fastest and the default are timed a second
    time (each keeps the lower of its two medians) and the default is kept unless the fastest
    beats it by :data:`MIN_GAIN`. A candidate that fails to build or launch (e.g. a
    work-group size the device does not support) is skipped; a size where every candidate fails
    stores nothing.
    """
    from .benchmarks.harness import time_call

    problem = problem or problem_for(tunable)
    cache = cache or default_cache()
    chosen = {}
    for size in tunable.sizes:
        trials = []
        for params in tunable.grid():
            try:
                fn = problem(device, size, params)
                trial = Trial(params, time_call(fn, device.synchronize, min_time=min_time))
                msg = f"{trial.timing.median_s * 1e3:.3f} ms"
            except Exception as e:  # noqa: BLE001 - a candidate the device cannot run
                trial = Trial(params, error=f"{type(e).__name__}: {e}".splitlines()[0][:200])
                msg = f"failed ({trial.error})"
            trials.append(trial)
            if progress:
                progress(f"{tunable.op} on {device.spec} {size_bucket(size)} {params}: {msg}")
        ok = [t for t in trials if t.timing is not None]
        best = _confirm(device, tunable, problem, size, ok, min_time, progress) if ok else None
        if best is not None:
            timings = {json.dumps(t.params, sort_keys=True): t.timing.median_s * 1e3 for t in ok}
            cache.put(device, tunable, size, best, timings)
            chosen[size_bucket(size)] = best
        if report:
            report(size, trials, best)
    cache.save()
    return chosen

"""The one owner of Taichi's process-global state.

Taichi can run one arch per process: ``ti.init`` for a second arch silently frees every field
and ndarray of the first. gputrack therefore initialises Taichi once, and asking for another
arch while a Taichi device is open raises :class:`TaichiArchConflict`. Closing the open device
(``Device.close()``) releases Taichi so that another arch can be started.

The arrays of the running program come from a caching allocator (:data:`pool`,
gputrack/pool.py): the memory of a garbage-collected array is kept, by dtype and shape, and
handed to the next array of that dtype and shape instead of allocating (and first touching)
new memory. Reuse is safe in Taichi's launch order: an array is given back only when nothing
references it, and its next user's kernels and copies run after every kernel launched before.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import io
import linecache
import logging
import math
import os
import re
import sys
import textwrap
import threading
import types
import warnings

import numpy as np

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")
import taichi as ti  # noqa: E402

from ...device import TaichiArchConflict, per_device  # noqa: E402
from ...pool import BufferPool, limit_from_env  # noqa: E402

log = logging.getLogger("gputrack")

ARCHS = {"cpu": ti.cpu, "vulkan": ti.vulkan, "cuda": ti.cuda}

#: the size of Taichi's offline cache of compiled kernels (~/.cache/taichi), above which it evicts
OFFLINE_CACHE_BYTES = 1 << 30  # Taichi holds it in a 32-bit int

_lock = threading.Lock()
_current: str | None = None
#: why every kernel goes through Taichi's public launch path in this process (read by launch.py), or None
direct_off: str | None = None
_generation = 0  # Taichi programs started and stopped by gputrack so far
_alive: dict = {}  # generation -> arrays of that program (from ndarray()) not yet freed
#: freed arrays of the running program, (Taichi dtype, shape) -> Taichi's array object (not its Python
#: wrapper); emptied when Taichi stops
pool = BufferPool(limit_from_env())


def cpu_threads() -> int:
    """Worker threads of Taichi's CPU thread pool: ``$GPUTRACK_CPU_THREADS``, else twice the CPUs
    this process may run on (a value that is not a positive integer: a RuntimeWarning naming it,
    and the default).

    Taichi's workers sleep between parallel loops. Where an idle core halts (virtual machines with
    cpuidle haltpoll, power-saving hosts), a loop that follows serial work often ran at one-thread
    speed because the second core's worker started late; with two workers per core the loops keep
    their speed. Body tracker frame, PF 3 stages + LM 10, taichi:cpu on a 2-vCPU VM (2026-11-24,
    medians of 80 frames): 2 threads 20.4-22.3 ms, 4 threads 15.5-17.7 ms (6: 18.3, 8: 17.0).
    """
    env = os.environ.get("GPUTRACK_CPU_THREADS")
    if env is not None:
        try:
            n = int(env)
        except ValueError:
            n = 0
        if n >= 1:
            return n
        warnings.warn(f"GPUTRACK_CPU_THREADS: expected a positive integer, got {env!r}; using the default "
                      "(twice the CPUs)", RuntimeWarning, stacklevel=2)  # fmt: skip
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    return 2 * max(1, cpus)


def current_arch() -> str | None:
    """The arch gputrack initialised Taichi with, or None."""
    return _current


#: loop passes one shader invocation may run in total on Mesa's llvmpipe (the compiler of lavapipe,
#: Vulkan on a CPU): gallivm's LP_MAX_TGSI_LOOP_ITERATIONS, one counter shared by every loop of the
#: shader and decremented at each pass. Past it every loop runs its body once and exits: the kernel
#: goes on with wrong numbers and no error. Each task (top-level loop) of a Taichi kernel is its own
#: shader; an invocation runs one item of its loop, or several past Taichi's grid-stride cap
#: (SPIRV_GRID_ITEMS items), and the lanes of one SIMD vector share the counter.
LLVMPIPE_LOOP_LIMIT = 65535
#: items of a parallel loop above which Taichi's SPIR-V tasks give an invocation several (grid-stride loop)
SPIRV_GRID_ITEMS = 131072


def loop_limit(device) -> int | None:
    """Loop passes one invocation of a kernel task may run on ``device``: LLVMPIPE_LOOP_LIMIT for
    taichi:vulkan on anything but a GPU (lavapipe), None where there is no such limit."""
    if device.spec == "taichi:vulkan" and device.info.kind != "gpu":
        return LLVMPIPE_LOOP_LIMIT
    return None


def _short_pos_info(self, node) -> str:
    """The debug position of an AST node as Taichi's frontend records it for every node: file, line,
    function and the source line (Taichi 1.7's own form also draws a caret hint under the span,
    wrapping both with textwrap: measured, that was 10 of the 18 s the frontend took to turn the body
    tracker's kernels into IR at its first frame on taichi:cpu, work that no kernel cache saves)."""
    src = self.src[node.lineno - 1] if 0 < node.lineno <= len(self.src) else ""
    return f'File "{self.file}", line {node.lineno + self.lineno_offset}, in {self.func.func.__name__}:\n{src}\n'


def _cached_source(lookup):
    """``lookup`` (Taichi's getsourcefile / getsourcelines) remembered per code object: Taichi's
    frontend looks a function's source up again at every call of it in a kernel (``inspect`` walks
    every loaded module and tokenises the file each time), and the source of a loaded function does
    not change. Lists come back as copies."""
    memo = {}

    def cached(obj):
        key = getattr(obj, "__code__", None)
        if key is None:
            return lookup(obj)
        hit = memo.get(key)
        if hit is None:
            hit = memo[key] = lookup(obj)
        if isinstance(hit, tuple) and isinstance(hit[0], list):
            return list(hit[0]), hit[1]
        return hit

    return cached


def _inside_class(level_of_class_stackframe):
    """Taichi's test whether a decorated kernel or function is defined in a class body (the
    statement of the frame ``level_of_class_stackframe`` up starts with ``class`` or
    ``@...data_oriented``), reading that one line through ``linecache`` where Taichi's own
    ``inspect.getframeinfo`` looks the whole module's source up (measured under cProfile: 1.3 s for
    the 246 definitions the body tracker's first frame imports)."""
    try:
        frame = sys._getframe(level_of_class_stackframe)
        line = linecache.getline(frame.f_code.co_filename, frame.f_lineno, frame.f_globals).strip()
    except Exception:  # noqa: BLE001 - no such frame or no line: not a class body, as Taichi's own test
        return False
    return line.startswith("class ") or re.match(r"@(\w+\.)?data_oriented", line) is not None


def _lighter_frontend() -> None:
    """Lighten Taichi's AST frontend, the work that turns a kernel into IR at its first launch in a
    process and that no kernel cache saves: :func:`_short_pos_info` for every node's debug position
    (error messages keep file, line and code), each function's source looked up once
    (:func:`_cached_source`) and each source line's ``textwrap.fill`` done once; and the class test
    of every definition (:func:`_inside_class`). Applied when this module is imported, before any
    kernel of the package is defined."""
    try:
        from taichi.lang import kernel_impl
        from taichi.lang.ast import checkers
        from taichi.lang.ast.ast_transformer_utils import ASTTransformerContext
    except ImportError:  # another Taichi layout: keep its own
        return
    if hasattr(ASTTransformerContext, "get_pos_info"):
        ASTTransformerContext.get_pos_info = _short_pos_info
    for module in (kernel_impl, checkers):
        for name in ("getsourcefile", "getsourcelines"):
            fn = getattr(module, name, None)
            if fn is not None and not hasattr(fn, "__wrapped_lookup__"):
                cached = _cached_source(fn)
                cached.__wrapped_lookup__ = fn
                setattr(module, name, cached)
    if callable(getattr(kernel_impl, "_inside_class", None)):
        kernel_impl._inside_class = _inside_class
    tw = getattr(kernel_impl, "textwrap", None)
    if tw is textwrap:  # the module itself: a copy whose fill remembers its lines
        kernel_impl.textwrap = types.SimpleNamespace(fill=functools.lru_cache(maxsize=65536)(textwrap.fill),
                                                     dedent=textwrap.dedent)


_lighter_frontend()


def start(arch: str) -> None:
    """Initialise Taichi on ``arch`` unless it already runs it; refuse a different arch.

    Raises RuntimeError (with Taichi's words) if the arch cannot start, e.g. no CUDA driver.
    """
    global _current, direct_off
    with _lock:
        if _current == arch:
            return
        if _current is not None:
            raise TaichiArchConflict(
                f"Taichi already runs on taichi:{_current} in this process and cannot also run taichi:{arch} "
                f"(re-initialising would free every Taichi array); close the taichi:{_current} device first "
                "or use another process"
            )
        if _stale_arrays() and direct_off is None:
            # arrays of a stopped program are still referenced: kernels launched directly (launch.py)
            # in the next program were seen to corrupt its arrays then (Taichi 1.7), Taichi's own
            # launches were not
            direct_off = "arrays of a stopped Taichi program are still alive"
            log.debug("taichi: direct kernel launches off (%s)", direct_off)
        options = {"cpu_max_num_threads": cpu_threads()} if arch == "cpu" else {}
        # Taichi's default cap of 100 MB is near what the package and its tests compile (68 MB for
        # one suite run from an empty cache, more as kernels change): past the cap its LRU policy
        # evicts a quarter, which the next start compiles again
        options["offline_cache_max_size_of_files"] = OFFLINE_CACHE_BYTES
        if arch == "cuda":
            # fast math on CUDA lets LLVM assume no NaN or inf (the kernels' finiteness checks would
            # fold away) and use approximate sqrt and division; multiply-adds are still contracted
            # (Taichi marks every CUDA function unsafe-fp-math), see tests/tolerances.py FUSES
            options["fast_math"] = False
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            ti.init(
                arch=ARCHS[arch],
                default_fp=ti.f32,
                default_ip=ti.i32,
                offline_cache=True,
                log_level=ti.ERROR,
                enable_fallback=False,
                **options,
            )
        log.debug("taichi: %s", out.getvalue().strip())
        got = ti.lang.impl.current_cfg().arch
        if ARCHS[arch] == ti.cpu:
            ok = got in (ti.x64, ti.arm64)
        else:
            ok = got == ARCHS[arch]
        if not ok:
            ti.reset()
            raise RuntimeError(f"Taichi started on {got.name} instead of {arch}")
        _current = arch


def _stale_arrays() -> bool:
    """Whether arrays of a stopped program are still referenced (garbage collected first)."""
    if not any(n > 0 for g, n in _alive.items() if g != _generation):
        return False
    gc.collect()
    return any(n > 0 for g, n in _alive.items() if g != _generation)


#: called by :func:`stop` before Taichi is reset: modules that keep objects of the running program
#: (launch.py's compiled kernels and the program they belong to) drop them there
_on_stop: list = []


def on_stop(drop) -> None:
    """Call ``drop()`` whenever Taichi is stopped, before the program goes."""
    _on_stop.append(drop)


def stop() -> None:
    """Release Taichi (every Taichi array becomes invalid).

    Nothing of the stopped program may outlive it: a Python reference to its program object (or to
    a kernel compiled by it) kept past ``ti.reset()`` destroys that program later, inside the next
    program's life, and the next program's kernels then crashed now and then (a segfault in a
    kernel launch, depending on where memory lay). So the holders drop theirs first (``on_stop``).
    """
    global _current, _generation
    with _lock:
        for drop in _on_stop:
            drop()
        empty_pool()
        _generation += 1  # arrays of the stopped program must not free memory of the next one
        if _current is not None:
            ti.reset()
            _current = None


def _release(arrays) -> None:
    """Free Taichi arrays of the running program (the pool's ``give``/``clear`` hand them back)."""
    if arrays:
        prog = ti.lang.impl.get_runtime().prog
        if prog is not None:
            for arr in arrays:
                prog.delete_ndarray(arr)


def empty_pool() -> None:
    """Free every array the pool holds."""
    _release(pool.clear())


def set_pool_limit(limit: int) -> None:
    _release(pool.set_limit(limit))


def ndarray(dtype, shape):
    """A new, uninitialised Taichi ndarray of ``dtype`` (a Taichi primitive type) and ``shape``
    (another element type, e.g. a ``ti.types.vector``, goes through ``ti.ndarray`` and not the
    pool).

    ``ti.ndarray`` zero-fills the memory and records the Python stack of its caller for Taichi's
    debug messages: 0.1-0.7 ms per array on a CPU (more under a deep stack), where the allocation
    itself takes about 0.01 ms. gputrack fills every array it allocates, so it allocates through
    Taichi's program object directly; if that internal interface is not there (another Taichi
    version), it falls back to ``ti.ndarray`` for the rest of the process.
    """
    global _fast_alloc
    shape = tuple(int(s) for s in shape)
    if dtype not in _ITEMSIZE:  # a vector or matrix element type: Taichi's own path, pool bypassed
        return ti.ndarray(dtype, shape)
    if _fast_alloc:
        try:
            nbytes = math.prod(shape) * _ITEMSIZE[dtype]
            arr = _Array.__new__(_Array)
            _Ndarray.__init__(arr)
            arr.dtype = dtype
            arr.arr = pool.take((dtype, shape), nbytes)
            if arr.arr is None:
                prog = ti.lang.impl.get_runtime().prog
                arr.arr = prog.create_ndarray(dtype, shape, layout=_Layout.NULL, zero_fill=False, dbg_info=_DebugInfo(""))
            arr._nbytes = nbytes
            arr._generation = _generation
            _alive[_generation] = _alive.get(_generation, 0) + 1
            arr.shape = tuple(arr.arr.shape)
            arr.element_type = dtype
            return arr
        except Exception as e:  # noqa: BLE001 - an interface change: use the public path from now on
            log.debug("taichi: fast ndarray allocation unavailable (%s); using ti.ndarray", e)
            _fast_alloc = False
    return ti.ndarray(dtype, shape)


def scratch(device, name: str, shape, dtype):
    """A scratch ndarray kept per device, ``name``, shape and dtype (the 64 most recently made,
    all dropped with the device; a dropped one goes back to the pool). Contents are undefined
    between calls."""
    return _scratch(device, name, tuple(int(s) for s in shape), dtype)


@per_device(maxsize=64)
def _scratch(device, name, shape, dtype):
    return ndarray(dtype, shape)


try:
    from taichi._lib import core as _core
    from taichi.lang._ndarray import Ndarray as _Ndarray
    from taichi.lang._ndarray import ScalarNdarray as _ScalarNdarray
    from taichi.lang.enums import Layout as _Layout

    _DebugInfo = _core.DebugInfo
    _fast_alloc = True

    class _Array(_ScalarNdarray):
        """A Taichi ndarray that gives its memory back to the pool (or frees it, past the pool's
        limit) only in the Taichi program that allocated it. (Taichi's own frees through the current program: an array that outlives a restart of
        Taichi, e.g. one kept by a closed device's caches, would free an array of the next one.
        The program is told by gputrack's count of stopped programs, not by a reference to it,
        which would keep the stopped program alive into the next one's life.)"""

        _impl = ti.lang.impl  # kept: module globals may be gone when the interpreter exits
        _runtime = sys.modules[__name__]

        def __del__(self):
            try:
                prog = self._impl.get_runtime().prog
                gen = getattr(self, "_generation", None)
                same = self._runtime._generation == gen
                self._runtime._alive[gen] -= 1
            except (AttributeError, TypeError, KeyError):  # Taichi is being torn down
                return
            if prog is not None and same:
                for arr in self._runtime.pool.give((self.dtype, self.shape), self.arr, getattr(self, "_nbytes", 0)):
                    prog.delete_ndarray(arr)  # past the pool's limit
except (ImportError, AttributeError):  # pragma: no cover - another Taichi version
    _fast_alloc = False


DTYPES = {
    "float32": ti.f32,
    "float64": ti.f64,
    "int32": ti.i32,
    "int64": ti.i64,
    "uint32": ti.u32,
    "uint8": ti.u8,
}
_ITEMSIZE = {t: np.dtype(name).itemsize for name, t in DTYPES.items()}
_BY_DTYPE = {}


def taichi_dtype(dtype):
    """The Taichi type of a NumPy dtype in DTYPES (memoised: ``np.dtype.name`` costs microseconds)."""
    found = _BY_DTYPE.get(dtype)
    if found is None:
        found = _BY_DTYPE[dtype] = DTYPES[np.dtype(dtype).name]
    return found

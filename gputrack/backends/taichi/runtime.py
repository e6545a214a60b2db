"""The one owner of Taichi's process-global state.

Taichi can run one arch per process: ``ti.init`` for a second arch silently frees every field
and ndarray of the first. gputrack therefore initialises Taichi once, and asking for another
arch while a Taichi device is open raises :class:`TaichiArchConflict`. Closing the open device
(``Device.close()``) releases Taichi so that another arch can be started.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import threading

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")
import taichi as ti  # noqa: E402

from ...device import TaichiArchConflict  # noqa: E402

log = logging.getLogger("gputrack")

ARCHS = {"cpu": ti.cpu, "vulkan": ti.vulkan, "cuda": ti.cuda}

_lock = threading.Lock()
_current: str | None = None


def current_arch() -> str | None:
    """The arch gputrack initialised Taichi with, or None."""
    return _current


def start(arch: str) -> None:
    """Initialise Taichi on ``arch`` unless it already runs it; refuse a different arch.

    Raises RuntimeError (with Taichi's words) if the arch cannot start, e.g. no CUDA driver.
    """
    global _current
    with _lock:
        if _current == arch:
            return
        if _current is not None:
            raise TaichiArchConflict(
                f"Taichi already runs on taichi:{_current} in this process and cannot also run taichi:{arch} "
                f"(re-initialising would free every Taichi array); close the taichi:{_current} device first "
                "or use another process"
            )
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            ti.init(
                arch=ARCHS[arch],
                default_fp=ti.f32,
                default_ip=ti.i32,
                offline_cache=True,
                log_level=ti.ERROR,
                enable_fallback=False,
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


def stop() -> None:
    """Release Taichi (every Taichi array becomes invalid)."""
    global _current
    with _lock:
        if _current is not None:
            ti.reset()
            _current = None


DTYPES = {
    "float32": ti.f32,
    "float64": ti.f64,
    "int32": ti.i32,
    "int64": ti.i64,
    "uint32": ti.u32,
    "uint8": ti.u8,
}

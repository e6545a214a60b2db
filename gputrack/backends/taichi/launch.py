"""Launching a compiled Taichi kernel with less Python per call.

``kernel(*args)`` spends most of a small kernel's launch time in Python: it builds the template
key from every argument, checks each argument's annotation and sets it through a generic
recursive setter. Measured on taichi:cpu (2 shared cores, 2026-11-23), with six ndarray arguments
and one template argument: ~38 us per call through ``kernel(...)``, ~13 us through
:func:`launch` (a new launch context, six ``set_arg_ndarray`` calls and the launch itself).

:func:`launch` takes the kernel's ndarray arguments (first in its signature, all of them) and its
template values (last, hashable) separately. The first call with a given kernel, template values
and dtypes and ranks of the arrays goes through ``kernel(...)``, which compiles and checks
everything, and remembers the compiled kernel; later calls launch it directly. Only calls whose
arrays are all Taichi ndarrays without gradients or C-contiguous NumPy arrays (passed by address,
as ``kernel(...)`` passes them) are remembered; others always go through ``kernel(...)``. A launch
context is not reused between launches (Taichi's LLVM launcher does not support that). A restarted
Taichi (another program object) empties the cache. If Taichi's internal interface is not what this
module expects (another Taichi version), every call goes through ``kernel(...)`` from then on.
"""

from __future__ import annotations

import logging

import numpy as np

from .runtime import ti

log = logging.getLogger("gputrack")


def _direct(a) -> bool:
    """``a`` can be passed by :func:`launch` itself: a Taichi ndarray without gradient, or a
    C-contiguous NumPy array (which Taichi reads and writes in place on the CPU arch)."""
    if type(a) is np.ndarray:
        return a.flags.c_contiguous
    return isinstance(a, ti.lang._ndarray.Ndarray) and a.grad is None


_cache: dict = {}  # (kernel, templates, (dtype, rank) of each array) -> (kernel, compiled, program)
_enabled = True


def launch(kernel, arrays: tuple, templates: tuple = ()) -> None:
    """``kernel(*arrays, *templates)`` for a kernel whose arguments are Taichi ndarrays, then templates."""
    global _enabled
    if _enabled:
        key = (kernel, templates, *((a.dtype, len(a.shape)) for a in arrays))
        hit = _cache.get(key)
        if hit is not None:
            tk, ckd, prog = hit
            if prog is not ti.lang.impl.get_runtime().prog:  # Taichi was restarted: compile again
                _cache.clear()
            else:
                ctx = tk.make_launch_context()
                for i, a in enumerate(arrays):
                    if type(a) is np.ndarray:
                        if not a.flags.c_contiguous:
                            break
                        ctx.set_arg_external_array_with_shape((i,), a.ctypes.data, a.nbytes, a.shape, 0)
                    else:
                        ctx.set_arg_ndarray((i,), a.arr)
                else:
                    prog.launch_kernel(ckd, ctx)
                    return
    kernel(*arrays, *templates)
    if _enabled and all(_direct(a) for a in arrays):
        try:
            primal = kernel._primal
            tk = primal.compiled_kernels[primal.ensure_compiled(*arrays, *templates)]
            prog = ti.lang.impl.get_runtime().prog
            _cache[key] = (tk, prog.compile_kernel(prog.config(), prog.get_device_caps(), tk), prog)
        except Exception as e:  # noqa: BLE001 - another Taichi: the public call path from now on
            log.debug("taichi: direct kernel launch unavailable (%s); using kernel(...)", e)
            _enabled = False

"""Launching a compiled Taichi kernel with less Python per call.

``kernel(*args)`` spends most of a small kernel's launch time in Python: it builds the template
key from every argument, checks each argument's annotation and sets it through a generic
recursive setter. Measured on taichi:cpu (2 shared cores, 2026-11-23), with six ndarray arguments
and one template argument: ~38 us per call through ``kernel(...)``, ~13 us through
:func:`launch` (a new launch context, six ``set_arg_ndarray`` calls and the launch itself).

:func:`launch` takes the kernel's array arguments (first in its signature, all of them), its
Python int/float scalars (next) and its template values (last, hashable) separately. The first
call with a given kernel, template values, dtypes and ranks of the arrays and types of the scalars
goes through ``kernel(...)``, which compiles and checks everything, and remembers the compiled
kernel; later calls launch it directly. Only calls whose
arrays are all Taichi ndarrays without gradients or C-contiguous NumPy arrays (passed by address,
as ``kernel(...)`` passes them, with the shape of the array without its element's dimensions where
the kernel's annotation gives the elements a vector type) are remembered; others always go through
``kernel(...)``. A launch
context is not reused between launches (Taichi's LLVM launcher does not support that). gputrack's stop of
Taichi (runtime.stop) empties the cache before the program goes, and a program restarted elsewhere is
noticed at the next call (another program object empties the cache). A program started while arrays of the stopped program
are still referenced turns direct launches off for the process (``runtime.direct_off``: kernels
launched directly then were seen to overwrite the new program's arrays; ``kernel(...)`` did not). If Taichi's internal
interface is not what this module expects (another Taichi version), every call goes through
``kernel(...)`` from then on.
"""

from __future__ import annotations

import ctypes
import logging

import numpy as np

from . import runtime
from .runtime import ti

log = logging.getLogger("gputrack")


def _direct(a) -> bool:
    """``a`` can be passed by :func:`launch` itself: a Taichi ndarray without gradient, or a
    C-contiguous NumPy array (which Taichi reads and writes in place on the CPU arch)."""
    if type(a) is np.ndarray:
        return a.flags.c_contiguous
    return isinstance(a, ti.lang._ndarray.Ndarray) and a.grad is None


# (kernel, templates, scalarize, kinds of the arguments) -> (kernel, compiled, program, element dims)
_cache: dict = {}
_enabled = True
runtime.on_stop(_cache.clear)  # the program and its compiled kernels go with it, not in the next one's life


def disable_direct(why: str) -> None:
    """Launch every kernel through ``kernel(...)`` from now on in this process."""
    global _enabled
    if _enabled:
        log.debug("taichi: direct kernel launches off (%s)", why)
    _enabled = False
    _cache.clear()


def address(a: np.ndarray) -> int:
    """The address of a C-contiguous NumPy array's data: through ctypes' view of a writable buffer
    (~0.4 us), else ``a.ctypes.data`` (~1.1-2.2 us: it builds a helper object each time)."""
    try:
        return ctypes.addressof(ctypes.c_char.from_buffer(a))
    except (TypeError, ValueError):  # read-only, or empty
        return a.ctypes.data


def _element_dims(annotation) -> int:
    """The dimensions of an array argument's element (1 for an ndarray of vectors, 0 for scalars)."""
    dtype = getattr(annotation, "dtype", None)
    return 0 if dtype is None or id(dtype) in ti.types.primitive_types.type_ids else int(dtype.ndim)


def _kind(a):
    """What the cache key needs of an argument: dtype and rank of an array, the type of a scalar."""
    return (a.dtype, len(a.shape)) if hasattr(a, "shape") else type(a)


def launch(
    kernel, arrays: tuple, templates: tuple = (), *, scalars: tuple = (), scalarize: bool = True, ir_passes: bool = True
) -> None:
    """``kernel(*arrays, *scalars, *templates)``: arrays (Taichi ndarrays or NumPy arrays) first in
    the kernel's signature, then Python int/float scalars, then template values (hashable).

    ``scalarize=False`` compiles the kernel with Taichi's ``real_matrix_scalarize`` off on the CPU
    archs, so that LLVM keeps ``ti.types.vector`` values as SIMD vectors (the Kalman kernels' track
    lanes, the template kernels' hypothesis lanes, forward kinematics, which must round as the
    fused kernels that pose through it); elsewhere, and for every other kernel, Taichi's default
    applies.

    ``ir_passes=False`` compiles the kernel without Taichi's own optimisation of its IR
    (``advanced_optimization``: common subexpressions, loop-invariant code, store forwarding over the
    whole kernel) on the CPU archs; LLVM's -O3 pipeline, which does the same work, still runs. Those
    passes grow faster than the kernel: for the body tracker's five largest kernels they took most
    of a fresh install's first frame (perf/first_frame.py: 25.7 -> 12.6 s from empty caches on a
    2-core AMD EPYC), and the frames with and without them took the same time; the face bundle's
    ``_landmarks`` uses it too (8.3-8.6 -> 2.9-3.8 s from empty caches, 4 us more a call). A
    warm process reads the compiled kernel from the offline cache, so it is not affected either way.
    """
    global _enabled
    key = None
    if _enabled and runtime.direct_off is None:
        key = (kernel, templates, scalarize, ir_passes, *(_kind(a) for a in arrays), *(type(c) for c in scalars))
        hit = _cache.get(key)
        if hit is not None:
            tk, ckd, prog, edims = hit
            if prog is not ti.lang.impl.get_runtime().prog:  # Taichi was restarted: compile again
                _cache.clear()
            else:
                ctx = tk.make_launch_context()  # a fresh one: a launch rewrites its array arguments
                for i, a in enumerate(arrays):
                    if type(a) is np.ndarray:
                        if not a.flags.c_contiguous:
                            break
                        shape = a.shape[: a.ndim - edims[i]]  # Taichi takes the shape without the element's
                        ctx.set_arg_external_array_with_shape((i,), address(a), a.nbytes, shape, 0)
                    else:
                        ctx.set_arg_ndarray((i,), a.arr)
                else:
                    for j, c in enumerate(scalars, len(arrays)):
                        (ctx.set_arg_int if type(c) is int else ctx.set_arg_float)((j,), c)
                    prog.launch_kernel(ckd, ctx)
                    return
    args = (*arrays, *scalars, *templates)
    cfg = ti.lang.impl.current_cfg()
    cpu = cfg.arch in (ti.x64, ti.arm64)
    vector_lanes = not scalarize and cpu
    plain = not ir_passes and cpu and cfg.advanced_optimization
    if vector_lanes:
        cfg.real_matrix_scalarize = False
    if plain:
        cfg.advanced_optimization = False
    try:
        kernel(*args)
        if key is not None and all(_direct(a) for a in arrays) and all(type(c) in (int, float) for c in scalars):
            try:
                primal = kernel._primal
                tk = primal.compiled_kernels[primal.ensure_compiled(*args)]
                prog = ti.lang.impl.get_runtime().prog
                edims = tuple(_element_dims(primal.arguments[i].annotation) for i in range(len(arrays)))
                _cache[key] = (tk, prog.compile_kernel(prog.config(), prog.get_device_caps(), tk), prog, edims)
            except Exception as e:  # noqa: BLE001 - another Taichi: the public call path from now on
                log.debug("taichi: direct kernel launch unavailable (%s); using kernel(...)", e)
                _enabled = False
    finally:
        if vector_lanes:
            cfg.real_matrix_scalarize = True
        if plain:
            cfg.advanced_optimization = True

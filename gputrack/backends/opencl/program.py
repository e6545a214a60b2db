"""Locate the OpenCL C sources in ``kernels/`` and build them once per device and options.

Every build gets the codes and slots of gputrack/abi.py as ``-D`` defines (:func:`build_options`):
the sources hold no copy of them.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np

from ...abi import cl_defines
from ...device import per_device

_HERE = Path(__file__).resolve()


@functools.cache
def kernel_dir() -> Path:
    """The folder holding the ``.cl`` sources: inside the installed package, or the repo's ``kernels/``."""
    for candidate in (_HERE.parents[2] / "kernels", _HERE.parents[3] / "kernels"):
        if candidate.is_dir() and any(candidate.glob("*.cl")):
            return candidate
    raise FileNotFoundError(
        f"expected OpenCL kernel sources in {_HERE.parents[2] / 'kernels'} (installed) or "
        f"{_HERE.parents[3] / 'kernels'} (source tree), found none"
    )


class KernelSource(os.PathLike):
    """The path of ``kernels/<name>``, found when it is used (``os.fspath``): a tunable's
    ``sources`` name their kernel files with it without looking for the folder at import."""

    def __init__(self, name: str):
        self.name = name

    def __fspath__(self) -> str:
        return str(kernel_dir() / self.name)

    def __repr__(self) -> str:
        return f"KernelSource({self.name!r})"


def source(name: str) -> KernelSource:
    """``kernels/<name>`` as a path found when used (see :class:`KernelSource`)."""
    return KernelSource(name)


def kernel_files() -> list[Path]:
    """Every ``.cl`` file shipped with gputrack."""
    return sorted(kernel_dir().glob("*.cl"))


def build_options(defines=()) -> list[str]:
    """The options of every build: the include path, the ABI defines, then ``defines`` (pairs)."""
    abi = [f"-D{k}={v}" for k, v in cl_defines().items()]
    return [f"-I{kernel_dir()}", *abi, *(f"-D{k}={v}" for k, v in defines)]


def build(device, source_name: str, defines: dict | None = None):
    """Build ``kernels/<source_name>`` for ``device`` (memoised per device and defines);
    ``defines`` become -D options."""
    return _build(device, source_name, tuple(sorted((defines or {}).items())))


@per_device
def _build(device, source_name: str, defines: tuple):
    import pyopencl as cl

    path = kernel_dir() / source_name
    if not path.is_file():
        raise FileNotFoundError(f"expected an OpenCL source {path}, found none")
    options = build_options(defines)
    try:
        return cl.Program(device.context, path.read_text()).build(options=options)
    except cl.RuntimeError as e:
        raise RuntimeError(f"building {source_name} failed on {device.cl_device.name}: {e}") from None


#: Work-group shapes of :func:`ndrange` by dimensions.
GROUP = {1: (64,), 2: (8, 8)}


def ndrange(*sizes: int, group: tuple[int, ...] | None = None) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The NDRange over ``sizes`` work-items padded to whole work-groups of a fixed shape, and that
    shape, for kernels that skip the work-items past ``sizes``. Left to choose (local size None),
    PoCL made a range of a few thousand items one work-group, run by one thread, and built a new
    kernel variant for every new range (0.5-1 s each: every new number of tracks, samples or rows)."""
    group = group or GROUP[len(sizes)]
    if len(group) != len(sizes):
        raise ValueError(f"group: expected {len(sizes)} dimensions, got {group}")
    return tuple(max(-(-int(n) // g), 1) * g for n, g in zip(sizes, group)), tuple(group)


@per_device
def _last_args(device) -> dict:
    """cl.Kernel -> the arguments it was last given on ``device``."""
    return {}


def scalar_types(kernel, dtypes) -> None:
    """``kernel.set_scalar_arg_dtypes(dtypes)``, remembered on the kernel for :func:`enqueue` (which
    sets a changed Python scalar argument alone with its type)."""
    kernel.set_scalar_arg_dtypes(dtypes)
    kernel.gt_scalar_dtypes = tuple(dtypes)


def enqueue(device, kernel, gsize, lsize, *args):
    """Launch ``kernel`` on the device's queue, setting only the arguments that differ from its last
    launch (buffers by handle, scalars by value), one ``set_arg`` each: PyOpenCL's ``kernel(queue,
    ...)`` and ``set_args`` set every argument, 50-90 us a launch on PoCL here (83 us for the LM
    update's 13) against ~8 us for the launch itself. Scalars are typed as :func:`scalar_types`
    says, or must be NumPy scalars. Returns the launch's event."""
    import pyopencl as cl

    seen = _last_args(device)
    last = seen.get(kernel)
    if last is None or len(last) != len(args):
        kernel.set_args(*args)
    else:
        changed = [i for i, (a, b) in enumerate(zip(args, last)) if a is not b and a != b]
        if changed:
            _set_changed(kernel, args, changed)
    seen[kernel] = args
    return cl.enqueue_nd_range_kernel(device.queue, kernel, gsize, lsize)


def _set_changed(kernel, args, changed) -> None:
    """Arguments ``changed`` (indices) of ``args`` into ``kernel``, one by one; a Python scalar takes
    its type from the kernel's scalar dtypes (all of them set at once where it has none)."""
    dtypes = getattr(kernel, "gt_scalar_dtypes", ())
    values = []
    for i in changed:
        a = args[i]
        if isinstance(a, (bool, int, float)) and not isinstance(a, np.generic):
            dt = dtypes[i] if i < len(dtypes) else None
            if dt is None:
                kernel.set_args(*args)
                return
            a = np.dtype(dt).type(a)
        values.append((i, a))
    for i, a in values:
        kernel.set_arg(i, a)

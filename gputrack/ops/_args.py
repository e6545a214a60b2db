"""Validation of op arguments at the public boundary, shared by every op.

``arg`` checks one array argument (type, device, dtype, shape against named dimensions, finite
values) and returns it on the op's device: a NumPy array for the ``numpy`` device, else a
DeviceArray (uploading a NumPy input, which the device counts as a transfer). Messages read
"<name>: expected X, got Y". Finiteness is checked for host (NumPy) inputs; arrays already on a
device are trusted, since checking them would cost a download.

Checks run cheapest first and never copy more than the input holds: type and dtype, then the shape
(before any conversion, so a wrong-shaped broadcast view of 2**32 rows is rejected at once), then
whether the device can hold the array (:meth:`gputrack.Device.check_alloc`), then the values
(finiteness over the memory the view really reads), then the upload.
"""

from __future__ import annotations

import math
import numbers

import numpy as np

from ..device import Device, DeviceArray, as_host_array, foreign_array_error

FLOAT = (np.dtype(np.float32), np.dtype(np.float64))


def real(name: str, value, *, low=None, high=None, positive: bool = False, allow_inf: bool = False) -> float:
    """A scalar argument as a float, checked: a real number (not a bool), finite unless
    ``allow_inf``, > 0 with ``positive``, in [low, high] where given. Messages "<name>: expected X,
    got Y", Y the value as given."""
    if isinstance(value, bool) or not isinstance(value, (numbers.Real, np.integer, np.floating)):
        raise TypeError(f"{name}: expected a real number, got {type(value).__name__}")
    v = float(value)
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise ValueError(f"{name}: expected a finite number, got {value}")
    if positive and not v > 0:
        raise ValueError(f"{name}: expected a number > 0, got {value}")
    if (low is not None and v < low) or (high is not None and v > high):
        if low is not None and high is not None:
            want = f"in [{low}, {high}]"
        else:
            want = f">= {low}" if low is not None else f"<= {high}"
        raise ValueError(f"{name}: expected a number {want}, got {value}")
    return v


def _fmt_shape(spec, dims) -> str:
    parts = []
    for s in spec:
        if isinstance(s, str) and s in dims:
            parts.append(f"{s}={dims[s]}")
        else:
            parts.append(str(s))
    return "(" + ", ".join(parts) + ")"


def shape_of(x, name: str) -> tuple:
    """The shape ``x`` (an array, a DeviceArray or a nested sequence) has as an array, without
    copying an array; a ragged sequence raises "expected a rectangular array"."""
    shape = getattr(x, "shape", None)
    if isinstance(shape, tuple):
        return shape
    if x is None:
        raise TypeError(f"{name}: expected an array, got None")
    return as_host_array(x, name).shape


def check_shapes(dims: dict, *args) -> None:
    """Check the shapes of several arguments, ``(x, name, spec)`` each, before any of them is
    converted or its values checked, binding dimension names in ``dims`` (see match_shape). An op
    calls it first so that a wrong shape is reported before the work of validating the others
    (a ``None`` argument is skipped)."""
    for x, name, spec in args:
        if x is not None:
            match_shape(name, shape_of(x, name), spec, dims)


def compact(x: np.ndarray) -> np.ndarray:
    """The part of ``x`` its memory holds: index 0 of every axis of stride 0 (a broadcast view is
    as finite as the array it repeats), so a value check reads each element once."""
    if x.ndim and 0 in x.strides and x.size:
        return x[tuple(slice(0, 1) if st == 0 else slice(None) for st in x.strides)]
    return x


def real_array(value, name: str) -> np.ndarray:
    """``value`` as a NumPy array of real numbers (bool, integer or float), else TypeError naming
    its dtype (complex and object arrays are rejected, not silently converted)."""
    a = as_host_array(value, name)
    if a.dtype.kind not in "biuf":
        raise TypeError(f"{name}: expected real numbers, got dtype {a.dtype.name}")
    return a


def check_device(device) -> Device:
    if not isinstance(device, Device):
        raise TypeError(f"expected a gputrack.Device (from gputrack.device(spec)), got {type(device).__name__}")
    device._check_open()
    return device


def match_shape(name: str, shape: tuple, spec: tuple, dims: dict) -> None:
    """Check ``shape`` against ``spec`` (ints, dimension names or None for any), binding names in ``dims``."""
    if len(shape) != len(spec):
        raise ValueError(f"{name}: expected shape {_fmt_shape(spec, dims)}, got {tuple(shape)}")
    for got, want in zip(shape, spec):
        if want is None:
            continue
        if isinstance(want, str):
            if want not in dims:
                dims[want] = got
                continue
            want_n = dims[want]
        else:
            want_n = want
        if got != want_n:
            raise ValueError(f"{name}: expected shape {_fmt_shape(spec, dims)}, got {tuple(shape)}")


_ACCEPTED: dict = {}


def _accepted(dtype) -> tuple:
    """The accepted NumPy dtypes of ``arg``'s ``dtype`` (one dtype or a tuple), memoised: an op's
    arguments are checked on every call."""
    key = tuple(dtype) if isinstance(dtype, (tuple, list)) else dtype
    found = _ACCEPTED.get(key)
    if found is None:
        found = _ACCEPTED[key] = tuple(np.dtype(d) for d in (key if isinstance(key, tuple) else (key,)))
    return found


def _names(accepted) -> str:
    return " or ".join(d.name for d in accepted)


def arg(
    device: Device,
    x,
    name: str,
    shape: tuple | None = None,
    dims: dict | None = None,
    *,
    dtype=np.float32,
    finite: bool = True,
    cast: bool = False,
):
    """Validate array argument ``x`` of an op and return it on ``device``.

    ``dtype`` is one dtype or a tuple of accepted dtypes; a NumPy input of another dtype raises
    TypeError unless ``cast`` (then it is converted to the first accepted dtype). Python lists
    and scalars are converted to the first accepted dtype.
    """
    accepted = _accepted(dtype)
    if isinstance(x, DeviceArray):
        if x.device is not device:
            raise foreign_array_error(x, device, name)
        if x.dtype not in accepted:
            raise TypeError(f"{name}: expected dtype {_names(accepted)}, got {x.dtype.name}")
        if shape is not None:
            match_shape(name, x.shape, shape, dims if dims is not None else {})
        return x
    want = None  # the dtype to convert to, if any
    if not isinstance(x, np.ndarray):
        if x is None:
            raise TypeError(f"{name}: expected an array, got None")
        x = as_host_array(x, name)
        if x.dtype.kind in "biuf":
            want = accepted[0]  # lists and scalars: the first accepted dtype
    if want is None and x.dtype not in accepted:
        if cast and x.dtype.kind in "biuf":
            want = accepted[0]
        else:
            raise TypeError(f"{name}: expected dtype {_names(accepted)}, got {x.dtype.name}")
    if shape is not None:
        match_shape(name, x.shape, shape, dims if dims is not None else {})
    want = x.dtype if want is None else want
    if want != x.dtype or not x.flags.c_contiguous:
        device.check_alloc(x.shape, want)  # before the copy
    if want != x.dtype:
        x = x.astype(want)
    if finite and x.dtype.kind == "f":
        c = compact(x)
        if not np.isfinite(c).all():
            bad = tuple(int(i) for i in np.argwhere(~np.isfinite(c))[0])
            raise ValueError(f"{name}: expected finite values, got {c[bad]} at index {bad}")
    if device.backend == "numpy":
        return np.ascontiguousarray(x)
    return device.asarray(x)


def out_array(device, out, name: str, shape: tuple, dtype=np.float32):
    """Check a caller-supplied output array of an op (written in place), or allocate one."""
    if out is None:
        return device.empty(shape, dtype)
    if isinstance(out, DeviceArray) and out.device is not device and out.device.closed:
        raise foreign_array_error(out, device, name)
    if device.backend == "numpy":
        ok = isinstance(out, np.ndarray) and out.flags.c_contiguous and out.flags.writeable
    else:
        ok = isinstance(out, DeviceArray) and out.device is device
    if not ok:
        got = f"an array on {out.device.spec}" if isinstance(out, DeviceArray) else type(out).__name__
        raise TypeError(f"{name}: expected a writable array on {device.spec} (e.g. from an earlier call), got {got}")
    if tuple(out.shape) != tuple(shape) or out.dtype != dtype:
        raise ValueError(
            f"{name}: expected a {np.dtype(dtype).name} array of shape {tuple(shape)}, "
            f"got {out.dtype.name} {tuple(out.shape)}"
        )
    return out


def out_arrays(device, out, specs, *, allocate: bool = True):
    """Check a caller-supplied tuple of output arrays of an op, ``specs`` = ((name, shape, dtype),
    ...), each as :func:`out_array` does ("out <name>: ..."); ``out=None``: allocate them (or, with
    ``allocate=False``, return None)."""
    if out is None:
        return tuple(device.empty(shape, dtype) for _, shape, dtype in specs) if allocate else None
    if not isinstance(out, (tuple, list)) or len(out) != len(specs):
        names = ", ".join(name for name, _, _ in specs)
        raise TypeError(f"out: expected a tuple of {len(specs)} arrays ({names}) or None, got {type(out).__name__}")
    return tuple(out_array(device, a, f"out {name}", shape, dtype) for a, (name, shape, dtype) in zip(out, specs))

"""Validation of op arguments at the public boundary, shared by every op.

``arg`` checks one array argument (type, device, dtype, shape against named dimensions, finite
values) and returns it on the op's device: a NumPy array for the ``numpy`` device, else a
DeviceArray (uploading a NumPy input, which the device counts as a transfer). Messages read
"<name>: expected X, got Y". Finiteness is checked for host (NumPy) inputs; arrays already on a
device are trusted, since checking them would cost a download.
"""

from __future__ import annotations

import numpy as np

from ..device import Device, DeviceArray

FLOAT = (np.dtype(np.float32), np.dtype(np.float64))


def _fmt_shape(spec, dims) -> str:
    parts = []
    for s in spec:
        if isinstance(s, str) and s in dims:
            parts.append(f"{s}={dims[s]}")
        else:
            parts.append(str(s))
    return "(" + ", ".join(parts) + ")"


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
            raise ValueError(f"{name}: expected an array on {device.spec} or a NumPy array, got an array on {x.device.spec}")
        if x.dtype not in accepted:
            raise TypeError(f"{name}: expected dtype {_names(accepted)}, got {x.dtype.name}")
        if shape is not None:
            match_shape(name, x.shape, shape, dims if dims is not None else {})
        return x
    if not isinstance(x, np.ndarray):
        if x is None:
            raise TypeError(f"{name}: expected an array, got None")
        x = np.asarray(x)
        if x.dtype.kind in "biuf":
            x = x.astype(accepted[0])
    if x.dtype not in accepted:
        if cast and x.dtype.kind in "biuf":
            x = x.astype(accepted[0])
        else:
            raise TypeError(f"{name}: expected dtype {_names(accepted)}, got {x.dtype.name}")
    if shape is not None:
        match_shape(name, x.shape, shape, dims if dims is not None else {})
    if finite and x.dtype.kind == "f" and not np.isfinite(x).all():
        bad = np.argwhere(~np.isfinite(x))[0]
        raise ValueError(f"{name}: expected finite values, got {x[tuple(bad)]} at index {tuple(int(i) for i in bad)}")
    if device.backend == "numpy":
        return np.ascontiguousarray(x)
    return device.asarray(x)


def out_array(device, out, name: str, shape: tuple, dtype=np.float32):
    """Check a caller-supplied output array of an op (written in place), or allocate one."""
    if out is None:
        return device.empty(shape, dtype)
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

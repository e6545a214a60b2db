"""OpenCL devices (``opencl`` and ``opencl:<name>``): probing, selection and arrays."""

from __future__ import annotations

import math
import os
import re

import numpy as np

from ...device import Device, DeviceInfo, unavailable

_TRIVIAL = """
__kernel void gt_probe(__global float *y) { const int i = get_global_id(0); y[i] = 2.0f * y[i] + 1.0f; }
"""


def _slug(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


#: PoCL settings gputrack gives where the process has none (read when PoCL starts, at the first
#: platform query): its CPU driver's worker threads bound to one core each. A kernel that follows
#: host work (an LM iteration after the residual callables, a face frame's stages) then started and
#: ran on a worker whose core kept its place: on the 2-vCPU VM (2026-12-06, one process alternating
#: both settings, or runs in turn) the exp fit's whole solve of perf/bench_lm.py 4.63 / 4.76 -> 4.00
#: ms (the Taichi solve in the same process 4.14 / 4.17 -> 4.34 ms), the face tracker's frame 6.74 /
#: 6.29 -> 5.43 / 5.52 ms; the body frame within the noise (17.1-20.0 against 14.5-22.9 ms).
#: ``POCL_AFFINITY=0`` in the environment keeps PoCL's default.
POCL_DEFAULTS = {"POCL_AFFINITY": "1"}


def _enumerate():
    """[(spec, platform, device)] for every OpenCL device, or raise with the reason there are none."""
    import pyopencl as cl

    for name, value in POCL_DEFAULTS.items():
        os.environ.setdefault(name, value)
    try:
        platforms = cl.get_platforms()
    except cl.Error as e:
        raise RuntimeError(f"no OpenCL platform ({' '.join(str(e).split())}); install an ICD such as pocl-opencl-icd") from None
    found, seen = [], {}
    for p in platforms:
        try:
            devs = p.get_devices()
        except cl.Error:
            continue
        for d in devs:
            base = _slug(d.name) or "device"
            seen[base] = seen.get(base, -1) + 1
            spec = f"opencl:{base}" + (f"-{seen[base]}" if seen[base] else "")
            found.append((spec, p, d))
    return found


def _test(dev) -> str:
    """Build and run a trivial kernel; '' if it works, else the reason (one line)."""
    import pyopencl as cl

    try:
        ctx = cl.Context([dev])
        queue = cl.CommandQueue(ctx)
        prg = cl.Program(ctx, _TRIVIAL).build()
        host = np.arange(16, dtype=np.float32)
        buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=host)
        prg.gt_probe(queue, (16,), None, buf)
        out = np.empty_like(host)
        cl.enqueue_copy(queue, out, buf)
        queue.finish()
    except Exception as e:  # noqa: BLE001 - the reason is reported
        msg = " ".join(str(e).split())
        return f"cannot build or run a trivial kernel: {msg[:300]}"
    if not np.array_equal(out, 2 * host + 1):
        return "a trivial kernel gave wrong results"
    return ""


def _kind(dev) -> str:
    import pyopencl as cl

    if dev.type & cl.device_type.GPU:
        return "gpu"
    if dev.type & cl.device_type.CPU:
        return "cpu"
    return "other"


def _info(spec, platform, dev, reason) -> DeviceInfo:
    return DeviceInfo(
        spec,
        "opencl",
        not reason,
        name=f"{dev.name} ({platform.name})",
        reason=reason,
        fp64=bool(dev.double_fp_config),
        kind=_kind(dev),
        max_work_group_size=int(dev.max_work_group_size),
        driver=f"{platform.version} / {dev.driver_version}",
    )


def probe_opencl() -> list[DeviceInfo]:
    """``opencl`` (the best working device) plus one ``opencl:<name>`` per device found."""
    try:
        import pyopencl  # noqa: F401
    except ImportError as e:
        return [DeviceInfo("opencl", "opencl", False, reason=f"pyopencl is not installed ({e})")]
    try:
        found = _enumerate()
    except RuntimeError as e:
        return [DeviceInfo("opencl", "opencl", False, reason=str(e))]
    infos = [_info(spec, p, d, _test(d)) for spec, p, d in found]
    working = sorted((i for i in infos if i.available), key=lambda i: i.kind != "gpu")
    if working:
        best = working[0]
        default = DeviceInfo(**{**best.as_dict(), "spec": "opencl"})
    elif infos:
        default = DeviceInfo("opencl", "opencl", False, reason=f"no working OpenCL device ({infos[0].reason})")
    else:
        default = DeviceInfo("opencl", "opencl", False, reason="no OpenCL device found; install an ICD such as pocl-opencl-icd")
    return [default, *infos]


def open_opencl(selector: str) -> "OpenCLDevice":
    """The OpenCL device matching ``selector`` ('' = the best working device)."""
    spec = f"opencl:{selector}" if selector else "opencl"
    try:
        import pyopencl  # noqa: F401
    except ImportError as e:
        raise unavailable(spec, f"pyopencl is not installed ({e})") from None
    try:
        found = _enumerate()
    except RuntimeError as e:
        raise unavailable(spec, str(e)) from None
    key = selector.lower()
    if key:
        matches = [
            (s, p, d) for s, p, d in found if key == s[7:] or key in s[7:] or key in d.name.lower() or key in p.name.lower()
        ]
        if not matches:
            raise unavailable(spec, f"no OpenCL device matches {selector!r} (found: {', '.join(s for s, _, _ in found) or 'none'})")
    else:
        matches = sorted(found, key=lambda f: _kind(f[2]) != "gpu")
    reasons = []
    for s, p, d in matches:
        reason = _test(d)
        if not reason:
            info = _info(s if key else "opencl", p, d, "")
            return OpenCLDevice(info, d)
        reasons.append(f"{s}: {reason}")
    raise unavailable(spec, "; ".join(reasons) or "no OpenCL device found")


_STRIDES: dict = {}


def _strides(shape: tuple, itemsize: int) -> tuple:
    """C-contiguous strides, as PyOpenCL computes them (memoised: a handful of shapes recur)."""
    key = (shape, itemsize)
    found = _STRIDES.get(key)
    if found is None:
        acc, out = itemsize, []
        for s in reversed(shape):
            out.append(acc)
            acc *= max(1, s)
        found = _STRIDES[key] = tuple(reversed(out))
        if len(_STRIDES) > 4096:
            _STRIDES.clear()
    return found


class OpenCLDevice(Device):
    """Arrays are ``pyopencl.array.Array`` objects on one context and in-order queue.

    Their buffers come from PyOpenCL's caching allocator (``pyopencl.tools.MemoryPool``): the
    buffer of a garbage-collected array is kept and reused for the next array of the same size
    bin. Safe on the in-order queue: the commands of the buffer's next user are enqueued after
    every command that used it before (gputrack/pool.py). Past ``pool_limit`` bytes of freed
    buffers the pool releases them all at the next allocation. An array is at most
    CL_DEVICE_MAX_MEM_ALLOC_SIZE bytes and 2**31 - 1 elements (:meth:`Device.check_alloc`).
    """

    backend = "opencl"
    max_elements = 2**31 - 1
    max_elements_reason = "the kernels index arrays with 32-bit integers"

    def max_array_bytes(self) -> tuple[int | None, str]:
        """CL_DEVICE_MAX_MEM_ALLOC_SIZE (never more than CL_DEVICE_GLOBAL_MEM_SIZE): the largest
        buffer the device allocates."""
        return self._max_alloc

    def __init__(self, info: DeviceInfo, cl_device):
        import pyopencl as cl
        import pyopencl.tools as cl_tools

        super().__init__(info)
        self.cl_device = cl_device
        limit = min(int(cl_device.max_mem_alloc_size), int(cl_device.global_mem_size))
        self._max_alloc = (limit, "the OpenCL device's largest buffer")
        self.context = cl.Context([cl_device])
        self.queue = cl.CommandQueue(self.context)
        self._mem_pool = cl_tools.MemoryPool(cl_tools.ImmediateAllocator(self.queue))
        self._reused = self._allocated = 0

    def _allocate(self, nbytes: int):
        """A buffer of ``nbytes`` for a new array: from the pool when the limit allows one."""
        pool = self._mem_pool
        if not self._pool_limit:
            import pyopencl as cl

            self._allocated += 1
            return cl.Buffer(self.context, cl.mem_flags.READ_WRITE, nbytes)
        held = pool.held_blocks
        buf = pool.allocate(nbytes)
        if pool.held_blocks < held:
            self._reused += 1
        else:
            self._allocated += 1
            if pool.managed_bytes - pool.active_bytes > self._pool_limit:
                pool.free_held()
        return buf

    def pool_stats(self):
        """As Device.pool_stats; ``held_bytes`` also counts the rounding of the buffers in use up to
        the pool's size bins (PyOpenCL reports only managed and requested bytes)."""
        from ...pool import PoolStats

        pool = self._mem_pool
        return PoolStats(pool.managed_bytes - pool.active_bytes, pool.held_blocks, self._pool_limit, self._reused,
                         self._allocated)  # fmt: skip

    def empty_pool(self) -> None:
        self._mem_pool.free_held()

    def _set_pool_limit(self, limit: int) -> None:
        pool = self._mem_pool
        if pool.managed_bytes - pool.active_bytes > limit:
            pool.free_held()

    def _upload(self, host: np.ndarray):
        arr = self._empty(host.shape, host.dtype)
        if host.size:  # nothing to copy (and NumPy gives an empty array strides PyOpenCL would refuse)
            arr.set(host, queue=self.queue)
        return arr

    def _upload_into(self, buffer, host: np.ndarray) -> None:
        if host.size:
            buffer.set(host, queue=self.queue)

    def _empty(self, shape, dtype):
        """A C-contiguous array (``shape``: a tuple of ints, ``dtype``: a NumPy dtype), made with
        PyOpenCL's fast constructor: its checks cost ~50 us a call, more than the reuse saves."""
        import pyopencl.array as cla

        strides = _strides(shape, dtype.itemsize)
        return cla.Array(None, shape, dtype, allocator=self._allocate, strides=strides, _fast=True,
                         _size=math.prod(shape), _context=self.context, _queue=self.queue)  # fmt: skip

    def _download(self, buffer, shape, dtype) -> np.ndarray:
        return buffer.get(queue=self.queue).reshape(shape)

    def synchronize(self) -> None:
        self.queue.finish()

    def program(self, source_name: str, defines: dict | None = None):
        """The built program for ``kernels/<source_name>`` on this device (memoised per device)."""
        from .program import build

        return build(self, source_name, defines)

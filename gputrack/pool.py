"""The caching allocator's bookkeeping: freed device buffers kept for reuse, within a byte limit.

An op called without ``out=`` allocates fresh outputs. On some backends a fresh allocation costs
far more than the kernel that fills it (a (1e5, 6, 6) float32 Taichi ndarray: milliseconds on a
2-core CPU, mostly the first touch of new memory). As CuPy's and PyTorch's caching allocators do,
a device keeps the buffers of arrays that were garbage collected and hands them out again for the
next allocation of the same key (the backend's: shape and dtype for Taichi ndarrays), so that in
a steady state (the same op called again and again with fresh outputs) no memory is allocated.

Reuse is safe because every backend runs its work in order on one queue per device (Taichi's
stream, the OpenCL device's in-order command queue): a buffer returns to the pool only when no
Python object references it any more, so the only work that can still touch it is work already
queued; a later user of the buffer enqueues its own work (kernels, uploads) behind that work and
therefore reads and writes it only after the earlier work is done. Downloads wait for the queue.

The pool keeps at most ``limit_bytes`` of freed buffers (``$GPUTRACK_POOL_BYTES``, default
256 MiB; 0 turns reuse off): past it the least recently freed buffers are released, so memory
stays flat however many calls run. ``Device.close()`` releases every held buffer.
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from typing import NamedTuple

DEFAULT_LIMIT_BYTES = 256 << 20


def limit_from_env() -> int:
    """``$GPUTRACK_POOL_BYTES`` (bytes of freed buffers a device keeps; 0: none), default 256 MiB."""
    env = os.environ.get("GPUTRACK_POOL_BYTES")
    if env is None or not env.strip():
        return DEFAULT_LIMIT_BYTES
    try:
        n = int(env)
    except ValueError:
        n = -1
    if n < 0:
        raise ValueError(f"GPUTRACK_POOL_BYTES: expected a non-negative number of bytes, got {env!r}")
    return n


def check_limit(value) -> int:
    """``value`` as a byte limit (a non-negative int), else TypeError/ValueError."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"pool_limit: expected a non-negative int (bytes), got {type(value).__name__}")
    if value < 0:
        raise ValueError(f"pool_limit: expected a non-negative int (bytes), got {value}")
    return value


class PoolStats(NamedTuple):
    """What a device's caching allocator holds and did (``Device.pool_stats()``)."""

    held_bytes: int  # bytes of freed buffers kept for reuse
    held_buffers: int
    limit_bytes: int
    reused: int  # allocations served from the pool
    allocated: int  # allocations that asked the backend for new memory


class BufferPool:
    """Freed buffers kept per key for reuse, at most ``limit_bytes`` of them.

    ``take(key, nbytes)`` returns a held buffer of ``key`` (removing it from the pool) or None;
    ``give(key, buffer, nbytes)`` keeps a buffer nothing references any more and returns the
    buffers the caller must release (the least recently freed ones past the limit, possibly the
    given one). ``clear()`` returns every held buffer for release. A buffer is in the pool or in
    use, never both: ``take`` removes what it returns. Thread-safe (a buffer may be given back by
    the garbage collector in any thread, also while this thread is inside ``take``).
    """

    def __init__(self, limit_bytes: int = DEFAULT_LIMIT_BYTES):
        self.limit_bytes = check_limit(limit_bytes)
        self._free: OrderedDict = OrderedDict()  # key -> [(buffer, nbytes)], least recently freed key first
        self._lock = threading.RLock()
        self.held_bytes = 0
        self.held_buffers = 0
        self.reused = 0
        self.allocated = 0

    def take(self, key, nbytes: int):
        with self._lock:
            found = self._free.get(key)
            if found:
                buffer, n = found.pop()
                if not found:
                    del self._free[key]
                self.held_bytes -= n
                self.held_buffers -= 1
                self.reused += 1
                return buffer
            self.allocated += 1
            return None

    def give(self, key, buffer, nbytes: int) -> list:
        with self._lock:
            if nbytes > self.limit_bytes:
                return [buffer]
            self._free.setdefault(key, []).append((buffer, nbytes))
            self._free.move_to_end(key)
            self.held_bytes += nbytes
            self.held_buffers += 1
            return self._trim()

    def set_limit(self, limit_bytes: int) -> list:
        """Change the limit; returns the buffers to release to meet it."""
        with self._lock:
            self.limit_bytes = check_limit(limit_bytes)
            return self._trim()

    def _trim(self) -> list:
        released = []
        while self.held_bytes > self.limit_bytes and self._free:
            key = next(iter(self._free))
            found = self._free[key]
            buffer, n = found.pop(0)
            if not found:
                del self._free[key]
            self.held_bytes -= n
            self.held_buffers -= 1
            released.append(buffer)
        return released

    def clear(self) -> list:
        with self._lock:
            released = [b for found in self._free.values() for b, _ in found]
            self._free.clear()
            self.held_bytes = self.held_buffers = 0
            return released

    def stats(self) -> PoolStats:
        return PoolStats(self.held_bytes, self.held_buffers, self.limit_bytes, self.reused, self.allocated)

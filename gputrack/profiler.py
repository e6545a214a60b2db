"""Per-stage timing and transfer counts on one device.

A :class:`Profiler` records, for each named stage, its wall time and the bytes that crossed the bus
(host->device and device->host) while it ran, as counted by the device. With ``sync=True`` (the
default) a stage is timed between two device synchronisations, so the time is the device's; with
``sync=False`` nothing waits and the time is what the host spent issuing the work. A frame groups
the stages of one input frame so that a caller can check what a steady-state frame moved::

    prof = gputrack.Profiler(dev)
    with prof.frame() as frame:
        with prof.stage("upload"):
            gray = dev.asarray(gray_host)
        with prof.stage("download"):
            best = gray.numpy()
    print(prof.table())
    assert frame.h2d == gray_host.nbytes

:class:`gputrack.Scheduler` uses one to report its stages.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import statistics
import time

from .device import Device, Transfers

__all__ = ["FrameStats", "Profiler", "StageStats"]


@dataclasses.dataclass
class StageStats:
    """Accumulated figures for one named stage: the times of its last ``history`` calls, and the bytes
    of all its calls."""

    name: str
    history: int = 1000
    times_s: collections.deque = dataclasses.field(default=None)

    def __post_init__(self):
        if self.times_s is None:
            self.times_s = collections.deque(maxlen=self.history)
    h2d: int = 0
    d2h: int = 0

    @property
    def calls(self) -> int:
        return len(self.times_s)

    @property
    def total_s(self) -> float:
        return float(sum(self.times_s))

    @property
    def median_s(self) -> float:
        return float(statistics.median(self.times_s)) if self.times_s else 0.0

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "calls": self.calls,
            "median_ms": self.median_s * 1e3,
            "total_ms": self.total_s * 1e3,
            "h2d_bytes": self.h2d,
            "d2h_bytes": self.d2h,
        }


@dataclasses.dataclass
class FrameStats:
    """What one frame (one ``with profiler.frame()`` block) cost: time and bytes per stage."""

    stages: dict = dataclasses.field(default_factory=dict)  # name -> (seconds, h2d, d2h)
    wall_s: float = 0.0

    @property
    def h2d(self) -> int:
        return sum(s[1] for s in self.stages.values())

    @property
    def d2h(self) -> int:
        return sum(s[2] for s in self.stages.values())


class Profiler:
    """Named stages on one device: wall time (after a device sync by default) and bytes moved per stage.

    ``history``: the figures of the last this many frames (and stage calls) are kept, so that a
    tracker running for hours holds a bounded record (about 2-3 kB a frame for a dozen stages: the
    default 1000 frames hold a few MB, and the memory stops growing after them); ``reset()``
    forgets them all.
    """

    def __init__(self, device: Device, history: int = 1000):
        if not isinstance(device, Device):
            raise TypeError(f"expected a gputrack.Device, got {type(device).__name__}")
        if isinstance(history, bool) or not isinstance(history, int) or history < 1:
            raise ValueError(f"history: expected a positive int, got {history!r}")
        self.device = device
        self.history = history
        self.stats: dict[str, StageStats] = {}
        self._frame: FrameStats | None = None
        self.frames: collections.deque[FrameStats] = collections.deque(maxlen=history)

    @contextlib.contextmanager
    def stage(self, name: str, sync: bool = True):
        """Record the block as stage ``name``: its time (between device syncs when ``sync``) and transfers."""
        if not isinstance(name, str) or not name:
            raise ValueError(f"expected a non-empty stage name, got {name!r}")
        dev = self.device
        if sync:
            dev.synchronize()
        before: Transfers = dev.transfers.copy()
        t0 = time.perf_counter()
        try:
            yield
        finally:  # a stage that raises (e.g. SkipFrame) is recorded too
            if sync:
                dev.synchronize()
            self._record(name, time.perf_counter() - t0, dev.transfers - before)

    def _record(self, name: str, dt: float, moved: Transfers) -> None:
        st = self.stats.get(name) or self.stats.setdefault(name, StageStats(name, self.history))
        st.times_s.append(dt)
        st.h2d += moved.h2d
        st.d2h += moved.d2h
        if self._frame is not None:
            prev = self._frame.stages.get(name, (0.0, 0, 0))
            self._frame.stages[name] = (prev[0] + dt, prev[1] + moved.h2d, prev[2] + moved.d2h)

    @contextlib.contextmanager
    def frame(self, sync: bool = True):
        """Group the stages run inside the block into one :class:`FrameStats` (yielded); the frame's
        wall time ends after a device sync when ``sync``."""
        if self._frame is not None:
            raise RuntimeError("expected frames one after another, got a frame inside a frame")
        fs = FrameStats()
        self._frame = fs
        t0 = time.perf_counter()
        try:
            yield fs
        finally:
            if sync:
                self.device.synchronize()
            fs.wall_s = time.perf_counter() - t0
            self._frame = None
            self.frames.append(fs)

    def reset(self) -> None:
        """Forget the recorded figures (e.g. after warm-up frames)."""
        self.stats.clear()
        self.frames.clear()

    def report(self) -> list[dict]:
        """One dict per stage, in first-run order: calls, median/total ms, bytes each way."""
        return [s.as_dict() for s in self.stats.values()]

    def table(self, title: str | None = None) -> str:
        """The figures as a text table: ms per call (median, total) and, when frames were recorded,
        ms per frame (total / frames, the papers' Tables 1-2 figure) and bytes each way."""
        rows = self.report()
        nf = len(self.frames)
        head = f"{'stage':<24}{'calls':>7}{'median ms':>12}{'total ms':>12}{'ms/frame':>10}{'H->D bytes':>14}{'D->H bytes':>14}"
        lines = [title or f"stages on {self.device.spec} ({self.device.name})", head, "-" * len(head)]
        for r in rows:
            per_frame = f"{r['total_ms'] / nf:10.3f}" if nf else f"{'-':>10}"
            lines.append(
                f"{r['name']:<24}{r['calls']:>7}{r['median_ms']:>12.3f}{r['total_ms']:>12.3f}{per_frame}"
                f"{r['h2d_bytes']:>14}{r['d2h_bytes']:>14}"
            )
        if self.frames:
            med = statistics.median(f.wall_s for f in self.frames) * 1e3
            lines.append(f"{'frame (median)':<24}{len(self.frames):>7}{med:>12.3f}")
        return "\n".join(lines)

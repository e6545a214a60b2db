"""Host scheduler: a tracker's frame as declared stages over named device buffers.

A tracker declares its stages once, each with the buffers it reads and writes; per frame the
:class:`Scheduler` uploads the inputs (into last frame's arrays when the shapes match), runs the
stages in order and downloads the outputs. Nothing waits for the device between stages except a
stage that declares ``host_reads``: the scheduler downloads those buffers for it (a host
synchronisation, counted). Buffers persist from frame to frame, so a stage can write into last
frame's array (``out=b.get(name)``) and a tracker's state stays on the device::

    stages = [
        Stage("predict", predict, reads=("x", "P"), writes=("x", "P")),
        Stage("gate", gate, reads=("x", "P", "z"), writes=("d2",)),
        Stage("assign", assign, host_reads=("d2",), writes=("pairs",)),
        Stage("update", update, reads=("x", "P", "z", "pairs"), writes=("x", "P")),
    ]
    sched = Scheduler(dev, stages, inputs=("z",), state=("x", "P"), outputs=("x",))
    sched.set("x", x0); sched.set("P", P0)
    out = sched.run(z=detections)           # {"x": NumPy array}
    sched.last_frame.h2d                      # bytes uploaded in that frame
    print(sched.table())                      # per-stage time and bytes

A stage function takes one argument, a :class:`StageBuffers` view: ``b["x"]`` reads a declared buffer
(a NumPy array for a ``host_reads`` name), ``b["d2"] = array`` writes one, ``b.get("d2")`` is last
frame's array or None (for ``out=``). A stage that touches a buffer it did not declare raises, and
the declarations are checked when the scheduler is built: a stage that reads a buffer which no earlier
stage writes and which is neither an input nor state is an error then, not a wrong frame later.
A stage may leave a declared write unwritten (e.g. a template re-rendered every other frame); its
readers then see the buffer's value from an earlier frame. A stage may end the frame early by raising
:class:`SkipFrame`; ``run`` raises it on to the caller after recording the stages that ran.

``profile=True`` synchronises the device around each stage so that its time is the device's
(``table()`` then gives Tables 1-2 of paper 000); ``profile=False`` runs without those waits and the
times are what the host spent issuing the work. Bytes moved are counted either way.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Mapping

import numpy as np

from .device import Device, DeviceArray
from .profiler import FrameStats, Profiler

__all__ = ["Scheduler", "SkipFrame", "Stage", "StageBuffers"]

UPLOAD = "upload inputs"
DOWNLOAD = "download outputs"


class SkipFrame(Exception):
    """Raised by a stage to end the frame early (e.g. an unusable image); carries the reason."""


def _names(value, what: str, stage: str) -> tuple[str, ...]:
    if isinstance(value, str):
        value = (value,)
    try:
        names = tuple(value)
    except TypeError:
        raise TypeError(f"stage {stage!r}: {what}: expected a tuple of buffer names, got {value!r}") from None
    for n in names:
        if not isinstance(n, str) or not n:
            raise TypeError(f"stage {stage!r}: {what}: expected non-empty strings, got {n!r}")
    return names


@dataclasses.dataclass(frozen=True)
class Stage:
    """One step of a frame: ``fn(buffers)`` with the names it reads and writes.

    ``reads``: device buffers it reads (no wait); ``host_reads``: buffers it needs on the host (the
    scheduler downloads them first: a synchronisation point); ``writes``: buffers it binds or fills.
    """

    name: str
    fn: Callable
    reads: tuple = ()
    writes: tuple = ()
    host_reads: tuple = ()

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"expected a non-empty stage name, got {self.name!r}")
        if not callable(self.fn):
            raise TypeError(f"stage {self.name!r}: expected a callable fn(buffers), got {type(self.fn).__name__}")
        for field in ("reads", "writes", "host_reads"):
            object.__setattr__(self, field, _names(getattr(self, field), field, self.name))


class StageBuffers(Mapping):
    """The buffers one stage may touch: its reads, host reads and writes (see :class:`Stage`)."""

    __slots__ = ("_stage", "_buffers", "_host", "_readable")

    def __init__(self, stage: Stage, buffers: dict, host: dict):
        self._stage, self._buffers, self._host = stage, buffers, host
        self._readable = set(stage.reads) | set(stage.writes)

    def __getitem__(self, name: str):
        if name in self._host:
            return self._host[name]
        if name not in self._readable:
            raise KeyError(f"stage {self._stage.name!r} reads {name!r}, which it does not declare "
                           f"(reads={self._stage.reads}, host_reads={self._stage.host_reads})")  # fmt: skip
        if name not in self._buffers:
            raise KeyError(f"stage {self._stage.name!r} reads {name!r}, which has no value yet "
                           "(no stage has written it and it was not set)")  # fmt: skip
        return self._buffers[name]

    def get(self, name: str, default=None):
        """The buffer's current value (e.g. last frame's array, for ``out=``), or ``default``."""
        try:
            return self[name]
        except KeyError:
            return default

    def __setitem__(self, name: str, value) -> None:
        if name not in self._stage.writes:
            raise KeyError(f"stage {self._stage.name!r} writes {name!r}, which it does not declare "
                           f"(writes={self._stage.writes})")  # fmt: skip
        self._buffers[name] = value

    def __iter__(self):
        return iter([n for n in (*self._stage.reads, *self._stage.host_reads, *self._stage.writes)
                     if n in self._buffers])  # fmt: skip

    def __len__(self) -> int:
        return sum(1 for _ in self)


class Scheduler:
    """Runs a tracker's declared stages per frame on one device (see the module docstring)."""

    def __init__(self, device: Device, stages: Iterable[Stage], *, inputs=(), state=(), outputs=(),
                 profile: bool = False):  # fmt: skip
        if not isinstance(device, Device):
            raise TypeError(f"device: expected a gputrack.Device, got {type(device).__name__}")
        self.device = device
        self.stages = tuple(stages)
        for s in self.stages:
            if not isinstance(s, Stage):
                raise TypeError(f"stages: expected gputrack.Stage objects, got {type(s).__name__}")
        self.inputs = _names(inputs, "inputs", "<scheduler>")
        self.state = _names(state, "state", "<scheduler>")
        self.outputs = _names(outputs, "outputs", "<scheduler>")
        self.profile = bool(profile)
        self._check()
        self.buffers: dict = {}
        self.profiler = Profiler(device)
        self.last_frame: FrameStats | None = None

    def _check(self) -> None:
        seen, known = set(), set(self.inputs) | set(self.state)
        for n in self.inputs:
            if n in self.state:
                raise ValueError(f"{n!r} is declared both as an input and as state; expected one of them")
        for s in self.stages:
            if s.name in seen or s.name in (UPLOAD, DOWNLOAD):
                raise ValueError(f"expected unique stage names, got {s.name!r} twice (or a reserved name)")
            seen.add(s.name)
            for n in (*s.reads, *s.host_reads):
                if n not in known:
                    raise ValueError(f"stage {s.name!r} reads {n!r}, which no earlier stage writes and which is "
                                     f"neither an input {self.inputs} nor state {self.state}")  # fmt: skip
            known.update(s.writes)
        for n in self.outputs:
            if n not in known:
                raise ValueError(f"output {n!r} is written by no stage and is neither an input nor state")

    # -- buffers -----------------------------------------------------------------------------------
    def _put(self, name: str, value) -> None:
        """Copy ``value`` into buffer ``name``: into the array it holds when shape and dtype match (no
        allocation), else into a new one. A caller's NumPy array is never kept (stages write in place)."""
        dev = self.device
        if isinstance(value, DeviceArray):
            self.buffers[name] = dev.asarray(value)  # this device's array (checked), taken as it is
            return
        host = np.asarray(value)
        old = self.buffers.get(name)
        mine = isinstance(old, DeviceArray) or (dev.backend == "numpy" and isinstance(old, np.ndarray))
        if mine and old.shape == host.shape and old.dtype == host.dtype:
            self.buffers[name] = dev.asarray(host, out=old)
        else:
            self.buffers[name] = dev.asarray(np.array(host, copy=True) if dev.backend == "numpy" else host)

    def set(self, name: str, value) -> None:
        """Set a state buffer (e.g. a tracker's initial x and P) from NumPy or this device's array."""
        if name not in self.state:
            raise KeyError(f"{name!r} is not a state buffer of this scheduler; expected one of {self.state}")
        self._put(name, value)

    # -- a frame -----------------------------------------------------------------------------------
    def run(self, **inputs) -> dict:
        """Run one frame: upload ``inputs`` (NumPy arrays by name), run the stages, return the outputs
        as NumPy arrays by name. Raises :class:`SkipFrame` when a stage ends the frame early."""
        self.device._check_open()  # DeviceUnavailable for a closed device, before any stage runs
        missing = [n for n in self.inputs if n not in inputs]
        extra = [n for n in inputs if n not in self.inputs]
        if missing or extra:
            raise TypeError(f"run: expected the inputs {self.inputs}, got {tuple(inputs)}")
        prof, sync = self.profiler, self.profile
        with prof.frame(sync=sync) as frame:
            try:
                if self.inputs:
                    with prof.stage(UPLOAD, sync=sync):
                        for name in self.inputs:
                            self._put(name, inputs[name])
                for s in self.stages:
                    with prof.stage(s.name, sync=sync):
                        host = {}
                        for n in s.host_reads:
                            if n not in self.buffers:
                                raise KeyError(f"stage {s.name!r} reads {n!r}, which has no value yet "
                                               "(no stage has written it and it was not set)")  # fmt: skip
                            v = self.buffers[n]
                            host[n] = v.numpy() if isinstance(v, DeviceArray) else v
                        s.fn(StageBuffers(s, self.buffers, host))
                out = {}
                if self.outputs:
                    with prof.stage(DOWNLOAD, sync=sync):
                        for n in self.outputs:
                            v = self.buffers[n]
                            out[n] = v.numpy() if isinstance(v, DeviceArray) else v
            finally:
                self.last_frame = frame
        return out

    # -- figures -----------------------------------------------------------------------------------
    @property
    def frames(self):
        return self.profiler.frames

    def reset(self) -> None:
        """Forget the recorded figures (e.g. after warm-up frames); the buffers stay."""
        self.profiler.reset()

    def report(self) -> list[dict]:
        return self.profiler.report()

    def table(self, title: str | None = None) -> str:
        return self.profiler.table(title)

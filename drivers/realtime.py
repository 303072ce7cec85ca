"""Host real-time setup for the cyclic path of either end of the bus (the bench's loop, the emulator's clock).

What real-time Linux users do from Python, each step optional, each recorded in a :class:`RealtimeReport` with the
reason when it could not be applied (never fatal: a run without a privilege still runs, and says so):

- **garbage collector**: ``gc.freeze()`` moves every object that exists at the start into the permanent generation,
  then ``gc.disable()`` for the session. Why: a full collection of a bench process (numpy, canopen, pydantic, the
  design) takes milliseconds, and it would run on whichever thread allocates -- the loop thread included. Cyclic
  garbage made during the session is collected by the caller off the cyclic path (:func:`collect_young`).
- **GIL switch interval** (``sys.setswitchinterval``): a thread that wants the GIL waits up to this long for a
  CPU-bound holder (the log writer, the between-trial update) to hand it over. Python's default, 5 ms, is five
  periods at 1 kHz.
- **SCHED_FIFO** (``os.sched_setscheduler``) for every Python thread of the process: the cyclic threads (the
  calling thread and python-can's ``Notifier`` threads, where the frames of the cyclic path are received) at the
  given priority, every other thread (log writer, heartbeat, supervision, the between-trial update) at
  :data:`HELPER_PRIORITY_OFFSET` below it. A FIFO thread preempts every normal process, so a busy host no longer
  delays its wake-up. The helpers must be real-time too, only lower: they share the GIL with the cyclic threads,
  and a normal thread that holds the GIL when the busy host preempts it for a scheduler time slice (milliseconds)
  stalls the cyclic thread waiting for the GIL just as long (SYNC gaps of tens of milliseconds on a loaded host).
- **timer slack** (``prctl(PR_SET_TIMERSLACK, 1)``) of the calling thread: a normal thread's sleeps end up to 50 us
  late by design; FIFO threads have none.
- **CPU affinity** (``os.sched_setaffinity``) of the whole process.
- **memory locking** (``mlockall(MCL_CURRENT | MCL_FUTURE)`` via ctypes): no page fault on the cyclic path.
- **CPU idle-state latency** (PM QoS: the microseconds written to ``/dev/cpu_dma_latency``, in force while the
  session holds the file open, as ``cyclictest`` does by default): the CPUs stay out of idle states slower to leave
  than that. Why: an idle CPU (a virtual one, halted and woken by its hypervisor) wakes a sleeping cyclic thread
  late; with 0 the idle loop polls instead (:mod:`benchmarks.host_floor` measures the wake-ups, ``docs/benchmarks.md``
  has the figures). It costs power: the idle CPUs spin.

:class:`RealtimeSession` applies the request and restores everything it changed on exit.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import gc
import os
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from types import TracebackType
from typing import Any

from pydantic import Field

from drivers.schema import Section

__all__ = [
    "CPU_LATENCY_DEVICE",
    "HELPER_PRIORITY_OFFSET",
    "NOTIFIER_THREAD_PREFIX",
    "BenchRealtimeConfig",
    "CpuLatencyRequest",
    "CyclicReceive",
    "GcPolicy",
    "RealtimeConfig",
    "RealtimeReport",
    "RealtimeSession",
    "SyncSource",
    "collect_young",
    "demote_current_thread",
]

#: python-can names its receive threads ``Notifier for bus "..."``: the frames of the cyclic path arrive there
NOTIFIER_THREAD_PREFIX = "Notifier for bus"
#: helper threads run this many SCHED_FIFO priorities below the cyclic ones (never below 1)
HELPER_PRIORITY_OFFSET = 10
_MCL_CURRENT, _MCL_FUTURE = 1, 2  # <sys/mman.h>
_PR_SET_TIMERSLACK, _PR_GET_TIMERSLACK = 29, 30  # <linux/prctl.h>
_MIN_TIMER_SLACK_NS = 1  # 0 would mean "back to the thread's default slack"
#: the PM QoS device of the CPUs' wake-up latency (Linux): a request holds while its file stays open
CPU_LATENCY_DEVICE = "/dev/cpu_dma_latency"


class CyclicReceive(StrEnum):
    """Which thread receives the cyclic TPDOs of a realtime bench (``bench.realtime.cyclic_receive``).

    Defined here, with the config that names it, and not beside :class:`drivers.cyclic_rx.CyclicReceiver` (which
    re-exports it): that module imports python-can, and every config load imports this one.
    """

    LOOP = "loop"  # the loop thread, on a bus object of its own (CyclicReceiver)
    NOTIFIER = "notifier"  # the Notifier thread, handing each to the loop through a condition variable


class SyncSource(StrEnum):
    """Where a realtime run's SYNC comes from (``bench.realtime.sync``; :mod:`drivers.sync_clock`, which re-exports
    it: that module imports python-can, and every config load imports this one)."""

    CLOCK = "clock"  # a clock of its own: the kernel's broadcast manager on socketcan, else a producer thread
    LOOP = "loop"  # the loop sends each SYNC on its deadline after the previous cycle's work


class GcPolicy(StrEnum):
    """What the session does to the garbage collector."""

    FREEZE = "freeze"  # gc.freeze() at the start, automatic collection off until the end
    ON = "on"  # left alone


class RealtimeConfig(Section):
    """``bench.realtime`` / ``emulator.realtime``: the host settings of a realtime run (see the module docstring).

    Every step is optional; what was applied, and why not where it was not, is reported.
    """

    gc: GcPolicy = GcPolicy.FREEZE
    switch_interval: float | None = Field(default=0.0002, gt=0, le=0.1)  # seconds; None: Python's own (5 ms)
    sched_fifo_priority: int | None = Field(default=None, ge=1, le=99)  # None: normal scheduling
    cpus: list[int] | None = None  # CPU affinity of the process; None: unchanged
    lock_memory: bool = False  # mlockall
    # PM QoS: the CPUs' idle states may take at most this long to leave (microseconds; 0: never idle, the idle loop
    # polls); None: the system's own
    cpu_latency_us: int | None = Field(default=None, ge=0, le=1_000_000)
    # the last part of each wait for a deadline is spent spinning (the bench's scheduler); seconds
    spin_margin: float = Field(default=0.0002, ge=0, le=0.01)


class BenchRealtimeConfig(RealtimeConfig):
    """``bench.realtime``: the host settings plus how the loop receives its feedback (:mod:`drivers.cyclic_rx`)."""

    # loop: the loop thread receives the cyclic TPDOs itself (a second bus object, no Notifier hand-off);
    # notifier: the Notifier thread receives them and wakes the loop. Lockstep and the in-process bus: notifier.
    cyclic_receive: CyclicReceive = CyclicReceive.LOOP
    # seconds from the start of each wait for feedback spent polling without blocking before blocking receives
    # (loop only): the emulator's answer comes within 0.3 ms mostly; a blocking receive is woken by the kernel
    # and then waits for the GIL the Notifier took for the same frame (no faster than the Notifier path)
    receive_spin: float = Field(default=0.0003, ge=0, le=0.01)
    # clock: SYNC from a clock of its own (the kernel's broadcast manager on socketcan, a producer thread elsewhere),
    # the loop runs on the SYNCs it reads from the bus and a missed cycle never delays the next SYNC; it needs
    # cyclic_receive: loop (and no injected bus fault), else the loop sends SYNC (and says so). loop: the loop sends
    # each SYNC on its deadline, after the previous cycle's command
    sync: SyncSource = SyncSource.CLOCK
    # seconds the SYNC producer thread spins before each deadline after its sleep (sync: clock, not on socketcan); 0:
    # it sleeps to the deadline (SCHED_FIFO and timer slack 1 ns: tens of microseconds late); a spin holds the GIL
    sync_spin: float = Field(default=0.0, ge=0, le=0.001)


@dataclass(frozen=True)
class RealtimeReport:
    """What a :class:`RealtimeSession` applied (``run --json`` ``timing.realtime``).

    Attributes
    ----------
    gc
        ``"frozen"`` (frozen, automatic collection off) or ``"on"``.
    switch_interval
        The GIL switch interval in force, seconds.
    scheduler
        ``"SCHED_FIFO <priority>"`` or ``"SCHED_OTHER"``; ``fifo_threads`` names the threads it was given to.
    cpus
        The process's CPU affinity in force (sorted).
    memory_locked
        Whether ``mlockall`` succeeded.
    timer_slack_ns
        The calling thread's timer slack set, or ``None`` (not set).
    cpu_latency_us
        The PM QoS latency this session holds (microseconds), or ``None`` (none requested, or refused).
    not_applied
        One line per requested step that could not be applied, with the OS's reason.
    """

    gc: str
    switch_interval: float
    scheduler: str
    fifo_threads: tuple[str, ...]
    cpus: tuple[int, ...]
    memory_locked: bool
    timer_slack_ns: int | None
    cpu_latency_us: int | None = None
    not_applied: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {
            "gc": self.gc,
            "switch_interval": self.switch_interval,
            "scheduler": self.scheduler,
            "fifo_threads": list(self.fifo_threads),
            "cpus": list(self.cpus),
            "memory_locked": self.memory_locked,
            "timer_slack_ns": self.timer_slack_ns,
            "cpu_latency_us": self.cpu_latency_us,
            "not_applied": list(self.not_applied),
        }


class _ProcessSetting:
    """A setting of the whole process (the GIL switch interval, the garbage collector) that sessions of several
    threads share (an emulator's motion threads, one per drive, beside the bench's loop). They overlap and end in
    any order, so the first session in saves the setting, each applies its own, and the last one out restores what
    was there before. Restoring each session's own "before" left, after a non-nested order, the setting of a session
    that had already ended, for the rest of the process."""

    def __init__(self, save: Callable[[], Any], restore: Callable[[Any], None]) -> None:
        self._save, self._restore = save, restore
        self._lock = threading.Lock()
        self._holders = 0
        self._saved: Any = None

    def hold(self, apply: Callable[[], None]) -> None:
        with self._lock:
            if self._holders == 0:
                self._saved = self._save()
            self._holders += 1
            apply()

    def release(self) -> None:
        with self._lock:
            self._holders -= 1
            if self._holders == 0:
                self._restore(self._saved)


def _freeze_gc() -> None:
    gc.collect()  # what is garbage now is not frozen for the session
    gc.freeze()
    gc.disable()


def _restore_gc(enabled: bool) -> None:
    gc.unfreeze()
    if enabled:
        gc.enable()


_SWITCH_INTERVAL = _ProcessSetting(sys.getswitchinterval, sys.setswitchinterval)
_GC = _ProcessSetting(gc.isenabled, _restore_gc)


@dataclass
class _Undo:
    """What the session changed, to restore on exit."""

    gc_frozen: bool = False
    switch_interval: bool = False  # the session holds the process's switch interval (:class:`_ProcessSetting`)
    fifo_tids: list[tuple[int, int, int]] = field(default_factory=list)  # (tid, old policy, old priority)
    cpus: set[int] | None = None
    memory_locked: bool = False
    timer_slack_ns: int | None = None  # the calling thread's before
    cpu_latency: CpuLatencyRequest | None = None  # the PM QoS request held


class RealtimeSession:
    """Apply a :class:`RealtimeConfig` to this process and its cyclic threads; restore on exit.

    Parameters
    ----------
    config
        What to apply.
    cyclic_threads
        Threads to give the cyclic priority besides the calling thread; default: python-can's Notifier threads
        running now. Every other running Python thread gets the helper priority.
    """

    def __init__(self, config: RealtimeConfig, cyclic_threads: list[threading.Thread] | None = None) -> None:
        self.config = config
        self._threads = cyclic_threads
        self._undo = _Undo()
        self.report: RealtimeReport | None = None

    def __enter__(self) -> RealtimeSession:
        config, undo = self.config, self._undo
        problems: list[str] = []
        fifo_names: list[str] = []
        if config.sched_fifo_priority is not None:  # first: on a busy host the steps below then run at FIFO speed
            fifo_names, fifo_problems = self._set_fifo(config.sched_fifo_priority)
            problems += fifo_problems
        if config.gc is GcPolicy.FREEZE:
            _GC.hold(_freeze_gc)
            undo.gc_frozen = True
        if (interval := config.switch_interval) is not None:
            _SWITCH_INTERVAL.hold(lambda: sys.setswitchinterval(interval))
            undo.switch_interval = True
        if config.cpus is not None:
            problems += self._set_affinity(config.cpus)
        if config.lock_memory:
            problems += self._lock_memory()
        if config.cpu_latency_us is not None:
            problems += self._hold_cpu_latency(config.cpu_latency_us)
        undo.timer_slack_ns = _timer_slack()
        slack = _set_timer_slack(_MIN_TIMER_SLACK_NS) if undo.timer_slack_ns is not None else None
        if slack is None and not fifo_names:
            problems.append("timer slack: prctl(PR_SET_TIMERSLACK) is not available here")
        self.report = RealtimeReport(
            gc="frozen" if undo.gc_frozen else "on",
            switch_interval=sys.getswitchinterval(),
            scheduler=f"SCHED_FIFO {config.sched_fifo_priority}" if fifo_names else "SCHED_OTHER",
            fifo_threads=tuple(fifo_names),
            cpus=tuple(sorted(os.sched_getaffinity(0))),
            memory_locked=undo.memory_locked,
            timer_slack_ns=slack,
            cpu_latency_us=config.cpu_latency_us if undo.cpu_latency is not None else None,
            not_applied=tuple(problems),
        )
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        undo = self._undo
        for tid, policy, priority in undo.fifo_tids:
            with contextlib.suppress(OSError):  # the thread may have ended
                os.sched_setscheduler(tid, policy, os.sched_param(priority))
        if undo.timer_slack_ns is not None:
            _set_timer_slack(undo.timer_slack_ns)
        if undo.memory_locked:
            _libc().munlockall()
        if undo.cpu_latency is not None:
            undo.cpu_latency.close()
        if undo.cpus is not None:
            os.sched_setaffinity(0, undo.cpus)
        if undo.switch_interval:
            _SWITCH_INTERVAL.release()
        if undo.gc_frozen:
            _GC.release()
        self._undo = _Undo()

    def _set_affinity(self, cpus: list[int]) -> list[str]:
        before = os.sched_getaffinity(0)
        try:
            os.sched_setaffinity(0, cpus)
        except (OSError, ValueError) as exc:
            return [f"cpus {cpus}: {exc}"]
        self._undo.cpus = before
        return []

    def _lock_memory(self) -> list[str]:
        libc = _libc()
        if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
            return [f"lock_memory: mlockall: {os.strerror(ctypes.get_errno())}"]
        self._undo.memory_locked = True
        return []

    def _hold_cpu_latency(self, microseconds: int) -> list[str]:
        request = CpuLatencyRequest(microseconds)
        refused = request.open()
        if refused is not None:
            return [refused]
        self._undo.cpu_latency = request
        return []

    def _set_fifo(self, priority: int) -> tuple[list[str], list[str]]:
        """Cyclic threads at ``priority``, every other Python thread below it; the cyclic threads' names."""
        cyclic = self._threads
        if cyclic is None:
            cyclic = [t for t in threading.enumerate() if t.name.startswith(NOTIFIER_THREAD_PREFIX)]
        cyclic = [threading.current_thread(), *[t for t in cyclic if t is not threading.current_thread()]]
        helpers = [t for t in threading.enumerate() if t not in cyclic]
        names: list[str] = []
        for thread, level in [*[(t, priority) for t in cyclic], *[(t, _helper(priority)) for t in helpers]]:
            tid = thread.native_id
            if tid is None:
                continue
            try:
                old_policy, old_priority = os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(level))
            except OSError as exc:
                return names, [f"sched_fifo_priority {priority}: {exc.strerror or exc} (normal scheduling kept)"]
            self._undo.fifo_tids.append((tid, old_policy, old_priority))
            if level == priority:
                names.append(thread.name)
        return names, []


class CpuLatencyRequest:
    """A PM QoS request of the CPUs' wake-up latency (:data:`CPU_LATENCY_DEVICE`): in force from :meth:`open` until
    :meth:`close` -- the kernel drops it with its file, so a process that dies drops it too."""

    def __init__(self, microseconds: int) -> None:
        self.microseconds = microseconds
        self._fd: int | None = None

    def open(self) -> str | None:
        """Make the request; ``None``, or one line saying why it could not be made."""
        if self._fd is not None:
            return None
        try:
            fd = os.open(CPU_LATENCY_DEVICE, os.O_WRONLY | os.O_CLOEXEC)
        except OSError as exc:
            return f"cpu_latency_us {self.microseconds}: {CPU_LATENCY_DEVICE}: {exc.strerror or exc}"
        try:  # the kernel reads a binary s32
            os.write(fd, self.microseconds.to_bytes(4, sys.byteorder, signed=True))
        except OSError as exc:
            os.close(fd)
            return f"cpu_latency_us {self.microseconds}: {CPU_LATENCY_DEVICE}: {exc.strerror or exc}"
        self._fd = fd
        return None

    def close(self) -> None:
        """Withdraw the request (idempotent)."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)


def _helper(priority: int) -> int:
    return max(1, priority - HELPER_PRIORITY_OFFSET)


def demote_current_thread() -> None:
    """A helper started by a cyclic thread (it inherited the cyclic SCHED_FIFO priority) steps down to the helper
    priority; a thread with normal scheduling is left alone."""
    if os.sched_getscheduler(0) == os.SCHED_FIFO:
        level = _helper(os.sched_getparam(0).sched_priority)
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(level))


def collect_young() -> None:
    """Collect the young generations while automatic collection is off (between trials, off the cyclic path)."""
    if not gc.isenabled():
        gc.collect(1)


def _libc() -> Any:
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)


def _timer_slack() -> int | None:
    """The calling thread's timer slack, or None where prctl is unavailable."""
    try:
        slack = int(_libc().prctl(_PR_GET_TIMERSLACK, 0, 0, 0, 0))
    except (OSError, AttributeError):
        return None
    return slack if slack > 0 else None


def _set_timer_slack(nanoseconds: int) -> int | None:
    """Set the calling thread's timer slack; returns it, or None where prctl is unavailable."""
    try:
        if _libc().prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(nanoseconds), 0, 0, 0) != 0:
            return None
    except (OSError, AttributeError):
        return None
    return nanoseconds

"""SYNC from a clock, not from the control loop: the producers of a realtime bench's SYNC.

A realtime loop that sends SYNC itself after each cycle's work makes a late cycle a late SYNC, and every drive on the
bus is late with it. Here SYNC comes from a clock of its own, and the loop runs on the SYNCs it reads back from the
bus (:meth:`drivers.network.DriveNetwork.await_sync`): it has one period to send the next command, and a missed
cycle never delays the next SYNC.

Three producers, one per kind of interface (the third, a process of its own for ``udp_multicast``, is
:class:`drivers.sync_process.ProcessSync`: a thread in the bench's interpreter waits for the GIL when its SYNC is
due):

:class:`BroadcastSync` (``socketcan``)
    python-can's ``send_periodic``, whose period the kernel's broadcast manager (BCM) holds: no thread of this process
    is on the SYNC's path at all. The process learns each SYNC's time from its echo on the loop's own socket (a
    raw CAN socket receives the frames of every other socket on the interface, the BCM's included).
:class:`SyncProducer` (every other interface: ``virtual``, any without a process of its own)
    A dedicated thread with absolute deadlines ``t0 + k * period`` on :func:`time.perf_counter`, a sleep until
    ``spin_margin`` before each and a spin for the rest (as :class:`foilc_hil.loop.scheduler.DeadlineScheduler`
    waits), started from the loop thread inside the realtime session: it inherits the loop's SCHED_FIFO priority
    and timer slack (Linux threads inherit their creator's scheduling) and raises itself one priority above it, so
    the loop's own work never delays it. A wake-up later than a whole period (a host stall, the process stopped)
    sends ONE late SYNC at once for the latest slot passed and counts the others as skipped: never a burst of
    catch-up SYNCs.

Each SYNC a producer sends goes through the network's ``send`` (under canopen's send lock, the same lock every RPDO
of the master is sent under), which counts it: the count at an RPDO's send says which SYNCs went out before it, in
the order of the bus object's sends (:attr:`drivers.network.DriveNetwork.syncs_sent`).

Thread safety: :meth:`SyncProducer.start` and :meth:`SyncProducer.stop` are called from the control thread. The
record of each SYNC (:meth:`SyncProducer.record`) is written by the producer thread under the send lock just before
the frame goes out, and read by the control thread only after it received that frame's echo: the write is done by
then.
"""

from __future__ import annotations

import array
import contextlib
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import can

from drivers.realtime import SyncSource  # defined with the config that names it (no python-can there)

__all__ = [
    "RECORDS",
    "BroadcastSync",
    "SyncClock",
    "SyncProducer",
    "SyncRecord",
    "SyncSource",
]

#: SYNCs whose send record a producer keeps (a ring): the loop reads a SYNC's record within a few periods of it
RECORDS = 1 << 12


@dataclass(frozen=True, slots=True)
class SyncRecord:
    """What a producer knows of one SYNC it sent.

    Attributes
    ----------
    due
        Its deadline (``perf_counter`` seconds); NaN: not known (the kernel's broadcast manager).
    sent
        When it was handed to the bus (``perf_counter`` seconds, just before the send); NaN: not known.
    skipped
        Slots passed over without a SYNC just before it (the producer woke more than a period late).
    """

    due: float
    sent: float
    skipped: int


class SyncClock(Protocol):
    """A running SYNC producer, as the network holds it."""

    @property
    def name(self) -> str:
        """``"thread"``, ``"bcm"`` or ``"process"`` (``timing.sync_clock`` in ``--json``)."""
        ...

    @property
    def period(self) -> float: ...

    def record(self, number: int) -> SyncRecord | None:
        """The record of SYNC ``number`` (the network's count of SYNCs sent), or None where not kept."""
        ...

    def next_due(self, number: int) -> float | None:
        """When SYNC ``number + 1`` is due (``perf_counter``), or None where the producer does not know."""
        ...

    def stop(self) -> None: ...


class SyncProducer:
    """A thread that sends SYNC on absolute deadlines (module docstring).

    Parameters
    ----------
    send
        Sends one SYNC and returns the network's count of SYNCs sent, this one included (called on the thread); it
        calls its argument with that count just before the frame goes out (the producer's record of it).
    period
        Seconds between SYNCs.
    spin_margin
        The last part of each wait, seconds, is spent spinning on the clock instead of sleeping.
    clock, sleep
        Injected for tests.
    """

    name = "thread"

    def __init__(
        self,
        send: Callable[[Callable[[int], None]], int],
        period: float,
        *,
        spin_margin: float = 0.0002,
        clock: Callable[[], float] = time.perf_counter,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if not (period > 0 and math.isfinite(period)):
            raise ValueError(f"period must be a positive number of seconds, got {period!r}")
        self._send = send
        self.period = float(period)
        self.spin_margin = max(0.0, float(spin_margin))
        self._clock = clock
        self._sleep = sleep
        self._due = array.array("d", [math.nan]) * RECORDS
        self._sent = array.array("d", [math.nan]) * RECORDS
        self._skipped = array.array("q", [0]) * RECORDS
        self._numbers = array.array("q", [-1]) * RECORDS  # which SYNC each ring slot holds
        self._stopped = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = 0.0
        self._pending = (math.nan, 0)  # the SYNC about to be sent: its deadline and the slots skipped before it
        self.sent_count = 0  # SYNCs this producer sent
        self.skipped = 0  # slots it passed over (woke more than a period late)
        self.error: BaseException | None = None  # what stopped the thread, if anything did

    def start(self, t0: float | None = None) -> None:
        """Start the thread: the first SYNC is due at ``t0`` (default: one period from now)."""
        if self._thread is not None:
            raise RuntimeError("the SYNC producer is already running")
        self._t0 = self._clock() + self.period if t0 is None else float(t0)
        self._stopped.clear()
        self._thread = threading.Thread(target=self._run, name="SYNC producer", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread (idempotent); no SYNC is sent after this returns."""
        self._stopped.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def record(self, number: int) -> SyncRecord | None:
        slot = number % RECORDS
        if self._numbers[slot] != number:
            return None
        return SyncRecord(self._due[slot], self._sent[slot], int(self._skipped[slot]))

    def next_due(self, number: int) -> float | None:
        """When SYNC ``number + 1`` is due, from SYNC ``number``'s own deadline (None: no record of it)."""
        slot = number % RECORDS
        if self._numbers[slot] != number:
            return None
        return self._due[slot] + self.period

    def _run(self) -> None:
        _above_creator()
        clock, period, spin = self._clock, self.period, self.spin_margin
        index = 0
        try:
            while not self._stopped.is_set():
                due = self._t0 + index * period
                remaining = due - clock()
                if remaining > spin:
                    self._sleep(remaining - spin)
                    if self._stopped.is_set():
                        return
                now = clock()
                skipped = 0
                if now >= due + period:  # a stall: one late SYNC for the latest slot passed, the others skipped
                    skipped = int((now - due) // period)
                    index += skipped
                    due = self._t0 + index * period
                while clock() < due:
                    pass
                self._pending = (due, skipped)
                self._send(self._stamp)
                self.sent_count += 1
                self.skipped += skipped
                index += 1
        except BaseException as exc:  # the control thread sees SYNC stop and reports this
            self.error = exc


    def _stamp(self, number: int) -> None:
        """The record of SYNC ``number``, written under the send lock just before it goes out."""
        due, skipped = self._pending
        slot = number % RECORDS
        self._due[slot], self._sent[slot], self._skipped[slot] = due, self._clock(), skipped
        self._numbers[slot] = number


def _above_creator() -> None:
    """Under SCHED_FIFO (inherited from the loop thread that started it), one priority above it: the SYNC clock
    preempts the loop, never the other way round; normal scheduling is left alone."""
    with contextlib.suppress(OSError):
        if os.sched_getscheduler(0) == os.SCHED_FIFO:
            priority = os.sched_getparam(0).sched_priority
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(min(priority + 1, os.sched_get_priority_max(
                os.SCHED_FIFO))))


class BroadcastSync:
    """SYNC by python-can's ``send_periodic`` on a ``socketcan`` bus: the kernel's broadcast manager sends it.

    The process keeps no record of each SYNC's time: the network takes it from the SYNC's echo on the loop's socket.

    Parameters
    ----------
    bus
        A ``socketcan`` bus object (the BCM task belongs to it).
    message
        The SYNC frame.
    period
        Seconds between SYNCs.
    """

    name = "bcm"

    def __init__(self, bus: can.BusABC, message: can.Message, period: float) -> None:
        self.period = float(period)
        self._task = bus.send_periodic(message, self.period, store_task=False)

    def record(self, number: int) -> SyncRecord | None:
        return None

    def next_due(self, number: int) -> float | None:
        return None

    def stop(self) -> None:
        """Stop the kernel's task (idempotent)."""
        with contextlib.suppress(Exception):  # on the way out of a run: a bus already shut down has no task left
            self._task.stop()

"""The realtime drive's receive thread, awake when SYNC comes: :class:`SyncAnticipatingNotifier`.

A python-can ``Notifier`` thread sleeps in ``recv`` until the kernel wakes it for a frame; on a busy host that
wake-up is late by tens of microseconds to milliseconds, and at 1 kHz it is one of the wake-ups in series of every
cycle (SYNC -> TPDO). A real drive's SYNC consumer is an interrupt; here the thread instead anticipates SYNC: from
the cycle period (0x1006) and the time the last SYNC came, it polls without blocking from ``margin`` seconds before
the next SYNC is due until ``margin`` after, so a SYNC arriving then finds it running. Outside that window, and
once SYNCs stop coming (start-up, between runs, a stalled master: :data:`LOST_PERIODS` periods without one), it
blocks in ``recv`` as python-can's thread does. Every received frame goes to the listeners as with the Notifier.

One per process (:meth:`SyncAnticipatingNotifier.running`): the drives of a multi-node emulator process
(``--node-id 1,2,3,4``) each have a receive thread, and several threads polling without blocking would take the GIL
from each other; the first drive's anticipates, the others block.

Thread safety: the thread is python-can's (named as python-can names its own, so the realtime host setup gives it
the cyclic priority, :mod:`drivers.realtime`); ``period`` and ``sync_id`` are called on it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable

import can

__all__ = ["LOST_PERIODS", "SyncAnticipatingNotifier", "sync_wait"]

LOST_PERIODS = 10
"""Periods without SYNC after which the thread stops anticipating and blocks until the next one."""


def sync_wait(now: float, last: float, period: float, margin: float) -> float | None:
    """How long the receive thread may block at ``now`` after a SYNC at ``last``: 0 inside the window around the
    next SYNC due (``margin`` either side), the time until the window opens before it, None once no SYNC came for
    :data:`LOST_PERIODS` periods."""
    # the SYNC due next: the first of last + k periods (k >= 1) whose window has not closed yet
    periods = max(1, int((now - last - margin) // period) + 1)
    if periods > LOST_PERIODS:
        return None
    return max(0.0, last + periods * period - margin - now)


class SyncAnticipatingNotifier(can.Notifier):
    """A ``can.Notifier`` on one bus whose thread polls for SYNC around the time it is due.

    Parameters
    ----------
    bus, listeners, timeout
        As for ``can.Notifier`` (``timeout``: the blocking ``recv``'s, bounding how long :meth:`stop` waits).
    margin
        Seconds before (and after) the due time of the next SYNC during which ``recv`` does not block.
    period
        The cycle period now, seconds (the drive's 0x1006).
    sync_id
        The SYNC COB-ID now (the drive's 0x1005).
    """

    _running = 0  # instances started and not stopped, in this process
    _count_lock = threading.Lock()

    @classmethod
    def running(cls) -> int:
        """How many are running in this process."""
        with cls._count_lock:
            return cls._running

    def __init__(self, bus: can.BusABC, listeners: Iterable[can.Listener], timeout: float, *, margin: float,
                 period: Callable[[], float], sync_id: Callable[[], int]) -> None:
        if not margin > 0:
            raise ValueError(f"margin must be > 0 s, got {margin!r}")
        self.margin = float(margin)
        self._period = period
        self._sync_id = sync_id
        self._last_sync: float | None = None  # time.perf_counter() when the last SYNC was received
        #: SYNCs received while polling without blocking (the anticipated ones)
        self.anticipated = 0
        with SyncAnticipatingNotifier._count_lock:
            SyncAnticipatingNotifier._running += 1
        self._counted = True
        super().__init__(bus, list(listeners), timeout)
        for reader in self._readers:
            if isinstance(reader, threading.Thread):  # python-can names it after the class: the name it gives its own
                reader.name = f'Notifier for bus "{bus.channel_info}"'

    def stop(self, timeout: float = 5.0) -> None:
        """python-can's ``stop``; the process may start another one afterwards."""
        with SyncAnticipatingNotifier._count_lock:
            if self._counted:
                SyncAnticipatingNotifier._running -= 1
                self._counted = False
        super().stop(timeout)

    def _rx_thread(self, bus: can.BusABC) -> None:
        """python-can's receive loop, with :meth:`_receive` for ``bus.recv``."""
        while not self._stopped:
            try:
                msg = self._receive(bus)
                if msg is not None:
                    with self._lock:
                        self._on_message_received(msg)
            except Exception as exc:  # as python-can's thread: recorded, handed to the listeners, raised if unhandled
                self.exception = exc
                if not self._on_error(exc):
                    raise

    def _receive(self, bus: can.BusABC) -> can.Message | None:
        """One ``recv``: without blocking inside the window around the next SYNC, else blocking until it opens."""
        wait = None if self._last_sync is None else sync_wait(time.perf_counter(), self._last_sync, self._period(),
                                                               self.margin)
        if wait is None:
            self._last_sync = None  # no SYNC yet, or they stopped: wait for the next one as the kernel wakes us
            msg = bus.recv(self.timeout)
        else:
            msg = bus.recv(min(wait, self.timeout))  # before the window: other frames (the RPDO) may come meanwhile
        spinning = wait == 0.0
        if msg is not None and msg.arbitration_id == self._sync_id() and not msg.is_error_frame:
            # when it arrived, not when this thread got it: a late wake-up must not shift the next window late;
            # the bus's receive time stamp is wall-clock (python-can), so only its age is used, and bounded
            age = time.time() - msg.timestamp
            self._last_sync = time.perf_counter() - (age if 0.0 < age < self.margin else 0.0)
            if spinning:
                self.anticipated += 1
        return msg

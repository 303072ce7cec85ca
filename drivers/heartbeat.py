"""CiA 301 heartbeats, both ways: the master's producer and the supervision of the drive's heartbeat.

canopen records the last heartbeat (``NmtMaster.timestamp``) but never declares it lost, and its producer lives on
``LocalNode`` only. This module fills both gaps:

- :class:`HeartbeatProducer` sends the master's heartbeat (``0x700 + master node id``, state byte) with python-can's
  ``send_periodic``, so a drive whose consumer heartbeat 0x1016 watches the master can detect a dead master.
- :class:`HeartbeatMonitor` keeps the time and NMT state of the drive's last heartbeat (fed from the Notifier
  thread), answers :meth:`HeartbeatMonitor.check` with :class:`~drivers.errors.HeartbeatLostError` once no
  heartbeat arrived for ``timeout`` seconds, and optionally runs a watchdog thread that reports the loss even when
  nobody is polling.

On a lockstep in-process bus (:mod:`drivers.inprocess`) the monitor runs on the channel's
:class:`~drivers.inprocess.LockstepClock`: silence is simulated time, and :meth:`HeartbeatMonitor.wait_for` lets
simulated time pass (the drive's heartbeat timers fire) instead of sleeping, so a busy host never reads as a lost
heartbeat. The master's producer there is a timer on the same clock (python-can's ``send_periodic`` of that bus).

Thread safety: every method of :class:`HeartbeatMonitor` may be called from any thread (one lock guards its
state); the watchdog's ``on_lost`` callback runs on the watchdog thread.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import can

from drivers.cia301 import FunctionCode, NmtState, cob_id, heartbeat_state
from drivers.errors import DriveError, HeartbeatLostError
from drivers.inprocess import LockstepClock

__all__ = ["HeartbeatMonitor", "HeartbeatProducer"]


class HeartbeatProducer:
    """Periodic heartbeat of the master on ``0x700 + node_id``.

    Parameters
    ----------
    bus
        The bus to send on.
    node_id
        The master's node id (the one the drive's 0x1016 entry names).
    period
        Seconds between heartbeats.
    state
        The NMT state byte the master announces (operational by default).
    """

    def __init__(
        self, bus: can.BusABC, node_id: int, period: float, state: NmtState = NmtState.OPERATIONAL
    ) -> None:
        if period <= 0:
            raise DriveError(f"heartbeat producer period must be positive, got {period}")
        self.period = period
        self.message = can.Message(
            arbitration_id=cob_id(FunctionCode.HEARTBEAT, node_id), data=[int(state)], is_extended_id=False
        )
        self._bus = bus
        self._task: can.broadcastmanager.CyclicSendTaskABC | None = None

    @property
    def running(self) -> bool:
        """True between :meth:`start` and :meth:`stop`."""
        return self._task is not None

    def start(self) -> None:
        """Send the first heartbeat now and then every ``period`` seconds (idempotent)."""
        if self._task is None:
            self._task = self._bus.send_periodic(self.message, self.period, store_task=True)

    def stop(self) -> None:
        """Stop producing (idempotent)."""
        task, self._task = self._task, None
        if task is not None:
            task.stop()


class HeartbeatMonitor:
    """Last heartbeat of one node and its loss after ``timeout`` seconds.

    Supervision starts at :meth:`arm` (the first deadline is ``timeout`` after arming, so a drive that was just
    configured gets a full window) and stops at :meth:`disarm`. Unarmed, :meth:`check` never raises.

    Parameters
    ----------
    node_id
        The supervised node.
    clock
        Seconds, monotonic (the wall clock by default).
    lockstep
        A lockstep channel's clock: replaces ``clock``, and :meth:`wait_for` advances it instead of sleeping.
    """

    def __init__(
        self, node_id: int, clock: Callable[[], float] = time.monotonic, *, lockstep: LockstepClock | None = None
    ) -> None:
        self.node_id = node_id
        self._lockstep = lockstep
        self._clock = lockstep.now if lockstep is not None else clock
        self._lock = threading.Condition()
        self._last_time: float | None = None
        self._last_state: int | None = None
        self._beats = 0
        self._armed_at: float | None = None
        self._timeout = 0.0
        self._watchdog: threading.Thread | None = None
        self._stop_watchdog = threading.Event()

    # --- fed from the Notifier thread ---------------------------------------------------------------------------

    def beat(self, state: int, when: float | None = None) -> None:
        """Record a heartbeat (or boot-up, ``state == 0``) received at ``when`` (default: now)."""
        with self._lock:
            self._last_time = self._clock() if when is None else when
            self._last_state = heartbeat_state(state)
            self._beats += 1
            self._lock.notify_all()

    # --- queried from the control thread ------------------------------------------------------------------------

    @property
    def last_state(self) -> int | None:
        """NMT state byte of the last heartbeat, None before the first."""
        with self._lock:
            return self._last_state

    @property
    def beats(self) -> int:
        """Number of heartbeats (boot-ups included) received so far."""
        with self._lock:
            return self._beats

    @property
    def timeout(self) -> float:
        """Seconds without a heartbeat after which it is lost (0 while unarmed)."""
        return self._timeout if self._armed_at is not None else 0.0

    def wait_for(self, accept: Callable[[int], bool], since_beat: int, timeout: float) -> int | None:
        """Wait for a heartbeat numbered after ``since_beat`` whose state ``accept`` takes; return it or None."""
        if self._lockstep is not None:
            return self._wait_lockstep(self._lockstep, accept, since_beat, timeout)
        deadline = self._clock() + timeout
        with self._lock:
            seen = since_beat
            while True:
                if self._beats > seen:
                    seen = self._beats
                    if self._last_state is not None and accept(self._last_state):
                        return self._last_state
                remaining = deadline - self._clock()
                if remaining <= 0:
                    return None
                self._lock.wait(remaining)

    def _wait_lockstep(
        self, clock: LockstepClock, accept: Callable[[int], bool], since_beat: int, timeout: float
    ) -> int | None:
        """:meth:`wait_for` on simulated time: advance the clock timer by timer (the heartbeats arrive meanwhile)."""
        seen = since_beat
        accepted: int | None = None

        def ready() -> bool:
            nonlocal seen, accepted
            with self._lock:
                if self._beats > seen:
                    seen = self._beats
                    if self._last_state is not None and accept(self._last_state):
                        accepted = self._last_state
            return accepted is not None

        clock.wait_until(ready, timeout)
        return accepted

    def arm(self, timeout: float) -> None:
        """Start supervising: lost when no heartbeat arrives for ``timeout`` seconds from now on."""
        if timeout <= 0:
            raise DriveError(f"heartbeat timeout must be positive, got {timeout}")
        with self._lock:
            self._timeout = timeout
            self._armed_at = self._clock()

    def disarm(self) -> None:
        """Stop supervising (e.g. around an NMT reset)."""
        with self._lock:
            self._armed_at = None

    def silence(self) -> float:
        """Seconds since the last heartbeat, or since arming if none came after it."""
        with self._lock:
            return self._silence_locked()

    def _silence_locked(self) -> float:
        now = self._clock()
        last, armed = self._last_time, self._armed_at  # the later of the two (no list: check() runs every cycle)
        start = armed if last is None else last if armed is None or last > armed else armed
        return now - start if start is not None else 0.0

    def check(self) -> None:
        """Raise :class:`HeartbeatLostError` when armed and the heartbeat is overdue."""
        with self._lock:
            if self._armed_at is None:
                return
            silence = self._silence_locked()
            if silence > self._timeout:
                raise HeartbeatLostError(
                    f"heartbeat of node {self.node_id} lost: none for {silence:.3f} s "
                    f"(timeout {self._timeout:.3f} s)"
                )

    # --- watchdog -------------------------------------------------------------------------------------------------

    def start_watchdog(self, on_lost: Callable[[HeartbeatLostError], None], poll: float) -> None:
        """Check every ``poll`` seconds on a daemon thread; call ``on_lost`` once per loss (re-armed by :meth:`arm`)."""
        if self._watchdog is not None:
            return
        self._stop_watchdog.clear()

        def run() -> None:
            reported_for: float | None = None
            while not self._stop_watchdog.wait(poll):
                armed_at = self._armed_at
                if armed_at is None or armed_at == reported_for:
                    continue
                try:
                    self.check()
                except HeartbeatLostError as exc:
                    reported_for = armed_at
                    on_lost(exc)

        self._watchdog = threading.Thread(target=run, name=f"heartbeat-watchdog-{self.node_id}", daemon=True)
        self._watchdog.start()

    def stop_watchdog(self) -> None:
        """Stop the watchdog thread and wait for it."""
        thread, self._watchdog = self._watchdog, None
        if thread is not None:
            self._stop_watchdog.set()
            thread.join(timeout=5.0)

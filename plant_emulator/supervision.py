"""Supervision of the virtual drive's communication: heartbeat consumer, SYNC loss, PDO event timers.

:meth:`Supervisor.poll` runs every :data:`MONITOR_PERIOD`: a watched node (0x1016) whose heartbeat is overdue, or
(realtime only) no SYNC for ``emulator.sync_loss_cycles`` periods while OPERATIONAL, is reported once to
``on_loss``; then the TPDO event timers are served. On a wall-clock bus a thread polls (:meth:`Supervisor.run`);
on a lockstep in-process bus the poll is a timer on the channel's simulated time (see
:class:`~plant_emulator.device.VirtualDrive`), so the drive needs no thread and a busy host is never a lost
heartbeat.

SYNC loss counts only time the drive could watch: a poll that comes more than :data:`STALL_POLLS` polling periods
after the previous one means this process was stalled (a busy host descheduled it), and SYNCs may be waiting
unread in its receive queue; the SYNC-loss timer then restarts instead of reporting a loss the bench did not
cause. A real loss (the master stopped sending SYNC) is still reported one timeout after the drive can watch again.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from canopen import objectdictionary as cod

from drivers.cia301 import FunctionCode, HeartbeatConsumerEntry, NmtState, cob_id
from drivers.cia402 import Obj
from plant_emulator.application import FaultKind
from plant_emulator.node import EmulatedNode
from plant_emulator.pdo_engine import PdoEngine

__all__ = ["MONITOR_PERIOD", "Supervisor"]

MONITOR_PERIOD = 0.002  # s, resolution of the heartbeat consumer / SYNC-loss / event-timer supervision
STALL_POLLS = 5  # a poll this many periods late means the process was stalled: the SYNC-loss timer restarts


@dataclass
class _HeartbeatWatch:
    """One entry of the heartbeat consumer 0x1016."""

    node_id: int
    timeout: float  # s
    deadline: float | None = None  # None until the first heartbeat arrives (CiA 301: then the watch starts)


class Supervisor:
    """Heartbeat consumer (0x1016), SYNC-loss detection and the PDO event timers, on one polling thread.

    Parameters
    ----------
    node
        The drive's node (OD, network, NMT state).
    lock
        The drive's lock; every poll runs under it.
    pdos
        Whose event timers the poll serves.
    on_loss
        ``on_loss(FaultKind.HEARTBEAT_LOSS | FaultKind.SYNC_LOSS)``, once per loss.
    cycle_period
        The drive's present cycle period (0x1006 may change it at any time).
    sync_loss_cycles
        Periods without SYNC that make a SYNC loss; None: no SYNC supervision (lockstep, where SYNC is the clock).
    clock
        Seconds, monotonic: the wall clock, or a lockstep channel's simulated time (:attr:`clock` may be replaced
        until the drive starts).
    """

    def __init__(
        self,
        node: EmulatedNode,
        lock: threading.RLock,
        pdos: PdoEngine,
        *,
        on_loss: Callable[[FaultKind], None],
        cycle_period: Callable[[], float],
        sync_loss_cycles: float | None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.node = node
        self._lock = lock
        self._pdos = pdos
        self._on_loss = on_loss
        self._cycle_period = cycle_period
        self._sync_loss_cycles = sync_loss_cycles
        self.clock = clock
        self._watches: dict[int, _HeartbeatWatch] = {}
        self._last_sync: float | None = None
        self._last_poll: float | None = None  # the previous poll: a long gap since it means a stalled process
        self._sync_lost = False

    # --- heartbeat consumer -----------------------------------------------------------------------------------

    def rebuild_heartbeat_consumer(self) -> None:
        """Watch the nodes 0x1016 names now; a watch starts with the node's first heartbeat."""
        network = self.node.link
        for watch in self._watches.values():
            if network is not None:
                network.unsubscribe(cob_id(FunctionCode.HEARTBEAT, watch.node_id), self.on_heartbeat)
        self._watches = {}
        if not self.node.has(Obj.CONSUMER_HEARTBEAT_TIME):
            return
        record = self.node.object_dictionary[Obj.CONSUMER_HEARTBEAT_TIME]
        subs = [] if isinstance(record, cod.ODVariable) else [s for s in record.subindices if s > 0]
        for sub in subs:
            entry = HeartbeatConsumerEntry.decode(int(self.node.read(Obj.CONSUMER_HEARTBEAT_TIME, sub)))
            if not entry.active:
                continue
            self._watches[entry.node_id] = _HeartbeatWatch(node_id=entry.node_id, timeout=entry.time_ms / 1000)
            if network is not None:
                network.subscribe(cob_id(FunctionCode.HEARTBEAT, entry.node_id), self.on_heartbeat)

    def on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """Network callback: a watched node's heartbeat re-arms its deadline."""
        watch = self._watches.get(can_id - FunctionCode.HEARTBEAT)
        if watch is not None and self.node.alive:
            watch.deadline = self.clock() + watch.timeout

    # --- SYNC ---------------------------------------------------------------------------------------------------

    def sync_received(self) -> None:
        """A SYNC arrived: restart the SYNC-loss timer and clear the loss (a SYNC always ends it)."""
        self._last_sync = self.clock()
        self._sync_lost = False

    def forget_sync(self) -> None:
        """After an NMT reset: no SYNC seen yet, so none can be missing."""
        self._last_sync = None
        self._sync_lost = False

    # --- the polling thread -------------------------------------------------------------------------------------

    def run(self, stop: threading.Event) -> None:
        """Poll every :data:`MONITOR_PERIOD` until ``stop`` is set (the drive's supervision thread)."""
        while not stop.wait(MONITOR_PERIOD):
            self.poll()

    def poll(self) -> None:
        """Report overdue heartbeats and SYNC (once per loss), then serve the TPDO event timers."""
        if not self.node.alive:
            return
        with self._lock:
            now = self.clock()  # after the lock: waiting for it is time the drive could not watch either
            if (self._last_poll is not None and now - self._last_poll > STALL_POLLS * MONITOR_PERIOD
                    and self._last_sync is not None):
                self._last_sync = now  # it could not watch during the stall: the timeout starts again
            self._last_poll = now
            for watch in self._watches.values():
                if watch.deadline is not None and now > watch.deadline:
                    watch.deadline = None  # wait for the next heartbeat before watching again
                    self._on_loss(FaultKind.HEARTBEAT_LOSS)
            if self._sync_overdue(now):
                self._sync_lost = True
                self._on_loss(FaultKind.SYNC_LOSS)
            self._pdos.send_event_driven(timer_only=True)

    def _sync_overdue(self, now: float) -> bool:
        return (
            self._sync_loss_cycles is not None
            and self._last_sync is not None
            and not self._sync_lost
            and self.node.nmt_state is NmtState.OPERATIONAL
            and now - self._last_sync > self._sync_loss_cycles * self._cycle_period()
        )

"""Supervision of the drive's heartbeat by the master: :class:`DriveSupervision`.

The drive's heartbeat (``0x700 + node id``) feeds a :class:`~drivers.heartbeat.HeartbeatMonitor`. Its loss (no
heartbeat for ``heartbeat_timeout_factor x 0x1017``) is a :class:`~drivers.errors.HeartbeatLostError`, found by the
next wait for feedback (:meth:`DriveSupervision.check`) or by the watchdog thread, which posts it. Once armed after
``configure``, a heartbeat reporting any other NMT state than OPERATIONAL while the master is operational is a
:class:`~drivers.errors.DriveNmtStateError` (a drive out of OPERATIONAL ignores RPDOs). A heartbeat frame of the wrong
length is a bad frame. Well-formed heartbeats are passed on to canopen's NMT state tracking.
"""

from __future__ import annotations

from collections.abc import Callable

from drivers.cia301 import NmtState, nmt_state_name
from drivers.errors import DriveNmtStateError, DriveTimeoutError, HeartbeatLostError, ProtocolError
from drivers.heartbeat import HeartbeatMonitor
from drivers.inprocess import LockstepClock
from drivers.master.inbox import Inbox
from drivers.master.link import MasterLink

__all__ = ["HEARTBEAT_WATCHDOG_POLL", "DriveSupervision"]

HEARTBEAT_WATCHDOG_POLL = 0.05  # s between checks of the drive's heartbeat deadline

Forward = Callable[[int, bytearray, float], None]


class DriveSupervision:
    """The master's consumer of the drive's heartbeat.

    Parameters
    ----------
    link, inbox
        The drive, and where a loss, a departure or a bad frame is posted.
    forward
        Called with every well-formed heartbeat frame (canopen's ``NmtMaster.on_heartbeat``).

    Attributes
    ----------
    monitor
        The last heartbeat's time and state, its loss; on a lockstep bus on the channel's simulated time.
    frames
        Heartbeat frames of the drive received (guarded by ``inbox.cv``).
    """

    def __init__(self, link: MasterLink, inbox: Inbox, *, forward: Forward) -> None:
        self._link = link
        self._inbox = inbox
        self._forward = forward
        lockstep = link.timebase if isinstance(link.timebase, LockstepClock) else None
        self.monitor = HeartbeatMonitor(link.node_id, lockstep=lockstep)
        self.frames = 0

    def on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """The Notifier thread's callback for the drive's heartbeat COB-ID."""
        if len(data) != 1:
            self._inbox.post(ProtocolError(f"heartbeat of node {self._link.node_id} has DLC {len(data)}, not 1"),
                             bad_frame=True)
            return
        with self._inbox.cv:
            self.frames += 1
        monitor = self.monitor
        before = monitor.last_state
        monitor.beat(data[0])
        state = monitor.last_state
        if (state is not None and state != NmtState.OPERATIONAL and before == NmtState.OPERATIONAL
                and self._link.operational and monitor.timeout > 0):
            self._inbox.post_departure(DriveNmtStateError(
                f"node {self._link.node_id} left NMT OPERATIONAL: its heartbeat reports {nmt_state_name(state)} "
                "while the bench runs (a drive outside OPERATIONAL ignores RPDOs)"))
        self._forward(can_id, data, timestamp)

    def on_lost(self, error: HeartbeatLostError) -> None:
        """The watchdog's report of a loss."""
        self._inbox.post_heartbeat_fault(error)

    def start_watchdog(self) -> None:
        """Watch the deadline on a thread, unless the bus is synchronous (time passes only in the control thread,
        which checks anyway)."""
        if not self._link.timebase.synchronous:
            self.monitor.start_watchdog(self.on_lost, poll=HEARTBEAT_WATCHDOG_POLL)

    def stop_watchdog(self) -> None:
        """Stop the watchdog thread (safe when it never ran)."""
        self.monitor.stop_watchdog()

    def check(self) -> None:
        """Raise :class:`HeartbeatLostError` when armed and overdue, flagging the heartbeat fault (the caller holds
        ``inbox.cv``: it is the wait for feedback)."""
        try:
            self.monitor.check()
        except HeartbeatLostError:
            self._inbox.heartbeat_fault = True
            raise

    def confirm_operational(self, beats_before: int) -> None:
        """After NMT start: wait for a heartbeat (numbered after ``beats_before``) reporting OPERATIONAL, then arm
        the loss detection; nothing when the drive produces no heartbeat (0x1017 = 0)."""
        cfg = self._link.cfg
        if cfg.heartbeat_producer_ms <= 0:
            return
        state = self.monitor.wait_for(
            lambda s: s == NmtState.OPERATIONAL,
            beats_before,
            timeout=cfg.state_timeout + 2 * cfg.heartbeat_producer_ms / 1000,
        )
        if state is None:
            raise DriveTimeoutError(
                f"node {self._link.node_id} did not report NMT OPERATIONAL in its heartbeat after NMT start"
            )
        self.monitor.arm(cfg.heartbeat_timeout_factor * cfg.heartbeat_producer_ms / 1000)

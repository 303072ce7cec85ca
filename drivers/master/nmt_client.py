"""The master's NMT client: commands to the drive, the reset that waits for its boot-up, and NMT tracking.

Commands go through canopen's ``NmtMaster`` (which tracks the state it commanded). canopen's tracking unpacks NMT
command frames without a length check: :meth:`NmtClient.on_command` replaces its subscription and passes it the
well-formed frames only (as :class:`~drivers.master.supervision.DriveSupervision` does for heartbeats). Every wait
here is for the drive's heartbeat (or boot-up) on the monitor of the supervision.
"""

from __future__ import annotations

from collections.abc import Iterable

import can
from canopen.nmt import NmtMaster

from drivers.cia301 import NmtCommand, NmtState
from drivers.errors import DriveError, DriveTimeoutError
from drivers.heartbeat import HeartbeatMonitor
from drivers.master.link import MasterLink

__all__ = ["NmtClient"]


class NmtClient:
    """NMT commands to the drive of ``link``; ``monitor`` sees its answers (heartbeats, the boot-up)."""

    def __init__(self, link: MasterLink, monitor: HeartbeatMonitor) -> None:
        self._link = link
        self._monitor = monitor
        self.master: NmtMaster = link.node.nmt

    def send(self, command: NmtCommand) -> None:
        """Send ``command`` to the drive; a bus failure is a :class:`DriveError`."""
        try:
            self.master.send_command(int(command))
        except can.CanError as exc:
            raise DriveError(f"cannot send NMT {command.name} to node {self._link.node_id}: {exc}") from exc

    def reset_communication(self) -> None:
        """NMT reset communication, then wait for the boot-up; a :class:`DriveTimeoutError` that says what to check
        when none comes within ``state_timeout``."""
        timeout = self._link.cfg.state_timeout
        beats_before = self._monitor.beats
        self.send(NmtCommand.RESET_COMMUNICATION)
        # boot-up (state 0) is what CiA 301 sends; a heartbeat in pre-operational also proves the reset is done
        state = self._monitor.wait_for(lambda s: s in (NmtState.INITIALISING, NmtState.PRE_OPERATIONAL),
                                       beats_before, timeout=timeout)
        if state is None:
            raise DriveTimeoutError(
                f"no boot-up from node {self._link.node_id} within {timeout} s after NMT reset "
                "communication: is the drive powered, on this bus, with this node id?"
            )

    def enter(self, command: NmtCommand, states: Iterable[NmtState], timeout: float) -> None:
        """Send ``command`` and wait (bounded) for a heartbeat in one of ``states``; a missing heartbeat is not an
        error here: what follows (an SDO read) is what confirms."""
        accepted = tuple(states)
        self._monitor.disarm()
        beats_before = self._monitor.beats
        self.send(command)
        self._monitor.wait_for(lambda s: s in accepted, beats_before, timeout=timeout)

    def on_command(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """The Notifier thread's callback for NMT command frames (COB-ID 0): tracked when well formed."""
        if len(data) >= 2:  # command and node id; a drive ignores a shorter frame, and so does the tracking here
            self.master.on_command(can_id, data, timestamp)

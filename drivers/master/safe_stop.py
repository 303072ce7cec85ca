"""The confirmed stop: :class:`SafeStop`, quick stop then disable voltage, read back from the drive.

The paths of :class:`~drivers.drive.StopPath` are tried in order until one confirms a disabled power stage: the RPDO
(only while the drive's heartbeat says OPERATIONAL: outside it a drive ignores RPDOs), an SDO write of 0x6040 (not in
NMT STOPPED), NMT enter pre-operational then SDO (which also triggers the drive's own 0x6007 reaction), and last NMT
reset node (an application reset switches the power stage off). The :class:`~drivers.drive.StopReport` says what was
read back, or that nothing could be, and the faults the drive reported that nobody raised. It never raises: every
exit path calls it.
"""

from __future__ import annotations

import logging

from drivers.cia301 import NmtCommand, NmtState, nmt_state_name
from drivers.cia402 import Command402, Obj, State402, decode_state
from drivers.drive import DISABLED_STATES, StopPath, StopReport
from drivers.errors import DriveError
from drivers.heartbeat import HeartbeatMonitor
from drivers.master.cyclic import CyclicPath
from drivers.master.inbox import Inbox
from drivers.master.link import MasterLink
from drivers.master.nmt_client import NmtClient
from drivers.master.sdo_client import U16, SdoClient
from drivers.master.state402 import DISABLE_GOAL, QUICK_STOP_GOAL, PowerStateCommands

__all__ = ["SafeStop"]

logger = logging.getLogger("drivers.cia402_master")  # the master's log, as before the split into services


class SafeStop:
    """The confirmed stop of one drive, over every path the master has to it."""

    def __init__(self, link: MasterLink, cyclic: CyclicPath, power: PowerStateCommands, nmt: NmtClient,
                 monitor: HeartbeatMonitor, sdo: SdoClient, inbox: Inbox) -> None:
        self._link = link
        self._cyclic = cyclic
        self._power = power
        self._nmt = nmt
        self._monitor = monitor
        self._sdo = sdo
        self._inbox = inbox

    def run(self) -> StopReport:
        """Stop and read back (module docstring); never raises."""
        link = self._link
        if link.closed or not link.connected:
            return StopReport(commanded=False, confirmed=False)
        attempts: list[str] = []
        statusword: int | None = None
        state: State402 | None = None
        for path in StopPath:
            self._cyclic.target_raw = 0
            try:
                statusword = self._via(path)
                state = decode_state(statusword)
            except Exception as exc:  # safe_stop never raises: every exit path calls it
                attempts.append(f"{path}: {exc}")
                logger.info("safe stop of node %d via %s failed: %s", link.node_id, path, exc)
                continue
            if state in DISABLED_STATES:
                report = StopReport(True, True, state, statusword, path, tuple(attempts), self._inbox.pending_faults())
                logger.info("%s", report.describe(link.node_id))
                return report
            attempts.append(f"{path}: drive still {state.name}")
        report = StopReport(True, False, state, statusword, None, tuple(attempts), self._inbox.pending_faults())
        logger.info("%s", report.describe(link.node_id))  # the caller has the report; the CLI says it in its one line
        return report

    def _via(self, path: StopPath) -> int:
        """Quick stop then disable voltage through ``path``; the statusword read back afterwards."""
        link = self._link
        short = min(link.cfg.state_timeout, 0.5)
        nmt = self._monitor.last_state
        if path is StopPath.PDO:
            if not link.operational or self._cyclic.rpdo_codec is None:
                raise DriveError("no PDO path (the drive was never started)")
            if nmt is not None and nmt != NmtState.OPERATIONAL:
                raise DriveError(f"the drive reports NMT {nmt_state_name(nmt)}: it ignores RPDOs")
        else:
            link.operational = False  # from here on, commands go over SDO
            if path is StopPath.SDO and nmt == NmtState.STOPPED:
                raise DriveError("the drive reports NMT STOPPED: it answers no SDO")
            if path is StopPath.NMT_SDO:
                self._nmt.enter(NmtCommand.ENTER_PRE_OPERATIONAL, (NmtState.PRE_OPERATIONAL,), short)
            elif path is StopPath.NMT_RESET:
                self._nmt.enter(NmtCommand.RESET_NODE, (NmtState.INITIALISING, NmtState.PRE_OPERATIONAL),
                                link.cfg.state_timeout)
                return self._sdo.read(Obj.STATUSWORD, 0, U16)  # the application reset itself disabled the power stage
        self._power.drive_to(Command402.QUICK_STOP, QUICK_STOP_GOAL, short, ignore_errors=True)
        self._power.drive_to(Command402.DISABLE_VOLTAGE, DISABLE_GOAL, short, ignore_errors=True)
        return self._power.last_statusword

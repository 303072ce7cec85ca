"""The drive's CiA 402 state as the master commands it: :class:`PowerStateCommands`.

Enable walks controlword 0x06 / 0x07 / 0x0F (:data:`drivers.cia402.ENABLE_PATH`) through the RPDO, one SYNC each,
until the TPDO statusword shows OPERATION_ENABLED; disable, quick stop and fault reset repeat their controlword until
the drive shows one of their goal states, over the cyclic path while the drive is operational, else over SDO
(controlword 0x6040 written, statusword 0x6041 read back). A state that does not change within ``state_timeout`` is a
:class:`~drivers.errors.StateTransitionError` naming where it stuck.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from drivers.cia402 import ENABLE_PATH, Command402, Obj, State402, decode_state
from drivers.drive import Feedback
from drivers.errors import DriveFaultError, FeedbackTimeoutError, ProductError, ProtocolError, StateTransitionError
from drivers.master.cyclic import CyclicPath
from drivers.master.inbox import Inbox
from drivers.master.link import MasterLink
from drivers.master.sdo_client import U16, SdoClient

__all__ = ["DISABLE_GOAL", "QUICK_STOP_GOAL", "PowerStateCommands"]

QUICK_STOP_GOAL = frozenset({State402.QUICK_STOP_ACTIVE, State402.SWITCH_ON_DISABLED, State402.FAULT})
DISABLE_GOAL = frozenset({State402.SWITCH_ON_DISABLED, State402.FAULT})


class PowerStateCommands:
    """The 402 commands to one drive.

    Parameters
    ----------
    link, cyclic, sdo, inbox
        The drive; the paths a command takes (PDO while operational, else SDO); the errors a fault reset answers.
    restore_communication
        Brings the drive's communication back after a heartbeat fault (NMT reset communication, boot-up, the last
        ``configure``): a fault reset calls it first then.

    Attributes
    ----------
    last_statusword
        The statusword of the last state exchange (PDO or SDO).
    """

    def __init__(self, link: MasterLink, cyclic: CyclicPath, sdo: SdoClient, inbox: Inbox, *,
                 restore_communication: Callable[[], None]) -> None:
        self._link = link
        self._cyclic = cyclic
        self._sdo = sdo
        self._inbox = inbox
        self._restore = restore_communication
        self.last_statusword = 0

    def enable(self) -> None:
        """Controlword 0x06 / 0x07 / 0x0F until OPERATION_ENABLED (target held at 0); on failure, quick stop."""
        self._link.require_operational()
        cyclic = self._cyclic
        cyclic.target_raw = 0
        try:
            state = self._answered(cyclic.controlword).state
            for _ in range(len(State402) + 2):  # the path is at most 4 transitions; bounded against a looping drive
                if state is State402.OPERATION_ENABLED:
                    return
                if state is State402.FAULT:
                    raise DriveFaultError(
                        f"node {self._link.node_id} is in FAULT; fault_reset() first "
                        f"(statusword 0x{self._statusword():04X})"
                    )
                state = self._leave(state, ENABLE_PATH[state], goal=State402.OPERATION_ENABLED)
            raise StateTransitionError(
                f"node {self._link.node_id} never reached OPERATION_ENABLED (last state {state.name})"
            )
        except ProductError:
            cyclic.fail_safe()
            raise

    def disable(self) -> None:
        """Disable voltage until SWITCH_ON_DISABLED (or FAULT, which disable voltage does not leave)."""
        self._link.require_connected()
        self._cyclic.target_raw = 0
        self.drive_to(Command402.DISABLE_VOLTAGE, DISABLE_GOAL, self._link.cfg.state_timeout)

    def quick_stop(self) -> None:
        """Quick stop until QUICK_STOP_ACTIVE, or SWITCH_ON_DISABLED (quick stop options 0..4, or not enabled)."""
        self._link.require_connected()
        self._cyclic.target_raw = 0
        self.drive_to(Command402.QUICK_STOP, QUICK_STOP_GOAL, self._link.cfg.state_timeout)

    def fault_reset(self) -> None:
        """Rising edge on controlword bit 7 until the drive leaves FAULT; after a heartbeat fault the drive's
        communication is restored first (see ``restore_communication``)."""
        link = self._link
        link.require_connected()
        if self._inbox.take_heartbeat_fault() and self._cyclic.mode is not None:
            self._restore()
        self._cyclic.target_raw = 0
        self.command_state(int(Command402.DISABLE_VOLTAGE))  # bit 7 low first: the reset acts on the rising edge
        timeout = link.cfg.state_timeout
        deadline = link.timebase.now() + timeout
        state = self.command_state(int(Command402.FAULT_RESET))
        while state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
            if link.timebase.now() > deadline:
                self.command_state(int(Command402.DISABLE_VOLTAGE))
                raise StateTransitionError(
                    f"node {link.node_id} stuck in {state.name}: fault reset (controlword 0x80) for "
                    f"{timeout} s did not clear it"
                )
            state = self.command_state(int(Command402.FAULT_RESET))
        self.command_state(int(Command402.DISABLE_VOLTAGE))
        self._inbox.clear_fault()

    def drive_to(self, command: Command402, goal: frozenset[State402], timeout: float, *,
                 ignore_errors: bool = False) -> None:
        """Send ``command`` until the drive is in one of ``goal`` (over PDO when operational, else SDO).

        ``ignore_errors``: errors the drive reported earlier (already raised to the caller, or about to be in the
        stop report) do not interrupt the exchange; a stop must go on through them.
        """
        timebase = self._link.timebase
        deadline = timebase.now() + timeout
        while True:
            state = self.command_state(int(command), ignore_errors=ignore_errors)
            if state in goal:
                return
            if timebase.now() > deadline:
                names = " or ".join(sorted(s.name for s in goal))
                raise StateTransitionError(
                    f"node {self._link.node_id} stuck in {state.name}: controlword 0x{int(command):02X} "
                    f"({command.name}) for {timeout} s did not reach {names}"
                )

    def command_state(self, controlword: int, *, ignore_errors: bool = False) -> State402:
        """One exchange with ``controlword``: the 402 state the drive shows afterwards."""
        cyclic = self._cyclic
        if self._link.operational and cyclic.rpdo_codec is not None:
            feedback = cyclic.exchange(controlword, ignore_errors=ignore_errors)
            self.last_statusword = feedback.statusword
            return feedback.state
        cyclic.controlword = controlword
        self._sdo.write(Obj.CONTROLWORD, 0, U16, controlword)
        self._link.timebase.sleep(cyclic.sample_time)
        statusword = self._sdo.read(Obj.STATUSWORD, 0, U16)
        self.last_statusword = statusword
        try:
            return decode_state(statusword)
        except ValueError as exc:
            raise ProtocolError(f"node {self._link.node_id}: {exc}") from exc

    def _leave(self, state: State402, command: Command402 | None, *, goal: State402) -> State402:
        """Repeat ``command`` until the drive leaves ``state``; StateTransitionError naming it otherwise."""
        link = self._link
        controlword = self._cyclic.controlword if command is None else int(command)
        deadline = link.timebase.now() + link.cfg.state_timeout
        while True:
            new_state = self._answered(controlword).state
            if new_state is not state:
                return new_state
            if link.timebase.now() > deadline:
                what = f"controlword 0x{controlword:02X} ({command.name})" if command else "waiting"
                raise StateTransitionError(
                    f"node {link.node_id} stuck in {state.name}: {what} for {link.cfg.state_timeout} s did not "
                    f"leave it (wanted {goal.name})"
                )

    def _answered(self, controlword: int) -> Feedback:
        """One exchange of the enable path, sent again while its SYNC goes unanswered, up to ``state_timeout``'s worth
        of waits. Why: on a loaded host one answer can come later than the exchange's bound (0.2 s; a CI run's
        enable failed so), and a controlword is a level, so sending it again changes nothing on the drive. A mute
        drive still fails, after ``state_timeout``; on a synchronous bus an answer is there or never, so once."""
        cyclic, link = self._cyclic, self._link
        waits = math.ceil(link.cfg.state_timeout / cyclic.exchange_timeout())
        tries = 1 if link.timebase.synchronous else max(1, waits)
        for _ in range(tries - 1):
            try:
                return cyclic.exchange(controlword)
            except FeedbackTimeoutError:
                continue  # unanswered: the same controlword with the next SYNC
        return cyclic.exchange(controlword)

    def _statusword(self) -> int:
        with self._inbox.cv:
            feedback = self._cyclic.feedback
        return feedback.statusword if feedback is not None else 0

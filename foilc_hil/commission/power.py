"""``commission enable|disable|fault-reset``: walk the CiA 402 power state machine and report every transition.

These commands act over SDO (controlword 0x6040 written, statusword 0x6041 polled), not over PDOs: they must work
on a drive in any NMT state the SDO server answers in, with whatever PDO mapping it has, and they leave its
communication settings alone (no NMT reset, no PDO configuration) -- except before a fault reset after a
communication fault, below.

- ``enable``: from each state, the command that leads towards OPERATION ENABLED (shutdown 0x06, switch on 0x07,
  enable operation 0x0F; disable voltage 0x00 out of QUICK STOP ACTIVE). A drive in FAULT is refused: reset it first.
- ``disable``: disable voltage 0x00 until SWITCH ON DISABLED (a drive in FAULT stays there, reported).
- ``fault-reset``: if 0x603F shows a heartbeat or SYNC loss (EMCY 0x8130 / 0x8700), the fault is a communication
  fault and real drives keep re-raising it until their communication is restarted: NMT reset communication
  first, wait for the boot-up, then the fault reset (controlword 0x00 then 0x80, the reset acts on the rising edge
  of bit 7) until the drive leaves FAULT, then 0x00.

Every state seen is recorded with the time since the command started (:class:`Transition`). A state that is not
left within ``state_timeout`` raises :class:`~foilc_hil.errors.StateTransitionError` naming it (exit 1).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import can

from drivers.cia301 import EmcyCode, NmtCommand, NmtState, emcy_text
from drivers.cia402 import ENABLE_PATH, Command402, Obj, OperationMode, State402, decode_state
from drivers.cia402_master import Cia402Drive
from foilc_hil.errors import DriveError, DriveFaultError, DriveTimeoutError, ProtocolError, StateTransitionError

__all__ = ["PowerReport", "Transition", "disable", "disable_all", "enable", "fault_reset"]

logger = logging.getLogger(__name__)

POLL_PERIOD = 0.01  # s between statusword reads while waiting for a transition
COMMUNICATION_FAULTS = frozenset({int(EmcyCode.HEARTBEAT_LOSS), int(EmcyCode.SYNC_LOSS)})



@dataclass(frozen=True)
class Transition:
    """One state the drive was seen in: when (seconds since the command started), the statusword and the
    controlword the master was sending."""

    time: float
    state: State402
    statusword: int
    controlword: int | None

    def to_json(self) -> dict[str, Any]:
        return {
            "t": round(self.time, 6),
            "state": self.state.name,
            "statusword": f"0x{self.statusword:04X}",
            "controlword": None if self.controlword is None else f"0x{self.controlword:02X}",
        }


@dataclass
class PowerReport:
    """What a power command did."""

    action: str
    node_id: int
    transitions: list[Transition] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    final_state: State402 | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "action": self.action,
            "node_id": self.node_id,
            "final_state": None if self.final_state is None else self.final_state.name,
            "transitions": [t.to_json() for t in self.transitions],
            "notes": list(self.notes),
        }

    def render(self) -> str:
        lines = [f"node {self.node_id} {self.action}:"]
        lines += [f"  {note}" for note in self.notes]
        for item in self.transitions:
            sent = "" if item.controlword is None else f" (controlword {item.controlword:#04x})"
            lines.append(f"  {item.time:8.3f} s  {item.state.name:<24} statusword 0x{item.statusword:04X}{sent}")
        if self.final_state is not None:
            lines.append(f"  -> {self.final_state.name}")
        return "\n".join(lines)


class _Walker:
    """Controlword writes and statusword polls over SDO, recording each new state."""

    def __init__(self, drive: Cia402Drive, report: PowerReport, timeout: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.drive = drive
        self.report = report
        self.timeout = timeout
        self.clock = clock
        self.start = clock()
        self.controlword: int | None = None
        self.state = self.read()

    def read(self) -> State402:
        statusword = self.drive.read_object(Obj.STATUSWORD)
        try:
            state = decode_state(statusword)
        except ValueError as exc:
            raise ProtocolError(f"node {self.drive.node_id}: {exc}") from exc
        transitions = self.report.transitions
        if not transitions or transitions[-1].state is not state:
            transitions.append(Transition(self.clock() - self.start, state, statusword, self.controlword))
        self.state = state
        return state

    def command(self, controlword: int) -> None:
        self.controlword = controlword
        self.drive.write_object(Obj.CONTROLWORD, 0, controlword)

    def leave(self, command: Command402 | None, goal: str) -> State402:
        """Send ``command`` (if any) until the drive leaves the present state; StateTransitionError if not."""
        stuck = self.state
        deadline = self.clock() + self.timeout
        if command is not None:
            self.command(int(command))
        while True:
            if self.read() is not stuck:
                return self.state
            if self.clock() > deadline:
                what = f"controlword 0x{int(command):02X} ({command.name})" if command is not None else "waiting"
                raise StateTransitionError(
                    f"node {self.drive.node_id} stuck in {stuck.name}: {what} for {self.timeout} s did not leave "
                    f"it (wanted {goal})"
                )
            time.sleep(POLL_PERIOD)


def enable(drive: Cia402Drive, *, state_timeout: float, mode: OperationMode | None = None) -> PowerReport:
    """Walk to OPERATION ENABLED; DriveFaultError for a drive in FAULT, StateTransitionError when stuck.

    With ``mode``, first the checks ``run`` makes before configuring the drive for it
    (:meth:`~drivers.cia402_master.Cia402Drive.preflight`): a drive ``run`` would refuse is refused here, before
    any motion, with the same error; the objects ``run`` would leave out are listed in the notes.
    """
    report = PowerReport("enable", drive.node_id)
    if mode is not None:
        plan = drive.preflight(mode)
        mapped = "; ".join(f"{layout.name}: " + ", ".join(f"0x{v.index:04X}" for v in layout.variables)
                           for layout in (*plan.rpdos, *plan.tpdos))
        report.notes.append(f"run can configure {mode.name}: {mapped}")
        report.notes.extend(plan.notes)
    walker = _Walker(drive, report, state_timeout)
    for _ in range(2 * len(State402)):  # at most four transitions on the way; bounded against a looping drive
        state = walker.state
        if state is State402.OPERATION_ENABLED:
            report.final_state = state
            return report
        if state is State402.FAULT:
            report.final_state = state
            code = _error_code(drive)
            raise DriveFaultError(
                f"node {drive.node_id} is in FAULT (0x603F 0x{code:04X}: {emcy_text(code)}); "
                "run `foilc-hil commission fault-reset` first"
            )
        walker.leave(ENABLE_PATH[state], "OPERATION_ENABLED")
    raise StateTransitionError(f"node {drive.node_id} never reached OPERATION_ENABLED (last state {walker.state.name})")


def disable(drive: Cia402Drive, *, state_timeout: float) -> PowerReport:
    """Disable voltage until SWITCH ON DISABLED (a drive in FAULT stays in FAULT; reported in the notes)."""
    report = PowerReport("disable", drive.node_id)
    walker = _Walker(drive, report, state_timeout)
    goal = {State402.SWITCH_ON_DISABLED, State402.FAULT}
    if walker.state not in goal:
        walker.command(int(Command402.DISABLE_VOLTAGE))
        deadline = time.monotonic() + state_timeout
        while walker.read() not in goal:
            if time.monotonic() > deadline:
                raise StateTransitionError(
                    f"node {drive.node_id} stuck in {walker.state.name}: controlword 0x00 (DISABLE_VOLTAGE) for "
                    f"{state_timeout} s did not reach SWITCH_ON_DISABLED"
                )
            time.sleep(POLL_PERIOD)
    if walker.state is State402.FAULT:
        report.notes.append("the drive is in FAULT, which disable voltage does not leave; use fault-reset")
    report.final_state = walker.state
    return report


def disable_all(drives: Sequence[Cia402Drive], *, state_timeout: float) -> None:
    """Best effort: :func:`disable` every drive (an error on one is logged and does not stop the others).

    Called while another error propagates (a multi-node ``enable`` that failed on a later node), so it never raises.
    """
    for drive in drives:
        try:
            disable(drive, state_timeout=state_timeout)
        except Exception as exc:  # the original error is what the caller reports
            logger.warning("could not disable node %d after a failed enable: %s", drive.node_id, exc)


def fault_reset(drive: Cia402Drive, *, state_timeout: float) -> PowerReport:
    """Clear a fault (see the module docstring); NMT reset communication first after a communication fault."""
    report = PowerReport("fault-reset", drive.node_id)
    code = _error_code(drive)
    if code in COMMUNICATION_FAULTS:
        report.notes.append(
            f"0x603F = 0x{code:04X} ({emcy_text(code)}): communication fault, NMT reset communication first"
        )
        _reset_communication(drive, state_timeout)
        report.notes.append("boot-up received after NMT reset communication")
    walker = _Walker(drive, report, state_timeout)
    if walker.state not in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
        report.notes.append(f"no fault to reset (drive in {walker.state.name})")
        report.final_state = walker.state
        return report
    if walker.state is State402.FAULT_REACTION_ACTIVE:
        walker.leave(None, "FAULT")  # the reaction finishes by itself
    walker.command(int(Command402.DISABLE_VOLTAGE))  # bit 7 low first: the reset acts on the rising edge
    walker.leave(Command402.FAULT_RESET, "SWITCH_ON_DISABLED")
    walker.command(int(Command402.DISABLE_VOLTAGE))
    walker.read()
    remaining = _error_code(drive)
    if remaining:
        report.notes.append(f"0x603F still shows 0x{remaining:04X} ({emcy_text(remaining)})")
    report.final_state = walker.state
    return report


def _error_code(drive: Cia402Drive) -> int:
    return drive.read_object(Obj.ERROR_CODE) if Obj.ERROR_CODE in drive.od else 0


def _reset_communication(drive: Cia402Drive, timeout: float) -> None:
    beats_before = drive.heartbeat.beats
    try:
        drive.node.nmt.send_command(int(NmtCommand.RESET_COMMUNICATION))
    except can.CanError as exc:
        raise DriveError(f"cannot send NMT reset communication to node {drive.node_id}: {exc}") from exc
    state = drive.heartbeat.wait_for(
        lambda s: s in (NmtState.INITIALISING, NmtState.PRE_OPERATIONAL), beats_before, timeout=timeout
    )
    if state is None:
        raise DriveTimeoutError(
            f"no boot-up from node {drive.node_id} within {timeout} s after NMT reset communication"
        )

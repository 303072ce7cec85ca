"""The CiA 402 application of the virtual drive: controlword and mode, faults, EMCY, statusword.

The power state machine itself is the table-driven :class:`~plant_emulator.state_machine.PowerStateMachine`;
this object feeds it the controlwords that reach the store, raises faults (EMCY, 0x603F, 0x1001, transition
13), applies the abort-connection option 0x6007 to communication losses and keeps 0x6041 / 0x6061 up to date.
"""

from __future__ import annotations

from collections.abc import Callable
from enum import StrEnum

from drivers.cia301 import EmcyCode, ErrorRegister, NmtState
from drivers.cia402 import (
    FAULT_RESET_BIT,
    AbortConnectionOption,
    Command402,
    Obj,
    OperationMode,
    QuickStopOption,
    State402,
)
from plant_emulator.axis import Axis, Units
from plant_emulator.node import EmulatedNode
from plant_emulator.sdo_guard import SUPPORTED_MODES
from plant_emulator.settings import EmulatorConfig
from plant_emulator.state_machine import MotionKind, PowerStateMachine

__all__ = ["APPLICATION_OBJECTS", "FAULT_CODES", "Cia402Application", "FaultKind"]


class FaultKind(StrEnum):
    """Faults the drive detects (and tests can inject)."""

    OVER_CURRENT = "over-current"
    OVER_SPEED = "over-speed"
    HEARTBEAT_LOSS = "heartbeat-loss"
    SYNC_LOSS = "sync-loss"
    NMT_LEFT_OPERATIONAL = "nmt-left-operational"
    GENERIC = "generic"
    PLANT_DIVERGED = "plant-diverged"  # the emulated physics gave a non-finite output


# fault -> (EMCY error code, error register bits besides "generic")
FAULT_CODES: dict[FaultKind, tuple[EmcyCode, int]] = {
    FaultKind.OVER_CURRENT: (EmcyCode.OVER_CURRENT, ErrorRegister.CURRENT),
    FaultKind.OVER_SPEED: (EmcyCode.OVER_SPEED, ErrorRegister.DEVICE_PROFILE),
    FaultKind.HEARTBEAT_LOSS: (EmcyCode.HEARTBEAT_LOSS, ErrorRegister.COMMUNICATION),
    FaultKind.SYNC_LOSS: (EmcyCode.SYNC_LOSS, ErrorRegister.COMMUNICATION),
    FaultKind.NMT_LEFT_OPERATIONAL: (EmcyCode.COMMUNICATION, ErrorRegister.COMMUNICATION),
    FaultKind.GENERIC: (EmcyCode.GENERIC, 0),
    FaultKind.PLANT_DIVERGED: (EmcyCode.INTERNAL_SOFTWARE, ErrorRegister.MANUFACTURER),
}
_COMMUNICATION_FAULTS = frozenset({FaultKind.HEARTBEAT_LOSS, FaultKind.SYNC_LOSS, FaultKind.NMT_LEFT_OPERATIONAL})
# the power stage may produce torque in these states: an abort-connection event must act on them
_POWERED_STATES = frozenset({State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE})
APPLICATION_OBJECTS = frozenset({Obj.CONTROLWORD, Obj.MODES_OF_OPERATION, Obj.QUICK_STOP_OPTION})
"""Objects whose write the application reacts to (:meth:`Cia402Application.react`)."""


class Cia402Application:
    """Controlword, mode, faults and status of one axis.

    Parameters
    ----------
    node
        The drive's node (store, EMCY producer, NMT state).
    settings
        The ``emulator:`` section (velocity window).
    axis
        The motion state shared with the physics tick.
    units
        Plant <-> drive units.
    on_state_change
        Called after the 402 state changed or a fault was raised (the PDO engine sends event-driven TPDOs).
    """

    def __init__(
        self,
        node: EmulatedNode,
        settings: EmulatorConfig,
        axis: Axis,
        units: Units,
        *,
        on_state_change: Callable[[], None],
    ) -> None:
        self.node = node
        self.settings = settings
        self.axis = axis
        self.units = units
        self._on_state_change = on_state_change
        self.machine = PowerStateMachine()
        self.emcy_log: list[tuple[int, int]] = []  # (code, register) as sent, for tests and the CLI
        self._latched_errors: list[EmcyCode] = []
        self._fault_reset_bit = False
        self._statuswords: dict[tuple[State402, int, bool, bool], int] = {}
        # (controlword, state, quick stop option) whose last application changed nothing: the master repeats its
        # controlword in every RPDO, so in steady state the table lookup is skipped (same input, same no-op)
        self._idle: tuple[int, State402, int] | None = None

    def power_on(self) -> None:
        """A fresh application (power on or NMT reset node; the store was reset first): *switch on disabled*."""
        self.machine = PowerStateMachine(quick_stop_option=self._quick_stop_option())
        self.machine.power_on()
        self._idle = None  # a new machine: its fault-reset edge starts again
        self._latched_errors.clear()
        self._fault_reset_bit = False
        self.publish_status()

    def react(self, index: int) -> None:
        """A value of :data:`APPLICATION_OBJECTS` is now in the store (from SDO or RPDO)."""
        if index == Obj.CONTROLWORD:
            self._apply_controlword(self.node.read(Obj.CONTROLWORD))
        elif index == Obj.MODES_OF_OPERATION:
            self._apply_mode(self.node.read(Obj.MODES_OF_OPERATION))
        elif index == Obj.QUICK_STOP_OPTION:
            self.machine.quick_stop_option = self._quick_stop_option()

    # --- faults -----------------------------------------------------------------------------------------------

    def detect(self, fault: FaultKind) -> None:
        """Fault ``fault`` as the drive detects it: EMCY, 0x603F, 0x1001, then the fault or 0x6007 reaction."""
        if fault in _COMMUNICATION_FAULTS:
            self._communication_abort(fault)
        else:
            self.raise_fault(fault)
        self.publish_status()
        self._on_state_change()

    def left_operational(self) -> None:
        """NMT left OPERATIONAL: no RPDO reaches the drive any more, so a powered axis applies 0x6007."""
        # Why: a master could no longer stop it over PDO. CiA 402 drives apply the abort-connection reaction when
        # the NMT state leaves OPERATIONAL (NMT stop or pre-operational, by anyone) while the power stage is on.
        if self.machine.state in _POWERED_STATES:
            self.detect(FaultKind.NMT_LEFT_OPERATIONAL)

    def raise_fault(self, fault: FaultKind) -> None:
        """Latch the error and enter *fault reaction active* (a fault already latched in *fault* is not resent)."""
        code, register_bits = FAULT_CODES[fault]
        if self.machine.state is State402.FAULT and code in self._latched_errors:
            return
        self._latch_error(code, register_bits)
        self.machine.fault()
        # Fault reaction "disable drive": torque off at once, so the reaction is complete immediately (14).
        if self.machine.motion() is MotionKind.TORQUE_OFF:
            self.machine.ramp_finished()

    def _communication_abort(self, fault: FaultKind) -> None:
        """Heartbeat or SYNC loss, or NMT leaving OPERATIONAL: EMCY, then the 0x6007 reaction."""
        option = (int(self.node.read(Obj.ABORT_CONNECTION_OPTION)) if self.node.has(Obj.ABORT_CONNECTION_OPTION)
                  else int(AbortConnectionOption.FAULT))
        if option == AbortConnectionOption.FAULT:
            self.raise_fault(fault)
            return
        code, register_bits = FAULT_CODES[fault]
        self._latch_error(code, register_bits)
        self._idle = None  # the machine gets a controlword of its own below (its fault-reset edge moves)
        keep = self.machine.state
        if option == AbortConnectionOption.DISABLE_VOLTAGE:
            self.machine.apply_controlword(Command402.DISABLE_VOLTAGE)
        elif option == AbortConnectionOption.QUICK_STOP:
            self.machine.apply_controlword(Command402.QUICK_STOP)
            if self.machine.state is State402.QUICK_STOP_ACTIVE and keep is not State402.QUICK_STOP_ACTIVE:
                self.axis.start_ramp()

    def _latch_error(self, code: EmcyCode, register_bits: int) -> None:
        if code not in self._latched_errors:
            self._latched_errors.append(code)
        register = int(self.node.read(Obj.ERROR_REGISTER)) | ErrorRegister.GENERIC | register_bits
        self.node.produce(Obj.ERROR_REGISTER, register)
        self.node.produce(Obj.ERROR_CODE, int(code))
        self.emcy(int(code), register)

    def _clear_errors(self) -> None:
        self._latched_errors.clear()
        self.axis.torque_limited_cycles = 0
        self.node.produce(Obj.ERROR_REGISTER, 0)
        self.node.produce(Obj.ERROR_CODE, 0)
        self.emcy(EmcyCode.NO_ERROR, 0)

    # --- EMCY -------------------------------------------------------------------------------------------------

    def emcy(self, code: int, register: int, data: bytes = b"") -> None:
        """Log and send an EMCY frame (not from NMT stopped, CiA 301: the error stays latched in 0x1001/0x603F)."""
        self.emcy_log.append((code, register))
        if self.node.sending and self.node.nmt_state is not NmtState.STOPPED:
            self.node.emcy.send(code, register, data)

    def pdo_length_error(self) -> None:
        """An RPDO shorter than its mapping: EMCY 0x8210 with the present error register, no state change."""
        self.emcy(EmcyCode.PDO_LENGTH, int(self.node.read(Obj.ERROR_REGISTER)))

    # --- controlword, mode, status ----------------------------------------------------------------------------

    def _quick_stop_option(self) -> int:
        if not self.node.has(Obj.QUICK_STOP_OPTION):
            return int(QuickStopOption.QUICK_STOP_RAMP_THEN_DISABLE)
        return int(self.node.read(Obj.QUICK_STOP_OPTION))

    def _apply_controlword(self, controlword: int) -> None:
        machine = self.machine
        before = machine.state
        key = (controlword, before, machine.quick_stop_option)
        if key == self._idle:
            return  # applied in this very state last time and nothing happened: it would not now either
        reset_bit = bool(controlword & FAULT_RESET_BIT)
        rising = reset_bit and not self._fault_reset_bit
        self._fault_reset_bit = reset_bit
        after = machine.apply_controlword(controlword)
        # a repeat finds the fault-reset bit already recorded (here and in the machine): no edge, the same no-op
        self._idle = key if after is before else None
        if rising and (before is State402.FAULT or self._latched_errors):
            self._clear_errors()
        if after is State402.QUICK_STOP_ACTIVE and before is not State402.QUICK_STOP_ACTIVE:
            self.axis.start_ramp()
        if after is State402.OPERATION_ENABLED and before is not State402.OPERATION_ENABLED:
            self.axis.profile_velocity = self.axis.velocity  # PV ramps start where the axis is
        if after != before:
            self.publish_status()
            self._on_state_change()

    def _apply_mode(self, mode: int) -> None:
        if mode in SUPPORTED_MODES:
            self.node.produce(Obj.MODES_OF_OPERATION_DISPLAY, mode)
            self.axis.profile_velocity = self.axis.velocity
            self.publish_status()

    def publish_status(self) -> None:
        """0x6041 from the state, the mode shown in 0x6061, target reached and the internal limit."""
        mode = int(self.node.read(Obj.MODES_OF_OPERATION_DISPLAY))
        target_reached = False
        if self.machine.state is State402.OPERATION_ENABLED and mode == OperationMode.PROFILE_VELOCITY:
            target = float(self.node.read(Obj.TARGET_VELOCITY))
            window = self.units.counts(self.settings.velocity_window)
            target_reached = abs(self.axis.velocity - target) <= window
        elif self.machine.state is State402.QUICK_STOP_ACTIVE:
            target_reached = self.machine.ramp_done
        key = (self.machine.state, mode, target_reached, self.axis.internal_limit)
        word = self._statuswords.get(key)
        if word is None:  # the statusword is a function of these four: made once each, looked up every cycle
            word = self._statuswords[key] = self.machine.statusword(mode, target_reached=target_reached,
                                                                    internal_limit=self.axis.internal_limit)
        self.node.produce(Obj.STATUSWORD, word)

"""The CiA 402 power drive state machine of the virtual drive: pure, table-driven, no CAN.

The device (:mod:`plant_emulator.device`) feeds it controlwords, ramp completion and faults; it answers with
the new state and the statusword. Transition numbers in comments are those of CiA 402-2 (figure "state
machine"):

====  =========================================  ==========================================
 no.  from -> to                                 trigger
====  =========================================  ==========================================
  0   start -> not ready to switch on            power on (automatic)
  1   not ready -> switch on disabled            self test done (automatic)
  2   switch on disabled -> ready to switch on   shutdown
  3   ready to switch on -> switched on          switch on
  4   switched on -> operation enabled           enable operation
  5   operation enabled -> switched on           disable operation
  6   switched on -> ready to switch on          shutdown
  7   ready to switch on -> switch on disabled   disable voltage or quick stop
  8   operation enabled -> ready to switch on    shutdown
  9   operation enabled -> switch on disabled    disable voltage
 10   switched on -> switch on disabled          disable voltage or quick stop
 11   operation enabled -> quick stop active     quick stop
 12   quick stop active -> switch on disabled    disable voltage, or the quick stop ramp ends (0x605A 1..4)
 13   any -> fault reaction active               a fault
 14   fault reaction active -> fault             fault reaction done (automatic)
 15   fault -> switch on disabled                fault reset (rising edge of controlword bit 7)
 16   quick stop active -> operation enabled     enable operation (only with 0x605A 5..8)
====  =========================================  ==========================================

"Switch on + enable operation" (0x0F) in *ready to switch on* runs 3 and 4 at once, as CiA 402-2 allows.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

from drivers.cia402 import (
    FAULT_RESET_BIT,
    STATE_STATUSWORD,
    Command402,
    OperationMode,
    QuickStopOption,
    State402,
    Statusword,
    decode_command,
)

S = State402
C = Command402

# (state, command) -> next state. SWITCH_ON and DISABLE_OPERATION share code 0x07; the state decides.
TRANSITIONS: dict[tuple[State402, Command402], State402] = {
    (S.SWITCH_ON_DISABLED, C.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 2
    (S.READY_TO_SWITCH_ON, C.SWITCH_ON): S.SWITCHED_ON,  # 3
    (S.READY_TO_SWITCH_ON, C.ENABLE_OPERATION): S.OPERATION_ENABLED,  # 3 + 4
    (S.SWITCHED_ON, C.ENABLE_OPERATION): S.OPERATION_ENABLED,  # 4
    (S.OPERATION_ENABLED, C.DISABLE_OPERATION): S.SWITCHED_ON,  # 5
    (S.SWITCHED_ON, C.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 6
    (S.READY_TO_SWITCH_ON, C.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 7
    (S.READY_TO_SWITCH_ON, C.QUICK_STOP): S.SWITCH_ON_DISABLED,  # 7
    (S.OPERATION_ENABLED, C.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 8
    (S.OPERATION_ENABLED, C.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 9
    (S.SWITCHED_ON, C.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 10
    (S.SWITCHED_ON, C.QUICK_STOP): S.SWITCH_ON_DISABLED,  # 10
    (S.OPERATION_ENABLED, C.QUICK_STOP): S.QUICK_STOP_ACTIVE,  # 11
    (S.QUICK_STOP_ACTIVE, C.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 12
}

# Transition 16 exists only when the quick stop option keeps the drive in quick stop active.
_STAY_OPTIONS = frozenset({5, 6, 7, 8})

# States in which the power stage may be energised: statusword bit 4 "voltage enabled".
_VOLTAGE_STATES = frozenset({S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE})

_CYCLIC_MODES = frozenset({OperationMode.CYCLIC_SYNC_VELOCITY, OperationMode.CYCLIC_SYNC_TORQUE})


class MotionKind(IntEnum):
    """What the power stage does in a state: the device turns this into the plant input."""

    TORQUE_OFF = 0  # coast: no torque
    FOLLOW_TARGET = 1  # operation enabled: follow the mode's target value
    QUICK_STOP_RAMP = 2  # ramp to standstill (quick stop or fault reaction)
    HOLD_STANDSTILL = 3  # quick stop active after the ramp with a "stay" option


def quick_stop_stays(option: int) -> bool:
    """Whether quick stop option ``option`` (0x605A) stays in *quick stop active* after the ramp."""
    return option in _STAY_OPTIONS


def quick_stop_ramps(option: int) -> bool:
    """Whether quick stop option ``option`` ramps down (1, 2, 5, 6 ...) rather than cutting torque (0)."""
    return option != QuickStopOption.DISABLE_DRIVE


@dataclass
class PowerStateMachine:
    """The 402 state machine of one axis.

    Parameters
    ----------
    quick_stop_option
        0x605A; read on every quick stop so an SDO write takes effect at the next one.
    state
        The initial state; a freshly powered drive is *not ready to switch on* until :meth:`power_on`.
    """

    quick_stop_option: int = int(QuickStopOption.QUICK_STOP_RAMP_THEN_DISABLE)
    state: State402 = State402.NOT_READY_TO_SWITCH_ON
    ramp_done: bool = False  # the quick stop ramp reached standstill
    _fault_reset_bit: bool = field(default=False, repr=False)

    def power_on(self) -> State402:
        """Transitions 0 and 1: the self test passes at once, the drive shows *switch on disabled*."""
        self.state = State402.SWITCH_ON_DISABLED
        self._fault_reset_bit = False
        self.ramp_done = False
        return self.state

    def apply_controlword(self, controlword: int) -> State402:
        """Run the transition ``controlword`` requests in the present state; return the new state.

        A controlword that requests nothing valid in this state leaves it unchanged (as real drives do).
        Fault reset acts on the rising edge of bit 7 only.
        """
        reset_bit = bool(controlword & FAULT_RESET_BIT)
        rising = reset_bit and not self._fault_reset_bit
        self._fault_reset_bit = reset_bit
        if self.state is State402.FAULT:
            if rising:
                self.state = State402.SWITCH_ON_DISABLED  # 15
            return self.state
        if self.state in (State402.FAULT_REACTION_ACTIVE, State402.NOT_READY_TO_SWITCH_ON):
            return self.state  # commands are not accepted while the drive reacts or starts
        command = decode_command(controlword & ~FAULT_RESET_BIT)
        if command is None:
            return self.state
        if self.state is State402.QUICK_STOP_ACTIVE and command is Command402.ENABLE_OPERATION:
            if quick_stop_stays(self.quick_stop_option):
                self.state = State402.OPERATION_ENABLED  # 16
            return self.state
        target = TRANSITIONS.get((self.state, command))
        if target is None:
            return self.state
        if target is State402.QUICK_STOP_ACTIVE:
            self.ramp_done = False
            if not quick_stop_ramps(self.quick_stop_option):
                target = State402.SWITCH_ON_DISABLED  # option 0: disable drive function at once
        self.state = target
        return self.state

    def fault(self) -> State402:
        """Transition 13: a fault from any state but *fault* itself enters *fault reaction active*."""
        if self.state is not State402.FAULT:
            self.state = State402.FAULT_REACTION_ACTIVE
            self.ramp_done = False
        return self.state

    def ramp_finished(self) -> State402:
        """The ramp of quick stop or of the fault reaction reached standstill: transitions 12 and 14."""
        self.ramp_done = True
        if self.state is State402.FAULT_REACTION_ACTIVE:
            self.state = State402.FAULT  # 14
        elif self.state is State402.QUICK_STOP_ACTIVE and not quick_stop_stays(self.quick_stop_option):
            self.state = State402.SWITCH_ON_DISABLED  # 12 (automatic at the end of the ramp)
        return self.state

    def motion(self) -> MotionKind:
        """What the power stage does in the present state."""
        if self.state is State402.OPERATION_ENABLED:
            return MotionKind.FOLLOW_TARGET
        if self.state is State402.QUICK_STOP_ACTIVE:
            return MotionKind.HOLD_STANDSTILL if self.ramp_done else MotionKind.QUICK_STOP_RAMP
        return MotionKind.TORQUE_OFF  # the fault reaction is "disable drive, motor free to rotate"

    def statusword(
        self,
        mode: int,
        *,
        target_reached: bool = False,
        internal_limit: bool = False,
        remote: bool = True,
    ) -> int:
        """The statusword (0x6041) of the present state.

        Parameters
        ----------
        mode
            The mode of operation shown in 0x6061: in CSV/CST bit 12 says the target value is followed.
        target_reached
            Bit 10 (profile velocity: actual velocity within the window; quick stop: standstill reached).
        internal_limit
            Bit 11: a torque or speed limit is active.
        remote
            Bit 9: the controlword is processed (always, once the device is on the network).
        """
        word = STATE_STATUSWORD[self.state]
        if self.state in _VOLTAGE_STATES:
            word |= Statusword.VOLTAGE_ENABLED
        if remote:
            word |= Statusword.REMOTE
        if target_reached:
            word |= Statusword.TARGET_REACHED
        if internal_limit:
            word |= Statusword.INTERNAL_LIMIT_ACTIVE
        if mode in _CYCLIC_MODES and self.state is State402.OPERATION_ENABLED:
            word |= Statusword.OPERATION_MODE_SPECIFIC_12  # target value followed
        return int(word)

"""The virtual drive's CiA 402 power state machine, without CAN.

Expected transitions are written from CiA 402-2's transition list (numbers in the ids), and each statusword is
checked against canopen's own independent state decoding (``canopen.profiles.p402.State402.SW_MASK``), not
against the table the machine uses.
"""

from __future__ import annotations

import pytest
from canopen.profiles.p402 import State402 as CanopenState402

from drivers.cia402 import Command402, OperationMode, QuickStopOption, State402, Statusword
from plant_emulator.state_machine import MotionKind, PowerStateMachine

S = State402
C = Command402

# state name used by canopen's independent master for each of ours
CANOPEN_NAME = {
    S.NOT_READY_TO_SWITCH_ON: "NOT READY TO SWITCH ON",
    S.SWITCH_ON_DISABLED: "SWITCH ON DISABLED",
    S.READY_TO_SWITCH_ON: "READY TO SWITCH ON",
    S.SWITCHED_ON: "SWITCHED ON",
    S.OPERATION_ENABLED: "OPERATION ENABLED",
    S.QUICK_STOP_ACTIVE: "QUICK STOP ACTIVE",
    S.FAULT_REACTION_ACTIVE: "FAULT REACTION ACTIVE",
    S.FAULT: "FAULT",
}

# controlwords chosen to show the command with irrelevant bits set where CiA 402 says "x" (don't care)
SHUTDOWN = 0x0006 | 0x0008  # bit 3 is don't-care for shutdown
SWITCH_ON = 0x0007
DISABLE_VOLTAGE = 0x0000 | 0x0008 | 0x0004  # bits 2, 3 don't care
QUICK_STOP = 0x0002 | 0x0001  # bit 0 don't care
DISABLE_OPERATION = 0x0007
ENABLE_OPERATION = 0x000F


def _canopen_state(statusword: int) -> str:
    for name, (mask, value) in CanopenState402.SW_MASK.items():
        if statusword & mask == value:
            return name
    return "UNKNOWN"


def _machine_in(state: State402, quick_stop_option: int = 2) -> PowerStateMachine:
    """Drive the machine to ``state`` through legal transitions only."""
    machine = PowerStateMachine(quick_stop_option=quick_stop_option)
    if state is S.NOT_READY_TO_SWITCH_ON:
        return machine
    machine.power_on()
    path = {
        S.SWITCH_ON_DISABLED: [],
        S.READY_TO_SWITCH_ON: [SHUTDOWN],
        S.SWITCHED_ON: [SHUTDOWN, SWITCH_ON],
        S.OPERATION_ENABLED: [SHUTDOWN, SWITCH_ON, ENABLE_OPERATION],
        S.QUICK_STOP_ACTIVE: [SHUTDOWN, SWITCH_ON, ENABLE_OPERATION, QUICK_STOP],
    }
    if state in path:
        for word in path[state]:
            machine.apply_controlword(word)
    elif state is S.FAULT_REACTION_ACTIVE:
        machine.fault()
    elif state is S.FAULT:
        machine.fault()
        machine.ramp_finished()
    assert machine.state is state
    return machine


@pytest.mark.parametrize(
    ("start", "controlword", "expected"),
    [
        pytest.param(S.SWITCH_ON_DISABLED, SHUTDOWN, S.READY_TO_SWITCH_ON, id="2-shutdown"),
        pytest.param(S.READY_TO_SWITCH_ON, SWITCH_ON, S.SWITCHED_ON, id="3-switch-on"),
        pytest.param(S.READY_TO_SWITCH_ON, ENABLE_OPERATION, S.OPERATION_ENABLED, id="3+4-switch-on-enable"),
        pytest.param(S.SWITCHED_ON, ENABLE_OPERATION, S.OPERATION_ENABLED, id="4-enable-operation"),
        pytest.param(S.OPERATION_ENABLED, DISABLE_OPERATION, S.SWITCHED_ON, id="5-disable-operation"),
        pytest.param(S.SWITCHED_ON, SHUTDOWN, S.READY_TO_SWITCH_ON, id="6-shutdown"),
        pytest.param(S.READY_TO_SWITCH_ON, DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED, id="7-disable-voltage"),
        pytest.param(S.READY_TO_SWITCH_ON, QUICK_STOP, S.SWITCH_ON_DISABLED, id="7-quick-stop"),
        pytest.param(S.OPERATION_ENABLED, SHUTDOWN, S.READY_TO_SWITCH_ON, id="8-shutdown"),
        pytest.param(S.OPERATION_ENABLED, DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED, id="9-disable-voltage"),
        pytest.param(S.SWITCHED_ON, DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED, id="10-disable-voltage"),
        pytest.param(S.SWITCHED_ON, QUICK_STOP, S.SWITCH_ON_DISABLED, id="10-quick-stop"),
        pytest.param(S.OPERATION_ENABLED, QUICK_STOP, S.QUICK_STOP_ACTIVE, id="11-quick-stop"),
        pytest.param(S.QUICK_STOP_ACTIVE, DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED, id="12-disable-voltage"),
    ],
)
def test_commanded_transitions(start: State402, controlword: int, expected: State402) -> None:
    machine = _machine_in(start)
    assert machine.apply_controlword(controlword) is expected
    assert _canopen_state(machine.statusword(OperationMode.CYCLIC_SYNC_VELOCITY)) == CANOPEN_NAME[expected]


@pytest.mark.parametrize(
    ("start", "controlword"),
    [
        (S.SWITCH_ON_DISABLED, SWITCH_ON),  # needs shutdown first
        (S.SWITCH_ON_DISABLED, ENABLE_OPERATION),
        (S.SWITCH_ON_DISABLED, QUICK_STOP),
        (S.READY_TO_SWITCH_ON, SHUTDOWN),
        (S.FAULT, ENABLE_OPERATION),  # only a fault reset leaves fault
        (S.FAULT, SHUTDOWN),
        (S.FAULT_REACTION_ACTIVE, ENABLE_OPERATION),
        (S.FAULT_REACTION_ACTIVE, 0x80),
        (S.NOT_READY_TO_SWITCH_ON, SHUTDOWN),
        (S.QUICK_STOP_ACTIVE, ENABLE_OPERATION),  # option 2 does not allow transition 16
        (S.QUICK_STOP_ACTIVE, SHUTDOWN),
        (S.OPERATION_ENABLED, ENABLE_OPERATION),  # already there
    ],
)
def test_commands_with_no_transition_leave_the_state(start: State402, controlword: int) -> None:
    machine = _machine_in(start)
    assert machine.apply_controlword(controlword) is start


def test_automatic_transitions_0_1_13_14() -> None:
    machine = PowerStateMachine()
    assert machine.state is S.NOT_READY_TO_SWITCH_ON  # 0
    assert machine.power_on() is S.SWITCH_ON_DISABLED  # 1
    for start in (S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED,
                  S.QUICK_STOP_ACTIVE):
        machine = _machine_in(start)
        assert machine.fault() is S.FAULT_REACTION_ACTIVE  # 13
        assert machine.motion() is MotionKind.TORQUE_OFF
        assert machine.ramp_finished() is S.FAULT  # 14
        assert machine.fault() is S.FAULT  # a second fault while in fault stays in fault


def test_fault_reset_acts_on_the_rising_edge_only() -> None:
    # bit 7 already high when the fault came: holding it is no edge
    machine = PowerStateMachine()
    machine.power_on()
    machine.apply_controlword(0x80)  # bit 7 high before the fault
    machine.fault()
    machine.ramp_finished()
    assert machine.apply_controlword(0x80) is S.FAULT  # still high: no rising edge
    assert machine.apply_controlword(0x00) is S.FAULT  # falling edge does nothing
    assert machine.apply_controlword(0x80) is S.SWITCH_ON_DISABLED  # 15 on the rising edge
    assert _canopen_state(machine.statusword(0)) == "SWITCH ON DISABLED"


def test_canopen_fault_reset_sequence_is_accepted() -> None:
    """canopen's BaseNode402 resets a fault with 0x00 then 0x80 (``CW_SWITCH_ON_DISABLED``)."""
    machine = _machine_in(S.FAULT)
    machine.apply_controlword(CanopenState402.CW_DISABLE_VOLTAGE)
    assert machine.apply_controlword(CanopenState402.CW_SWITCH_ON_DISABLED) is S.SWITCH_ON_DISABLED


@pytest.mark.parametrize(
    ("option", "after_ramp", "allows_16"),
    [
        (QuickStopOption.SLOW_DOWN_RAMP_THEN_DISABLE, S.SWITCH_ON_DISABLED, False),
        (QuickStopOption.QUICK_STOP_RAMP_THEN_DISABLE, S.SWITCH_ON_DISABLED, False),
        (QuickStopOption.SLOW_DOWN_RAMP_STAY, S.QUICK_STOP_ACTIVE, True),
        (QuickStopOption.QUICK_STOP_RAMP_STAY, S.QUICK_STOP_ACTIVE, True),
    ],
)
def test_quick_stop_options(option: int, after_ramp: State402, allows_16: bool) -> None:
    machine = _machine_in(S.OPERATION_ENABLED, quick_stop_option=option)
    assert machine.apply_controlword(QUICK_STOP) is S.QUICK_STOP_ACTIVE  # 11
    assert machine.motion() is MotionKind.QUICK_STOP_RAMP
    assert machine.ramp_finished() is after_ramp  # 12 automatic, or stay
    if after_ramp is S.QUICK_STOP_ACTIVE:
        assert machine.motion() is MotionKind.HOLD_STANDSTILL
        word = machine.statusword(OperationMode.CYCLIC_SYNC_VELOCITY, target_reached=True)
        assert _canopen_state(word) == "QUICK STOP ACTIVE"
        assert word & Statusword.TARGET_REACHED
    machine = _machine_in(S.OPERATION_ENABLED, quick_stop_option=option)
    machine.apply_controlword(QUICK_STOP)
    expected = S.OPERATION_ENABLED if allows_16 else S.QUICK_STOP_ACTIVE
    assert machine.apply_controlword(ENABLE_OPERATION) is expected  # 16 only with a "stay" option


def test_quick_stop_option_0_disables_at_once() -> None:
    machine = _machine_in(S.OPERATION_ENABLED, quick_stop_option=QuickStopOption.DISABLE_DRIVE)
    assert machine.apply_controlword(QUICK_STOP) is S.SWITCH_ON_DISABLED
    assert machine.motion() is MotionKind.TORQUE_OFF


@pytest.mark.parametrize("state", list(State402))
def test_statusword_per_state(state: State402) -> None:
    machine = _machine_in(state)
    for mode in (OperationMode.CYCLIC_SYNC_VELOCITY, OperationMode.CYCLIC_SYNC_TORQUE,
                 OperationMode.PROFILE_VELOCITY):
        word = machine.statusword(mode)
        assert _canopen_state(word) == CANOPEN_NAME[state]
        assert bool(word & Statusword.REMOTE)
        powered = state in (S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE)
        assert bool(word & Statusword.VOLTAGE_ENABLED) == powered
        follows = state is S.OPERATION_ENABLED and mode != OperationMode.PROFILE_VELOCITY
        assert bool(word & Statusword.OPERATION_MODE_SPECIFIC_12) == follows  # CSV/CST: target followed
        # bit 5 (quick stop, active low) is clear exactly in quick stop active (and where the table says 0)
        assert bool(word & Statusword.QUICK_STOP) == (
            state in (S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED)
        )
    limited = machine.statusword(0, internal_limit=True, target_reached=True, remote=False)
    assert limited & Statusword.INTERNAL_LIMIT_ACTIVE
    assert limited & Statusword.TARGET_REACHED
    assert not limited & Statusword.REMOTE


def test_motion_per_state() -> None:
    assert _machine_in(S.OPERATION_ENABLED).motion() is MotionKind.FOLLOW_TARGET
    for state in (S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.FAULT):
        assert _machine_in(state).motion() is MotionKind.TORQUE_OFF

"""CiA 402 (drives and motion control) definitions shared by the master and the emulated device.

The power state machine, controlword commands, statusword decoding, modes of operation and the standard
object indices. Everything is an ``IntEnum``/``IntFlag``; no bare integers for states.
"""

from __future__ import annotations

from enum import IntEnum, IntFlag, unique


@unique
class Obj(IntEnum):
    """Object dictionary indices used by the product (CiA 301 communication + CiA 402 profile)."""

    DEVICE_TYPE = 0x1000
    ERROR_REGISTER = 0x1001
    COB_ID_SYNC = 0x1005
    COMMUNICATION_CYCLE_PERIOD = 0x1006  # microseconds
    CONSUMER_HEARTBEAT_TIME = 0x1016
    PRODUCER_HEARTBEAT_TIME = 0x1017  # milliseconds
    IDENTITY = 0x1018
    RPDO_COMMUNICATION = 0x1400  # .. 0x1403
    RPDO_MAPPING = 0x1600  # .. 0x1603
    TPDO_COMMUNICATION = 0x1800  # .. 0x1803
    TPDO_MAPPING = 0x1A00  # .. 0x1A03
    ERROR_CODE = 0x603F
    ABORT_CONNECTION_OPTION = 0x6007
    CONTROLWORD = 0x6040
    STATUSWORD = 0x6041
    QUICK_STOP_OPTION = 0x605A
    SHUTDOWN_OPTION = 0x605B
    DISABLE_OPERATION_OPTION = 0x605C
    FAULT_REACTION_OPTION = 0x605E
    MODES_OF_OPERATION = 0x6060
    MODES_OF_OPERATION_DISPLAY = 0x6061
    POSITION_ACTUAL_VALUE = 0x6064
    VELOCITY_DEMAND_VALUE = 0x606B  # the velocity the drive latched and follows this cycle (0x60FF's units)
    VELOCITY_ACTUAL_VALUE = 0x606C
    TARGET_TORQUE = 0x6071
    MAX_TORQUE = 0x6072
    TORQUE_DEMAND = 0x6074  # the torque the drive latched and applies this cycle (0x6071's units)
    TORQUE_ACTUAL_VALUE = 0x6077
    MAX_MOTOR_SPEED = 0x6080
    PROFILE_ACCELERATION = 0x6083
    PROFILE_DECELERATION = 0x6084
    QUICK_STOP_DECELERATION = 0x6085
    INTERPOLATION_TIME_PERIOD = 0x60C2  # record: sub 1 value (UNSIGNED8), sub 2 exponent of 10 s (INTEGER8)
    TARGET_VELOCITY = 0x60FF
    SUPPORTED_DRIVE_MODES = 0x6502


@unique
class IdentitySub(IntEnum):
    """Sub-indices of the identity object 0x1018."""

    VENDOR_ID = 1
    PRODUCT_CODE = 2
    REVISION = 3
    SERIAL = 4


@unique
class OperationMode(IntEnum):
    """Modes of operation (0x6060 / 0x6061) the product uses."""

    PROFILE_VELOCITY = 3
    CYCLIC_SYNC_VELOCITY = 9
    CYCLIC_SYNC_TORQUE = 10


SUPPORTED_MODE_BITS: dict[OperationMode, int] = {
    # 0x6502 bit positions (CiA 402-2): pv = bit 2, csv = bit 8, cst = bit 9
    OperationMode.PROFILE_VELOCITY: 1 << 2,
    OperationMode.CYCLIC_SYNC_VELOCITY: 1 << 8,
    OperationMode.CYCLIC_SYNC_TORQUE: 1 << 9,
}


@unique
class State402(IntEnum):
    """The CiA 402 power drive system states."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


class Statusword(IntFlag):
    """Statusword (0x6041) bits."""

    READY_TO_SWITCH_ON = 1 << 0
    SWITCHED_ON = 1 << 1
    OPERATION_ENABLED = 1 << 2
    FAULT = 1 << 3
    VOLTAGE_ENABLED = 1 << 4
    QUICK_STOP = 1 << 5  # active low: 0 means quick stop is active
    SWITCH_ON_DISABLED = 1 << 6
    WARNING = 1 << 7
    REMOTE = 1 << 9
    TARGET_REACHED = 1 << 10
    INTERNAL_LIMIT_ACTIVE = 1 << 11
    OPERATION_MODE_SPECIFIC_12 = 1 << 12  # CSV/CST: target value ignored when clear
    OPERATION_MODE_SPECIFIC_13 = 1 << 13


# (mask, value) pairs from CiA 402-2 table "state coding"
_STATE_CODING: tuple[tuple[int, int, State402], ...] = (
    (0x4F, 0x00, State402.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, State402.SWITCH_ON_DISABLED),
    (0x6F, 0x21, State402.READY_TO_SWITCH_ON),
    (0x6F, 0x23, State402.SWITCHED_ON),
    (0x6F, 0x27, State402.OPERATION_ENABLED),
    (0x6F, 0x07, State402.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, State402.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, State402.FAULT),
)

# The statusword bits 0-3, 5, 6 each state shows (bit 4 voltage enabled is set wherever power may be on).
STATE_STATUSWORD: dict[State402, int] = {
    State402.NOT_READY_TO_SWITCH_ON: 0x00,
    State402.SWITCH_ON_DISABLED: 0x40,
    State402.READY_TO_SWITCH_ON: 0x21,
    State402.SWITCHED_ON: 0x23,
    State402.OPERATION_ENABLED: 0x27,
    State402.QUICK_STOP_ACTIVE: 0x07,
    State402.FAULT_REACTION_ACTIVE: 0x0F,
    State402.FAULT: 0x08,
}


def decode_state(statusword: int) -> State402:
    """The 402 state a statusword shows. Raises ``ValueError`` for a pattern no state has."""
    for mask, value, state in _STATE_CODING:
        if statusword & mask == value:
            return state
    raise ValueError(f"statusword 0x{statusword:04X} matches no CiA 402 state")


class Controlword(IntFlag):
    """Controlword (0x6040) bits."""

    SWITCH_ON = 1 << 0
    ENABLE_VOLTAGE = 1 << 1
    QUICK_STOP = 1 << 2  # active low: 0 requests quick stop
    ENABLE_OPERATION = 1 << 3
    FAULT_RESET = 1 << 7
    HALT = 1 << 8


FAULT_RESET_BIT = int(Controlword.FAULT_RESET)
"""Controlword bit 7 as a plain ``int``: ``word & Controlword.FAULT_RESET`` runs ``IntFlag``'s Python-level operator
(about a microsecond), and the drive tests this bit on every RPDO."""


class Command402(IntEnum):
    """Device control commands: the controlword value that requests each transition (CiA 402-2).

    Not ``@unique`` on purpose: CiA 402 gives SWITCH_ON and DISABLE_OPERATION the same code 0x07 (the state decides
    the transition), so DISABLE_OPERATION is an alias by the standard's own definition.
    """

    SHUTDOWN = 0x06  # -> READY_TO_SWITCH_ON (transitions 2, 6, 8)
    SWITCH_ON = 0x07  # -> SWITCHED_ON (3, 5)
    DISABLE_VOLTAGE = 0x00  # -> SWITCH_ON_DISABLED (7, 9, 10, 12)
    QUICK_STOP = 0x02  # -> QUICK_STOP_ACTIVE (11) or SWITCH_ON_DISABLED (7, 10)
    DISABLE_OPERATION = 0x07  # -> SWITCHED_ON (5)
    ENABLE_OPERATION = 0x0F  # -> OPERATION_ENABLED (4, 16)
    FAULT_RESET = 0x80  # rising edge: FAULT -> SWITCH_ON_DISABLED (15)


#: The command that leaves each state on the way to OPERATION_ENABLED (None: the drive leaves it by itself;
#: FAULT is absent: leaving it takes a fault reset, which enabling must not do silently).
ENABLE_PATH: dict[State402, Command402 | None] = {
    State402.NOT_READY_TO_SWITCH_ON: None,
    State402.SWITCH_ON_DISABLED: Command402.SHUTDOWN,
    State402.READY_TO_SWITCH_ON: Command402.SWITCH_ON,
    State402.SWITCHED_ON: Command402.ENABLE_OPERATION,
    State402.QUICK_STOP_ACTIVE: Command402.DISABLE_VOLTAGE,
    State402.FAULT_REACTION_ACTIVE: None,
}


def decode_command(controlword: int) -> Command402 | None:
    """The device control command a controlword encodes (CiA 402-2 command coding), or None if none.

    Fault reset is detected on the rising edge by the caller; here bit 7 set decodes as FAULT_RESET.
    """
    if controlword & FAULT_RESET_BIT:
        return Command402.FAULT_RESET
    low = int(controlword) & 0x0F
    if low & 0x02 == 0:  # enable voltage clear
        return Command402.DISABLE_VOLTAGE
    if low & 0x06 == 0x02:  # enable voltage set, quick stop clear
        return Command402.QUICK_STOP
    if low & 0x07 == 0x06:
        return Command402.SHUTDOWN
    if low == 0x07:
        return Command402.SWITCH_ON  # same code as DISABLE_OPERATION; the state decides
    if low == 0x0F:
        return Command402.ENABLE_OPERATION
    return None


@unique
class QuickStopOption(IntEnum):
    """Quick stop option code 0x605A values (CiA 402-2)."""

    DISABLE_DRIVE = 0
    SLOW_DOWN_RAMP_THEN_DISABLE = 1
    QUICK_STOP_RAMP_THEN_DISABLE = 2
    SLOW_DOWN_RAMP_STAY = 5
    QUICK_STOP_RAMP_STAY = 6


@unique
class AbortConnectionOption(IntEnum):
    """Abort connection option code 0x6007 values (CiA 402-2)."""

    NO_ACTION = 0
    FAULT = 1
    DISABLE_VOLTAGE = 2
    QUICK_STOP = 3

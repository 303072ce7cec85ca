"""CiA 301 protocol definitions shared by the master (``drivers``) and the device (``plant_emulator``).

COB-IDs are never written inline elsewhere: use :class:`FunctionCode` and :func:`cob_id`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from enum import IntEnum, unique

from drivers.errors import ProtocolError

NODE_ID_MIN = 1
NODE_ID_MAX = 127


@enum.unique
class FunctionCode(IntEnum):
    """The 4-bit function code of an 11-bit CANopen COB-ID, in its base COB-ID form (``code + node_id``).

    SYNC is not a member: it shares function code 0x080 with EMCY but is a broadcast without a node id, so it is
    the constant :data:`SYNC_COB_ID` (an alias member would make ``FunctionCode.EMCY`` the SYNC member).
    """

    NMT = 0x000
    EMCY = 0x080
    TIME = 0x100
    TPDO1 = 0x180
    RPDO1 = 0x200
    TPDO2 = 0x280
    RPDO2 = 0x300
    TPDO3 = 0x380
    RPDO3 = 0x400
    TPDO4 = 0x480
    RPDO4 = 0x500
    SDO_TX = 0x580  # server -> client (from the drive)
    SDO_RX = 0x600  # client -> server (to the drive)
    HEARTBEAT = 0x700


TPDO_BASES = (FunctionCode.TPDO1, FunctionCode.TPDO2, FunctionCode.TPDO3, FunctionCode.TPDO4)
RPDO_BASES = (FunctionCode.RPDO1, FunctionCode.RPDO2, FunctionCode.RPDO3, FunctionCode.RPDO4)
NMT_COB_ID = int(FunctionCode.NMT)
SYNC_COB_ID = 0x080  # CiA 301 default COB-ID of SYNC (0x1005); EMCY uses the same function code plus a node id
COB_ID_INVALID = 1 << 31  # bit 31 of a COB-ID entry: the PDO (or SYNC consumer) is not valid
_COB_ID_MASK = 0x7FF  # the 11-bit identifier of a COB-ID entry
_FUNCTION_CODE_MASK = 0x780  # the 4 function-code bits of an 11-bit COB-ID (the low 7 are the node id)
_HEARTBEAT_STATE_MASK = 0x7F


def check_node_id(node_id: int) -> int:
    """Return ``node_id`` if it is a valid CANopen node ID (1..127), else raise :class:`ProtocolError`."""
    if not NODE_ID_MIN <= node_id <= NODE_ID_MAX:
        raise ProtocolError(f"node id {node_id} is outside {NODE_ID_MIN}..{NODE_ID_MAX}")
    return node_id


def cob_id(function: FunctionCode, node_id: int) -> int:
    """The COB-ID of ``function`` for ``node_id`` (e.g. ``cob_id(FunctionCode.TPDO1, 5) == 0x185``)."""
    return int(function) + check_node_id(node_id)


def split_cob_id(can_id: int) -> tuple[int, int]:
    """``(function code, node id)`` of an 11-bit COB-ID: the inverse of :func:`cob_id` (node id 0: a broadcast)."""
    return can_id & _FUNCTION_CODE_MASK, can_id & NODE_ID_MAX


def heartbeat_state(byte: int) -> int:
    """The NMT state carried in a heartbeat byte (bit 7 is the node-guarding toggle bit, not part of it)."""
    return byte & _HEARTBEAT_STATE_MASK


@dataclass(frozen=True, slots=True)
class CobIdEntry:
    """A COB-ID entry (0x1005, 0x14xx:01, 0x18xx:01): the 11-bit identifier and bit 31 "not valid" (CiA 301).

    Bits 29 (extended frame) and 30 (SYNC producer / RTR) are not used by the product and are dropped on decode.
    """

    can_id: int
    valid: bool = True

    def encode(self) -> int:
        """The UNSIGNED32 written to the entry."""
        if not 0 <= self.can_id <= _COB_ID_MASK:
            raise ProtocolError(f"COB-ID 0x{self.can_id:X} is not an 11-bit identifier")
        return self.can_id | (0 if self.valid else COB_ID_INVALID)

    @classmethod
    def decode(cls, value: int) -> CobIdEntry:
        """Inverse of :meth:`encode`."""
        return cls(value & _COB_ID_MASK, valid=not value & COB_ID_INVALID)


@dataclass(frozen=True, slots=True)
class HeartbeatConsumerEntry:
    """One sub-index of the consumer heartbeat time 0x1016: ``node_id << 16 | time_ms`` (CiA 301).

    The master encodes it when it asks the drive to watch its heartbeat; the drive decodes it to know whom to
    watch. A node id or time of 0 means the entry is unused.
    """

    node_id: int
    time_ms: int

    def encode(self) -> int:
        """The UNSIGNED32 written to 0x1016:n."""
        if not 0 <= self.node_id <= NODE_ID_MAX:
            raise ProtocolError(f"heartbeat consumer: node id {self.node_id} is outside 0..{NODE_ID_MAX}")
        if not 0 <= self.time_ms <= _HEARTBEAT_TIME_MASK:
            raise ProtocolError(f"heartbeat consumer: {self.time_ms} ms is outside 0..{_HEARTBEAT_TIME_MASK}")
        return (self.node_id << _HEARTBEAT_NODE_SHIFT) | self.time_ms

    @classmethod
    def decode(cls, value: int) -> HeartbeatConsumerEntry:
        """Inverse of :meth:`encode` (bits 24..31 are reserved and ignored)."""
        return cls((value >> _HEARTBEAT_NODE_SHIFT) & NODE_ID_MAX, value & _HEARTBEAT_TIME_MASK)

    @property
    def active(self) -> bool:
        """Whether the entry watches a node (neither the node id nor the time is 0)."""
        return self.node_id != 0 and self.time_ms != 0


_HEARTBEAT_NODE_SHIFT = 16
_HEARTBEAT_TIME_MASK = 0xFFFF


@unique
class NmtState(IntEnum):
    """NMT states as carried in the heartbeat byte."""

    INITIALISING = 0x00  # the boot-up message
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


def nmt_state_name(state: int) -> str:
    """The name of NMT state byte ``state``, or its hex value when it is none of :class:`NmtState`."""
    try:
        return NmtState(state).name
    except ValueError:
        return f"state 0x{state:02X}"


@unique
class NmtCommand(IntEnum):
    """NMT command specifiers (first byte of a frame on COB-ID 0x000)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


@unique
class ErrorRegister(IntEnum):
    """Bits of the error register 0x1001."""

    GENERIC = 0x01
    CURRENT = 0x02
    VOLTAGE = 0x04
    TEMPERATURE = 0x08
    COMMUNICATION = 0x10
    DEVICE_PROFILE = 0x20
    MANUFACTURER = 0x80


@unique
class EmcyCode(IntEnum):
    """Emergency error codes used by the emulator and understood by the master (CiA 301 / CiA 402)."""

    NO_ERROR = 0x0000
    GENERIC = 0x1000
    OVER_CURRENT = 0x2310  # continuous over-current: torque limit exceeded
    OVER_SPEED = 0x8400  # velocity speed controller: over-speed
    HEARTBEAT_LOSS = 0x8130  # life guard error or heartbeat error
    SYNC_LOSS = 0x8700  # sync controller error (CiA 402: 0x8700 "sync controller")
    PDO_LENGTH = 0x8210  # PDO not processed due to length error
    COMMUNICATION = 0x8100
    INTERNAL_SOFTWARE = 0x6100  # internal software error (the emulator: its plant's physics diverged)


EMCY_TEXT: dict[int, str] = {
    EmcyCode.NO_ERROR: "error reset or no error",
    EmcyCode.GENERIC: "generic error",
    EmcyCode.OVER_CURRENT: "continuous over-current (torque limit)",
    EmcyCode.OVER_SPEED: "over-speed",
    EmcyCode.HEARTBEAT_LOSS: "heartbeat consumer timeout",
    EmcyCode.SYNC_LOSS: "SYNC loss",
    EmcyCode.PDO_LENGTH: "PDO not processed due to length error",
    EmcyCode.COMMUNICATION: "communication error",
    EmcyCode.INTERNAL_SOFTWARE: "internal software error",
}


def emcy_text(code: int) -> str:
    """Decoded meaning of an EMCY error code (by exact code, then by its class)."""
    if code in EMCY_TEXT:
        return EMCY_TEXT[code]
    classes = {
        0x1: "generic",
        0x2: "current",
        0x3: "voltage",
        0x4: "temperature",
        0x5: "device hardware",
        0x6: "device software",
        0x7: "additional modules",
        0x8: "monitoring / communication",
        0x9: "external error",
        0xF: "additional functions",
        0xFF: "device specific",
    }
    if (code >> 8) == 0xFF:
        return "device specific"
    return f"{classes.get(code >> 12, 'unknown')} error"


@unique
class SdoAbortCode(IntEnum):
    """CiA 301 SDO abort codes the product raises or decodes."""

    TOGGLE_BIT = 0x05030000
    TIMEOUT = 0x05040000
    INVALID_COMMAND = 0x05040001
    OUT_OF_MEMORY = 0x05040005
    UNSUPPORTED_ACCESS = 0x06010000
    WRITE_ONLY = 0x06010001
    READ_ONLY = 0x06010002
    NO_OBJECT = 0x06020000
    CANNOT_MAP = 0x06040041
    PDO_TOO_LONG = 0x06040042
    GENERAL_PARAMETER = 0x06040043
    GENERAL_INTERNAL = 0x06040047
    HARDWARE_ERROR = 0x06060000
    LENGTH_MISMATCH = 0x06070010
    LENGTH_TOO_HIGH = 0x06070012
    LENGTH_TOO_LOW = 0x06070013
    NO_SUBINDEX = 0x06090011
    INVALID_VALUE = 0x06090030
    VALUE_TOO_HIGH = 0x06090031
    VALUE_TOO_LOW = 0x06090032
    GENERAL_ERROR = 0x08000000
    CANNOT_STORE = 0x08000020
    CANNOT_STORE_LOCAL = 0x08000021
    CANNOT_STORE_STATE = 0x08000022
    NO_DATA = 0x08000024


SDO_ABORT_TEXT: dict[int, str] = {
    SdoAbortCode.TOGGLE_BIT: "toggle bit not alternated",
    SdoAbortCode.TIMEOUT: "SDO protocol timed out",
    SdoAbortCode.INVALID_COMMAND: "client/server command specifier not valid or unknown",
    SdoAbortCode.OUT_OF_MEMORY: "out of memory",
    SdoAbortCode.UNSUPPORTED_ACCESS: "unsupported access to an object",
    SdoAbortCode.WRITE_ONLY: "attempt to read a write-only object",
    SdoAbortCode.READ_ONLY: "attempt to write a read-only object",
    SdoAbortCode.NO_OBJECT: "object does not exist in the object dictionary",
    SdoAbortCode.CANNOT_MAP: "object cannot be mapped to the PDO",
    SdoAbortCode.PDO_TOO_LONG: "number and length of mapped objects would exceed PDO length",
    SdoAbortCode.GENERAL_PARAMETER: "general parameter incompatibility",
    SdoAbortCode.GENERAL_INTERNAL: "general internal incompatibility in the device",
    SdoAbortCode.HARDWARE_ERROR: "access failed due to a hardware error",
    SdoAbortCode.LENGTH_MISMATCH: "data type does not match, length of service parameter does not match",
    SdoAbortCode.LENGTH_TOO_HIGH: "data type does not match, length of service parameter too high",
    SdoAbortCode.LENGTH_TOO_LOW: "data type does not match, length of service parameter too low",
    SdoAbortCode.NO_SUBINDEX: "sub-index does not exist",
    SdoAbortCode.INVALID_VALUE: "invalid value for parameter (download only)",
    SdoAbortCode.VALUE_TOO_HIGH: "value of parameter written too high (download only)",
    SdoAbortCode.VALUE_TOO_LOW: "value of parameter written too low (download only)",
    SdoAbortCode.GENERAL_ERROR: "general error",
    SdoAbortCode.CANNOT_STORE: "data cannot be transferred or stored to the application",
    SdoAbortCode.CANNOT_STORE_LOCAL: "data cannot be transferred or stored because of local control",
    SdoAbortCode.CANNOT_STORE_STATE: "data cannot be transferred or stored in the present device state",
    SdoAbortCode.NO_DATA: "no data available",
}


def sdo_abort_text(code: int) -> str:
    """Decoded meaning of an SDO abort code."""
    return SDO_ABORT_TEXT.get(code, f"unknown abort code 0x{code:08X}")

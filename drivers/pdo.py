"""Precomputed PDO codecs: a mapping becomes one ``struct.Struct`` built once, used every cycle.

The cyclic path never touches SDO or canopen's per-variable PDO machinery: :meth:`PdoCodec.encode` and
:meth:`PdoCodec.decode` are one ``struct`` call each. :meth:`PdoCodec.decode` checks the data length code (a frame
whose DLC differs from the mapping is a :class:`~drivers.errors.ProtocolError`, as CiA 301 asks a device to
reject it with EMCY 0x8210).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum, unique

import can

from drivers.cia301 import COB_ID_INVALID
from drivers.cia402 import Obj
from drivers.errors import ProtocolError

__all__ = [
    "PDO_DISABLED",
    "MappedVariable",
    "MappingEntry",
    "PdoCodec",
    "PdoDirection",
    "PdoLayout",
    "TransmissionType",
    "data_frame",
]

PDO_DISABLED = COB_ID_INVALID
"""Bit 31 of a PDO COB-ID (sub-index 1 of 0x1400../0x1800..): the PDO is not valid."""

_FORMAT = {(8, False): "B", (8, True): "b", (16, False): "H", (16, True): "h", (32, False): "I", (32, True): "i"}
_FORMAT |= {(64, False): "Q", (64, True): "q"}


@unique
class PdoDirection(IntEnum):
    """Which way a PDO travels, seen from the drive: RPDO = to the drive, TPDO = from it."""

    RPDO = 0
    TPDO = 1


@unique
class TransmissionType(IntEnum):
    """Sub-index 2 of a PDO communication parameter (CiA 301) the product uses."""

    SYNCHRONOUS = 1  # TPDO: sent on every SYNC; RPDO: applied at the next SYNC
    EVENT_MANUFACTURER = 254
    EVENT_PROFILE = 255


@dataclass(frozen=True, slots=True)
class MappingEntry:
    """One sub-index of a PDO mapping object (0x16xx / 0x1Axx): ``index << 16 | subindex << 8 | bits`` (CiA 301).

    The raw codec, with no judgement on the size: a device validates what a master writes
    (:class:`MappedVariable` is the master's typed, checked form).
    """

    index: int
    subindex: int
    bits: int

    def encode(self) -> int:
        """The UNSIGNED32 written to the mapping sub-index."""
        return (self.index << 16) | (self.subindex << 8) | self.bits

    @classmethod
    def decode(cls, value: int) -> MappingEntry:
        """Inverse of :meth:`encode`."""
        return cls(value >> 16, (value >> 8) & 0xFF, value & 0xFF)


@dataclass(frozen=True, slots=True)
class MappedVariable:
    """One entry of a PDO mapping: object, sub-index, size in bits and signedness."""

    index: int
    subindex: int
    bits: int
    signed: bool

    def __post_init__(self) -> None:
        if (self.bits, self.signed) not in _FORMAT:
            raise ProtocolError(
                f"object 0x{self.index:04X}:{self.subindex:02X}: {self.bits}-bit values cannot be mapped "
                "(whole 8/16/32/64-bit integers only)"
            )

    @property
    def mapping_entry(self) -> int:
        """The UNSIGNED32 written to a mapping sub-index (:class:`MappingEntry`)."""
        return MappingEntry(self.index, self.subindex, self.bits).encode()

    @classmethod
    def from_entry(cls, entry: int, *, signed: bool) -> MappedVariable:
        """Inverse of :attr:`mapping_entry` (signedness is not in the entry and must be given)."""
        raw = MappingEntry.decode(entry)
        return cls(raw.index, raw.subindex, raw.bits, signed)

    @property
    def minimum(self) -> int:
        """Smallest value the entry carries."""
        return -(1 << (self.bits - 1)) if self.signed else 0

    @property
    def maximum(self) -> int:
        """Largest value the entry carries."""
        return (1 << (self.bits - 1)) - 1 if self.signed else (1 << self.bits) - 1


def data_frame(can_id: int, data: bytes) -> can.Message:
    """A classic data frame with an 11-bit COB-ID, as ``can.Message(arbitration_id=can_id, data=data,
    is_extended_id=False)`` makes it.

    Built by setting every slot of ``can.Message`` without ``Message.__init__``, whose argument checks cost more
    than the rest of sending a PDO on the in-process transport; ``tests/drivers/test_pdo.py`` compares the two field by
    field, so a slot python-can adds fails there.
    """
    frame = _new_message(can.Message)
    frame.timestamp = 0.0
    frame.arbitration_id = can_id
    frame.is_extended_id = False
    frame.is_remote_frame = False
    frame.is_error_frame = False
    frame.channel = None
    frame.dlc = len(data)
    frame.data = bytearray(data)
    frame.is_fd = False
    frame.is_rx = True
    frame.bitrate_switch = False
    frame.error_state_indicator = False
    return frame


_new_message = can.Message.__new__


class PdoCodec:
    """Encoder/decoder for one PDO mapping, little-endian as CANopen requires.

    Parameters
    ----------
    variables
        The mapping, in order.
    name
        Used in error messages, e.g. ``"TPDO1 (0x185)"``.
    """

    __slots__ = ("_struct", "name", "size", "variables")

    def __init__(self, variables: Sequence[MappedVariable], name: str = "PDO") -> None:
        if not variables:
            raise ProtocolError(f"{name}: a PDO mapping needs at least one object")
        self.variables = tuple(variables)
        self.name = name
        self._struct = struct.Struct("<" + "".join(_FORMAT[(v.bits, v.signed)] for v in self.variables))
        self.size = self._struct.size
        if self.size > 8:
            raise ProtocolError(f"{name}: mapping is {self.size} bytes, a CAN PDO carries at most 8")

    def encode(self, *values: int) -> bytes:
        """Pack ``values`` (one per mapped object, in order) into the frame payload.

        Raises :class:`ProtocolError` when a value does not fit its object's type.
        """
        try:
            return self._struct.pack(*values)
        except struct.error as exc:
            raise ProtocolError(f"{self.name}: cannot encode {values}: {exc}") from exc

    def decode(self, data: bytes | bytearray) -> tuple[int, ...]:
        """Unpack a frame payload; raises :class:`ProtocolError` when its length differs from the mapping."""
        if len(data) != self.size:
            raise ProtocolError(f"{self.name}: DLC {len(data)} does not match the mapped length {self.size}")
        return self._struct.unpack(data)

    def __repr__(self) -> str:
        entries = ", ".join(f"0x{v.index:04X}:{v.subindex:02X}/{v.bits}" for v in self.variables)
        return f"PdoCodec({self.name}: {entries})"


@dataclass(frozen=True, slots=True)
class PdoLayout:
    """One PDO as the master configures it: direction, number (1..4), COB-ID, transmission type, mapping."""

    direction: PdoDirection
    number: int
    cob_id: int
    variables: tuple[MappedVariable, ...]
    transmission_type: TransmissionType = TransmissionType.SYNCHRONOUS

    @property
    def communication_index(self) -> int:
        """0x1400 + n - 1 (RPDO) or 0x1800 + n - 1 (TPDO)."""
        base = Obj.RPDO_COMMUNICATION if self.direction is PdoDirection.RPDO else Obj.TPDO_COMMUNICATION
        return int(base) + self.number - 1

    @property
    def mapping_index(self) -> int:
        """0x1600 + n - 1 (RPDO) or 0x1A00 + n - 1 (TPDO)."""
        base = Obj.RPDO_MAPPING if self.direction is PdoDirection.RPDO else Obj.TPDO_MAPPING
        return int(base) + self.number - 1

    @property
    def name(self) -> str:
        """E.g. ``"TPDO1 (0x185)"``."""
        return f"{self.direction.name}{self.number} (0x{self.cob_id:03X})"

    def codec(self) -> PdoCodec:
        """The precomputed codec of this mapping."""
        return PdoCodec(self.variables, self.name)

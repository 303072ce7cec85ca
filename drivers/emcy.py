"""Emergency (EMCY) frames from the drive, decoded into typed errors.

canopen's ``EmcyConsumer`` unpacks with a fixed ``struct`` and fails inside the Notifier thread on a short frame;
:func:`decode_emcy` checks the length and returns an :class:`Emergency` whose :meth:`Emergency.error` is the
:class:`~drivers.errors.EmergencyError` the bench sees, with the code decoded by
:func:`drivers.cia301.emcy_text`.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from drivers.cia301 import emcy_text
from drivers.errors import EmergencyError, ProtocolError

__all__ = ["EMCY_LENGTH", "Emergency", "decode_emcy"]

EMCY_LENGTH = 8
_EMCY = struct.Struct("<HB5s")  # error code, error register (0x1001), manufacturer-specific bytes


@dataclass(frozen=True, slots=True)
class Emergency:
    """One EMCY frame: error code, error register and the five manufacturer-specific bytes."""

    code: int
    register: int
    manufacturer: bytes
    timestamp: float

    @property
    def is_reset(self) -> bool:
        """CiA 301: codes 0x00xx announce "error reset or no error"."""
        return self.code & 0xFF00 == 0

    @property
    def text(self) -> str:
        """Decoded meaning of :attr:`code`."""
        return emcy_text(self.code)

    def error(self) -> EmergencyError:
        """The typed error the bench raises for this EMCY."""
        return EmergencyError(self.code, self.register, self.text)


def decode_emcy(data: bytes | bytearray, timestamp: float) -> Emergency:
    """Decode an EMCY payload; raises :class:`ProtocolError` unless it is exactly 8 bytes."""
    if len(data) != EMCY_LENGTH:
        raise ProtocolError(f"EMCY frame has DLC {len(data)}, CiA 301 requires {EMCY_LENGTH}")
    code, register, manufacturer = _EMCY.unpack(data)
    return Emergency(code, register, bytes(manufacturer), timestamp)

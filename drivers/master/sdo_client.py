"""The master's SDO client: canopen's, with the product's errors and integers typed by the EDS.

Start-up, the stop's SDO paths and commissioning use it; the cyclic path never does. canopen's exceptions become the
product's: an abort is an :class:`~drivers.errors.SdoError` with its decoded meaning, no answer a
:class:`~drivers.errors.DriveTimeoutError` naming the object, a frame that cannot be sent a
:class:`~drivers.errors.DriveError`. On a synchronous (lockstep) bus an answer is in the queue when the request's
``send`` returns, or never comes: the response timeout is 0 there.
"""

from __future__ import annotations

import contextlib
import struct
from collections.abc import Iterator

import can
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.cia301 import SdoAbortCode, sdo_abort_text
from drivers.errors import ConfigError, DriveError, DriveTimeoutError, SdoError
from drivers.master.link import MasterLink
from drivers.od import mapped_variable
from drivers.pdo import MappedVariable

__all__ = ["I8", "I16", "U8", "U16", "U32", "SdoClient", "SdoFormat", "format_of"]

SdoFormat = tuple[str, bool]
"""An integer object's ``struct`` code and signedness."""
U8: SdoFormat = ("B", False)
U16: SdoFormat = ("H", False)
U32: SdoFormat = ("I", False)
I8: SdoFormat = ("b", True)
I16: SdoFormat = ("h", True)


def format_of(variable: MappedVariable) -> SdoFormat:
    """The SDO format of an integer object of ``variable.bits`` bits."""
    codes = {8: "b", 16: "h", 32: "i", 64: "q"}
    code = codes[variable.bits]
    return (code if variable.signed else code.upper()), variable.signed


class SdoClient:
    """SDO transfers to the drive of ``link``, failures as the product's errors."""

    def __init__(self, link: MasterLink) -> None:
        self._link = link
        self._sdo = link.node.sdo
        self._sdo.RESPONSE_TIMEOUT = 0.0 if link.timebase.synchronous else link.cfg.sdo_timeout

    def upload(self, index: int, subindex: int) -> bytes:
        """Raw SDO upload."""
        with self._errors(index, subindex, "upload"):
            return bytes(self._sdo.upload(index, subindex))

    def download(self, index: int, subindex: int, data: bytes) -> None:
        """Raw SDO download."""
        with self._errors(index, subindex, "download"):
            self._sdo.download(index, subindex, data)

    def read(self, index: int, subindex: int, fmt: SdoFormat) -> int:
        """An integer object; an answer shorter than ``fmt`` is an :class:`SdoError` (abort code "length too low")."""
        code, signed = fmt
        size = struct.calcsize(code)
        data = self.upload(index, subindex)
        if len(data) < size:
            raise SdoError(index, subindex, int(SdoAbortCode.LENGTH_TOO_LOW),
                           f"answered {len(data)} bytes, expected {size}")
        return int.from_bytes(data[:size], "little", signed=signed)

    def write(self, index: int, subindex: int, fmt: SdoFormat, value: int) -> None:
        """Write an integer object; a value that does not fit ``fmt`` is a :class:`ConfigError` (nothing sent)."""
        code, _ = fmt
        try:
            data = struct.pack("<" + code, value)
        except struct.error as exc:
            raise ConfigError(f"0x{index:04X}:{subindex:02X} = {value} does not fit its type: {exc}") from exc
        self.download(index, subindex, data)

    def expect(self, index: int, subindex: int, fmt: SdoFormat, value: int, *, mask: int = -1) -> None:
        """Read back an object written before; a :class:`DriveError` when it holds another value (under ``mask``)."""
        read = self.read(index, subindex, fmt)
        if read & mask != value & mask:
            raise DriveError(
                f"node {self._link.node_id}: 0x{index:04X}:{subindex:02X} reads back {read} (0x{read:X}) after "
                f"writing {value} (0x{value:X})"
            )

    def read_object(self, index: int, subindex: int = 0) -> int:
        """An integer object, typed by the EDS (or the CiA 402 standard)."""
        return self.read(index, subindex, format_of(mapped_variable(self._link.od, index, subindex)))

    def write_object(self, index: int, subindex: int, value: int) -> None:
        """Write an integer object, typed by the EDS (or the CiA 402 standard)."""
        self.write(index, subindex, format_of(mapped_variable(self._link.od, index, subindex)), value)

    @contextlib.contextmanager
    def _errors(self, index: int, subindex: int, transfer: str) -> Iterator[None]:
        """canopen's SDO exceptions as the product's (module docstring)."""
        try:
            yield
        except SdoAbortedError as exc:
            raise SdoError(index, subindex, exc.code, sdo_abort_text(exc.code)) from exc
        except SdoCommunicationError as exc:
            raise DriveTimeoutError(
                f"node {self._link.node_id}: no valid SDO response for 0x{index:04X}:{subindex:02X} within "
                f"{self._link.cfg.sdo_timeout} s ({exc}): is the drive on this bus with this node id?"
            ) from exc
        except can.CanError as exc:
            raise DriveError(f"SDO {transfer} 0x{index:04X}:{subindex:02X} could not be sent: {exc}") from exc

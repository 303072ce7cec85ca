"""The SDO server's guard: what canopen's ``LocalNode`` stores without question, a real drive refuses.

canopen answers SDO requests and aborts for unknown objects / sub-indices / read-only objects / length mismatch.
The guard adds, through ``LocalNode``'s write callbacks (which run before the value is stored and may raise
``SdoAbortedError``): the value range from the EDS limits, the supported modes of operation, the range of 0x605A,
and the PDO mapping checks of CiA 301 (object exists, is mappable in that direction, has the size the entry says,
and the whole mapping fits 64 bits). It also answers no SDO request in NMT *stopped* (canopen would); it ignores a
frame that is not 8 bytes long, as CANopenNode's server does (every CiA 301 SDO request has DLC 8); it aborts a
segment that belongs to no open transfer; and it answers a block upload or block download request with abort
0x05040001 (client/server command specifier not valid), which tells a client to fall back to segmented transfer
-- canopen's server would answer a block upload with a segmented start the client cannot read.
"""

from __future__ import annotations

import struct
import threading
from typing import Any

import canopen
from canopen import objectdictionary as cod
from canopen.sdo import SdoAbortedError
from canopen.sdo.constants import (
    REQUEST_BLOCK_DOWNLOAD,
    REQUEST_BLOCK_UPLOAD,
    REQUEST_SEGMENT_DOWNLOAD,
    REQUEST_SEGMENT_UPLOAD,
    RESPONSE_ABORTED,
)

from drivers.cia301 import NmtState, SdoAbortCode
from drivers.cia402 import Obj, OperationMode
from drivers.pdo import MappingEntry
from plant_emulator.node import EmulatedNode

__all__ = ["PDO_CHANNELS", "SdoGuard"]

PDO_CHANNELS = 512  # 0x1400..0x15FF / 0x1800..0x19FF
PDO_MAX_BITS = 64
SDO_FRAME_BYTES = 8  # CiA 301: every SDO request and response has DLC 8
_CLIENT_COMMAND = 0xE0  # the client command specifier bits of an SDO request's first byte
_ABORT = struct.Struct("<BHBL")  # command, index, subindex, abort code
_MULTIPLEXER = struct.Struct("<HB")  # index, subindex at bytes 1..3 of an initiate request
QUICK_STOP_OPTION_MAX = 8  # 0x605A: 0..8 are defined by CiA 402-2
SUPPORTED_MODES = frozenset(int(m) for m in OperationMode)
_RPDO_MAPPING_AREA = range(Obj.RPDO_MAPPING, Obj.RPDO_MAPPING + PDO_CHANNELS)
_TPDO_MAPPING_AREA = range(Obj.TPDO_MAPPING, Obj.TPDO_MAPPING + PDO_CHANNELS)


class SdoGuard:
    """Write validation (before store) and the NMT gate of the SDO server.

    Parameters
    ----------
    node
        The drive's node; the guard registers itself as its write callback.
    lock
        The drive's lock: a request is served under it, like every other bus event.
    """

    def __init__(self, node: EmulatedNode, lock: threading.RLock) -> None:
        self.node = node
        self._lock = lock
        node.add_write_callback(self.validate_write)

    def attach(self, network: canopen.Network) -> None:
        """Replace canopen's SDO subscription with the gated one."""
        network.unsubscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)
        network.subscribe(self.node.sdo.rx_cobid, self.on_request)

    def on_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """canopen's SDO server, except in NMT stopped (CiA 301: no SDO there) or after ``stop_responding``."""
        if not self.node.alive or self.node.nmt_state is NmtState.STOPPED:
            return
        if len(data) != SDO_FRAME_BYTES:  # canopen would unpack past the end of a short frame and log an error
            return
        with self._lock:
            command = data[0] & _CLIENT_COMMAND
            if command in (REQUEST_BLOCK_UPLOAD, REQUEST_BLOCK_DOWNLOAD):  # no block transfer: the client falls back
                index, subindex = _MULTIPLEXER.unpack_from(data, 1)
                self.node.sdo.send_response(_ABORT.pack(RESPONSE_ABORTED, index, subindex,
                                                        SdoAbortCode.INVALID_COMMAND))
                return
            segment = command in (REQUEST_SEGMENT_DOWNLOAD, REQUEST_SEGMENT_UPLOAD)
            if segment and self.node.sdo._buffer is None:
                # no transfer was ever opened: canopen would fail on its missing buffer, then on its missing index
                self.node.sdo.send_response(_ABORT.pack(RESPONSE_ABORTED, 0, 0, SdoAbortCode.INVALID_COMMAND))
                return
            self.node.sdo.on_request(can_id, data, timestamp)

    def validate_write(self, index: int, subindex: int, od: cod.ODVariable, data: bytes, **_: Any) -> None:
        """``LocalNode`` write callback: raise ``SdoAbortedError`` with the code a real drive answers."""
        value: int | float | None = None
        if od.data_type in cod.NUMBER_TYPES and od.data_type in od.STRUCT_TYPES:
            decoded = od.decode_raw(bytes(data))
            assert isinstance(decoded, (int, float))  # numeric types decode to numbers
            value = decoded
            if od.min is not None and value < od.min:
                raise SdoAbortedError(SdoAbortCode.VALUE_TOO_LOW)
            if od.max is not None and value > od.max:
                raise SdoAbortedError(SdoAbortCode.VALUE_TOO_HIGH)
        if index == Obj.MODES_OF_OPERATION and value not in SUPPORTED_MODES:
            raise SdoAbortedError(SdoAbortCode.INVALID_VALUE)
        if (index in _RPDO_MAPPING_AREA or index in _TPDO_MAPPING_AREA) and isinstance(value, int):
            if subindex == 0:
                self._check_mapping_length(index, value)
            elif value != 0:
                self._check_mappable(index, MappingEntry.decode(value))
        if index == Obj.QUICK_STOP_OPTION and isinstance(value, int) and not 0 <= value <= QUICK_STOP_OPTION_MAX:
            raise SdoAbortedError(SdoAbortCode.INVALID_VALUE)

    def _check_mappable(self, mapping_index: int, entry: MappingEntry) -> None:
        od = self.node.object_dictionary
        if entry.index not in od:
            raise SdoAbortedError(SdoAbortCode.NO_OBJECT)
        obj = od[entry.index]
        if not isinstance(obj, cod.ODVariable):
            if entry.subindex not in obj:
                raise SdoAbortedError(SdoAbortCode.NO_SUBINDEX)
            obj = obj[entry.subindex]
        if not obj.pdo_mappable:
            raise SdoAbortedError(SdoAbortCode.CANNOT_MAP)
        is_rpdo = mapping_index in _RPDO_MAPPING_AREA
        if (is_rpdo and not obj.writable) or (not is_rpdo and not obj.readable):
            raise SdoAbortedError(SdoAbortCode.CANNOT_MAP)
        if entry.bits != len(obj):
            raise SdoAbortedError(SdoAbortCode.GENERAL_PARAMETER)

    def _check_mapping_length(self, mapping_index: int, count: int) -> None:
        total = 0
        for sub in range(1, count + 1):
            try:
                entry = MappingEntry.decode(self.node.read(mapping_index, sub))
            except (KeyError, SdoAbortedError):
                raise SdoAbortedError(SdoAbortCode.NO_SUBINDEX) from None
            self._check_mappable(mapping_index, entry)
            total += entry.bits
        if total > PDO_MAX_BITS:
            raise SdoAbortedError(SdoAbortCode.PDO_TOO_LONG)

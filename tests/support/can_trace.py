"""CANopen frames in words: one line per frame for traces, logs and reports.

:func:`describe_frame` names the service (NMT, SYNC, EMCY, PDO, SDO, heartbeat) from the COB-ID and decodes what
CiA 301 fixes (NMT commands, SDO expedited transfers and aborts, EMCY codes, heartbeat states). PDO payloads are
decoded only when their mapping is given (``codecs``), since the mapping is whatever the master configured.
"""

from __future__ import annotations

from collections.abc import Mapping

import can

from drivers.cia301 import (
    NMT_COB_ID,
    RPDO_BASES,
    SYNC_COB_ID,
    TPDO_BASES,
    FunctionCode,
    NmtCommand,
    NmtState,
    emcy_text,
    heartbeat_state,
    sdo_abort_text,
    split_cob_id,
)
from drivers.pdo import PdoCodec

__all__ = ["describe_frame"]

_SDO_ABORT = 0x80


def _nmt(data: bytes) -> str:
    if len(data) != 2:
        return f"NMT (DLC {len(data)}, malformed)"
    command, node = data
    try:
        name = NmtCommand(command).name.lower().replace("_", " ")
    except ValueError:
        name = f"command 0x{command:02X}"
    return f"NMT {name} node {node if node else 'all'}"


def _sdo(data: bytes, request: bool) -> str:
    if len(data) != 8:
        return f"SDO (DLC {len(data)}, malformed)"
    command = data[0]
    where = f"0x{int.from_bytes(data[1:3], 'little'):04X}:{data[3]:02X}"
    if command == _SDO_ABORT:
        code = int.from_bytes(data[4:8], "little")
        return f"SDO abort {where} 0x{code:08X} ({sdo_abort_text(code)})"
    specifier = command >> 5
    expedited, sized = command & 0x02, command & 0x01
    size = 4 - ((command >> 2) & 0x03) if expedited and sized else 4
    value = int.from_bytes(data[4 : 4 + size], "little")
    if request:
        if specifier == 1:  # initiate download
            if expedited:
                return f"SDO download {where} = 0x{value:0{2 * size}X}"
            return f"SDO download {where} (segmented, {value} bytes)"
        if specifier == 2:
            return f"SDO upload {where}"
        return f"SDO request 0x{command:02X} {where}"
    if specifier == 3:  # download response
        return f"SDO download ack {where}"
    if specifier == 2:  # upload response
        if expedited:
            return f"SDO upload reply {where} = 0x{value:0{2 * size}X}"
        return f"SDO upload reply {where} (segmented, {value} bytes)"
    return f"SDO response 0x{command:02X} {where}"


def _pdo(kind: str, data: bytes, codec: PdoCodec | None) -> str:
    if codec is None:
        return f"{kind} {data.hex(' ') if data else '(empty)'}"
    try:
        values = codec.decode(data)
    except ValueError as exc:  # ProtocolError is a ValueError
        return f"{kind} {exc}"
    fields = []
    for variable, value in zip(codec.variables, values, strict=True):
        shown = f"0x{value:04X}" if not variable.signed else str(value)
        fields.append(f"{variable.index:04X}={shown}")
    return f"{kind} " + " ".join(fields)


def describe_frame(msg: can.Message, codecs: Mapping[int, PdoCodec] | None = None) -> str:
    """One line saying what ``msg`` is, e.g. ``"SDO download 0x1600:01 = 0x60400010"`` or ``"SYNC"``.

    Parameters
    ----------
    msg
        The frame (11-bit CANopen COB-IDs; extended frames are shown raw).
    codecs
        PDO codecs by COB-ID, to decode PDO payloads into object values.
    """
    data = bytes(msg.data)
    if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
        return f"frame 0x{msg.arbitration_id:X} {data.hex(' ')}"
    can_id = msg.arbitration_id
    function, node = split_cob_id(can_id)
    if can_id == NMT_COB_ID:
        return _nmt(data)
    if can_id == SYNC_COB_ID:
        return "SYNC" if not data else f"SYNC counter {data[0]}"
    if function == FunctionCode.EMCY and node:
        if len(data) != 8:
            return f"EMCY node {node} (DLC {len(data)}, malformed)"
        code = int.from_bytes(data[:2], "little")
        return f"EMCY node {node} 0x{code:04X} ({emcy_text(code)}) register 0x{data[2]:02X}"
    for number, base in enumerate(TPDO_BASES, start=1):
        if function == base:
            return _pdo(f"TPDO{number} node {node}", data, (codecs or {}).get(can_id))
    for number, base in enumerate(RPDO_BASES, start=1):
        if function == base:
            return _pdo(f"RPDO{number} node {node}", data, (codecs or {}).get(can_id))
    if function == FunctionCode.SDO_RX:
        return _sdo(data, request=True)
    if function == FunctionCode.SDO_TX:
        return _sdo(data, request=False)
    if function == FunctionCode.HEARTBEAT:
        if len(data) != 1:
            return f"heartbeat node {node} (DLC {len(data)}, malformed)"
        if data[0] == NmtState.INITIALISING:
            return f"boot-up node {node}"
        try:
            state = NmtState(heartbeat_state(data[0])).name.lower().replace("_", "-")
        except ValueError:
            state = f"state 0x{data[0]:02X}"
        return f"heartbeat node {node} {state}"
    return f"frame 0x{can_id:03X} {data.hex(' ')}"

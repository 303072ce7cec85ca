"""``commission info``: what a drive is and how it is configured, read over SDO without changing anything.

Read: 0x1000 device type, 0x1018 identity, the NMT state (its next heartbeat, when 0x1017 is non-zero), 0x6502
supported drive modes (every CiA 402-2 bit decoded), 0x6061 the mode it is in, 0x6041 statusword decoded into the
402 state and its flags, 0x1001 error register (bits named), 0x603F error code (decoded like an EMCY code), and the
PDO mapping as configured now: for RPDO/TPDO 1..4 the COB-ID (valid or not), the transmission type and the mapped
objects with their EDS names.

``info --dbc`` writes the mapping ``run`` will install (not the one read here), see
:mod:`foilc_hil.commission.dbc`; ``info --dcf`` the drive as ``run`` configures it, see
:mod:`foilc_hil.commission.dcf`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from canopen.objectdictionary import ODVariable

from drivers.cia301 import CobIdEntry, ErrorRegister, NmtState, SdoAbortCode, emcy_text
from drivers.cia402 import IdentitySub, Obj, Statusword, decode_state
from drivers.cia402_master import Cia402Drive
from drivers.pdo import MappingEntry
from foilc_hil.errors import SdoError

__all__ = [
    "MODE_NAMES",
    "SUPPORTED_MODE_BITS_402",
    "DriveInfo",
    "MappedObjectReport",
    "PdoReport",
    "read_info",
]

#: 0x6502 bit -> (mode of operation number, name), CiA 402-2
SUPPORTED_MODE_BITS_402: dict[int, tuple[int, str]] = {
    0: (1, "profile position (pp)"),
    1: (2, "velocity (vl)"),
    2: (3, "profile velocity (pv)"),
    3: (4, "profile torque (tq)"),
    5: (6, "homing (hm)"),
    6: (7, "interpolated position (ip)"),
    7: (8, "cyclic synchronous position (csp)"),
    8: (9, "cyclic synchronous velocity (csv)"),
    9: (10, "cyclic synchronous torque (cst)"),
}
MODE_NAMES: dict[int, str] = {number: name for number, name in SUPPORTED_MODE_BITS_402.values()}
PDO_COUNT = 4
HEARTBEAT_WAIT_FACTOR = 1.5


@dataclass(frozen=True)
class MappedObjectReport:
    """One entry of a PDO mapping as read from the drive, with the object's name from the EDS."""

    entry: MappingEntry
    name: str

    def to_json(self) -> dict[str, Any]:
        return {"index": self.entry.index, "subindex": self.entry.subindex, "bits": self.entry.bits, "name": self.name}


@dataclass(frozen=True)
class PdoReport:
    """One PDO as the drive has it configured."""

    direction: str  # "RPDO" or "TPDO"
    number: int
    cob_id: int
    valid: bool
    transmission_type: int
    mapped: tuple[MappedObjectReport, ...]

    def to_json(self) -> dict[str, Any]:
        return {
            "direction": self.direction,
            "number": self.number,
            "cob_id": self.cob_id,
            "valid": self.valid,
            "transmission_type": self.transmission_type,
            "mapped": [entry.to_json() for entry in self.mapped],
        }


@dataclass(frozen=True)
class DriveInfo:
    """Everything ``info`` reads (raw values; :meth:`to_json` decodes them)."""

    node_id: int
    device_type: int
    identity: dict[str, int]  # 0x1018 sub-index name -> value
    nmt_state: str
    heartbeat_producer_ms: int | None
    supported_bits: int | None  # 0x6502; None when the drive lacks it
    mode: int | None  # 0x6061
    statusword: int
    error_register: int
    error_code: int | None  # 0x603F
    pdos: tuple[PdoReport, ...]
    heartbeat_wait_seconds: float

    def to_json(self) -> dict[str, Any]:
        bits, mode, error_code = self.supported_bits, self.mode, self.error_code
        modes = [] if bits is None else [
            {"mode": number, "name": name}
            for bit, (number, name) in SUPPORTED_MODE_BITS_402.items()
            if bits & (1 << bit)
        ]
        return {
            "node_id": self.node_id,
            "device_type": self.device_type,
            "profile": self.device_type & 0xFFFF,
            "identity": dict(self.identity),
            "nmt_state": self.nmt_state,
            "heartbeat_producer_ms": self.heartbeat_producer_ms,
            "supported_modes": {"value": bits, "hex": None if bits is None else f"0x{bits:08X}", "modes": modes},
            "mode": {"value": mode, "name": MODE_NAMES.get(mode, "unknown") if mode is not None else None},
            "statusword": decode_statusword(self.statusword),
            "error_register": decode_error_register(self.error_register),
            "error_code": None if error_code is None else {
                "value": error_code,
                "hex": f"0x{error_code:04X}",
                "text": "no error" if error_code == 0 else emcy_text(error_code),
            },
            "pdos": [pdo.to_json() for pdo in self.pdos],
            "heartbeat_wait_seconds": self.heartbeat_wait_seconds,
        }


def _object_name(drive: Cia402Drive, index: int, subindex: int) -> str:
    try:
        obj = drive.od[index]
    except KeyError:
        return f"0x{index:04X}:{subindex:02X}"
    if isinstance(obj, ODVariable):
        return str(obj.name)
    try:
        return f"{obj.name}.{obj[subindex].name}"
    except KeyError:
        return f"{obj.name}.{subindex}"


def read_optional(drive: Cia402Drive, index: int, subindex: int = 0) -> int | None:
    """The object's value, or None when the drive does not have it (abort 'no object / sub-index')."""
    try:
        return drive.read_object(index, subindex)
    except SdoError as exc:
        if exc.abort_code in (SdoAbortCode.NO_OBJECT, SdoAbortCode.NO_SUBINDEX):
            return None
        raise


def decode_statusword(statusword: int) -> dict[str, Any]:
    """Statusword -> its 402 state and the names of the bits set."""
    try:
        state: str = decode_state(statusword).name
    except ValueError:
        state = "invalid"
    flags = [flag.name for flag in Statusword if statusword & flag and flag.name]
    return {"value": statusword, "hex": f"0x{statusword:04X}", "state": state, "flags": flags}


def decode_error_register(register: int) -> dict[str, Any]:
    """0x1001 -> the names of the bits set."""
    bits = [bit.name.lower() for bit in ErrorRegister if register & bit]
    return {"value": register, "hex": f"0x{register:02X}", "bits": bits}


def read_pdos(drive: Cia402Drive) -> tuple[PdoReport, ...]:
    """RPDO and TPDO 1..4 as configured (communication and mapping parameters over SDO)."""
    reports: list[PdoReport] = []
    for direction, com_base, map_base in (
        ("RPDO", Obj.RPDO_COMMUNICATION, Obj.RPDO_MAPPING),
        ("TPDO", Obj.TPDO_COMMUNICATION, Obj.TPDO_MAPPING),
    ):
        for number in range(1, PDO_COUNT + 1):
            com, mapping = com_base + number - 1, map_base + number - 1
            if com not in drive.od or mapping not in drive.od:
                continue  # the drive's EDS has fewer PDOs
            raw_cob = read_optional(drive, com, 1)
            if raw_cob is None:
                continue  # the drive has fewer PDOs
            transmission = read_optional(drive, com, 2)
            count = read_optional(drive, mapping, 0) or 0
            mapped = []
            for sub in range(1, count + 1):
                entry = MappingEntry.decode(drive.read_object(mapping, sub))
                mapped.append(MappedObjectReport(entry, _object_name(drive, entry.index, entry.subindex)))
            cob = CobIdEntry.decode(raw_cob)
            reports.append(
                PdoReport(
                    direction=direction,
                    number=number,
                    cob_id=cob.can_id,
                    valid=cob.valid,
                    transmission_type=transmission if transmission is not None else -1,
                    mapped=tuple(mapped),
                )
            )
    return tuple(reports)


def _nmt_state(drive: Cia402Drive, producer_ms: int | None) -> str:
    if not producer_ms:
        return "unknown"
    state = drive.heartbeat.wait_for(lambda _: True, 0, timeout=HEARTBEAT_WAIT_FACTOR * producer_ms / 1000)
    if state is None:
        return "no heartbeat"
    try:
        return NmtState(state).name
    except ValueError:
        return f"0x{state:02X}"


def read_info(drive: Cia402Drive) -> DriveInfo:
    """Read identity, modes, state, errors and PDO mapping of ``drive`` (see the module docstring)."""
    device_type = drive.read_object(Obj.DEVICE_TYPE)
    identity = {sub.name.lower(): drive.read_object(Obj.IDENTITY, sub) for sub in IdentitySub}
    supported_bits = read_optional(drive, Obj.SUPPORTED_DRIVE_MODES)
    mode = read_optional(drive, Obj.MODES_OF_OPERATION_DISPLAY)
    statusword = drive.read_object(Obj.STATUSWORD)
    register = drive.read_object(Obj.ERROR_REGISTER)
    error_code = read_optional(drive, Obj.ERROR_CODE)
    producer_ms = read_optional(drive, Obj.PRODUCER_HEARTBEAT_TIME)
    started = time.monotonic()
    nmt = _nmt_state(drive, producer_ms)
    return DriveInfo(
        node_id=drive.node_id,
        device_type=device_type,
        identity=identity,
        nmt_state=nmt,
        heartbeat_producer_ms=producer_ms,
        supported_bits=supported_bits,
        mode=mode,
        statusword=statusword,
        error_register=register,
        error_code=error_code,
        pdos=read_pdos(drive),
        heartbeat_wait_seconds=round(time.monotonic() - started, 3),
    )


def render_info(document: dict[str, Any]) -> str:
    """The human-readable rendering of :func:`read_info`'s document."""
    identity = document["identity"]
    lines = [
        f"node {document['node_id']}: device type 0x{document['device_type']:08X} (profile {document['profile']}), "
        f"NMT {document['nmt_state']}",
        "identity: " + ", ".join(f"{key} 0x{value:08X}" for key, value in identity.items()),
    ]
    modes = document["supported_modes"]
    names = ", ".join(f"{m['mode']} {m['name']}" for m in modes["modes"]) or "not given (0x6502 absent)"
    lines.append(f"supported modes ({modes['hex']}): {names}")
    mode = document["mode"]
    lines.append(f"mode of operation (0x6061): {mode['value']} {mode['name']}")
    status = document["statusword"]
    lines.append(f"statusword {status['hex']}: {status['state']} [{', '.join(status['flags'])}]")
    register = document["error_register"]
    lines.append(f"error register {register['hex']}: {', '.join(register['bits']) or 'no error'}")
    code = document["error_code"]
    if code is not None:
        lines.append(f"error code (0x603F) {code['hex']}: {code['text']}")
    lines.append("PDO mapping:")
    for pdo in document["pdos"]:
        mapped = ", ".join(f"0x{m['index']:04X}:{m['subindex']:02X}/{m['bits']} {m['name']}" for m in pdo["mapped"])
        state = "valid" if pdo["valid"] else "not valid"
        lines.append(
            f"  {pdo['direction']}{pdo['number']} COB-ID 0x{pdo['cob_id']:03X} ({state}), "
            f"transmission type {pdo['transmission_type']}: {mapped or '(nothing mapped)'}"
        )
    if "dbc" in document:
        lines.append(f"DBC of the mapping run installs written to {document['dbc']['file']} "
                     f"({len(document['dbc']['frames'])} frames)")
    if "dcf" in document:
        lines.append(f"DCF of the configured drive written to {document['dcf']['file']} "
                     f"({len(document['dcf']['parameters'])} parameter values)")
    return "\n".join(lines)


"""``commission info --dcf``: the configured drive as a CiA 306 DCF (device configuration file).

A DCF is the drive's EDS plus what the network's configuration sets on it. :func:`write_dcf` copies the EDS the
master loaded (``drive.eds``, section by section) and adds:

- ``[DeviceComissioning]`` (CiA 306 spells it so): ``NodeID``, ``NodeName`` (``drive_<id>``, the DBC's node name),
  ``Baudrate`` in kbit/s (the bus's bit rate; 1000 when none is set, the bus-load check's default), ``NetNumber``,
  ``NetworkName``, ``CANopenManager`` (0: the drive is no manager);
- ``ParameterValue`` on every object ``run``'s start-up writes for ``drive.mode``
  (:meth:`~drivers.cia402_master.Cia402Drive.configure`): each RPDO/TPDO of the plan (COB-ID valid, transmission
  type, mapping count and entries), every other PDO the EDS has disabled (COB-ID bit 31), and the settings after
  the PDOs -- 0x6060 mode, 0x605A, 0x6007, 0x1006, 0x60C2, 0x1017 and 0x1016:1 (heartbeats) -- where the EDS
  has them (``run`` skips an optional object the EDS lacks; so does the DCF).

canopen's ``import_od`` loads it back (``od.node_id``, ``od.bitrate`` and each object's ``value``). Why not
canopen's ``export_dcf``: it marks every object with a value (every default, after ``import_od``) as configured, its
commissioning section lacks most of CiA 306's keys, and it rewrites the EDS from what it parsed
(``docs/commissioning.md``).
"""

from __future__ import annotations

import configparser
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from canopen.objectdictionary import ODVariable

from drivers.cia301 import COB_ID_INVALID, RPDO_BASES, TPDO_BASES, cob_id
from drivers.cia402 import Obj, OperationMode
from drivers.cia402_master import Cia402Drive, PdoPlan
from drivers.od import DEFAULT_EDS
from foilc_hil.commission.dbc import drive_node_name
from foilc_hil.errors import InputError

__all__ = ["DcfExport", "configured_values", "write_dcf"]

NETWORK_NAME = "foilc-hil"
COMMISSIONING = "DeviceComissioning"  # CiA 306's spelling, which canopen reads


@dataclass(frozen=True)
class DcfExport:
    """What :func:`write_dcf` wrote: the file, the node id, the bit rate and every ``ParameterValue`` set."""

    file: str
    node_id: int
    bitrate: int
    values: tuple[tuple[int, int, int], ...]  # (index, sub-index, value), in start-up order

    def to_json(self) -> dict[str, Any]:
        return {
            "file": self.file,
            "node_id": self.node_id,
            "bitrate": self.bitrate,
            "parameters": [{"index": index, "subindex": sub, "value": value} for index, sub, value in self.values],
        }


def configured_values(drive: Cia402Drive, plan: PdoPlan, mode: OperationMode) -> dict[tuple[int, int], int]:
    """``(index, sub-index) -> value`` of everything ``configure`` leaves on the drive (module docstring)."""
    values: dict[tuple[int, int], int] = {}
    for layouts, bases, base_index in ((plan.rpdos, RPDO_BASES, Obj.RPDO_COMMUNICATION),
                                       (plan.tpdos, TPDO_BASES, Obj.TPDO_COMMUNICATION)):
        used = {layout.number: layout for layout in layouts}
        for number, base in enumerate(bases, start=1):
            if number in used:
                layout = used[number]
                values[layout.communication_index, 1] = layout.cob_id
                values[layout.communication_index, 2] = int(layout.transmission_type)
                values[layout.mapping_index, 0] = len(layout.variables)
                for sub, variable in enumerate(layout.variables, start=1):
                    values[layout.mapping_index, sub] = variable.mapping_entry
            elif base_index + number - 1 in drive.od:
                values[base_index + number - 1, 1] = cob_id(base, drive.node_id) | COB_ID_INVALID
    for index, sub, value, optional in drive.settings(mode):
        if index in drive.od or not optional:
            values[index, sub] = value
    return values


def _section(drive: Cia402Drive, index: int, subindex: int) -> str:
    """The EDS section of one object: ``XXXX`` for a variable, ``XXXXsubN`` for a record or array member."""
    if isinstance(drive.od.get(index), ODVariable):
        return f"{index:04X}"
    return f"{index:04X}sub{subindex:X}"


def write_dcf(drive: Cia402Drive, plan: PdoPlan, *, bitrate: int, path: str | Path) -> DcfExport:
    """Write the DCF of ``drive`` configured for ``drive.cfg``'s mode with ``plan`` (module docstring)."""
    source = Path(drive.cfg.eds) if drive.cfg.eds else DEFAULT_EDS
    parser = configparser.RawConfigParser(strict=False)
    parser.optionxform = str  # type: ignore[assignment,method-assign]  # keep the EDS's key spelling
    parser.read(source, encoding="utf-8")
    sections = {name.upper(): name for name in parser.sections()}
    values = configured_values(drive, plan, drive.cfg.operation_mode)
    written: list[tuple[int, int, int]] = []
    for (index, sub), value in values.items():
        section = sections.get(_section(drive, index, sub).upper())
        if section is None:  # a DCF describes the objects of its EDS; the master types others by the standard
            continue
        parser.set(section, "ParameterValue", f"0x{value:X}" if value >= 0 else str(value))
        written.append((index, sub, value))
    target = Path(path)
    if COMMISSIONING in parser:
        parser.remove_section(COMMISSIONING)
    parser.add_section(COMMISSIONING)
    for key, text in (("NodeID", str(drive.node_id)), ("NodeName", drive_node_name(drive.node_id)),
                      ("Baudrate", str(bitrate // 1000)), ("NetNumber", "1"), ("NetworkName", NETWORK_NAME),
                      ("CANopenManager", "0")):
        parser.set(COMMISSIONING, key, text)
    if "FileInfo" in parser:
        parser.set("FileInfo", "FileName", target.name)
    try:
        with target.open("w", encoding="utf-8") as stream:
            parser.write(stream, space_around_delimiters=False)
    except OSError as exc:
        raise InputError(f"--dcf: cannot write {target}: {exc}") from exc
    return DcfExport(str(target), drive.node_id, bitrate, tuple(written))

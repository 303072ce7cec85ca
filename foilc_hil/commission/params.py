"""``commission params read|write``: named parameter sets written over SDO, verified, and rolled back on failure.

A parameter set is a YAML file::

    parameters:
      - {name: max_torque, index: 0x6072, subindex: 0, value: 1500, unit: per mille}
      - {name: velocity_loop_gain, index: 0x2001, value: 120}

What is transactional, precisely
--------------------------------
``write`` runs in four phases and changes nothing on the drive unless phase 3 starts:

1. **Check the file** (types, duplicates): a malformed file is a usage error (exit 2), nothing is sent.
2. **Check every entry against the EDS** (the object exists, is writable, has a numeric type, the value fits the
   type and the EDS ``LowLimit``/``HighLimit``). If any entry fails, the whole set is refused before anything is
   written; each failure is reported with the SDO abort code the drive would answer (e.g. 0x06010002 "attempt to
   write a read-only object", 0x06090031 "value of parameter written too high") and the command exits 1.
   ``--skip-eds-check`` sends the set anyway (for a drive whose EDS is wrong), leaving the checks to the drive.
3. **Read every old value** over SDO (an abort here also leaves the drive untouched).
4. **Write in file order, reading each value back.** If a write aborts or reads back a different value, the
   entries already written are written back to their old values (newest first) and verified, the abort is reported
   with its decoded meaning, and the command exits 1. The report says which entries were restored and which could
   not be (if the drive also rejects the restore).

Not covered: the values are not stored to non-volatile memory (no 0x1010 "store parameters"); a power loss or
another master writing between phases 3 and 4 is not detected; a write the drive acts on at once (a controlword, a
mode) has had its effect even if it is rolled back.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

import yaml
from canopen.objectdictionary import (
    FLOAT_TYPES,
    INTEGER_TYPES,
    SIGNED_TYPES,
    ObjectDictionaryError,
    ODArray,
    ODRecord,
    ODVariable,
)
from pydantic import Field, field_validator

from drivers.cia301 import SdoAbortCode, sdo_abort_text
from drivers.cia402 import Obj
from drivers.cia402_master import Cia402Drive
from foilc_hil.errors import ConfigError, DriveError, SdoError
from foilc_hil.schema import Section, load_document, validate

__all__ = [
    "ChangeStatus",
    "ParameterChange",
    "ParameterEntry",
    "ParameterSet",
    "ParameterValue",
    "WriteReport",
    "check_against_eds",
    "dump_parameter_set",
    "eds_parameters",
    "load_parameter_set",
    "read_parameters",
    "write_parameters",
]

_WRITABLE = frozenset({"rw", "wo", "rww", "rwr"})
_PARAMETER_AREA = range(0x2000, 0xA000)  # manufacturer + device profile objects (not communication 0x1xxx)
_PROCESS_DATA = frozenset({Obj.CONTROLWORD, Obj.TARGET_VELOCITY, Obj.TARGET_TORQUE})  # commands, not settings


def _index(value: Any) -> Any:
    """Accept ``0x6072`` (an int in YAML) or the string ``"0x6072"``."""
    if isinstance(value, str):
        try:
            return int(value, 0)
        except ValueError:
            raise ValueError(f"{value!r} is not an object index like 0x6072") from None
    return value


class ParameterEntry(Section):
    """One parameter: a name for people, the object address, the value and its unit."""

    name: str = Field(min_length=1)
    index: int = Field(ge=0x1000, le=0xFFFF)
    subindex: int = Field(default=0, ge=0, le=0xFF)
    value: int | float | None = None  # None: only read it
    unit: str = ""

    _coerce_index = field_validator("index", "subindex", mode="before")(_index)

    @property
    def address(self) -> str:
        return f"0x{self.index:04X}:{self.subindex:02X}"


class ParameterSet(Section):
    """The file: a list of entries with unique names and addresses."""

    parameters: list[ParameterEntry] = Field(min_length=1)

    @field_validator("parameters")
    @classmethod
    def _unique(cls, entries: list[ParameterEntry]) -> list[ParameterEntry]:
        names: set[str] = set()
        addresses: set[tuple[int, int]] = set()
        for entry in entries:
            if entry.name in names:
                raise ValueError(f"name {entry.name!r} appears twice")
            if (entry.index, entry.subindex) in addresses:
                raise ValueError(f"object {entry.address} appears twice")
            names.add(entry.name)
            addresses.add((entry.index, entry.subindex))
        return entries


def load_parameter_set(path: str | Path, *, need_values: bool) -> ParameterSet:
    """Load and validate a parameter file; ConfigError (exit 2) naming the file and key otherwise."""
    document = load_document(path)
    parameter_set = validate(ParameterSet, document, source=str(path))
    if need_values:
        for number, entry in enumerate(parameter_set.parameters):
            if entry.value is None:
                raise ConfigError("needs a value to write", key=f"parameters.{number}.value", source=str(path))
    return parameter_set


@dataclass(frozen=True)
class ParameterValue:
    """One parameter as read from the drive (the fields of a parameter-set file)."""

    name: str
    index: int
    subindex: int
    value: int | float
    unit: str = ""

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "index": self.index, "subindex": self.subindex, "value": self.value,
                "unit": self.unit}


def dump_parameter_set(entries: list[ParameterValue]) -> str:
    """The YAML text of a parameter set (indices as hex strings)."""
    rows = [
        {
            "name": entry.name,
            "index": f"0x{entry.index:04X}",
            "subindex": entry.subindex,
            "value": entry.value,
            "unit": entry.unit,
        }
        for entry in entries
    ]
    return yaml.safe_dump({"parameters": rows}, sort_keys=False)


# --- EDS checks -------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EdsViolation:
    """An entry the EDS says the drive would reject, with the abort code it would answer."""

    entry: ParameterEntry
    abort_code: int
    detail: str

    def message(self) -> str:
        return (
            f"{self.entry.name} ({self.entry.address}): {self.detail} -- the drive would abort with "
            f"0x{self.abort_code:08X} ({sdo_abort_text(self.abort_code)})"
        )


def _variable(drive: Cia402Drive, entry: ParameterEntry) -> ODVariable | None:
    try:
        obj = drive.od[entry.index]
    except KeyError:
        return None
    if isinstance(obj, ODVariable):
        return obj if entry.subindex == 0 else None
    if isinstance(obj, (ODRecord, ODArray)):
        try:
            sub = obj[entry.subindex]
        except KeyError:
            return None
        return sub if isinstance(sub, ODVariable) else None
    return None


def _type_range(variable: ODVariable) -> tuple[float, float]:
    if variable.data_type in INTEGER_TYPES:
        bits = len(variable)
        if variable.data_type in SIGNED_TYPES:
            return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
        return 0, (1 << bits) - 1
    return float("-inf"), float("inf")


def check_against_eds(drive: Cia402Drive, entries: list[ParameterEntry]) -> list[EdsViolation]:
    """Every entry the drive's EDS says would be rejected (empty: all pass)."""
    violations: list[EdsViolation] = []
    for entry in entries:
        variable = _variable(drive, entry)
        if variable is None:
            missing = entry.index not in drive.od
            code = SdoAbortCode.NO_OBJECT if missing else SdoAbortCode.NO_SUBINDEX
            violations.append(EdsViolation(entry, code, "not in the EDS"))
            continue
        if variable.access_type not in _WRITABLE:
            violations.append(
                EdsViolation(entry, SdoAbortCode.READ_ONLY, f"access type {variable.access_type!r} in the EDS")
            )
            continue
        if variable.data_type not in INTEGER_TYPES and variable.data_type not in FLOAT_TYPES:
            violations.append(
                EdsViolation(entry, SdoAbortCode.LENGTH_MISMATCH,
                             f"data type 0x{variable.data_type:04X} is not numeric")
            )
            continue
        value = entry.value
        assert value is not None  # load_parameter_set(need_values=True)
        if variable.data_type in INTEGER_TYPES and not float(value).is_integer():
            violations.append(EdsViolation(entry, SdoAbortCode.INVALID_VALUE, f"{value} is not an integer"))
            continue
        low, high = _type_range(variable)
        if variable.min is not None:
            low = max(low, variable.min)
        if variable.max is not None:
            high = min(high, variable.max)
        if value < low:
            violations.append(EdsViolation(entry, SdoAbortCode.VALUE_TOO_LOW, f"{value} is below {low}"))
        elif value > high:
            violations.append(EdsViolation(entry, SdoAbortCode.VALUE_TOO_HIGH, f"{value} is above {high}"))
    return violations


# --- SDO access -------------------------------------------------------------------------------------------------


def _upload(drive: Cia402Drive, entry: ParameterEntry) -> int | float:
    variable = _variable(drive, entry)
    data = drive.sdo_upload(entry.index, entry.subindex)
    if variable is None:  # not in the EDS (only with --skip-eds-check): read as a little-endian integer
        return int.from_bytes(bytes(data), "little", signed=False)
    try:
        value = variable.decode_raw(bytes(data))
    except (struct.error, ValueError, ObjectDictionaryError) as exc:  # a wrong length
        raise SdoError(entry.index, entry.subindex, int(SdoAbortCode.LENGTH_MISMATCH),
                       f"answered {len(data)} bytes, not a {variable.data_type:#06x}: {exc}") from exc
    if not isinstance(value, (int, float)):
        raise SdoError(entry.index, entry.subindex, int(SdoAbortCode.LENGTH_MISMATCH), "not a numeric object")
    return value


def _download(drive: Cia402Drive, entry: ParameterEntry, value: int | float) -> None:
    variable = _variable(drive, entry)
    if variable is None:
        data = int(value).to_bytes(4, "little", signed=value < 0)
    else:
        typed = int(value) if variable.data_type in INTEGER_TYPES else float(value)
        try:
            data = variable.encode_raw(typed)
        except (struct.error, ValueError, TypeError, ObjectDictionaryError) as exc:  # value outside the type
            raise SdoError(entry.index, entry.subindex, int(SdoAbortCode.INVALID_VALUE),
                           f"{value} does not fit the object's type: {exc}") from exc
    drive.sdo_download(entry.index, entry.subindex, data)


# --- read / write -----------------------------------------------------------------------------------------------


def read_parameters(drive: Cia402Drive, entries: list[ParameterEntry]) -> list[ParameterValue]:
    """Current values of ``entries`` (same fields as the file)."""
    return [ParameterValue(e.name, e.index, e.subindex, _upload(drive, e), e.unit) for e in entries]


def eds_parameters(drive: Cia402Drive) -> list[ParameterEntry]:
    """Every writable numeric object of the EDS outside the communication area (0x2000..0x9FFF) that is not
    process data (controlword, targets)."""
    entries: list[ParameterEntry] = []
    for index in sorted(drive.od.indices if hasattr(drive.od, "indices") else drive.od.keys()):
        if index not in _PARAMETER_AREA:
            continue
        obj = drive.od[index]
        variables = [obj] if isinstance(obj, ODVariable) else [v for v in obj.values() if isinstance(v, ODVariable)]
        for variable in variables:
            numeric = variable.data_type in INTEGER_TYPES or variable.data_type in FLOAT_TYPES
            if variable.access_type in _WRITABLE and numeric and index not in _PROCESS_DATA:
                name = variable.name if isinstance(obj, ODVariable) else f"{obj.name}.{variable.name}"
                slug = "_".join(name.lower().replace(".", " ").split())
                entries.append(ParameterEntry(name=slug, index=variable.index, subindex=variable.subindex,
                                              unit=variable.unit or ""))
    return entries


class ChangeStatus(StrEnum):
    """What happened to one entry of ``params write`` (the ``status`` of the JSON document)."""

    PENDING = "pending"  # not reached: an earlier entry failed
    CHANGED = "changed"
    UNCHANGED = "unchanged"  # written, and the drive already had the value
    FAILED = "failed"
    ROLLED_BACK = "rolled back"
    NOT_RESTORED = "NOT restored"


@dataclass
class ParameterChange:
    """One entry of ``params write``: old value, value read back after writing, and after a rollback."""

    name: str
    index: int
    subindex: int
    old: int | float
    unit: str = ""
    new: int | float | None = None  # read back after writing; None: not written
    status: ChangeStatus = ChangeStatus.PENDING
    now: int | float | None = None  # read back after a successful rollback

    def to_json(self) -> dict[str, Any]:
        document: dict[str, Any] = {"name": self.name, "index": self.index, "subindex": self.subindex,
                                    "old": self.old, "new": self.new, "unit": self.unit, "status": str(self.status)}
        if self.now is not None:
            document["now"] = self.now
        return document


@dataclass
class WriteReport:
    """What ``params write`` did: per entry old -> new, and on failure the abort and the rollback."""

    changes: list[ParameterChange]
    error: str = ""
    rolled_back: list[str] | None = None
    not_restored: list[str] | None = None
    refused: list[str] | None = None

    @property
    def ok(self) -> bool:
        return not self.error

    def to_json(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "changes": [change.to_json() for change in self.changes],
            "error": self.error or None,
            "refused": self.refused,
            "rolled_back": self.rolled_back,
            "not_restored": self.not_restored,
        }

    def render(self) -> str:
        lines: list[str] = []
        for change in self.changes:
            old, new = change.old, change.new
            arrow = f"{old} -> {new}" if new is not None else f"{old} (not written)"
            if change.now is not None:
                arrow += f" -> {change.now}"
            unit = f" {change.unit}" if change.unit else ""
            lines.append(f"{change.name:<28} 0x{change.index:04X}:{change.subindex:02X}  {arrow}{unit}  "
                         f"[{change.status}]")
        for line in self.refused or []:
            lines.append(f"refused: {line}")
        if self.error:
            lines.append(f"error: {self.error}")
        if self.rolled_back is not None:
            lines.append(f"rolled back: {', '.join(self.rolled_back) or 'nothing had been written'}")
        if self.not_restored:
            lines.append(f"NOT restored: {', '.join(self.not_restored)}")
        return "\n".join(lines)


def _same(a: int | float, b: int | float) -> bool:
    return a == b or ((isinstance(a, float) or isinstance(b, float)) and abs(a - b) <= 1e-6 * max(abs(a), abs(b)))


def write_parameters(drive: Cia402Drive, entries: list[ParameterEntry], *, eds_check: bool = True) -> WriteReport:
    """Write ``entries`` transactionally (module docstring). Never raises for an abort: the report says."""
    if eds_check:
        violations = check_against_eds(drive, entries)
        if violations:
            return WriteReport(
                changes=[],
                error=f"{len(violations)} of {len(entries)} entries fail the EDS check; nothing was written",
                refused=[v.message() for v in violations],
                rolled_back=[],
            )
    old_values = {e.name: _upload(drive, e) for e in entries}  # phase 3: nothing written yet
    changes = [ParameterChange(e.name, e.index, e.subindex, old_values[e.name], e.unit) for e in entries]
    written: list[ParameterEntry] = []
    for entry, change in zip(entries, changes, strict=True):
        assert entry.value is not None
        try:
            _download(drive, entry, entry.value)
            read_back = _upload(drive, entry)
            if not _same(read_back, entry.value):
                written.append(entry)
                change.new = read_back
                raise DriveError(f"{entry.name} ({entry.address}) reads back {read_back} after writing {entry.value}")
        except (SdoError, DriveError) as exc:
            change.status = ChangeStatus.FAILED
            restored, not_restored = _roll_back(drive, written, old_values, changes)
            return WriteReport(changes, error=f"{entry.name}: {exc}", rolled_back=restored,
                               not_restored=not_restored)
        written.append(entry)
        change.new = read_back
        change.status = ChangeStatus.UNCHANGED if _same(read_back, old_values[entry.name]) else ChangeStatus.CHANGED
    return WriteReport(changes)


def _roll_back(
    drive: Cia402Drive,
    written: list[ParameterEntry],
    old_values: dict[str, int | float],
    changes: list[ParameterChange],
) -> tuple[list[str], list[str]]:
    restored: list[str] = []
    not_restored: list[str] = []
    by_name = {change.name: change for change in changes}
    for entry in reversed(written):
        old = old_values[entry.name]
        try:
            _download(drive, entry, old)
            ok = _same(_upload(drive, entry), old)
        except (SdoError, DriveError) as exc:
            not_restored.append(f"{entry.name} ({exc})")
            by_name[entry.name].status = ChangeStatus.NOT_RESTORED
            continue
        if ok:
            restored.append(entry.name)
            by_name[entry.name].status = ChangeStatus.ROLLED_BACK
            by_name[entry.name].now = old
        else:
            not_restored.append(f"{entry.name} (reads back a different value)")
            by_name[entry.name].status = ChangeStatus.NOT_RESTORED
    return restored, not_restored

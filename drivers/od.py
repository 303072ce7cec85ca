"""Object dictionaries: loading an EDS with canopen's parser, and the sizes of the objects the master maps.

:func:`load_od` is the one way the product reads an EDS (the shipped ``configs/foilc_servo.eds`` by default, or the
drive's own EDS from ``drive.eds``). Every failure -- missing file, syntax error, a sub-index with no parent, a
missing mandatory object -- becomes one :class:`~drivers.errors.EdsError` line naming the file.

:func:`mapped_variable` gives the size and signedness of an object for a PDO codec: from the EDS when it describes
the object, else from the CiA 301/402 standard type of the object (:data:`STANDARD_TYPES`), so the master can map
the standard objects of a drive whose EDS is incomplete.

A parsed EDS is kept per process (:data:`PARSED_CACHE_SIZE` files, keyed by the file's path, modification time,
size and the node id), as ``pickle`` bytes: every :func:`load_od` returns an object dictionary of its own, as a fresh
parse would. Why: a run parses its EDS at least twice (the master, the embedded drive), and canopen's parser takes
an order of magnitude longer than unpickling its result.

"""

from __future__ import annotations

import collections
import configparser
import pickle
import stat
import threading
from pathlib import Path

import canopen
from canopen.objectdictionary import ObjectDictionary, ObjectDictionaryError, ODArray, ODRecord, ODVariable, datatypes

from drivers.cia402 import Obj
from drivers.errors import EdsError, InputError
from drivers.pdo import MappedVariable

__all__ = [
    "DEFAULT_EDS",
    "MAX_EDS_BYTES",
    "PARSED_CACHE_SIZE",
    "REQUIRED_OBJECTS",
    "STANDARD_TYPES",
    "load_od",
    "mapped_variable",
    "object_address",
]

DEFAULT_EDS = Path(__file__).resolve().parents[1] / "configs" / "foilc_servo.eds"
"""The object dictionary of the product's own drive (the plant emulator)."""

REQUIRED_OBJECTS: tuple[Obj, ...] = (
    Obj.DEVICE_TYPE,
    Obj.ERROR_REGISTER,
    Obj.IDENTITY,
    Obj.CONTROLWORD,
    Obj.STATUSWORD,
    Obj.MODES_OF_OPERATION,
    Obj.MODES_OF_OPERATION_DISPLAY,
)
"""Objects every drive the bench controls must describe (CiA 301 mandatory + the CiA 402 device control)."""

PARSED_CACHE_SIZE = 16
"""EDS files whose parse :func:`load_od` keeps (the least recently used goes first)."""

# (bits, signed) of the standard objects the master maps into PDOs (CiA 402-2 data types).
STANDARD_TYPES: dict[int, tuple[int, bool]] = {
    Obj.ERROR_CODE: (16, False),
    Obj.CONTROLWORD: (16, False),
    Obj.STATUSWORD: (16, False),
    Obj.MODES_OF_OPERATION: (8, True),
    Obj.MODES_OF_OPERATION_DISPLAY: (8, True),
    Obj.POSITION_ACTUAL_VALUE: (32, True),
    Obj.VELOCITY_DEMAND_VALUE: (32, True),
    Obj.VELOCITY_ACTUAL_VALUE: (32, True),
    Obj.TARGET_TORQUE: (16, True),
    Obj.MAX_TORQUE: (16, False),
    Obj.TORQUE_DEMAND: (16, True),
    Obj.TORQUE_ACTUAL_VALUE: (16, True),
    Obj.TARGET_VELOCITY: (32, True),
}

_SIGNED_BITS = {
    datatypes.INTEGER8: 8,
    datatypes.INTEGER16: 16,
    datatypes.INTEGER32: 32,
    datatypes.INTEGER64: 64,
}
_UNSIGNED_BITS = {
    datatypes.BOOLEAN: 8,
    datatypes.UNSIGNED8: 8,
    datatypes.UNSIGNED16: 16,
    datatypes.UNSIGNED32: 32,
    datatypes.UNSIGNED64: 64,
}


#: the largest EDS accepted: a drive's is tens of kilobytes (the shipped one 40 kB), as a config is at most 1 MiB
MAX_EDS_BYTES = 1 << 20


def load_od(path: str | Path | None = None, node_id: int | None = None) -> ObjectDictionary:
    """Load an EDS (or DCF) with canopen's parser and check it describes a CiA 402 drive.

    Parameters
    ----------
    path
        The EDS file; ``None`` loads :data:`DEFAULT_EDS`.
    node_id
        Resolves ``$NODEID`` in default values (COB-IDs).

    Raises
    ------
    EdsError
        Naming the file: it is missing, not a regular file, larger than :data:`MAX_EDS_BYTES`, unreadable,
        malformed, or lacks one of :data:`REQUIRED_OBJECTS`.
    """
    source = Path(path) if path is not None else DEFAULT_EDS
    try:
        status = source.stat()  # one stat: whether it is a file, and the kept parse's key
    except (OSError, ValueError):
        status = None
    if status is None:
        raise EdsError("EDS file not found", source=str(source))
    if not stat.S_ISREG(status.st_mode):
        kind = "a directory" if stat.S_ISDIR(status.st_mode) else "not a regular file (a device, FIFO or socket)"
        raise EdsError(f"is {kind}: an EDS is a file", source=str(source))
    if status.st_size > MAX_EDS_BYTES:
        # Why: canopen's parser read a 50 MB EDS-syntax file for 30 s in 1.7 GB; configs are capped the same way
        raise EdsError(f"is {status.st_size} bytes; an EDS is at most {MAX_EDS_BYTES} (a drive's is tens of kB)",
                       source=str(source))
    key = (str(source.resolve()), status.st_mtime_ns, status.st_size, node_id)
    with _parsed_lock:
        parsed = _parsed.get(key)
        if parsed is not None:
            _parsed.move_to_end(key)
    if parsed is not None:
        od: ObjectDictionary = pickle.loads(parsed)
        return od
    od = _parse(source, node_id)
    with _parsed_lock:
        _parsed[key] = pickle.dumps(od, protocol=pickle.HIGHEST_PROTOCOL)
        while len(_parsed) > PARSED_CACHE_SIZE:
            _parsed.popitem(last=False)
    return od


_parsed: collections.OrderedDict[tuple[str, int, int, int | None], bytes] = collections.OrderedDict()
_parsed_lock = threading.Lock()


def _parse(source: Path, node_id: int | None) -> ObjectDictionary:
    """canopen's parse of ``source``, checked (see :func:`load_od`)."""
    try:
        od = canopen.import_od(str(source), node_id)
    except (
        configparser.Error,
        ObjectDictionaryError,
        KeyError,
        ValueError,
        UnicodeDecodeError,
        OSError,
    ) as exc:
        raise EdsError(f"not a valid EDS: {type(exc).__name__}: {exc}", source=str(source)) from exc
    for index in REQUIRED_OBJECTS:
        if index not in od:
            raise EdsError(f"lacks object 0x{index:04X} ({index.name.lower()})", source=str(source))
    return od


def mapped_variable(od: ObjectDictionary | None, index: int, subindex: int = 0) -> MappedVariable:
    """Size and signedness of object ``index:subindex`` for a PDO mapping.

    The EDS decides when it describes the object with an integer type; otherwise the CiA 402 standard type.
    Raises :class:`EdsError` for an object neither knows, or one whose type cannot be carried in a PDO here.
    """
    variable = od.get_variable(index, subindex) if od is not None else None
    if isinstance(variable, ODVariable):
        if variable.data_type in _SIGNED_BITS:
            return MappedVariable(index, subindex, _SIGNED_BITS[variable.data_type], signed=True)
        if variable.data_type in _UNSIGNED_BITS:
            return MappedVariable(index, subindex, _UNSIGNED_BITS[variable.data_type], signed=False)
        raise EdsError(f"object 0x{index:04X}:{subindex:02X} has data type 0x{variable.data_type:04X}, not an integer")
    if subindex == 0 and index in STANDARD_TYPES:
        bits, signed = STANDARD_TYPES[index]
        return MappedVariable(index, subindex, bits, signed=signed)
    raise EdsError(f"object 0x{index:04X}:{subindex:02X} is neither in the EDS nor a known CiA 402 object")


def object_address(od: ObjectDictionary, obj: int | str, subindex: int | str = 0) -> tuple[int, int]:
    """``(index, sub-index)`` of an object named as the EDS names it, or given by number.

    Parameters
    ----------
    od
        The drive's object dictionary (:func:`load_od`).
    obj
        The index (``0x6041``) or the EDS's ``ParameterName`` (``"Statusword"``, ``"Identity object"``).
    subindex
        The sub-index, or its ``ParameterName`` within a record or array (``"Vendor-ID"``).

    Raises
    ------
    InputError
        A name the EDS does not have (an object given by number passes unchecked: the drive's answer decides).
    """
    if isinstance(obj, int) and isinstance(subindex, int):
        return obj, subindex
    try:
        entry = od[obj]
        if isinstance(entry, (ODRecord, ODArray)):
            entry = entry[subindex]
        elif subindex not in (0, entry.name):
            raise KeyError(subindex)
    except KeyError:
        raise InputError(f"the EDS has no object {obj!r}" + (f" sub-index {subindex!r}" if subindex else "")) from None
    return int(entry.index), int(entry.subindex)

"""The DBC of the PDO mapping ``run`` installs: what a log's ``/can`` frames need to be decoded.

:func:`build_matrix` turns a :class:`~drivers.cia402_master.PdoPlan` (the mapping
:meth:`~drivers.cia402_master.Cia402Drive.configure` writes -- not the drive's defaults) into a
``canmatrix.CanMatrix`` (one for several drives on a bus: every drive's PDOs); :func:`write_dbc` writes it in the
format the file's suffix names (``.dbc``, ``.kcd``,
``.arxml``, ...). In it:

- node names: the master (``foilc_hil_master``) and the drive (``drive_<node id>``), as transmitter and receiver
  of each PDO;
- velocities (0x60FF, 0x606C) scaled by ``1 / drive.velocity_scale`` with ``drive.velocity_unit``, torques
  (0x6071, 0x6077) by ``1 / drive.torque_scale`` with ``drive.torque_unit``: the plant units the bench logs in
  ``/ilc/sample``; position (0x6064) in raw increments;
- the statusword split into ``statusword_state`` (bits 0..6, a value table naming the CiA 402 state of every
  pattern that has one, from :func:`drivers.cia402.decode_state`) and ``statusword_flags`` (bits 7..15); the
  controlword into ``controlword_command`` (bits 0..7, a value table from :func:`drivers.cia402.decode_command`)
  and ``controlword_flags`` (bits 8..15). Signals never overlap, so strict DBC readers (cantools) load the file.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivers.cia402 import Obj, decode_command, decode_state
from drivers.pdo import MappedVariable, PdoDirection, PdoLayout
from foilc_hil.errors import InputError

if TYPE_CHECKING:
    import canmatrix

    from drivers.cia402_master import PdoPlan
    from drivers.config import DriveConfig

__all__ = ["MASTER_NODE_NAME", "DbcExport", "build_matrix", "drive_node_name", "write_dbc"]

MASTER_NODE_NAME = "foilc_hil_master"
_STATE_BITS = 7  # statusword bits 0..6 code the 402 state (CiA 402-2 "state coding")
_COMMAND_BITS = 8  # controlword bits 0..3 and 7 code the command; bits 4..6 are mode specific and decode as is


def drive_node_name(node_id: int) -> str:
    """The DBC node name of the drive."""
    return f"drive_{node_id}"


@dataclass(frozen=True)
class DbcExport:
    """What :func:`write_dbc` wrote: the file and, per frame, its name, COB-ID and signal names."""

    file: str
    frames: tuple[tuple[str, int, tuple[str, ...]], ...]

    def to_json(self) -> dict[str, Any]:
        return {
            "file": self.file,
            "frames": [{"name": name, "arbitration_id": cob, "signals": list(signals)}
                       for name, cob, signals in self.frames],
        }


@dataclass(frozen=True)
class _SignalSpec:
    name: str
    start: int
    bits: int
    signed: bool
    factor: float = 1.0
    unit: str = ""
    values: dict[int, str] | None = None


def _value_table(bits: int, decode: Any) -> dict[int, str]:
    """Every ``bits``-bit pattern the decoder names (patterns it refuses are left out)."""
    table: dict[int, str] = {}
    for value in range(1 << bits):
        try:
            named = decode(value)
        except ValueError:
            continue
        if named is not None:
            table[value] = named.name
    return table


def _signals(variable: MappedVariable, start: int, cfg: DriveConfig) -> list[_SignalSpec]:
    """The DBC signals of one mapped object at bit ``start`` of its frame."""
    if variable.index == Obj.STATUSWORD:
        return [
            _SignalSpec("statusword_state", start, _STATE_BITS, False, values=_value_table(_STATE_BITS, decode_state)),
            _SignalSpec("statusword_flags", start + _STATE_BITS, variable.bits - _STATE_BITS, False),
        ]
    if variable.index == Obj.CONTROLWORD:
        return [
            _SignalSpec("controlword_command", start, _COMMAND_BITS, False,
                        values=_value_table(_COMMAND_BITS, decode_command)),
            _SignalSpec("controlword_flags", start + _COMMAND_BITS, variable.bits - _COMMAND_BITS, False),
        ]
    try:
        name = Obj(variable.index).name.lower()
    except ValueError:  # a manufacturer object: its index names it
        name = f"object_{variable.index:04X}_{variable.subindex:02X}"
    if variable.index in (Obj.TARGET_VELOCITY, Obj.VELOCITY_ACTUAL_VALUE):
        return [_SignalSpec(name, start, variable.bits, variable.signed, 1.0 / cfg.velocity_scale, cfg.velocity_unit)]
    if variable.index in (Obj.TARGET_TORQUE, Obj.TORQUE_ACTUAL_VALUE):
        return [_SignalSpec(name, start, variable.bits, variable.signed, 1.0 / cfg.torque_scale, cfg.torque_unit)]
    return [_SignalSpec(name, start, variable.bits, variable.signed, unit="inc" if variable.index ==
                        Obj.POSITION_ACTUAL_VALUE else "")]


def _frame(layout: PdoLayout, cfg: DriveConfig) -> canmatrix.Frame:
    import canmatrix

    drive = drive_node_name(cfg.node_id)
    sender, receiver = (MASTER_NODE_NAME, drive) if layout.direction is PdoDirection.RPDO else (drive, MASTER_NODE_NAME)
    size = sum(variable.bits for variable in layout.variables) // 8
    frame = canmatrix.Frame(f"{layout.direction.name}{layout.number}_{drive}",
                            arbitration_id=canmatrix.ArbitrationId(id=layout.cob_id, extended=False), size=size,
                            transmitters=[sender], receivers=[receiver])
    start = 0
    for variable in layout.variables:
        for spec in _signals(variable, start, cfg):
            frame.add_signal(canmatrix.Signal(
                spec.name, start_bit=spec.start, size=spec.bits, is_little_endian=True, is_signed=spec.signed,
                factor=Decimal(repr(spec.factor)), unit=spec.unit, receivers=[receiver], values=spec.values or {},
            ))
        start += variable.bits
    return frame


def build_matrix(drives: Sequence[tuple[PdoPlan, DriveConfig]]) -> canmatrix.CanMatrix:
    """The CAN matrix of every drive's ``(plan, cfg)`` on one bus (module docstring: names, scales, value tables).

    One matrix for several drives: each drive is its own node (``drive_<node id>``) and its frames are named after
    it, so the frames of an ``axes:`` run's four drives sit side by side in one file.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # canmatrix's own imports; not ours to fix
        import canmatrix

    matrix = canmatrix.CanMatrix()
    matrix.add_ecu(canmatrix.Ecu(MASTER_NODE_NAME))
    for plan, cfg in drives:
        matrix.add_ecu(canmatrix.Ecu(drive_node_name(cfg.node_id)))
        for layout in (*plan.rpdos, *plan.tpdos):
            matrix.add_frame(_frame(layout, cfg))
    return matrix


def write_dbc(drives: Sequence[tuple[PdoPlan, DriveConfig]], path: str | Path) -> DbcExport:
    """Write :func:`build_matrix` of ``drives`` to ``path`` (format by suffix); :class:`InputError` when canmatrix
    cannot."""
    import canmatrix.formats

    matrix = build_matrix(drives)
    target = Path(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            canmatrix.formats.dumpp({"": matrix}, str(target))
    except (OSError, KeyError, ValueError, NotImplementedError) as exc:
        raise InputError(f"--dbc: cannot write {target}: {exc}") from exc
    if not target.is_file():
        raise InputError(f"--dbc: canmatrix wrote nothing to {target} (is the suffix a format it knows?)")
    built: list[Any] = list(matrix.frames)  # canmatrix's Frame is not typed for mypy
    frames = tuple((frame.name, frame.arbitration_id.id, tuple(signal.name for signal in frame.signals))
                   for frame in built)
    return DbcExport(str(target), frames)

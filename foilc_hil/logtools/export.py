"""``foilc-hil export``: a log's CAN frames through python-can's writers (ASC, BLF, CSV).

Each ``/can`` record becomes a :class:`can.Message` with its logged timestamp and direction (``is_rx``; ``tx``
frames are ``is_rx=False``), written in log order. What each format keeps:

- ASC: timestamps (microseconds, relative to the first frame; the start date in the header), direction (Rx/Tx).
- BLF: timestamps (nanoseconds relative to the start; the start itself to the millisecond), direction.
- CSV: timestamps (full float precision) -- python-can's CSV format has no direction column.

``--format dbc`` (:func:`export_dbc`) writes instead the DBC of the PDO mapping the run installed on every axis
(metadata ``foilc_hil.pdo_mapping``, ``foilc_hil.axis.<node>.pdo_mapping`` for each axis of an ``axes:`` run; logs
written before it: the mapping :func:`drivers.cia402_master.pdo_plan` gives for the
logged ``drive:`` section and its EDS), with the writer of ``commission info --dbc``
(:mod:`foilc_hil.commission.dbc`): cantools decodes the log's ``/can`` frames with it.
"""

from __future__ import annotations

import collections
import enum
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from foilc_hil.errors import FoilcHilError, InputError, LogFormatError

if TYPE_CHECKING:
    from drivers.cia402_master import PdoPlan
    from drivers.config import DriveConfig
    from foilc_hil.commission.dbc import DbcExport

__all__ = ["ExportFormat", "ExportResult", "export_dbc", "export_frames", "logged_mappings"]


@enum.unique
class ExportFormat(enum.StrEnum):
    """The file formats of ``export --format`` (python-can's writers)."""

    ASC = "asc"
    BLF = "blf"
    CSV = "csv"
    DBC = "dbc"  # not frames: the DBC of the logged PDO mapping (export_dbc)


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export_frames` wrote."""

    out: Path
    format: ExportFormat
    frames: int
    truncated: bool
    damage: str


def export_frames(log: str | Path, out: str | Path, fmt: str, *, channel: int | str = 0) -> ExportResult:
    """Write the ``/can`` frames of ``log`` to ``out`` as ``fmt`` (``asc``, ``blf`` or ``csv``).

    ``channel`` is written on every frame (ASC/BLF carry a channel, numbered from 1 in the file: python-can
    writes channel 0 as 1; the bench has one bus). A truncated log
    exports every frame read before the damage.

    Raises
    ------
    foilc_hil.errors.LogFormatError
        ``log`` is missing or not MCAP.
    foilc_hil.errors.InputError
        Unknown format, or ``out`` cannot be written.
    """
    import can

    from foilc_hil.io.mcap_log import McapLogReader, frame_to_message
    from foilc_hil.io.schemas import TOPIC_CAN

    writers: dict[ExportFormat, type[can.io.generic.MessageWriter]] = {
        ExportFormat.ASC: can.ASCWriter,
        ExportFormat.BLF: can.BLFWriter,
        ExportFormat.CSV: can.CSVWriter,
    }
    if fmt not in writers:  # dbc is export_dbc's
        raise InputError(f"--format: must be one of {', '.join(writers)}, not {fmt!r}")
    file_format = ExportFormat(fmt)
    out_path = Path(out)
    with McapLogReader(log) as reader:
        try:
            writer = writers[file_format](out_path)
        except OSError as exc:
            raise InputError(f"--out: {out_path}: cannot write: {exc.strerror or exc}") from None
        count = 0
        try:
            for message in reader.iter_messages([TOPIC_CAN]):
                frame = frame_to_message(message.data)
                frame.channel = channel
                writer.on_message_received(frame)
                count += 1
        finally:
            writer.stop()
        return ExportResult(out_path, file_format, count, reader.truncated, reader.damage)


def logged_mappings(log: str | Path) -> list[tuple[PdoPlan, DriveConfig]]:
    """The PDO mapping every axis of a run installed and its ``drive:`` section, from the log's metadata.

    A log of several axes (``foilc_hil.axis.<node>.config`` records) gives one entry per axis, in node order, each
    from the axis's own records; a single-axis log gives one from ``foilc_hil.config`` and
    ``foilc_hil.pdo_mapping``. A mapping record missing (logs written before it) is :func:`pdo_plan` of the logged
    ``drive:`` section on its EDS, which is what ``configure`` installs on a drive described by that EDS.

    Raises
    ------
    foilc_hil.errors.LogFormatError
        The log has no ``foilc_hil.config``, or a record does not load.
    """
    from foilc_hil.io.mcap_log import McapLogReader
    from foilc_hil.io.schemas import METADATA_AXIS_PREFIX, METADATA_CONFIG, METADATA_PDO_MAPPING

    with McapLogReader(log) as reader:
        collections.deque(reader.iter_messages(()), maxlen=0)  # metadata is collected while the records pass
        metadata = reader.metadata
    prefix = f"{METADATA_AXIS_PREFIX}."
    nodes = sorted(int(name[len(prefix):-len(".config")]) for name in metadata
                   if name.startswith(prefix) and name.endswith(".config"))
    if not nodes:
        return [_logged_mapping(log, metadata, METADATA_CONFIG, METADATA_PDO_MAPPING)]
    return [_logged_mapping(log, metadata, f"{prefix}{node}.config", f"{prefix}{node}.pdo_mapping")
            for node in nodes]


def _logged_mapping(log: str | Path, metadata: dict[str, Any], config_name: str, mapping_name: str
                    ) -> tuple[PdoPlan, DriveConfig]:
    """One axis's mapping (record ``mapping_name``, else derived) and ``drive:`` section (from ``config_name``)."""
    import yaml

    from drivers.cia402_master import PdoPlan, pdo_plan
    from drivers.config import DriveConfig
    from drivers.od import load_od
    from foilc_hil.io.pdo_mapping import decode_pdo_mapping
    from foilc_hil.schema import load_yaml_text, validate

    try:
        document = load_yaml_text(metadata[config_name]["yaml"]) or {}
        drive = validate(DriveConfig, document.get("drive", {}), source=f"{log} ({config_name})")
    except KeyError:
        raise LogFormatError(f"{log}: no {config_name} metadata; the DBC needs the run's drive section") from None
    except (AttributeError, yaml.YAMLError, FoilcHilError) as exc:
        raise LogFormatError(f"{log}: metadata {config_name} does not load: {exc}") from None
    record = metadata.get(mapping_name)
    if record is None:
        od = load_od(drive.eds, drive.node_id)
        return pdo_plan(drive.operation_mode, drive.node_id, od, demand_echo=drive.demand_echo), drive
    try:
        rpdos, tpdos = decode_pdo_mapping(record)
    except (ValueError, KeyError, TypeError) as exc:
        raise LogFormatError(f"{log}: metadata {mapping_name} does not load: {exc!r}") from None
    return PdoPlan(rpdos, tpdos), drive


def export_dbc(log: str | Path, out: str | Path) -> DbcExport:
    """Write the DBC of the mapping every axis of the run of ``log`` installed to ``out`` (one file, every node's
    PDOs; format by suffix, as ``--dbc``)."""
    from foilc_hil.commission.dbc import write_dbc

    return write_dbc(logged_mappings(log), out)

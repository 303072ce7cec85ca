"""``foilc-hil export``: a log's CAN frames through python-can's writers (ASC, BLF, CSV).

Each ``/can`` record becomes a :class:`can.Message` with its logged timestamp and direction (``is_rx``; ``tx``
frames are ``is_rx=False``), written in log order. What each format keeps:

- ASC: timestamps (microseconds, relative to the first frame; the start date in the header), direction (Rx/Tx).
- BLF: timestamps (nanoseconds relative to the start; the start itself to the millisecond), direction.
- CSV: timestamps (full float precision) -- python-can's CSV format has no direction column.

``--format dbc`` (:func:`export_dbc`) writes instead the DBC of the PDO mapping the run installed (metadata
``foilc_hil.pdo_mapping``; logs written before it: the mapping :func:`drivers.cia402_master.pdo_plan` gives for the
logged ``drive:`` section and its EDS), with the writer of ``commission info --dbc``
(:mod:`foilc_hil.commission.dbc`): cantools decodes the log's ``/can`` frames with it.
"""

from __future__ import annotations

import collections
import enum
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from foilc_hil.errors import FoilcHilError, InputError, LogFormatError

if TYPE_CHECKING:
    from drivers.cia402_master import PdoPlan
    from drivers.config import DriveConfig
    from foilc_hil.commission.dbc import DbcExport

__all__ = ["ExportFormat", "ExportResult", "export_dbc", "export_frames", "logged_mapping"]


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


def logged_mapping(log: str | Path) -> tuple[PdoPlan, DriveConfig]:
    """The PDO mapping a run installed and its ``drive:`` section, from the log's metadata.

    ``foilc_hil.pdo_mapping`` when the log has it; else (logs written before it) :func:`pdo_plan` of the logged
    ``drive:`` section on its EDS, which is what ``configure`` installs on a drive described by that EDS.

    Raises
    ------
    foilc_hil.errors.LogFormatError
        The log has no ``foilc_hil.config``, or a record does not load.
    """
    import yaml

    from drivers.cia402_master import PdoPlan, pdo_plan
    from drivers.config import DriveConfig
    from drivers.od import load_od
    from foilc_hil.io.mcap_log import McapLogReader
    from foilc_hil.io.schemas import METADATA_CONFIG, METADATA_PDO_MAPPING, decode_pdo_mapping
    from foilc_hil.schema import load_yaml_text, validate

    with McapLogReader(log) as reader:
        collections.deque(reader.iter_messages(()), maxlen=0)  # metadata is collected while the records pass
        metadata = reader.metadata
    try:
        document = load_yaml_text(metadata[METADATA_CONFIG]["yaml"]) or {}
        drive = validate(DriveConfig, document.get("drive", {}), source=f"{log} ({METADATA_CONFIG})")
    except KeyError:
        raise LogFormatError(f"{log}: no {METADATA_CONFIG} metadata; the DBC needs the run's drive section") from None
    except (AttributeError, yaml.YAMLError, FoilcHilError) as exc:
        raise LogFormatError(f"{log}: metadata {METADATA_CONFIG} does not load: {exc}") from None
    record = metadata.get(METADATA_PDO_MAPPING)
    if record is None:
        return pdo_plan(drive.operation_mode, drive.node_id, load_od(drive.eds, drive.node_id)), drive
    try:
        rpdos, tpdos = decode_pdo_mapping(record)
    except (ValueError, KeyError, TypeError) as exc:
        raise LogFormatError(f"{log}: metadata {METADATA_PDO_MAPPING} does not load: {exc!r}") from None
    return PdoPlan(rpdos, tpdos), drive


def export_dbc(log: str | Path, out: str | Path) -> DbcExport:
    """Write the DBC of the mapping the run of ``log`` installed to ``out`` (format by suffix, as ``--dbc``)."""
    from foilc_hil.commission.dbc import write_dbc

    plan, drive = logged_mapping(log)
    return write_dbc(plan, drive, out)

"""``foilc-hil export``: a log's CAN frames through python-can's writers (ASC, BLF, CSV).

Each ``/can`` record becomes a :class:`can.Message` with its logged timestamp and direction (``is_rx``; ``tx``
frames are ``is_rx=False``), written in log order. What each format keeps:

- ASC: timestamps (microseconds, relative to the first frame; the start date in the header), direction (Rx/Tx).
- BLF: timestamps (nanoseconds relative to the start; the start itself to the millisecond), direction.
- CSV: timestamps (full float precision) -- python-can's CSV format has no direction column.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from pathlib import Path

from foilc_hil.errors import InputError

__all__ = ["ExportFormat", "ExportResult", "export_frames"]


@enum.unique
class ExportFormat(enum.StrEnum):
    """The file formats of ``export --format`` (python-can's writers)."""

    ASC = "asc"
    BLF = "blf"
    CSV = "csv"


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
    try:
        file_format = ExportFormat(fmt)
    except ValueError:
        raise InputError(f"--format: must be one of {', '.join(ExportFormat)}, not {fmt!r}") from None
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

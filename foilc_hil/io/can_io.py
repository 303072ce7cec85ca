"""``.mcap`` for python-can's ``can.io``: ``can.LogReader``, ``can.Logger``, ``can_logger``, ``can_player``.

Registered through the entry point groups python-can 4.6 reads (``can.io.message_reader`` /
``can.io.message_writer``, see ``can/io/player.py`` and ``can/io/logger.py``), declared in ``pyproject.toml``.
Only the ``/can`` topic is involved: a bench log read here yields the frames the bench sent and received, with
their logged timestamps and directions (``is_rx``).
"""

from __future__ import annotations

from collections.abc import Generator
from typing import IO, Any, BinaryIO, cast

import can
from can.io.generic import BinaryIOMessageReader, BinaryIOMessageWriter
from can.typechecking import StringPathLike

from foilc_hil.io.mcap_log import McapLogReader, McapLogWriter, frame_to_message
from foilc_hil.io.schemas import TOPIC_CAN

__all__ = ["McapCanReader", "McapCanWriter"]


class McapCanReader(BinaryIOMessageReader):
    """Iterates the ``/can`` frames of an MCAP log as :class:`can.Message` (file order).

    A truncated log yields every frame up to the damage; :attr:`truncated` says whether that happened.

    Parameters
    ----------
    file
        Path or binary file object of the log.
    """

    def __init__(self, file: StringPathLike | BinaryIO, **kwargs: Any) -> None:
        super().__init__(file, mode="rb")
        self._reader = McapLogReader(cast(IO[bytes], self.file))
        self.truncated = False

    def __iter__(self) -> Generator[can.Message, None, None]:
        for message in self._reader.iter_messages([TOPIC_CAN]):
            yield frame_to_message(message.data)
        self.truncated = self._reader.truncated
        self.stop()


class McapCanWriter(BinaryIOMessageWriter):
    """Writes received frames to the ``/can`` topic of an MCAP file (``can.Logger("x.mcap")``).

    Direction comes from ``msg.is_rx`` (``"rx"`` for what a bus delivers). No config metadata is written: this
    is a plain CAN capture, not a bench run.

    Parameters
    ----------
    file
        Path or binary file object to write.
    compression
        ``"zstd"`` (default), ``"lz4"`` or ``"none"``.
    """

    def __init__(self, file: StringPathLike | BinaryIO, compression: str = "zstd", **kwargs: Any) -> None:
        super().__init__(file, mode="wb")
        self._writer = McapLogWriter(
            cast(IO[bytes], self.file),
            compression=compression,  # type: ignore[arg-type]  # validated by McapLogWriter
            config_yaml=None,
            fsync=False,
        )

    def on_message_received(self, msg: can.Message) -> None:
        self._writer.log_frame(msg, "rx" if msg.is_rx else "tx")

    def stop(self) -> None:
        """Write the summary and footer, then close the file."""
        self._writer.close()
        super().stop()

"""The bench's MCAP log: a writer (a python-can listener) and a reader.

Layout (topics, schemas, metadata) is in :mod:`foilc_hil.io.schemas` and ``docs/interface.md``.

Durability
----------
:meth:`McapLogWriter.end_trial` closes the MCAP chunk in progress, writes it and its message indexes, flushes the
stream and (by default) ``fsync``s it. Everything logged for a trial -- its samples, frames, timing and its
``/ilc/trial`` metrics -- is therefore on disk before the next trial starts, and a process that dies mid-trial
loses at most the trial in progress. An orderly stop (Ctrl-C, a drive fault, an exception leaving a ``with``
block) closes the file with its summary and footer, so ``mcap.reader.make_reader`` opens it as it is.
A file cut short (a crash, a full disk) has no footer; :class:`McapLogReader` reads it front to back with mcap's
non-seeking :class:`~mcap.stream_reader.StreamReader`, checking every chunk's CRC, and stops at the first damage
with ``truncated=True``.

Real time
---------
:class:`McapLogWriter` encodes JSON and compresses on the calling thread (``simulate``, ``can_logger``). The bench's
cycle must not pay for that: ``run`` logs through :class:`foilc_hil.io.log_process.ProcessLogWriter`, the same
writer in a child process, off the loop's GIL.
"""

from __future__ import annotations

import base64
import json
import os
import struct
from collections.abc import Iterable, Iterator, Mapping, Sequence, Set
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Final, NamedTuple, cast

import can
import orjson
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Footer, Message, Metadata
from mcap.stream_reader import StreamReader, breakup_chunk, get_chunk_data_stream

from foilc_hil.errors import LogFormatError
from foilc_hil.io.mcap_chunks import MCAP_MAGIC
from foilc_hil.io.mcap_writer import (
    _FRAME_BATCH_VALUES,
    _ROW_CHANNEL_TYPES,
    Compression,
    Direction,
    FrameFields,
    LogWriteError,
    McapFileWriter,
    _LogLifecycle,
    _time_ns,
    encode_design,
    frame_json,
)
from foilc_hil.io.schemas import (
    METADATA_CONFIG,
    METADATA_DESIGN,
    TOPIC_CAN,
    TOPIC_SAMPLE,
    TOPIC_TIMING,
    TOPIC_TRIAL,
)

__all__ = [
    "Compression",
    "Direction",
    "LogContents",
    "LogMessage",
    "LogWriteError",
    "McapLogReader",
    "McapLogWriter",
    "count_directions",
    "encode_design",
    "frame_fields",
    "frame_json",
    "frame_to_message",
    "read_log",
]

class _ClosingListener(_LogLifecycle, can.Listener):
    """The lifecycle of a writer that is also a python-can listener: python-can's ``stop()`` means :meth:`close`."""

    def stop(self) -> None:
        """python-can listener hook: same as :meth:`close`."""
        self.close()


class McapLogWriter(McapFileWriter, _ClosingListener):
    """Writes one bench run as MCAP.

    A :class:`can.Listener`: attach it to a :class:`can.Notifier` and every received frame is logged with
    ``dir: "rx"``; the bench logs what it sends with :meth:`log_frame`. Thread-safe (one lock), but it encodes
    and writes on the calling thread -- the real-time loop logs through
    :class:`~foilc_hil.io.log_process.ProcessLogWriter`.

    Everything but the two frame methods is :class:`~foilc_hil.io.mcap_writer.McapFileWriter`'s (same parameters).
    Lifecycle: construct (writes the header and the metadata, flushed at once) -> log trial 1 ... ->
    :meth:`end_trial` -> ... -> :meth:`close` (summary and footer). Use it as a context manager so an exception
    still closes the file.
    """

    def on_message_received(self, msg: can.Message) -> None:
        """python-can listener hook: log a received frame (``dir: "rx"``; :meth:`log_frame` inlined: a Python call
        is a tenth of a frame's cost)."""
        channel = msg.channel
        odd = msg.is_remote_frame or msg.is_error_frame or msg.is_fd or type(channel) not in _ROW_CHANNEL_TYPES
        rare = frame_fields(msg) if odd else None
        frames = self._frames
        frames.extend(
            (msg.timestamp, msg.arbitration_id, msg.is_extended_id, msg.dlc, msg.data, channel, "rx", _time_ns(), rare)
        )
        if len(frames) >= _FRAME_BATCH_VALUES:
            self._write_batch()

    def log_frame(self, msg: can.Message, direction: Direction, log_time_ns: int | None = None) -> None:
        """Log one CAN frame on ``/can``.

        ``timestamp`` is the frame's own (bus) timestamp; a frame built by the bench has none (0.0), so it gets
        its log time. Frames are encoded in batches (:data:`FRAME_BATCH`, and before any other message, so the file
        keeps the calls' order): the payload is referenced until then, so do not change ``msg.data`` in place.
        """
        channel = msg.channel
        odd = msg.is_remote_frame or msg.is_error_frame or msg.is_fd or type(channel) not in _ROW_CHANNEL_TYPES
        rare = frame_fields(msg) if odd else None
        frames = self._frames
        # one row of _FRAME_ROW values; list.extend is one C call, atomic under the GIL, whatever thread logs
        frames.extend((msg.timestamp, msg.arbitration_id, msg.is_extended_id, msg.dlc, msg.data, channel, direction,
                       _time_ns() if log_time_ns is None else log_time_ns, rare))
        if len(frames) >= _FRAME_BATCH_VALUES:
            self._write_batch()


# --- queued writer (the real-time path) -----------------------------------------------------------------------

@dataclass(frozen=True)
class LogMessage:
    """One decoded message: its topic, MCAP times (ns) and JSON document."""

    topic: str
    log_time_ns: int
    publish_time_ns: int
    data: dict[str, Any]


@dataclass
class LogContents:
    """Everything readable in a log. ``truncated`` says the file ended or broke before its footer."""

    path: str
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    frames: list[dict[str, Any]] = field(default_factory=list)
    samples: list[dict[str, Any]] = field(default_factory=list)
    trials: list[dict[str, Any]] = field(default_factory=list)
    timing: list[dict[str, Any]] = field(default_factory=list)
    truncated: bool = False
    damage: str = ""
    frame_directions: dict[str, int] = field(default_factory=dict)
    """The ``/can`` messages read, by their ``dir`` (``"tx"``, ``"rx"``; anything else as its text): counted by
    :meth:`McapLogReader.read` whether it kept the frames or only counted them (``count_frames``)."""

    @property
    def config_yaml(self) -> str | None:
        """The resolved config's YAML text, if the log has it."""
        record = self.metadata.get(METADATA_CONFIG)
        return None if record is None else record.get("yaml")

    @property
    def design(self) -> dict[str, Any] | None:
        """The design record with its values decoded from JSON, if the log has it."""
        record = self.metadata.get(METADATA_DESIGN)
        if record is None:
            return None
        try:
            return {key: json.loads(value) for key, value in record.items()}
        except ValueError as exc:
            raise LogFormatError(f"{self.path}: metadata {METADATA_DESIGN} is not JSON: {exc}") from None

    @property
    def completed_trials(self) -> list[int]:
        """Trials with an ``/ilc/trial`` record: completed before the log ended."""
        return [int(record["trial"]) for record in self.trials]


# What a damaged or cut file can raise inside mcap's stream reader: its own errors, CRC mismatches
# (ValueError), short reads decoded by struct, and the decompressors' errors (zstandard.ZstdError derives from
# Exception only; lz4.frame raises RuntimeError). A corrupt zstd frame header declares its content size, up to
# 2^64 bytes, and zstandard allocates that before it decompresses: the MemoryError is the file's damage.
_DAMAGE: tuple[type[BaseException], ...] = (McapError, ValueError, struct.error, RuntimeError, EOFError, MemoryError)
try:
    import zstandard

    _DAMAGE = (*_DAMAGE, zstandard.ZstdError)
except ImportError:  # pragma: no cover - zstandard is a declared dependency
    pass

#: the most one read asks of the file at once
_READ_PIECE = 1 << 20


class _PiecewiseReads:
    """The file as mcap's stream reader sees it: ``read(n)`` asks the file for at most :data:`_READ_PIECE` bytes at a
    time, so a corrupt length field inside a record (mcap bounds only the record's own) costs what the file holds,
    not an ``n``-byte buffer (``MemoryError``, or ``OverflowError`` past ``sys.maxsize``)."""

    def __init__(self, stream: IO[bytes]) -> None:
        self._stream = stream

    def read(self, n: int = -1) -> bytes:
        if n < 0:
            return self._stream.read()
        pieces = []
        while n > 0:
            piece = self._stream.read(min(n, _READ_PIECE))
            if not piece:
                break
            pieces.append(piece)
            n -= len(piece)
        return b"".join(pieces)


class _FrontToBackReader(StreamReader):
    """mcap's stream reader that skips message index records: a reader going front to back has no use for them,
    and mcap parses them entry by entry (two 8-byte reads per message, a third of reading a log). Their bytes are
    still read, so the data section's CRC still covers them."""

    def _read_record(self, opcode: int, length: int) -> Any:
        if opcode == Opcode.MESSAGE_INDEX:
            self._stream.read(length)
            return None
        return super()._read_record(opcode, length)


class McapLogReader:
    """Reads a foilc-hil MCAP log front to back, surviving truncation and damage.

    Parameters
    ----------
    source
        Path of the log, or a binary stream positioned at its start.

    Raises
    ------
    LogFormatError
        The file does not exist, cannot be read, or is not MCAP (names the file).
    """

    def __init__(self, source: str | os.PathLike[str] | IO[bytes]) -> None:
        if isinstance(source, (str, os.PathLike)):
            self.path = str(source)
            try:
                self._stream: IO[bytes] = open(source, "rb")  # noqa: SIM115 -- closed in close()
            except FileNotFoundError:
                raise LogFormatError(f"{self.path}: no such file") from None
            except OSError as exc:
                raise LogFormatError(f"{self.path}: cannot read: {exc.strerror or exc}") from None
            self._owns_stream = True
        else:
            self.path = str(getattr(source, "name", "<stream>"))
            self._stream = source
            self._owns_stream = False
        self._start = self._stream.tell() if self._stream.seekable() else 0
        magic = self._stream.read(len(MCAP_MAGIC))
        if magic != MCAP_MAGIC:
            self.close()
            raise LogFormatError(f"{self.path}: not an MCAP file")
        self._size = self._file_size()
        self.metadata: dict[str, dict[str, str]] = {}
        self.truncated = False
        self.damage = ""
        self._spent = False

    def _file_size(self) -> int | None:
        if not self._stream.seekable():
            return None
        here = self._stream.tell()
        end = self._stream.seek(0, os.SEEK_END)
        self._stream.seek(here)
        return end - self._start

    def iter_messages(self, topics: Sequence[str] | None = None) -> Iterator[LogMessage]:
        """Messages in file order, decoded; metadata is collected into :attr:`metadata` on the way.

        At the first damage (cut file, bad CRC, undecodable record) iteration stops, :attr:`truncated` becomes
        ``True`` and :attr:`damage` says what and where. One pass per reader (the stream is read once).
        """
        for topic, log_time, publish_time, document in self._documents(topics):
            yield LogMessage(topic, log_time, publish_time, document)

    def _documents(
        self, topics: Sequence[str] | None, directions: dict[str, int] | None = None
    ) -> Iterator[tuple[str, int, int, dict[str, Any]]]:
        """:meth:`iter_messages` as plain tuples (:meth:`read` builds no :class:`LogMessage` per message);
        ``directions``: the ``/can`` messages are only counted there, by direction (see :meth:`read`)."""
        if self._spent:
            raise RuntimeError("McapLogReader reads its file once; create another reader")
        self._spent = True
        if self._stream.seekable():
            self._stream.seek(self._start)
        wanted = None if topics is None else set(topics)
        if wanted is not None and directions is not None:
            wanted.add(TOPIC_CAN)
        # A corrupt length field must not make the reader allocate gigabytes: no record exceeds the file.
        reader = _FrontToBackReader(
            cast(IO[bytes], _PiecewiseReads(self._stream)),  # mcap calls read() only
            skip_magic=not self._stream.seekable(),  # the magic was consumed by the check above
            validate_crcs=True,
            record_size_limit=self._size,
            emit_chunks=True,  # split by _chunk_records
        )
        channels: dict[int, Channel] = {}
        unwanted: set[int] = set()  # known channels whose messages are skipped undecoded (unknown ones are damage)
        counted = _Counted(set(), directions) if directions is not None else None  # /can: counted by direction
        complete = False
        records = reader.records
        while True:
            try:
                record = next(records)
                # a chunk is split here, not by mcap (a Message dataclass and eight small reads per message)
                batch = _chunk_records(record, unwanted, counted) if isinstance(record, Chunk) else (record,)
            except StopIteration:
                break
            except _DAMAGE as exc:
                self._mark_damage(exc)
                return
            for item in batch:
                if isinstance(item, (_ChunkMessage, Message)):
                    channel = channels.get(item.channel_id)
                    if channel is None:
                        self._mark_damage(McapError(f"message on unknown channel {item.channel_id}"))
                        return
                    if wanted is not None and channel.topic not in wanted:
                        continue
                    try:
                        document = _loads(item.data)
                    except ValueError as exc:
                        self._mark_damage(exc)
                        return
                    if not isinstance(document, dict):
                        self._mark_damage(McapError(f"{channel.topic} message is not a JSON object"))
                        return
                    if directions is not None and channel.topic == TOPIC_CAN:
                        direction = str(document.get("dir"))
                        directions[direction] = directions.get(direction, 0) + 1
                        continue
                    yield channel.topic, item.log_time, item.publish_time, document
                elif isinstance(item, Channel):
                    channels[item.id] = item
                    if wanted is not None and item.topic not in wanted:
                        unwanted.add(item.id)
                    else:
                        unwanted.discard(item.id)
                    if counted is not None and item.topic == TOPIC_CAN:
                        counted.channels.add(item.id)
                elif isinstance(item, Metadata):
                    self.metadata[item.name] = dict(item.metadata)
                elif isinstance(item, Footer):
                    complete = True
        if not complete:  # pragma: no cover - the stream reader raises before this
            self._mark_damage(McapError("no footer"))

    def read(self, topics: Sequence[str] | None = None, *, count_frames: bool = False) -> LogContents:
        """Read the whole log (everything readable) into memory; only the messages of ``topics`` when given (the
        others are skipped undecoded and their lists in the result stay empty).

        ``count_frames`` with ``topics`` that leave out ``/can``: the frames are only counted, by direction, into
        :attr:`LogContents.frame_directions` (a report's "sent, received"). A frame document that ends as the
        writer spells its direction (``,"dir":"rx"}``) is counted by that end, undecoded: a valid JSON object that
        ends so has that direction (its last member; a duplicate key's last value is the one JSON keeps); any other
        is decoded and checked as the other messages (damage stops the read where it would). The chunks' CRCs are
        checked either way.
        """
        contents = LogContents(path=self.path)
        directions = contents.frame_directions
        buckets = {
            TOPIC_CAN: contents.frames,
            TOPIC_SAMPLE: contents.samples,
            TOPIC_TRIAL: contents.trials,
            TOPIC_TIMING: contents.timing,
        }
        counted = directions if count_frames and topics is not None and TOPIC_CAN not in topics else None
        for topic, _, _, document in self._documents(topics, counted):
            bucket = buckets.get(topic)
            if bucket is not None:
                bucket.append(document)
        if counted is None:
            directions.update(count_directions(contents.frames))
        contents.metadata = dict(self.metadata)
        contents.truncated = self.truncated
        contents.damage = self.damage
        return contents

    def _mark_damage(self, exc: BaseException) -> None:
        self.truncated = True
        try:
            offset = f" near byte {self._stream.tell()}"
        except (OSError, ValueError):
            offset = ""
        kind = "file ends before its footer" if _is_cut(exc) else f"damaged ({type(exc).__name__}: {exc})"
        self.damage = f"{kind}{offset}"

    def close(self) -> None:
        if self._owns_stream:
            self._stream.close()

    def __enter__(self) -> McapLogReader:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc_value: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()


class _ChunkMessage(NamedTuple):
    """A message record as :func:`_chunk_records` splits it off a chunk (the fields of ``mcap.records.Message`` the
    reader uses, without the dataclass)."""

    channel_id: int
    log_time: int
    publish_time: int
    data: bytes


# the end of a /can document as the writer spells it (mcap_writer's templates, orjson's key order): a counted frame
# that ends so is not decoded (``McapLogReader.read``'s ``count_frames``)
_RX_SUFFIX: Final = b',"dir":"rx"}'
_TX_SUFFIX: Final = b',"dir":"tx"}'
_R: Final = ord("r")

# opcode, record length, channel id, sequence, log time, publish time: a Message record's head
_MESSAGE_HEAD: Final = struct.Struct("<BQHIQQ")


def _chunk_bytes(chunk: Chunk) -> bytes:
    """The chunk's records, decompressed and checked against its CRC by mcap (``get_chunk_data_stream``)."""
    # mcap passes a compression it does not know through as if uncompressed: here it is the file's damage
    if chunk.compression not in ("zstd", "lz4", ""):
        raise McapError(f"chunk compression {chunk.compression!r} is not supported")
    stream, length = get_chunk_data_stream(chunk, validate_crc=True)
    return stream.read(length)


class _Counted(NamedTuple):
    """The ``/can`` channels whose frames a read counts by direction (``count_frames``), and the counts."""

    channels: set[int]
    directions: dict[str, int]


def _chunk_records(chunk: Chunk, skip: Set[int] = frozenset(), counted: _Counted | None = None) -> Sequence[Any]:
    """The records of ``chunk``: :class:`_ChunkMessage` for each message when it holds only messages (what the
    bench's writer puts in a chunk), else mcap's own split (a chunk with schemas or channels from another tool).
    Messages on the channels of ``skip`` are stepped over: checked for length, neither copied nor returned. A frame
    on a channel of ``counted`` whose document ends as the writer spells its direction is counted there instead
    (see :meth:`McapLogReader.read`); any other is returned, to be decoded.

    One ``unpack_from`` and one slice per message: mcap's ``breakup_chunk`` builds each ``Message`` from eight
    reads of a ``BytesIO``, three quarters of the time a report spent reading a log. A report skips the frames
    (four of every five messages of a lockstep log): 1.9 s of a 2.8 s read of the demo's log went to splitting.
    """
    data = _chunk_bytes(chunk)
    unpack_from = _MESSAGE_HEAD.unpack_from
    head = _MESSAGE_HEAD.size
    end = len(data)
    messages: list[_ChunkMessage] = []
    offset = 0
    while offset < end:
        if data[offset] != Opcode.MESSAGE:
            return breakup_chunk(chunk, validate_crc=True)
        if offset + head > end:
            raise McapError(f"chunk record at {offset} is cut short")
        _, length, channel_id, _, log_time, publish_time = unpack_from(data, offset)
        stop = offset + 9 + length
        if length < head - 9 or stop > end:
            raise McapError(f"chunk record at {offset} overruns its chunk")
        if channel_id in skip:
            pass
        elif counted is not None and channel_id in counted.channels and (
                data.endswith(_RX_SUFFIX, offset + head, stop) or data.endswith(_TX_SUFFIX, offset + head, stop)):
            # the direction's first letter, four bytes from the end: rx"} / tx"}
            direction = "rx" if data[stop - 4] == _R else "tx"
            counted.directions[direction] = counted.directions.get(direction, 0) + 1
        else:
            messages.append(_ChunkMessage(channel_id, log_time, publish_time, data[offset + head:stop]))
        offset = stop
    return messages


def _loads(data: bytes) -> Any:
    """A message's JSON with orjson (about 5x cheaper than ``json.loads``); ``json.loads`` for what orjson refuses
    but Python reads (``NaN`` from an old writer, integers past 64 bits). Raises ``ValueError`` on bad JSON."""
    try:
        return orjson.loads(data)
    except orjson.JSONDecodeError:
        return json.loads(data)


def _is_cut(exc: BaseException) -> bool:
    from mcap.exceptions import EndOfFile

    return isinstance(exc, (EndOfFile, struct.error, EOFError))


def count_directions(frames: Iterable[Mapping[str, Any]]) -> dict[str, int]:
    """``/can`` documents counted by their ``dir`` (``"tx"``, ``"rx"``; anything else as its text)."""
    counts: dict[str, int] = {}
    for frame in frames:
        direction = str(frame.get("dir"))
        counts[direction] = counts.get(direction, 0) + 1
    return counts


def read_log(
    path: str | os.PathLike[str], topics: Sequence[str] | None = None, *, count_frames: bool = False
) -> LogContents:
    """Read everything readable in the log at ``path``, or only the messages of ``topics`` (see
    :meth:`McapLogReader.read`, and its ``count_frames``)."""
    with McapLogReader(Path(path)) as reader:
        return reader.read(topics, count_frames=count_frames)


def frame_fields(msg: can.Message) -> FrameFields:
    """The attributes of a ``can.Message`` a ``/can`` record holds, in this order: timestamp, arbitration_id,
    is_extended_id, dlc, data, then the rarer remote, error, fd, brs, esi and channel.

    Plain attribute loads, not ``operator.attrgetter``: on ``can.Message``'s slots the interpreter's specialised
    loads are cheaper than the attrgetter's call (four frames a cycle on the logged hot path).

    """
    return (msg.timestamp, msg.arbitration_id, msg.is_extended_id, msg.dlc, msg.data, msg.is_remote_frame,
            msg.is_error_frame, msg.is_fd, msg.bitrate_switch, msg.error_state_indicator, msg.channel)


def frame_to_message(frame: Mapping[str, Any]) -> can.Message:
    """The python-can message of one ``/can`` record: timestamp, id, payload, direction as ``is_rx``, and the
    remote, error, FD, BRS and ESI flags and channel where logged (an error frame stays an error frame, which
    ``can.player`` and ``replay`` never transmit)."""
    try:
        data = base64.b64decode(frame["data"], validate=True)
        return can.Message(
            timestamp=float(frame["timestamp"]),
            arbitration_id=int(frame["id"]),
            is_extended_id=bool(frame["extended"]),
            is_remote_frame=bool(frame.get("remote", False)),
            is_error_frame=bool(frame.get("error", False)),
            is_fd=bool(frame.get("fd", False)),
            bitrate_switch=bool(frame.get("brs", False)),
            error_state_indicator=bool(frame.get("esi", False)),
            channel=frame.get("channel"),
            dlc=int(frame["dlc"]),
            data=data,
            is_rx=frame["dir"] != "tx",
        )
    except (KeyError, ValueError, TypeError) as exc:
        raise LogFormatError(f"/can message {dict(frame)!r} is malformed: {exc}") from None

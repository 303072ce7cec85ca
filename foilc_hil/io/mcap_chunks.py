"""A chunked MCAP writer whose per-message cost is one ``struct.pack`` and two ``bytearray`` appends.

Why not ``mcap.writer.Writer``: its ``add_message`` builds a ``Message`` dataclass, updates the statistics and writes
the record field by field through a ``BytesIO`` -- more per message than python-can's whole ``BLFWriter`` pipeline
per frame, and the bench logs four frames, a sample and a timing record per cycle. This
writer produces the same kind of file (MCAP v0: header, schemas and channels, metadata, compressed chunks each
followed by its message indexes, data end, a summary with schemas, channels, statistics, chunk and metadata indexes
and summary offsets, footer with the summary CRC), using ``mcap.records`` for every record except the hot
``Message`` and ``MessageIndex`` records, which are packed here (layout: MCAP specification, "Message" op 0x05 and
"Message Index" op 0x07). ``mcap``'s readers read it (``tests/io/test_mcap_log.py``).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable, Iterable, Sequence
from itertools import accumulate, chain, repeat
from operator import add
from typing import IO, Final

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from foilc_hil.errors import LogFormatError

__all__ = ["MCAP_MAGIC", "ChunkedMcapWriter", "compressor"]

MCAP_MAGIC: Final = b"\x89MCAP0\r\n"
# opcode, record length, channel id, sequence, log time, publish time (then the data)
_MESSAGE: Final = struct.Struct("<BQHIQQ")
_MESSAGE_FIELDS: Final = 2 + 4 + 8 + 8
_RECORD_PREFIX: Final = struct.Struct("<BQ")
_FOOTER_PREFIX: Final = struct.Struct("<BQQQ")
_FOOTER_FIELDS: Final = 8 + 8 + 4


def compressor(compression: str) -> Callable[[bytes], bytes]:
    """The chunk compressor for ``"zstd"``, ``"lz4"`` or ``""`` (none)."""
    if compression == "zstd":
        try:
            import zstandard
        except ImportError:
            raise LogFormatError("zstd compression needs the zstandard package") from None
        # level 1, not the default 3: on the bench's chunks (JSON frames and samples) faster for about the same
        # ratio, and the writer process shares two cores with the loop

        return zstandard.ZstdCompressor(level=1).compress
    if compression == "lz4":
        try:
            import lz4.frame
        except ImportError:
            raise LogFormatError("lz4 compression needs the lz4 package") from None
        return lz4.frame.compress
    return bytes


class ChunkedMcapWriter:
    """Writes an MCAP file to ``stream`` (which the caller owns); same call sequence as ``mcap.writer.Writer``:
    :meth:`start`, ``register_*``, :meth:`add_message` / :meth:`add_metadata`, :meth:`flush`, :meth:`finish`.

    Parameters
    ----------
    stream
        A binary stream positioned at 0 (``tell()`` gives the file offsets the indexes need).
    chunk_size
        A chunk is closed once its uncompressed records exceed this many bytes (and at every :meth:`flush`).
    compression
        ``"zstd"``, ``"lz4"`` or ``""``.
    """

    def __init__(self, stream: IO[bytes], *, chunk_size: int, compression: str) -> None:
        self._stream = stream
        self._chunk_size = chunk_size
        self._compression = compression
        self._compress = compressor(compression)
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._chunk_indexes: list[ChunkIndex] = []
        self._message_counts: dict[int, int] = {}
        self._metadata_count = 0
        self._first_time: int | None = None
        self._last_time = 0
        self._chunk = bytearray()
        self._index: dict[int, list[int]] = {}  # channel -> flat [log_time, offset, log_time, offset, ...]
        self._chunk_start = 0
        self._chunk_end = 0

    # -- the data section ----------------------------------------------------------------------------------------

    def start(self, profile: str, library: str) -> None:
        """Magic and header."""
        self._stream.write(MCAP_MAGIC)
        self._write_records(Header(profile=profile, library=library))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        """Write a schema record; its id (from 1)."""
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        self._write_records(schema)
        return schema.id

    def register_channel(
        self, topic: str, message_encoding: str, schema_id: int, metadata: dict[str, str] | None = None
    ) -> int:
        """Write a channel record (with its ``metadata``, str -> str); its id (from 1)."""
        channel = Channel(
            id=len(self._channels) + 1,
            topic=topic,
            message_encoding=message_encoding,
            schema_id=schema_id,
            metadata=dict(metadata or {}),
        )
        self._channels.append(channel)
        self._message_counts[channel.id] = 0
        self._write_records(channel)
        return channel.id

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Write a metadata record (between chunks) and remember its index."""
        offset = self._stream.tell()
        length = self._write_records(Metadata(name=name, metadata=data))
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))
        self._metadata_count += 1

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int) -> None:
        """Append one message to the chunk in progress (see :meth:`add_messages`; one record packed directly: the
        column machinery costs more than it saves for one)."""
        sequence = self._message_counts[channel_id]
        self._message_counts[channel_id] = sequence + 1
        size = _MESSAGE_FIELDS + len(data)
        header = _MESSAGE.pack(Opcode.MESSAGE, size, channel_id, sequence & 0xFFFFFFFF, log_time, publish_time)
        self._append_records(channel_id, (log_time,), (0,), header + data)

    def add_messages(
        self, channel_id: int, log_times: Sequence[int], datas: Sequence[bytes], publish_times: Sequence[int]
    ) -> None:
        """Append messages of one channel (columns: log times, data, publish times) to the chunk in progress, then
        close the chunk if it is full; a message's ``sequence`` is the channel's message count so far (modulo 2**32).

        The records, their index entries and the chunk's time range are built by ``map``/``zip`` over the columns
        (C loops): a batch of frames costs no Python bytecode per message here (``make bench``'s frames-written row).
        """
        count = len(datas)
        if not count:
            return
        sizes = list(map(len, datas))
        sequence = self._message_counts[channel_id]
        self._message_counts[channel_id] = sequence + count
        sequences: Iterable[int] = range(sequence, sequence + count)
        if sequence + count > 1 << 32:
            sequences = [number & 0xFFFFFFFF for number in sequences]
        headers = map(
            _MESSAGE.pack, repeat(Opcode.MESSAGE), map(add, sizes, repeat(_MESSAGE_FIELDS)), repeat(channel_id),
            sequences, log_times, publish_times,
        )
        offsets = accumulate(map(add, sizes, repeat(_MESSAGE.size)), initial=0)
        records = b"".join(chain.from_iterable(zip(headers, datas, strict=True)))
        self._append_records(channel_id, log_times, offsets, records)

    def _append_records(
        self, channel_id: int, log_times: Sequence[int], offsets: Iterable[int], records: bytes
    ) -> None:
        """Records to the chunk, their index entries and time range; closes the chunk when it is full."""
        chunk = self._chunk
        base = len(chunk)
        entries = zip(log_times, map(add, offsets, repeat(base)), strict=False)
        self._index.setdefault(channel_id, []).extend(chain.from_iterable(entries))
        earliest, latest = min(log_times), max(log_times)
        if chunk:
            self._chunk_start, self._chunk_end = min(self._chunk_start, earliest), max(self._chunk_end, latest)
        else:
            self._chunk_start, self._chunk_end = earliest, latest
        chunk += records
        if len(chunk) > self._chunk_size:
            self._finish_chunk()

    def message_count(self, channel_id: int) -> int:
        """Messages added on ``channel_id`` so far."""
        return self._message_counts[channel_id]

    def flush(self) -> None:
        """Close the chunk in progress (if it has messages) and flush the stream."""
        self._finish_chunk()
        self._stream.flush()

    def finish(self) -> None:
        """Close the last chunk; write data end, the summary, the footer and the closing magic."""
        self._finish_chunk()
        self._write_records(DataEnd(data_section_crc=0))
        summary_start = self._stream.tell()
        builder = RecordBuilder()
        groups: list[tuple[int, list[McapRecord]]] = [
            (Opcode.SCHEMA, list(self._schemas)),
            (Opcode.CHANNEL, list(self._channels)),
            (Opcode.STATISTICS, [self._statistics()]),
            (Opcode.CHUNK_INDEX, list(self._chunk_indexes)),
            (Opcode.ATTACHMENT_INDEX, []),  # this bench writes no attachments
            (Opcode.METADATA_INDEX, list(self._metadata_indexes)),
        ]
        offsets = []
        for opcode, records in groups:
            group_start = builder.count
            for record in records:
                record.write(builder)
            offsets.append(
                SummaryOffset(
                    group_opcode=opcode,
                    group_start=summary_start + group_start,
                    group_length=builder.count - group_start,
                )
            )
        summary_offset_start = summary_start + builder.count
        for offset in offsets:
            offset.write(builder)
        summary = builder.end()
        crc = zlib.crc32(summary)
        crc = zlib.crc32(_FOOTER_PREFIX.pack(Opcode.FOOTER, _FOOTER_FIELDS, summary_start, summary_offset_start), crc)
        self._stream.write(summary)
        self._write_records(
            Footer(summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc)
        )
        self._stream.write(MCAP_MAGIC)

    # -- internals -------------------------------------------------------------------------------------------------

    def _write_records(self, *records: McapRecord) -> int:
        """Write records to the stream; their length in bytes."""
        builder = RecordBuilder()
        for record in records:
            record.write(builder)
        data = builder.end()
        self._stream.write(data)
        return len(data)

    def _finish_chunk(self) -> None:
        chunk = bytes(self._chunk)
        if not chunk:
            return
        compressed = self._compress(chunk)
        record = Chunk(
            compression=self._compression,
            data=compressed,
            message_start_time=self._chunk_start,
            message_end_time=self._chunk_end,
            uncompressed_crc=zlib.crc32(chunk),
            uncompressed_size=len(chunk),
        )
        chunk_offset = self._stream.tell()
        chunk_length = self._write_records(record)
        index_offsets: dict[int, int] = {}
        position = chunk_offset + chunk_length
        for channel_id, flat in self._index.items():
            body = struct.pack(f"<HI{len(flat)}Q", channel_id, 8 * len(flat), *flat)
            index_offsets[channel_id] = position
            self._stream.write(_RECORD_PREFIX.pack(Opcode.MESSAGE_INDEX, len(body)))
            self._stream.write(body)
            position += _RECORD_PREFIX.size + len(body)
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=self._chunk_start,
                message_end_time=self._chunk_end,
                chunk_start_offset=chunk_offset,
                chunk_length=chunk_length,
                message_index_offsets=index_offsets,
                message_index_length=position - chunk_offset - chunk_length,
                compression=self._compression,
                compressed_size=len(compressed),
                uncompressed_size=len(chunk),
            )
        )
        self._first_time = self._chunk_start if self._first_time is None else min(self._first_time, self._chunk_start)
        self._last_time = max(self._last_time, self._chunk_end)
        self._chunk = bytearray()
        self._index = {}

    def _statistics(self) -> Statistics:
        return Statistics(
            attachment_count=0,
            channel_count=len(self._channels),
            channel_message_counts={key: count for key, count in self._message_counts.items() if count},
            chunk_count=len(self._chunk_indexes),
            message_count=sum(self._message_counts.values()),
            message_start_time=self._first_time or 0,
            message_end_time=self._last_time,
            metadata_count=self._metadata_count,
            schema_count=len(self._schemas),
        )

"""The bench's MCAP log: a writer (a python-can listener), a queued writer for the real-time loop, and a reader.

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
:class:`McapLogWriter` encodes JSON and compresses on the calling thread. The bench's cycle must not pay for that:
:class:`QueuedLogWriter` has the same logging methods, but they only put a small tuple on a
:class:`queue.SimpleQueue`; a background thread (python-can ``Notifier`` style) does the encoding and the I/O -- still
under the loop's GIL. ``run`` logs through :class:`foilc_hil.io.log_process.ProcessLogWriter` instead: the same
:class:`McapLogWriter` in a child process, off the loop's GIL.
"""

from __future__ import annotations

import base64
import binascii
import enum
import json
import math
import os
import struct
import threading
import time
from abc import abstractmethod
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from queue import SimpleQueue
from types import TracebackType
from typing import IO, Any, Final, Literal, NamedTuple, Self, cast

import can
import numpy as np
import orjson
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Footer, Message, Metadata
from mcap.stream_reader import StreamReader, breakup_chunk, get_chunk_data_stream

from foilc_hil.errors import FoilcHilError, LogFormatError
from foilc_hil.io.mcap_chunks import MCAP_MAGIC, ChunkedMcapWriter
from foilc_hil.io.records import SampleRecord, TimingRecord, TrialSamples
from foilc_hil.io.schemas import (
    MESSAGE_ENCODING,
    METADATA_CONFIG,
    METADATA_DESIGN,
    SCHEMA_ENCODING,
    TOPIC_CAN,
    TOPIC_SAMPLE,
    TOPIC_TIMING,
    TOPIC_TRIAL,
    TOPICS,
    channel_metadata,
    schema_bytes,
)

__all__ = [
    "Compression",
    "Direction",
    "LogContents",
    "LogMessage",
    "LogOp",
    "LogWriteError",
    "McapLogReader",
    "McapLogWriter",
    "QueuedLogWriter",
    "encode_design",
    "frame_to_message",
    "read_log",
]

Compression = Literal["zstd", "lz4", "none"]
Direction = Literal["tx", "rx"]

#: ``--compression`` value -> the MCAP chunk's compression field
_COMPRESSION: Final[dict[str, str]] = {"zstd": "zstd", "lz4": "lz4", "none": ""}
_PROFILE: Final = ""  # no ROS profile: plain JSON messages
_LIBRARY: Final = "foilc-hil"
#: frames encoded at once: one loop over them instead of a chain of calls per frame (the batch costs a few hundred
#: microseconds; a trial's end, any other message and close write a partial batch)
FRAME_BATCH: Final = 1024
#: a logged frame waits as one row of values: timestamp, id, extended, dlc, data, direction, log time, and its
#: :func:`frame_fields` if it is not a classic data frame (else ``None``)
_FRAME_ROW: Final = 8
_FRAME_BATCH_VALUES: Final = FRAME_BATCH * _FRAME_ROW
_time_ns: Final = time.time_ns  # one global lookup per frame instead of two
#: the rare fields of a classic data frame (not remote, not error, not FD, no channel)
_CLASSIC: Final = (False, False, False, False, False, None)


class LogWriteError(FoilcHilError, OSError):
    """Writing the log failed at run time (disk full, file gone). Exit 1."""


# --- JSON encoding --------------------------------------------------------------------------------------------


def _jsonable(value: Any) -> Any:
    """``value`` with numpy scalars/arrays turned into Python numbers/lists and non-finite floats into ``None``.

    JSON has no NaN or infinity (Foxglove's parser rejects Python's ``NaN`` extension), so a non-finite value is
    logged as ``null``. Finite floats are written with ``repr``, which round-trips float64 exactly.
    """
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, Mapping):
        return {str(key): _jsonable(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(item) for item in value]
    if hasattr(value, "to_json"):
        return _jsonable(value.to_json())
    raise TypeError(f"cannot log a value of type {type(value).__name__}")


def _encode(document: dict[str, Any]) -> bytes:
    """Compact JSON of ``document`` with orjson (about 20x cheaper than ``json.dumps`` here, and the writer thread
    holds the GIL while it encodes). orjson writes non-finite floats as ``null``, like :func:`_jsonable`, and
    floats in their shortest round-trip form, so ``replay --verify`` reads back the exact float64."""
    try:
        return orjson.dumps(document, option=orjson.OPT_SERIALIZE_NUMPY)
    except TypeError:  # orjson.JSONEncodeError: integers beyond 64 bits, objects with to_json(), ...
        return orjson.dumps(_jsonable(document))


# --- writer ---------------------------------------------------------------------------------------------------


class _ClosingListener(can.Listener):
    """What both writers share: the lifecycle (python-can's ``stop()`` and the context manager both mean
    :meth:`close`), :meth:`log_sample` and :meth:`log_timing`, the positional spellings of :meth:`write_sample` and
    :meth:`write_timing`."""

    @abstractmethod
    def close(self) -> None: ...

    @abstractmethod
    def write_sample(self, record: SampleRecord) -> None: ...

    def log_sample(
        self,
        trial: int,
        t: float,
        reference: Any,
        output: Any,
        control: Any,
        error: Any,
        E: Any = None,
        *,
        sample: int | None = None,
    ) -> None:
        """Log one sample on ``/ilc/sample`` (builds the :class:`~foilc_hil.io.records.SampleRecord`; see there)."""
        self.write_sample(SampleRecord(trial, t, reference, output, control, error, E, sample))

    def write_trial_samples(self, samples: TrialSamples) -> None:
        """Log a trial's ``/ilc/sample`` messages, one per row of ``samples``, in sample order."""
        for record in samples.records():
            self.write_sample(record)

    @abstractmethod
    def write_timing(self, record: TimingRecord) -> None: ...

    def log_timing(
        self,
        cycle: int,
        trial: int,
        sample: int,
        lateness_us: float,
        period_us: float,
        feedback_latency_us: float | None,
        missed: bool,
        *,
        lost_feedback: bool = False,
    ) -> None:
        """Log one real-time cycle on ``/timing`` (builds the :class:`~foilc_hil.io.records.TimingRecord`; see
        there)."""
        self.write_timing(
            TimingRecord(cycle, trial, sample, lateness_us, period_us, feedback_latency_us, missed, lost_feedback)
        )

    def started(self) -> None:
        """Return when the writer keeps pace with the loop: at once for a writer in this process (a writer process
        waits for its child here, :meth:`foilc_hil.io.log_process.ProcessLogWriter.started`)."""

    def stop(self) -> None:
        """python-can listener hook: same as :meth:`close`."""
        self.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc_value: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()


class McapLogWriter(_ClosingListener):
    """Writes one bench run as MCAP.

    A :class:`can.Listener`: attach it to a :class:`can.Notifier` and every received frame is logged with
    ``dir: "rx"``; the bench logs what it sends with :meth:`log_frame`. Thread-safe (one lock), but it encodes
    and writes on the calling thread -- the real-time loop uses :class:`QueuedLogWriter` in front of it.

    Lifecycle: construct (writes the header and the metadata, flushed at once) -> log trial 1 ... ->
    :meth:`end_trial` -> ... -> :meth:`close` (summary and footer). Use it as a context manager so an exception
    still closes the file.

    Parameters
    ----------
    output
        File path, or a binary stream the caller owns (it is flushed, not closed).
    compression
        Chunk compression: ``"zstd"`` (default), ``"lz4"`` or ``"none"``.
    config_yaml
        The resolved config as YAML text (metadata record ``foilc_hil.config``); ``None`` writes no record
        (e.g. a plain CAN capture through ``can_logger``).
    design
        Gains and certificates (metadata record ``foilc_hil.design``, each value JSON-encoded); can also be
        given later with :meth:`log_design`.
    chunk_size
        Chunks are closed at this size (bytes, uncompressed) as well as at every :meth:`end_trial`.
    fsync
        ``os.fsync`` the file at every :meth:`end_trial` so a completed trial survives a power cut too.
    compiled_frames
        Write batches of classic frames with the compiled kernel (:mod:`foilc_hil.io.frame_kernel`, loaded at the
        first batch: numba's import); ``False``: frame by frame in Python, the same bytes, for a process that must
        start fast and not pause at its first batch (the writer process of ``run``).
    """

    def __init__(
        self,
        output: str | os.PathLike[str] | IO[bytes],
        *,
        compression: Compression = "zstd",
        config_yaml: str | None,
        design: Mapping[str, Any] | None = None,
        chunk_size: int = 4 * 1024 * 1024,
        fsync: bool = True,
        compiled_frames: bool = True,
    ) -> None:
        if compression not in _COMPRESSION:
            raise LogFormatError(f"compression must be one of {', '.join(_COMPRESSION)}, not {compression!r}")
        self.path = str(output) if isinstance(output, (str, os.PathLike)) else str(getattr(output, "name", "<stream>"))
        if isinstance(output, (str, os.PathLike)):
            try:
                self._stream: IO[bytes] = open(output, "wb")  # noqa: SIM115 -- closed in close()
            except OSError as exc:
                raise LogFormatError(f"{output}: cannot create: {exc.strerror or exc}") from None
            self._owns_stream = True
        else:
            self._stream = output
            self._owns_stream = False
        self._fsync = fsync
        self._compiled_frames = compiled_frames
        self._lock = threading.Lock()
        self._frames: list[Any] = []  # logged, not yet encoded: rows of _FRAME_ROW values, one after the other
        self._closed = False
        try:
            self._writer = ChunkedMcapWriter(self._stream, chunk_size=chunk_size, compression=_COMPRESSION[compression])
        except LogFormatError as exc:  # lz4 / zstandard not installed
            self._close_stream()
            raise LogFormatError(f"{self.path}: {exc}") from None
        self._writer.start(profile=_PROFILE, library=_LIBRARY)
        self._channels: dict[str, int] = {}
        metadata = channel_metadata(config_yaml)  # units of the fields
        for topic, (name, schema) in TOPICS.items():
            schema_id = self._writer.register_schema(name=name, encoding=SCHEMA_ENCODING, data=schema_bytes(schema))
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=schema_id, metadata=metadata[topic]
            )
        self._can_channel = self._channels[TOPIC_CAN]
        if config_yaml is not None:
            self._writer.add_metadata(METADATA_CONFIG, {"yaml": config_yaml})
        if design is not None:
            self._writer.add_metadata(METADATA_DESIGN, encode_design(design))
        self._stream.flush()  # header and metadata reach the file before the first trial

    # -- logging ---------------------------------------------------------------------------------------------

    def on_message_received(self, msg: can.Message) -> None:
        """python-can listener hook: log a received frame (``dir: "rx"``; :meth:`log_frame` inlined: a Python call
        is a tenth of a frame's cost)."""
        odd = msg.is_remote_frame or msg.is_error_frame or msg.is_fd or msg.channel is not None
        rare = frame_fields(msg) if odd else None
        frames = self._frames
        frames.extend(
            (msg.timestamp, msg.arbitration_id, msg.is_extended_id, msg.dlc, msg.data, "rx", _time_ns(), rare)
        )
        if len(frames) >= _FRAME_BATCH_VALUES:
            self._write_batch()

    def log_frame(self, msg: can.Message, direction: Direction, log_time_ns: int | None = None) -> None:
        """Log one CAN frame on ``/can``.

        ``timestamp`` is the frame's own (bus) timestamp; a frame built by the bench has none (0.0), so it gets
        its log time. Frames are encoded in batches (:data:`FRAME_BATCH`, and before any other message, so the file
        keeps the calls' order): the payload is referenced until then, so do not change ``msg.data`` in place.
        """
        odd = msg.is_remote_frame or msg.is_error_frame or msg.is_fd or msg.channel is not None
        rare = frame_fields(msg) if odd else None
        frames = self._frames
        # one row of _FRAME_ROW values; list.extend is one C call, atomic under the GIL, whatever thread logs
        frames.extend((msg.timestamp, msg.arbitration_id, msg.is_extended_id, msg.dlc, msg.data, direction,
                       _time_ns() if log_time_ns is None else log_time_ns, rare))
        if len(frames) >= _FRAME_BATCH_VALUES:
            self._write_batch()

    def log_frame_fields(self, fields: FrameFields, direction: Direction, log_time_ns: int) -> None:
        """:meth:`log_frame` of a frame given as its :func:`frame_fields` (what the writer process receives)."""
        rare = fields if any(fields[5:10]) or fields[10] is not None else None
        frames = self._frames
        frames.extend((*fields[:5], direction, log_time_ns, rare))
        if len(frames) >= _FRAME_BATCH_VALUES:
            self._write_batch()

    def _write_batch(self) -> None:
        with self._lock:
            self._write_frames()  # raises if closed

    def write_sample(self, record: SampleRecord, log_time_ns: int | None = None) -> None:
        """Log one sample on ``/ilc/sample``: ``output`` is the feedback the law saw, ``control`` its command.

        Scalars for a SISO axis, sequences/arrays for a multi-variable one. Values are encoded exactly (float64
        ``repr``), so :func:`foilc_hil.logtools.replay.verify_log` can check the law bit for bit.
        """
        self._add(TOPIC_SAMPLE, record.to_json(), time.time_ns() if log_time_ns is None else log_time_ns)

    def write_trial_samples(self, samples: TrialSamples, log_time_ns: int | None = None) -> None:
        """Log a trial's ``/ilc/sample`` messages (:meth:`write_sample` of each row), all at one log time if given."""
        for record in samples.records():
            self.write_sample(record, log_time_ns)

    def log_trial(self, metrics: Any, /, **extra: Any) -> None:
        """Log one trial's metrics on ``/ilc/trial``.

        ``metrics`` is a :class:`foilc_hil.metrics.TrialMetrics` (or a mapping with ``trial``, ``sse``, ``rmse``,
        ``max_abs_error``); ``extra`` fields are added as they are (e.g. ``final_output``, the output ``y(N Ts)``
        that closes the trial's output array, which ``replay --verify`` uses).
        """
        self.log_trial_at(time.time_ns(), metrics, extra)

    def log_trial_at(self, log_time_ns: int, metrics: Any, extra: Mapping[str, Any]) -> None:
        """:meth:`log_trial` with an explicit log time (ns)."""
        base = metrics.to_json() if hasattr(metrics, "to_json") else dict(metrics)
        missing = [key for key in ("trial", "sse", "rmse", "max_abs_error") if key not in base]
        if missing:
            raise LogFormatError(f"/ilc/trial message lacks {', '.join(missing)}")
        self._add(TOPIC_TRIAL, {**base, **extra}, log_time_ns)

    def write_timing(self, record: TimingRecord, log_time_ns: int | None = None) -> None:
        """Log one real-time cycle on ``/timing`` (see :data:`foilc_hil.io.schemas.TIMING_SCHEMA`)."""
        self._add(TOPIC_TIMING, record.to_json(), time.time_ns() if log_time_ns is None else log_time_ns)

    def log_design(self, design: Mapping[str, Any]) -> None:
        """Write the ``foilc_hil.design`` metadata record (if it was not known at construction)."""
        with self._lock:
            self._write_frames()
            self._writer.add_metadata(METADATA_DESIGN, encode_design(design))

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Write another metadata record (str -> str)."""
        with self._lock:
            self._write_frames()
            self._writer.add_metadata(name, dict(data))

    def end_trial(self) -> None:
        """Close the chunk in progress and push it to disk: the trial just logged survives a crash."""
        with self._lock:
            try:
                self._write_frames()
                self._writer.flush()
                if self._fsync and hasattr(self._stream, "fileno"):
                    os.fsync(self._stream.fileno())
            except OSError as exc:
                raise LogWriteError(f"{self.path}: {exc.strerror or exc}") from None

    def close(self) -> None:
        """Write the summary and footer and close the file (idempotent)."""
        with self._lock:
            if self._closed:
                return
            try:
                self._write_frames()
                self._closed = True
                self._frames = _ClosedRows(self.path)
                self._writer.finish()
                self._stream.flush()
            except OSError as exc:
                raise LogWriteError(f"{self.path}: {exc.strerror or exc}") from None
            finally:
                self._closed = True
                self._frames = _ClosedRows(self.path)
                self._close_stream()

    @property
    def closed(self) -> bool:
        return self._closed

    def message_count(self, topic: str) -> int:
        """Messages written on ``topic`` so far."""
        with self._lock:
            self._write_frames()
            return self._writer.message_count(self._channels[topic])

    # -- internals -------------------------------------------------------------------------------------------

    def _add(self, topic: str, document: dict[str, Any], log_time_ns: int) -> None:
        self._append(self._channels[topic], _encode(document), log_time_ns, log_time_ns)

    def _append(self, channel: int, data: bytes, log_time_ns: int, publish_time_ns: int) -> None:
        with self._lock:
            self._write_frames()  # the frames logged before this message go first
            try:
                self._writer.add_message(channel, log_time_ns, data, publish_time_ns)
            except OSError as exc:
                raise LogWriteError(f"{self.path}: {exc.strerror or exc}") from None

    def _write_frames(self) -> None:
        """Encode and append the frames logged so far (the lock is held)."""
        self._check_open()
        frames = self._frames
        size = len(frames) - len(frames) % _FRAME_ROW  # whole rows: another thread may be extending
        if not size:
            return
        rows = frames[:size]
        del frames[:size]  # rows added meanwhile are past ``size``: they wait for the next batch
        stamps, ids, extended, dlcs, datas, directions, log_times, rares = (rows[k::_FRAME_ROW] for k in range(8))
        channel = self._can_channel
        encoded = None
        if self._compiled_frames and rares.count(None) == len(rares):
            first = self._writer.message_count(channel)
            encoded = classic_frames_records(stamps, ids, extended, dlcs, datas, directions, log_times, channel, first)
        try:
            if encoded is not None:
                self._writer.add_records(channel, log_times, encoded[1], encoded[0])
                return
            # a remote, error or FD frame, a channel, an odd timestamp, no compiled kernel: one by one
            classic = zip(stamps, ids, extended, dlcs, datas, strict=True)
            fields = [rare or (*row, *_CLASSIC) for rare, row in zip(rares, classic, strict=True)]
            timestamps = [field[0] or log_time / 1e9 for field, log_time in zip(fields, log_times, strict=True)]
            documents = list(map(frame_json, fields, timestamps, directions))
            publish_times = [round(timestamp * 1e9) for timestamp in timestamps]
            self._writer.add_messages(channel, log_times, documents, publish_times)
        except OSError as exc:
            raise LogWriteError(f"{self.path}: {exc.strerror or exc}") from None

    def _check_open(self) -> None:
        if self._closed:
            raise LogWriteError(f"{self.path}: the log is closed")

    def _close_stream(self) -> None:
        if self._owns_stream:
            self._stream.close()


class _ClosedRows(list[Any]):
    """The frame rows of a closed writer: logging a frame raises (the hot path checks no flag for that)."""

    def __init__(self, path: str) -> None:
        super().__init__()
        self.path = path

    def extend(self, values: Iterable[Any], /) -> None:
        raise LogWriteError(f"{self.path}: the log is closed")


def encode_design(design: Mapping[str, Any]) -> dict[str, str]:
    """MCAP metadata is str -> str: every value of the design becomes its JSON text."""
    return {str(key): json.dumps(_jsonable(value), allow_nan=False) for key, value in design.items()}


# --- queued writer (the real-time path) -----------------------------------------------------------------------

@enum.unique
class LogOp(enum.IntEnum):
    """Operation code of a queue item of :class:`QueuedLogWriter`: items are small tuples ``(op, ...)``, so the
    caller's thread does no JSON and no I/O."""

    FRAME = 0
    SAMPLE = 1
    TRIAL = 2
    TIMING = 3
    END_TRIAL = 4
    SYNC = 5
    STOP = 6


MAX_BACKLOG = 8192
"""Queued items (frames, samples, timing records) the writer thread may fall behind by before the loop waits for it:
about 1.3 s of a 1 kHz loop with six items per cycle, a few MiB at most."""
BACKPRESSURE_POLL = 0.0005  # seconds between checks while the loop waits for the writer


class QueuedLogWriter(_ClosingListener):
    """:class:`McapLogWriter` behind a queue: the caller only enqueues, a background thread writes.

    Same logging methods as :class:`McapLogWriter`. Each one stamps the time (``time.time_ns()``), puts a small
    tuple on a :class:`queue.SimpleQueue` and returns; the thread ``foilc-hil-mcap-log`` encodes and writes. Values
    are referenced, not copied: pass floats, or arrays the caller does not mutate afterwards.

    A write error in the background thread is kept and raised by the next :meth:`end_trial`, :meth:`sync` or
    :meth:`close` (never from the per-cycle calls), as :class:`LogWriteError`; later items are dropped.

    Parameters
    ----------
    writer
        The writer that does the work; this object owns it and closes it in :meth:`close`.
    """

    def __init__(self, writer: McapLogWriter) -> None:
        self.writer = writer
        self._queue: SimpleQueue[tuple[Any, ...]] = SimpleQueue()
        self.backpressure_waits = 0
        self._error: BaseException | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._drain, name="foilc-hil-mcap-log", daemon=True)
        self._thread.start()

    @classmethod
    def open(
        cls,
        output: str | os.PathLike[str],
        *,
        compression: Compression = "zstd",
        config_yaml: str | None,
        design: Mapping[str, Any] | None = None,
        fsync: bool = True,
    ) -> QueuedLogWriter:
        """Create the file and the writer thread in one step."""
        return cls(McapLogWriter(output, compression=compression, config_yaml=config_yaml, design=design, fsync=fsync))

    # -- hot path: enqueue only ----------------------------------------------------------------------------

    def on_message_received(self, msg: can.Message) -> None:
        """python-can listener hook (runs on the Notifier thread): enqueue a received frame."""
        self._queue.put((LogOp.FRAME, time.time_ns(), msg, "rx"))

    def log_frame(self, msg: can.Message, direction: Direction) -> None:
        """Enqueue one frame the bench sent (``"tx"``) or received (``"rx"``)."""
        self._queue.put((LogOp.FRAME, time.time_ns(), msg, direction))

    def write_sample(self, record: SampleRecord) -> None:
        """Enqueue one ``/ilc/sample`` message (see :meth:`McapLogWriter.write_sample`).

        Once per cycle it also applies back-pressure: past :data:`MAX_BACKLOG` queued items it waits until the
        writer has caught up to half of that (:attr:`backpressure_waits` counts these waits).
        """
        self._queue.put((LogOp.SAMPLE, time.time_ns(), record))
        if self._queue.qsize() > MAX_BACKLOG:
            self._relieve()

    def _relieve(self) -> None:
        # Why: a lockstep loop can outrun the writer thread; an unbounded backlog was the soak's RSS growth (16k
        # items queued after 200 fast trials). Waiting here bounds memory and loses nothing; in lockstep it only
        # slows the loop, in realtime sustained overload shows as missed deadlines, which are counted.
        self.backpressure_waits += 1
        while self._queue.qsize() > MAX_BACKLOG // 2 and self._error is None and self._thread.is_alive():
            time.sleep(BACKPRESSURE_POLL)

    def log_trial(self, metrics: Any, /, **extra: Any) -> None:
        """Enqueue one ``/ilc/trial`` message (see :meth:`McapLogWriter.log_trial`)."""
        self._queue.put((LogOp.TRIAL, time.time_ns(), metrics, extra))

    def write_timing(self, record: TimingRecord) -> None:
        """Enqueue one ``/timing`` message (see :meth:`McapLogWriter.write_timing`)."""
        self._queue.put((LogOp.TIMING, time.time_ns(), record))

    # -- between trials and at the end ---------------------------------------------------------------------

    def end_trial(self, wait: bool = False) -> None:
        """Close the trial's chunk once everything enqueued before it is written; ``wait`` blocks until then."""
        self._raise_pending()
        self._queue.put((LogOp.END_TRIAL,))
        if wait:
            self.sync()

    def log_design(self, design: Mapping[str, Any]) -> None:
        """Write the ``foilc_hil.design`` metadata record (waits for the queue first, to keep the order)."""
        self.sync()
        self.writer.log_design(design)

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Write another metadata record (waits for the queue first, to keep the order)."""
        self.sync()
        self.writer.add_metadata(name, data)

    def sync(self, timeout: float | None = None) -> bool:
        """Block until everything enqueued so far is written; ``False`` if ``timeout`` expired first."""
        done = threading.Event()
        self._queue.put((LogOp.SYNC, done))
        finished = done.wait(timeout)
        self._raise_pending()
        return finished

    def pending(self) -> int:
        """Items waiting in the queue (approximate)."""
        return self._queue.qsize()

    def close(self) -> None:
        """Write everything enqueued, then the summary and footer; stop the thread (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._queue.put((LogOp.STOP,))
        self._thread.join()
        try:
            self.writer.close()
        finally:
            self._raise_pending()

    # -- background thread ---------------------------------------------------------------------------------

    def _raise_pending(self) -> None:
        error = self._error
        if error is not None:
            self._error = None
            if isinstance(error, FoilcHilError):
                raise error
            raise LogWriteError(f"{self.writer.path}: {error}") from error

    def _drain(self) -> None:
        writer = self.writer
        get = self._queue.get
        while True:
            item = get()
            op = item[0]
            if op is LogOp.STOP:
                return
            if op is LogOp.SYNC:
                item[1].set()
                continue
            if self._error is not None:
                continue  # the log is broken: drop, never block the producer
            try:
                if op is LogOp.FRAME:
                    writer.log_frame(item[2], item[3], log_time_ns=item[1])
                elif op is LogOp.SAMPLE:
                    writer.write_sample(item[2], log_time_ns=item[1])
                elif op is LogOp.TRIAL:
                    writer.log_trial_at(item[1], item[2], item[3])
                elif op is LogOp.TIMING:
                    writer.write_timing(item[2], log_time_ns=item[1])
                elif op is LogOp.END_TRIAL:
                    writer.end_trial()
            except Exception as exc:  # kept, then raised on the caller's thread by end_trial/sync/close
                self._error = exc


# --- reader ---------------------------------------------------------------------------------------------------


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

    def _documents(self, topics: Sequence[str] | None) -> Iterator[tuple[str, int, int, dict[str, Any]]]:
        """:meth:`iter_messages` as plain tuples (:meth:`read` builds no :class:`LogMessage` per message)."""
        if self._spent:
            raise RuntimeError("McapLogReader reads its file once; create another reader")
        self._spent = True
        if self._stream.seekable():
            self._stream.seek(self._start)
        wanted = None if topics is None else set(topics)
        # A corrupt length field must not make the reader allocate gigabytes: no record exceeds the file.
        reader = _FrontToBackReader(
            cast(IO[bytes], _PiecewiseReads(self._stream)),  # mcap calls read() only
            skip_magic=not self._stream.seekable(),  # the magic was consumed by the check above
            validate_crcs=True,
            record_size_limit=self._size,
            emit_chunks=True,  # split by _chunk_records
        )
        channels: dict[int, Channel] = {}
        complete = False
        records = reader.records
        while True:
            try:
                record = next(records)
                # a chunk is split here, not by mcap (a Message dataclass and eight small reads per message)
                batch = _chunk_records(record) if isinstance(record, Chunk) else (record,)
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
                    yield channel.topic, item.log_time, item.publish_time, document
                elif isinstance(item, Channel):
                    channels[item.id] = item
                elif isinstance(item, Metadata):
                    self.metadata[item.name] = dict(item.metadata)
                elif isinstance(item, Footer):
                    complete = True
        if not complete:  # pragma: no cover - the stream reader raises before this
            self._mark_damage(McapError("no footer"))

    def read(self, topics: Sequence[str] | None = None) -> LogContents:
        """Read the whole log (everything readable) into memory; only the messages of ``topics`` when given (the
        others are skipped undecoded and their lists in the result stay empty)."""
        contents = LogContents(path=self.path)
        buckets = {
            TOPIC_CAN: contents.frames,
            TOPIC_SAMPLE: contents.samples,
            TOPIC_TRIAL: contents.trials,
            TOPIC_TIMING: contents.timing,
        }
        for topic, _, _, document in self._documents(topics):
            bucket = buckets.get(topic)
            if bucket is not None:
                bucket.append(document)
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


# opcode, record length, channel id, sequence, log time, publish time: a Message record's head
_MESSAGE_HEAD: Final = struct.Struct("<BQHIQQ")


def _chunk_bytes(chunk: Chunk) -> bytes:
    """The chunk's records, decompressed and checked against its CRC by mcap (``get_chunk_data_stream``)."""
    # mcap passes a compression it does not know through as if uncompressed: here it is the file's damage
    if chunk.compression not in ("zstd", "lz4", ""):
        raise McapError(f"chunk compression {chunk.compression!r} is not supported")
    stream, length = get_chunk_data_stream(chunk, validate_crc=True)
    return stream.read(length)


def _chunk_records(chunk: Chunk) -> Sequence[Any]:
    """The records of ``chunk``: :class:`_ChunkMessage` for each message when it holds only messages (what the
    bench's writer puts in a chunk), else mcap's own split (a chunk with schemas or channels from another tool).

    One ``unpack_from`` and one slice per message: mcap's ``breakup_chunk`` builds each ``Message`` from eight
    reads of a ``BytesIO``, three quarters of the time a report spent reading a log.
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


def read_log(path: str | os.PathLike[str], topics: Sequence[str] | None = None) -> LogContents:
    """Read everything readable in the log at ``path``, or only the messages of ``topics`` (see
    :class:`McapLogReader`)."""
    with McapLogReader(Path(path)) as reader:
        return reader.read(topics)


FrameFields = tuple[Any, ...]
"""A frame as :func:`frame_fields` gives it: plain values (``marshal`` ships them to the writer process)."""


def frame_fields(msg: can.Message) -> FrameFields:
    """The attributes of a ``can.Message`` a ``/can`` record holds, in this order: timestamp, arbitration_id,
    is_extended_id, dlc, data, then the rarer remote, error, fd, brs, esi and channel.

    Plain attribute loads, not ``operator.attrgetter``: on ``can.Message``'s slots the interpreter's specialised
    loads take 0.14 us for the eleven, the attrgetter 0.33 us (four frames a cycle on the logged hot path).
    """
    return (msg.timestamp, msg.arbitration_id, msg.is_extended_id, msg.dlc, msg.data, msg.is_remote_frame,
            msg.is_error_frame, msg.is_fd, msg.bitrate_switch, msg.error_state_indicator, msg.channel)


#: the classic data frame's document with its values left open, per direction: what ``orjson.dumps`` of the
#: document writes (same keys, same order, no spaces), built by formatting instead of a dict per frame
_FRAME_TEMPLATES: Final = {
    direction: '{"timestamp":%s,"id":%d,"extended":%s,"dlc":%d,"data":"%s","dir":"' + direction + '"}'
    for direction in ("tx", "rx")
}
_JSON_BOOL: Final = ("false", "true")


def classic_frames_records(
    stamps: Sequence[float],
    ids: Sequence[int],
    extended: Sequence[bool],
    dlcs: Sequence[int],
    datas: Sequence[bytes | bytearray],
    directions: Sequence[str],
    log_times: Sequence[int],
    channel_id: int,
    sequence: int,
) -> tuple[bytes, list[int]] | None:
    """The MCAP ``Message`` records (and their offsets) of a batch of classic data frames, given as columns, on
    ``channel_id`` from sequence number ``sequence`` on, with the ``/can`` JSON :func:`frame_json` writes (a frame
    without a timestamp gets its log time); ``None`` if a timestamp needs orjson's spelling or a direction is odd.

    The columns go to numpy by C loops and one compiled kernel writes the records
    (:func:`foilc_hil.io.frame_kernel.encode_frames`): no Python bytecode per frame.
    """
    from foilc_hil.io.frame_kernel import FIXED_BYTES, encode_frames

    count = len(ids)
    if not {"tx", "rx"}.issuperset(directions):
        return None
    if not all(stamps):  # the bench's own frames: their log time
        stamps = [stamp or log_time / 1e9 for stamp, log_time in zip(stamps, log_times, strict=True)]
    texts = list(map(repr, stamps))
    joined = "".join(texts)
    if "e" in joined or "n" in joined:  # an exponent or a non-finite value: orjson's spelling, frame by frame
        return None
    text = np.frombuffer(joined.encode("ascii"), np.uint8)
    payload = np.frombuffer(b"".join(datas), np.uint8)
    out = np.empty(count * FIXED_BYTES + text.size + 2 * payload.size, np.uint8)
    offsets = np.empty(count, np.int64)
    size = encode_frames(
        text, np.cumsum(np.fromiter(map(len, texts), np.int64, count)),
        np.fromiter(ids, np.int64, count), np.fromiter(extended, np.bool_, count), np.fromiter(dlcs, np.int64, count),
        payload, np.cumsum(np.fromiter(map(len, datas), np.int64, count)),
        np.frombuffer("".join(directions).encode("ascii"), np.uint8)[::2] == ord("t"),
        np.fromiter(log_times, np.int64, count), np.rint(np.fromiter(stamps, np.float64, count) * 1e9).astype(np.int64),
        channel_id, sequence, out, offsets,
    )
    return out[:size].tobytes(), offsets.tolist()


def frame_json(fields: FrameFields, timestamp: float, direction: Direction) -> bytes:
    """The ``/can`` JSON document of one frame (``fields`` from :func:`frame_fields`, ``timestamp`` resolved).

    A classic data frame (the cyclic traffic), with or without a text channel, is formatted from a template;
    ``repr`` of a float is its shortest round-trip form, as orjson writes it, except for exponents and non-finite
    values, which go to orjson. Any other frame (remote, error, FD, a channel that is not text) is a dict encoded by
    orjson with its optional fields.
    """
    template = _FRAME_TEMPLATES.get(direction)
    channel = fields[10]
    if template is not None and not any(fields[5:10]) and (channel is None or type(channel) is str):
        text = repr(timestamp)
        if "e" in text or "n" in text:  # 1e-05, 1e+16, inf, nan: orjson's spelling (null for non-finite)
            text = orjson.dumps(timestamp).decode()
        data = binascii.b2a_base64(fields[4], newline=False).decode("ascii")
        classic = (template % (text, fields[1], _JSON_BOOL[bool(fields[2])], fields[3], data)).encode()
        if channel is None:
            return classic
        # a received frame of a named channel (every frame of the in-process bus): the optional field orjson's
        # document puts last, spelled by orjson (its escapes)
        return b"%s,\"channel\":%s}" % (classic[:-1], orjson.dumps(channel))
    document = {
        "timestamp": timestamp,
        "id": fields[1],
        "extended": bool(fields[2]),
        "dlc": fields[3],
        "data": binascii.b2a_base64(fields[4], newline=False).decode("ascii"),
        "dir": direction,
    }
    document.update(_frame_flags(fields))
    return orjson.dumps(document)


def _frame_flags(fields: FrameFields) -> dict[str, Any]:
    """The optional ``/can`` fields of a frame that is not a classic data frame (schema: ``CAN_FRAME_SCHEMA``)."""
    flags: dict[str, Any] = {
        name: True for name, value in zip(("remote", "error", "fd", "brs", "esi"), fields[5:10], strict=True) if value
    }
    channel = fields[10]
    if channel is not None:
        flags["channel"] = channel if isinstance(channel, (str, int)) else str(channel)
    return flags


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

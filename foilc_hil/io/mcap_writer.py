"""The MCAP file of a foilc-hil log, written without python-can: what ``run``'s writer process runs.

:class:`McapFileWriter` writes the layout of :mod:`foilc_hil.io.schemas` (durability: see
:mod:`foilc_hil.io.mcap_log`); :class:`foilc_hil.io.mcap_log.McapLogWriter` is the same writer as a python-can
listener. Why a module of its own: the writer process (:mod:`foilc_hil.io.log_child`) imports this and not
python-can, whose import (its interface registry's entry points, its own log formats) would be a large part of the
child's start: a start every ``run`` waits for before its drive is enabled.
"""

from __future__ import annotations

import binascii
import functools
import json
import math
import operator
import os
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Iterable, Mapping, Sequence
from itertools import chain, repeat
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Final, Literal, Self

import numpy as np
import orjson

from foilc_hil.errors import FoilcHilError, LogFormatError
from foilc_hil.io.mcap_chunks import ChunkedMcapWriter
from foilc_hil.io.records import SampleRecord, TimingBlock, TimingRecord, TrialSamples
from foilc_hil.io.schemas import (
    MESSAGE_ENCODING,
    METADATA_CLOSING,
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
    "FRAME_BATCH",
    "Compression",
    "Direction",
    "FrameFields",
    "LogWriteError",
    "McapFileWriter",
    "check_log_path",
    "classic_frames_documents",
    "encode_design",
    "frame_json",
    "trial_samples_documents",
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
#: a logged frame waits as one row of values: timestamp, id, extended, dlc, data, channel, direction, log time, and
#: its :func:`frame_fields` if it is not a classic data frame with no channel or a text one (else ``None``)
_FRAME_ROW: Final = 9
_FRAME_BATCH_VALUES: Final = FRAME_BATCH * _FRAME_ROW
_time_ns: Final = time.time_ns  # one global lookup per frame instead of two
#: the flags of a classic data frame (not remote, not error, not FD, no BRS, no ESI)
_CLASSIC_FLAGS: Final = (False, False, False, False, False)
#: the channels a frame's row holds itself (the classic templates write them): none, or a name
_ROW_CHANNEL_TYPES: Final = frozenset({type(None), str})
#: the timestamps :meth:`McapFileWriter.log_frames` takes (a bool is no time; its ``repr`` is no JSON)
_TIMESTAMP_TYPES: Final = frozenset({float, int})


class LogWriteError(FoilcHilError, OSError):
    """Writing the log failed at run time (disk full, file gone). Exit 1."""


def check_log_path(path: str | os.PathLike[str]) -> None:
    """Refuse (:class:`LogFormatError`, exit 2) a log path that cannot be created or written, without creating
    anything: a directory, a missing directory, a read-only file system, no permission. Why before anything else:
    found at the file's creation, after the design, a bad ``--out`` cost the design's minutes."""
    target = Path(path)
    parent = target.resolve().parent
    if target.is_dir():
        raise LogFormatError(f"{path}: cannot create: is a directory")
    if not parent.is_dir():
        raise LogFormatError(f"{path}: cannot create: no such directory {parent}")
    if os.statvfs(parent).f_flag & os.ST_RDONLY:
        raise LogFormatError(f"{path}: cannot create: read-only file system")
    # a probe, as the writer will open it: the existing file without truncating it, else a scratch file beside it
    probe = target if target.exists() else parent / f".{target.name}.{os.getpid()}.probe"
    try:
        os.close(os.open(probe, os.O_WRONLY | (0 if probe == target else os.O_CREAT | os.O_EXCL), 0o600))
    except OSError as exc:
        raise LogFormatError(f"{path}: cannot create: {exc.strerror or exc}") from None
    if probe != target:
        probe.unlink(missing_ok=True)


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


class _LogLifecycle(ABC):
    """What every writer shares: the lifecycle (the context manager means :meth:`close`), :meth:`log_sample` and
    :meth:`log_timing`, the positional spellings of :meth:`write_sample` and :meth:`write_timing`."""

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

    def write_timing_block(self, block: TimingBlock) -> None:
        """Log a block of ``/timing`` messages, one per row of ``block``, in cycle order."""
        for record in block.records():
            self.write_timing(record)

    def started(self) -> None:  # noqa: B027 -- not abstract: a writer in this process has nothing to wait for
        """Return when the writer keeps pace with the loop: at once for a writer in this process (a writer process
        waits for its child here, :meth:`foilc_hil.io.log_process.ProcessLogWriter.started`)."""

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc_value: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()


class McapFileWriter(_LogLifecycle):
    """Writes one bench run as MCAP (frames given as :func:`~foilc_hil.io.mcap_log.frame_fields` tuples).

    Thread-safe (one lock), but it encodes and writes on the calling thread.
    :class:`foilc_hil.io.mcap_log.McapLogWriter` is this writer as a python-can listener (frames as ``can.Message``);
    the writer process of ``run`` runs this one.

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
    channels_metadata
        Each topic's channel metadata, as :func:`~foilc_hil.io.schemas.channel_metadata` gives it for
        ``config_yaml`` (what it is when ``None``). The writer process gets it from the loop's process: working it
        out loads the config's models (pydantic), half of that process's start-up.
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
        channels_metadata: Mapping[str, Mapping[str, str]] | None = None,
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
        self._trials: list[int] = []  # the /ilc/trial records written, for the closing record
        self._samples_per_trial: dict[int, int] = {}
        # units of the fields
        metadata = channel_metadata(config_yaml) if channels_metadata is None else channels_metadata
        for topic, (name, schema) in TOPICS.items():
            schema_id = self._writer.register_schema(name=name, encoding=SCHEMA_ENCODING, data=schema_bytes(schema))
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=schema_id, metadata=dict(metadata[topic])
            )
        self._can_channel = self._channels[TOPIC_CAN]
        if config_yaml is not None:
            self._writer.add_metadata(METADATA_CONFIG, {"yaml": config_yaml})
        if design is not None:
            self._writer.add_metadata(METADATA_DESIGN, encode_design(design))
        self._stream.flush()  # header and metadata reach the file before the first trial

    # -- logging ---------------------------------------------------------------------------------------------

    def log_frame_fields(self, fields: FrameFields, direction: Direction, log_time_ns: int) -> None:
        """Log one CAN frame on ``/can``, given as its :func:`~foilc_hil.io.mcap_log.frame_fields`; see
        :meth:`foilc_hil.io.mcap_log.McapLogWriter.log_frame`."""
        channel = fields[10]
        rare = fields if any(fields[5:10]) or type(channel) not in _ROW_CHANNEL_TYPES else None
        frames = self._frames
        frames.extend((*fields[:5], channel, direction, log_time_ns, rare))
        if len(frames) >= _FRAME_BATCH_VALUES:
            self._write_batch()

    def log_frames(
        self, fields: Sequence[FrameFields], directions: Sequence[Direction], log_times: Sequence[int]
    ) -> None:
        """Log a run of frames, each as its :func:`~foilc_hil.io.mcap_log.frame_fields`, its direction and its log
        time (what the writer process receives, a batch at a time); a timestamp that is not a number raises
        ``TypeError``.

        Why columns: the rows are built by ``zip`` and ``chain`` (C loops), where :meth:`log_frame_fields` is a
        Python call per frame: the calls per frame (the dispatch, the check, the row) were a large share of the
        writer process's time per frame.
        """
        columns = list(zip(*fields, strict=True))
        if not columns:
            return
        if not _TIMESTAMP_TYPES.issuperset(map(type, columns[0])):
            odd = next(stamp for stamp in columns[0] if type(stamp) not in _TIMESTAMP_TYPES)
            raise TypeError(f"a frame's timestamp must be a number, not {type(odd).__name__}")
        if any(chain.from_iterable(columns[5:10])) or not _ROW_CHANNEL_TYPES.issuperset(map(type, columns[10])):
            for row in zip(fields, directions, log_times, strict=True):  # a rare frame among them: one by one
                self.log_frame_fields(*row)
            return
        frames = self._frames
        frames.extend(chain.from_iterable(
            zip(*columns[:5], columns[10], directions, log_times, repeat(None, len(fields)), strict=True)
        ))
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
        self._samples_per_trial[int(record.trial)] = self._samples_per_trial.get(int(record.trial), 0) + 1
        self._add(TOPIC_SAMPLE, record.to_json(), time.time_ns() if log_time_ns is None else log_time_ns)

    def write_trial_samples(self, samples: TrialSamples, log_time_ns: int | None = None) -> None:
        """Log a trial's ``/ilc/sample`` messages, all at one log time (``log_time_ns``, else now): the documents
        :meth:`write_sample` writes for its rows (:func:`trial_samples_documents`), appended as one batch."""
        documents = trial_samples_documents(samples)
        log_time = time.time_ns() if log_time_ns is None else log_time_ns
        trial = int(samples.trial)
        self._samples_per_trial[trial] = self._samples_per_trial.get(trial, 0) + len(samples.reference)
        if documents is None:  # columns of vectors: row by row
            for record in samples.records():
                self.write_sample(record, log_time)
            return
        self._append_batch(TOPIC_SAMPLE, documents, log_time)

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
        self._trials.append(int(base["trial"]))

    def write_timing(self, record: TimingRecord, log_time_ns: int | None = None) -> None:
        """Log one real-time cycle on ``/timing`` (see :data:`foilc_hil.io.schemas.TIMING_SCHEMA`)."""
        self._add(TOPIC_TIMING, record.to_json(), time.time_ns() if log_time_ns is None else log_time_ns)

    def write_timing_block(self, block: TimingBlock, log_time_ns: int | None = None) -> None:
        """Log a block of ``/timing`` messages, all at one log time (``log_time_ns``, else now): the documents
        :meth:`write_timing` writes for its rows, appended as one batch."""
        documents = [_encode(record.to_json()) for record in block.records()]
        self._append_batch(TOPIC_TIMING, documents, time.time_ns() if log_time_ns is None else log_time_ns)

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
                self._writer.add_metadata(METADATA_CLOSING, self._closing_record())
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

    def _closing_record(self) -> dict[str, str]:
        """What this writer wrote (:data:`~foilc_hil.io.schemas.METADATA_CLOSING`): each /ilc/trial's trial, each
        trial's sample rows (an axis's rows counted with the others of its trial) and the /can messages."""
        trials = list(dict.fromkeys(self._trials))
        samples = [self._samples_per_trial.get(trial, 0) for trial in trials]
        frames = self._writer.message_count(self._can_channel)
        return {"trials": orjson.dumps(self._trials).decode(), "samples": orjson.dumps(samples).decode(),
                "frames": str(frames)}

    def message_count(self, topic: str) -> int:
        """Messages written on ``topic`` so far."""
        with self._lock:
            self._write_frames()
            return self._writer.message_count(self._channels[topic])

    # -- internals -------------------------------------------------------------------------------------------

    def _add(self, topic: str, document: dict[str, Any], log_time_ns: int) -> None:
        self._append(self._channels[topic], _encode(document), log_time_ns, log_time_ns)

    def _append_batch(self, topic: str, documents: Sequence[bytes], log_time_ns: int) -> None:
        """Append ``documents`` to ``topic`` as one batch, all at ``log_time_ns``, after the frames logged before."""
        times = [log_time_ns] * len(documents)
        with self._lock:
            self._write_frames()  # the frames logged before the batch go first
            try:
                self._writer.add_messages(self._channels[topic], times, documents, times)
            except OSError as exc:
                raise LogWriteError(f"{self.path}: {exc.strerror or exc}") from None

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
        stamps, ids, extended, dlcs, datas, channels, directions, log_times, rares = (
            rows[k::_FRAME_ROW] for k in range(_FRAME_ROW)
        )
        if not all(stamps):  # the bench's own frames: their log time
            stamps = [stamp or log_time / 1e9 for stamp, log_time in zip(stamps, log_times, strict=True)]
        can_channel = self._can_channel
        try:
            if rares.count(None) == len(rares):  # classic data frames, with no channel or a text one
                documents = classic_frames_documents(stamps, ids, extended, dlcs, datas, channels, directions)
                if documents is not None:
                    self._writer.add_messages(can_channel, log_times, documents, _publish_times(stamps))
                    return
            # a remote, error or FD frame, another channel, an odd timestamp or direction: one by one
            classic = zip(stamps, ids, extended, dlcs, datas, strict=True)
            fields = [
                rare or (*row, *_CLASSIC_FLAGS, channel)
                for rare, row, channel in zip(rares, classic, channels, strict=True)
            ]
            timestamps = [field[0] or log_time / 1e9 for field, log_time in zip(fields, log_times, strict=True)]
            documents = list(map(frame_json, fields, timestamps, directions))
            self._writer.add_messages(can_channel, log_times, documents, _publish_times(timestamps))
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


FrameFields = tuple[Any, ...]
"""A frame as :func:`frame_fields` gives it: plain values (``marshal`` ships them to the writer process)."""


#: the classic data frame's document with its values left open, per direction: what ``orjson.dumps`` of the
#: document writes (same keys, same order, no spaces), built by formatting instead of a dict per frame; the last
#: value is the channel's field (:func:`_channel_field`), the optional field orjson's document puts last
_FRAME_TEMPLATES: Final = {
    direction: '{"timestamp":%s,"id":%d,"extended":%s,"dlc":%d,"data":"%s","dir":"' + direction + '"%s}'
    for direction in ("tx", "rx")
}
_JSON_BOOL: Final = ("false", "true")
_base64 = functools.partial(binascii.b2a_base64, newline=False)


def _channel_field(channel: str | None) -> str:
    """A classic frame's channel as its template writes it: nothing without one, else the field, spelled by orjson
    (its escapes)."""
    return "" if channel is None else ',"channel":' + orjson.dumps(channel).decode()


def _publish_times(stamps: Iterable[float]) -> list[int]:
    """Frames' publish times: their timestamps in integer nanoseconds (``round``, half to even, as numpy's)."""
    return list(map(round, map(operator.mul, stamps, repeat(1e9))))


def _timestamp_texts(stamps: Sequence[float], directions: Sequence[str]) -> tuple[list[str], str] | None:
    """What both batch encoders write of a batch's timestamps: each one's ``repr`` (its shortest round trip, as
    orjson spells it) and their concatenation; ``None`` if a direction is neither ``tx`` nor ``rx`` or a timestamp
    needs orjson's own spelling (an exponent, a non-finite value): the batch then goes frame by frame."""
    if not {"tx", "rx"}.issuperset(directions):
        return None
    texts = list(map(repr, stamps))
    joined = "".join(texts)
    if "e" in joined or "n" in joined:
        return None
    return texts, joined


def _json_texts(values: list[float]) -> list[bytes]:
    """Each value's JSON text as orjson writes it in a document (its shortest round trip, ``null`` for a non-finite
    value): one ``orjson.dumps`` of the list, split at its commas (a number has none)."""
    return orjson.dumps(values)[1:-1].split(b",") if values else []


def trial_samples_documents(samples: TrialSamples) -> list[bytes] | None:
    """The ``/ilc/sample`` JSON documents of a trial's rows, byte for byte what :meth:`McapFileWriter.write_sample`
    writes for each of :meth:`TrialSamples.records` (same keys, order and spelling), built by formatting over the
    columns instead of a record, a dict and an ``orjson.dumps`` per row; ``None`` for columns of vectors.

    Why: a record, a dict and an ``orjson.dumps`` per row were half the writer process's work in a lockstep run of
    the first-order plant (one row and four frames a cycle) -- work that competes with the loop on a 2-core host.
    """
    columns = samples.columns()
    if any(column.ndim != 1 for column in columns):
        return None
    count = len(columns[2])
    # row i's instant as records() computes it, (i + 1) * Ts: an int times a float, exact either way
    instants = (np.arange(1, count + 1, dtype=np.float64) * float(samples.sample_time)).tolist()
    axis = b"" if samples.axis is None else b',"axis":%d' % int(samples.axis)
    latched = samples.latched_column()
    texts = [instants, *(column.tolist() for column in columns)]
    held = b""
    if latched is not None:  # after E, as SampleRecord.to_json writes it
        if latched.ndim != 1:
            return None
        texts.append(latched.tolist())
        held = b',"latched":%s'
    template = (b'{"trial":%d,"t":%%s,"reference":%%s,"output":%%s,"control":%%s,"error":%%s,"E":%%s%s,"sample":%%d%s}'
                % (int(samples.trial), held, axis))
    values = zip(*map(_json_texts, texts), range(count), strict=True)
    return list(map(template.__mod__, values))


def classic_frames_documents(
    stamps: Sequence[float],
    ids: Sequence[int],
    extended: Sequence[bool],
    dlcs: Sequence[int],
    datas: Sequence[bytes | bytearray],
    channels: Sequence[str | None],
    directions: Sequence[str],
) -> list[bytes] | None:
    """The ``/can`` JSON documents of a batch of classic data frames given as columns (timestamps resolved, channels
    ``None`` or text): :func:`frame_json`'s text of each, built by ``map`` over the columns (C loops, no Python
    bytecode per frame); ``None`` if a timestamp needs orjson's spelling or a direction is odd.

    Why: the writer process writes every frame of a run this way, without the compiled kernel (numba's import would
    hold its start; see :mod:`foilc_hil.io.log_child`), and C loops over columns beat :func:`frame_json` called per
    frame.

    """
    spelled = _timestamp_texts(stamps, directions)
    if spelled is None:
        return None
    texts = spelled[0]
    fields = {channel: _channel_field(channel) for channel in set(channels)}
    values = zip(
        texts, ids, map(_JSON_BOOL.__getitem__, map(bool, extended)), dlcs,
        map(bytes.decode, map(_base64, datas)), map(fields.__getitem__, channels), strict=True,
    )
    return list(map(str.encode, map(operator.mod, map(_FRAME_TEMPLATES.__getitem__, directions), values)))


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
        data = _base64(fields[4]).decode("ascii")
        values = (text, fields[1], _JSON_BOOL[bool(fields[2])], fields[3], data, _channel_field(channel))
        return (template % values).encode()
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

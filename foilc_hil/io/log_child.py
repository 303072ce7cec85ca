"""The writer process of ``run``'s log (``python -m foilc_hil.io.log_child DATA_FD REPLY_FD FILE_FD``): it reads
the batches :class:`foilc_hil.io.log_process.ProcessLogWriter` sends through a pipe, writes them with one
:class:`~foilc_hil.io.mcap_writer.McapFileWriter` and says back when a sync reached it or a write failed.

The wire (the opcodes, the replies, the framing of a payload) is defined here, with the reader; the sender imports it.
This module imports neither python-can nor the sender: the child's start (its imports) is what a run waits for
before its drive is enabled.
"""

from __future__ import annotations

import contextlib
import enum
import itertools
import marshal
import operator
import os
import struct
import sys
import time
from collections.abc import Iterable, Iterator
from typing import IO, Any, Final

import numpy as np

from foilc_hil.io.mcap_writer import McapFileWriter
from foilc_hil.io.records import SampleRecord, TimingBlock, TimingRecord, TrialSamples

__all__ = [
    "PAYLOAD_LENGTH", "PIPE_BYTES", "READ_BYTES", "READ_PAUSE", "ReplyKind", "WireOp", "framed", "serve", "unframed",
]


@enum.unique
class WireOp(enum.IntEnum):
    """Opcode of an item on the pipe to the writer process (the first element of its tuple)."""

    OPEN = 0
    FRAME = 1
    SAMPLE = 2
    TRIAL = 3
    TIMING = 4
    END_TRIAL = 5
    METADATA = 6
    SYNC = 7
    TRIAL_SAMPLES = 8
    TIMING_BLOCK = 9


@enum.unique
class ReplyKind(enum.IntEnum):
    """What the writer process says back: a :meth:`ProcessLogWriter.sync` reached it or a trial ended with
    ``END_TRIAL`` is written and synced (the item's token), or an error (its message, naming the file)."""

    SYNCED = 0
    ERROR = 1

PIPE_BYTES: Final = 1 << 20
"""Pipe capacity asked for (Linux ``F_SETPIPE_SZ``; the default 64 KiB where refused): about a second of a 1 kHz
loop's items, which the loop's process may run ahead of the writer."""
READ_PAUSE: Final = 0.002
"""Seconds the writer process sleeps after it has drained the pipe (a lockstep loop fills about one batch in that
time; a 1 kHz loop two cycles): its sleep is timed, never a wait on the pipe (see ``_payloads``)."""
READ_BYTES: Final = PIPE_BYTES
"""Bytes the writer process reads at once: the whole pipe."""
_OPCODE: Final = operator.itemgetter(0)
PAYLOAD_LENGTH: Final = struct.Struct("<I")
"""The length of each ``marshal`` payload on either pipe, written before it (:func:`framed`, :func:`unframed`)."""


def framed(payload: bytes) -> bytes:
    """``payload`` as it goes on a pipe: its length, then itself."""
    return PAYLOAD_LENGTH.pack(len(payload)) + payload


def unframed(buffer: bytearray) -> Iterator[Any]:
    """The values of the whole payloads at the front of ``buffer``, each removed from it as it is yielded (a
    payload not yet whole stays; a consumer that stops early leaves the rest for the next call)."""
    header = PAYLOAD_LENGTH.size
    while len(buffer) >= header:
        (size,) = PAYLOAD_LENGTH.unpack_from(buffer)
        if len(buffer) - header < size:
            return
        payload = bytes(buffer[header : header + size])
        del buffer[: header + size]  # from the front of a bytearray: no copy of the rest
        yield marshal.loads(payload)


def _payloads(data_fd: int, pause: float = READ_PAUSE) -> Iterator[list[tuple[Any, ...]]]:
    """The batches on the data pipe until it ends (a payload cut short by the sender's death is dropped).

    The pipe is read on the child's own clock: take what is there, then sleep ``pause`` unless the read filled its
    buffer. Why not a blocking read: a reader asleep on the pipe is woken by every write, and that wake-up took the
    loop's CPU (a pipe wake-up is a synchronous one: Linux favours the writer's CPU for the reader), so a write of
    one batch took many times its own CPU time in wall time. Read on a timer, a write only copies, and the child
    wakes wherever a CPU is free.
    """
    os.set_blocking(data_fd, False)
    buffer = bytearray()
    while True:
        try:
            chunk = os.read(data_fd, READ_BYTES)
        except BlockingIOError:  # nothing written since the last read
            chunk = None
        if chunk == b"":  # every write end closed: close(), or the bench's process ended
            return
        if chunk:
            buffer += chunk
            yield from unframed(buffer)
        if chunk is None or len(chunk) < READ_BYTES:  # drained: let the loop's writes pile up for a while
            time.sleep(pause)


def _runs(batch: list[tuple[Any, ...]]) -> Iterator[tuple[int, Iterator[tuple[Any, ...]]]]:
    """A batch's items grouped in runs of one opcode, in order (``itertools.groupby``: a C loop)."""
    return itertools.groupby(batch, key=_OPCODE)


def _reply(stream: IO[bytes], kind: ReplyKind, value: Any) -> None:
    payload = marshal.dumps((int(kind), value))
    with contextlib.suppress(OSError):  # the bench is gone: nobody to tell, the file is still finished
        stream.write(framed(payload))
        stream.flush()


def _open_writer(item: tuple[Any, ...], file_fd: int) -> McapFileWriter:
    path, compression, config_yaml, design, chunk_size, fsync, channels_metadata = item[1:]
    stream = os.fdopen(file_fd, "wb")
    writer = McapFileWriter(
        stream, compression=compression, config_yaml=config_yaml, design=design, chunk_size=chunk_size, fsync=fsync,
        channels_metadata=channels_metadata,
    )
    writer.path = path
    return writer


def _apply_run(writer: McapFileWriter, op: int, run: Iterable[tuple[Any, ...]], replies: IO[bytes]) -> None:
    """A run of items of one opcode (every op but ``OPEN`` and ``SYNC``) on the writer: frames all at once (their
    columns: see :meth:`McapFileWriter.log_frames`), a trial's end acknowledged once it is on disk, anything else
    one by one."""
    if op == WireOp.FRAME:
        _, log_times, directions, fields = zip(*run, strict=True)
        writer.log_frames(fields, directions, log_times)
    elif op == WireOp.END_TRIAL:
        for item in run:
            writer.end_trial()
            _reply(replies, ReplyKind.SYNCED, item[1])
    else:
        for item in run:
            _apply(writer, item)


def _apply(writer: McapFileWriter, item: tuple[Any, ...]) -> None:
    """One item on the writer (neither a frame, ``OPEN`` nor ``SYNC``)."""
    op = item[0]
    if op == WireOp.SAMPLE:
        writer.write_sample(SampleRecord(*item[2]), item[1])
    elif op == WireOp.TRIAL_SAMPLES:
        reference, output, control, error, big_e = (np.frombuffer(column, dtype=np.float64) for column in item[5:10])
        latched = None if item[10] is None else np.frombuffer(item[10], dtype=np.float64)
        samples = TrialSamples(item[2], item[3], reference, output, control, error, big_e, item[4], latched)
        writer.write_trial_samples(samples, item[1])
    elif op == WireOp.TIMING:
        writer.write_timing(TimingRecord(*item[2]), item[1])
    elif op == WireOp.TIMING_BLOCK:
        writer.write_timing_block(TimingBlock.from_columns(item[2], item[3], item[4:]), item[1])
    elif op == WireOp.TRIAL:
        writer.log_trial_at(item[1], item[2], {})
    elif op == WireOp.METADATA:
        writer.add_metadata(item[1], item[2])


def _failure(exc: Exception, path: str) -> str:
    """One line naming the file and the OS error (the writer's own errors name the file already)."""
    text = str(exc)
    if isinstance(exc, OSError) and exc.strerror:
        text = exc.strerror
    return text if text.startswith(path) else f"{path}: {text}"


def serve(data_fd: int, reply_fd: int, file_fd: int) -> None:
    """The writer process: apply the batches to one :class:`McapFileWriter`, then close the file (summary, footer).

    ``SYNC`` is answered when it is read; ``END_TRIAL`` once the trial's chunk is written and synced. After a
    failed write nothing more is written or acknowledged (the bench was told), but the pipe is read to its end."""
    writer: McapFileWriter | None = None
    failed = False
    path = "the log"
    with os.fdopen(reply_fd, "wb") as replies:
        try:
            # each batch in runs of one opcode (a lockstep batch is mostly one run of frames)
            for op, run in itertools.chain.from_iterable(map(_runs, _payloads(data_fd))):
                if op == WireOp.SYNC:
                    for item in run:
                        _reply(replies, ReplyKind.SYNCED, item[1])
                elif not failed:
                    try:
                        if op == WireOp.OPEN:
                            for item in run:
                                path = str(item[1])
                                writer = _open_writer(item, file_fd)
                        elif writer is not None:
                            _apply_run(writer, op, run, replies)
                    except Exception as exc:
                        failed = True
                        _reply(replies, ReplyKind.ERROR, _failure(exc, path))
        finally:  # the pipe ended (close, or the bench died): the file is closed with what it has
            if writer is not None:
                try:
                    writer.close()
                except Exception as exc:
                    _reply(replies, ReplyKind.ERROR, _failure(exc, path))


def _stand_back() -> None:
    """Put this process in ``SCHED_BATCH`` (Linux; elsewhere nothing): its fair share of the CPU, but it never
    preempts the loop when it wakes.

    Why: on a host with no idle core (two cores, other work) the writer's wake-ups took the loop's CPU mid-cycle:
    a logged lockstep run had 100 to 170 involuntary context switches of the loop's thread against 25 without the
    log, 55 to 92 with this.
    """
    with contextlib.suppress(AttributeError, OSError):
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))


if __name__ == "__main__":
    _stand_back()
    serve(*(int(argument) for argument in sys.argv[1:4]))


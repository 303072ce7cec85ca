"""The MCAP log written by a child process: the loop's process neither encodes JSON nor writes the file.

:class:`ProcessLogWriter` has the logging methods of :class:`~foilc_hil.io.mcap_log.QueuedLogWriter`. Each call
appends one plain tuple (an opcode, the log time, the values; a frame as its
:func:`~foilc_hil.io.mcap_log.frame_fields`, a trial's samples as the float64 columns of its
:class:`~foilc_hil.io.records.TrialSamples`) to a deque; every :data:`BATCH` items, at every trial's end and at
:meth:`~ProcessLogWriter.sync` the deque goes to the child as one ``marshal`` payload (C code, about 0.3 us an item)
through a pipe. The child (``python -m foilc_hil.io.log_child``, started by the writer) runs the one
:class:`~foilc_hil.io.mcap_writer.McapFileWriter`: the file, layout and JSON are the same as in-process logging.
The child reads the pipe on its own clock (every :data:`READ_PAUSE` once drained) and runs in ``SCHED_BATCH``: the
loop's writes never wake it, and its wake-ups never preempt the loop.

Why a process: a writer thread in the loop's process takes the GIL for every JSON document it encodes, and the loop
waits for it at its thread hand-offs (lockstep) or its deadline (realtime). Here the loop's process pays only the
tuple and its share of one ``marshal.dumps`` and one ``os.write`` (which releases the GIL).

Lifetime and safety
-------------------
- The file is created by the writer, so a bad ``--out`` fails at once (``LogFormatError``), as before.
- The child reads until the pipe ends (:meth:`~ProcessLogWriter.close`, or the loop's process dying in any way:
  the kernel closes the pipe): then it writes what it has, the summary and footer, and exits. It is in its own
  session, so a Ctrl-C in the terminal reaches only the bench, which closes the log in order. It never outlives
  the run for longer than it takes to write the backlog.
- Back-pressure is bounded: the pipe holds :data:`PIPE_BYTES`; when it is full ``os.write`` blocks (without the
  GIL) until the child catches up, and the deque never holds more than :data:`MAX_BACKLOG` items.
- A write error in the child (disk full) comes back on a reply pipe and is raised, as :class:`LogWriteError`, by
  the next :meth:`~ProcessLogWriter.end_trial`, :meth:`~ProcessLogWriter.sync` or
  :meth:`~ProcessLogWriter.close`, never by a per-cycle call; later items are dropped.
"""

from __future__ import annotations

import contextlib
import fcntl
import marshal
import os
import select
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Final

import can
import orjson

from foilc_hil.errors import LogFormatError
from foilc_hil.io.log_child import PIPE_BYTES, READ_PAUSE, ReplyKind, WireOp, framed, unframed
from foilc_hil.io.mcap_chunks import compressor
from foilc_hil.io.mcap_log import _ClosingListener, frame_fields
from foilc_hil.io.mcap_writer import _COMPRESSION, Compression, Direction, LogWriteError, _encode, encode_design
from foilc_hil.io.records import SampleRecord, TimingRecord, TrialSamples
from foilc_hil.io.schemas import METADATA_DESIGN, channel_metadata

__all__ = ["BATCH", "MAX_BACKLOG", "PIPE_BYTES", "READ_PAUSE", "ProcessLogWriter", "WireOp"]


BATCH: Final = 128
"""Items per payload: a few tens of microseconds of ``marshal`` on whichever thread fills the batch."""
MAX_BACKLOG: Final = 8192
"""Items the deque may hold while another thread's write is blocked on a full pipe, before a producer waits too."""
CLOSE_TIMEOUT: Final = 60.0
"""Seconds :meth:`ProcessLogWriter.close` waits for the child to write its backlog and the footer."""

# the opcodes as plain ints: marshal refuses int subclasses
_FRAME, _SAMPLE, _TRIAL, _TIMING = int(WireOp.FRAME), int(WireOp.SAMPLE), int(WireOp.TRIAL), int(WireOp.TIMING)
_TRIAL_SAMPLES: Final = int(WireOp.TRIAL_SAMPLES)
_time_ns: Final = time.time_ns  # one global lookup a frame instead of two
#: value types marshal writes as themselves (it writes anything else with a buffer, a numpy scalar for one, as bytes)
_PLAIN_TYPES: Final = frozenset({float, int, bool, type(None)})


# --- the loop's side ------------------------------------------------------------------------------------------


class ProcessLogWriter(_ClosingListener):
    """MCAP logging in a child process (see the module's docstring); same logging methods as
    :class:`~foilc_hil.io.mcap_log.QueuedLogWriter`, same parameters as
    :class:`~foilc_hil.io.mcap_log.McapLogWriter` (``output`` is a path here), and ``wait`` (see :meth:`started`).

    Values are referenced until their batch is sent: pass floats, or arrays the caller does not mutate afterwards.
    """

    def __init__(
        self,
        output: str | os.PathLike[str],
        *,
        compression: Compression = "zstd",
        config_yaml: str | None,
        design: Mapping[str, Any] | None = None,
        chunk_size: int = 4 * 1024 * 1024,
        fsync: bool = True,
        wait: bool = True,
    ) -> None:
        if compression not in _COMPRESSION:
            raise LogFormatError(f"compression must be one of {', '.join(_COMPRESSION)}, not {compression!r}")
        self.path = str(output)
        try:
            compressor(_COMPRESSION[compression])  # lz4 / zstandard installed: checked here, not in the child
        except LogFormatError as exc:
            raise LogFormatError(f"{self.path}: {exc}") from None
        try:
            file_fd = os.open(output, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        except OSError as exc:
            raise LogFormatError(f"{output}: cannot create: {exc.strerror or exc}") from None
        self._items: deque[tuple[Any, ...]] = deque()
        self._send_lock = threading.Lock()
        self._error: str | None = None
        self._broken = False  # an error was raised: said once, later items are dropped
        self._closed = False
        self._replies = bytearray()
        self.backpressure_waits = 0
        try:
            self._process, self._data, self._reply = _spawn(file_fd)
        finally:
            os.close(file_fd)  # the child has its own copy
        plain_design = None if design is None else _json_values(design)
        # the channels' units worked out here, where the config's models are loaded already (see McapFileWriter)
        opened = (self.path, compression, config_yaml, plain_design, chunk_size, fsync, channel_metadata(config_yaml))
        self._items.append((int(WireOp.OPEN), *opened))
        self._started = False
        if wait:
            self.started()

    def started(self) -> None:
        """Block until the child has written the file's header (at once once it has); a child that did not start
        raises :class:`LogWriteError`, and the writer is closed.

        Call it before the first trial: from then on the child reads as fast as the loop logs. Without this wait a
        child still importing (a second on a loaded machine) let the pipe fill during the first trial, and the loop's
        thread blocked on it (a 0.56 s SYNC gap, the emulator's SYNC-loss EMCY). Opened with ``wait=False``, the
        child starts (half a second of imports) while the bench commissions the drive, and this wait is then short.
        """
        if self._started:
            return
        try:
            if not self.sync():
                status = self._process.wait()
                raise LogWriteError(f"{self.path}: the log writer process did not start (exit status {status})")
        except BaseException:
            with contextlib.suppress(LogWriteError):  # the error being raised says it; the child is reaped
                self.close()
            raise
        self._started = True

    @classmethod
    def open(
        cls,
        output: str | os.PathLike[str],
        *,
        compression: Compression = "zstd",
        config_yaml: str | None,
        design: Mapping[str, Any] | None = None,
        fsync: bool = True,
        wait: bool = True,
    ) -> ProcessLogWriter:
        """Create the file and start the writer process (the spelling of ``QueuedLogWriter.open``); ``wait=False``:
        return while the child starts, and call :meth:`started` before the first trial."""
        return cls(output, compression=compression, config_yaml=config_yaml, design=design, fsync=fsync, wait=wait)

    # -- hot path: one tuple each --------------------------------------------------------------------------------

    def on_message_received(self, msg: can.Message) -> None:
        """python-can listener hook (runs on the Notifier thread): log a received frame."""
        self._put_received((_FRAME, time.time_ns(), "rx", frame_fields(msg)))

    def log_frame(self, msg: can.Message, direction: Direction) -> None:
        """Log one frame the bench sent (``"tx"``) or received (``"rx"``)."""
        items = self._items
        items.append((_FRAME, _time_ns(), direction, frame_fields(msg)))
        # _put and _put_received inlined (a call saved, four frames a cycle): a sent frame sends a full batch, a
        # received one only a backlog past its bound
        if len(items) >= BATCH and (direction != "rx" or len(items) > MAX_BACKLOG):
            self._send(block=len(items) > MAX_BACKLOG)

    def _put_received(self, item: tuple[Any, ...]) -> None:
        # Why: a received frame is logged on the receiving thread, whose hand-off of the feedback the loop waits for;
        # the batches go out from the loop's own calls (a sent frame: right after a SYNC or a command), unless the
        # backlog reaches its bound
        items = self._items
        items.append(item)
        if len(items) > MAX_BACKLOG:
            self._send(block=True)

    def write_sample(self, record: SampleRecord) -> None:
        """Log one ``/ilc/sample`` message (see :meth:`McapLogWriter.write_sample`)."""
        self._put((_SAMPLE, time.time_ns(), _plain_values(record)))

    def write_trial_samples(self, samples: TrialSamples) -> None:
        """Log a trial's ``/ilc/sample`` messages as one item: its columns as float64 bytes, one log time for all
        (the child builds the rows with :meth:`TrialSamples.records`, the same documents as :meth:`write_sample`).

        Why: built here, the rows cost the loop's process 3.2 to 5.4 us each (the record, its check, its tuple,
        its share of ``marshal``); sent as columns, 0.3 us a row.
        """
        axis = None if samples.axis is None else int(samples.axis)
        columns = tuple(column.tobytes() for column in samples.columns())
        self._put((_TRIAL_SAMPLES, time.time_ns(), int(samples.trial), float(samples.sample_time), axis, *columns))

    def write_timing(self, record: TimingRecord) -> None:
        """Log one ``/timing`` message (see :meth:`McapLogWriter.write_timing`)."""
        self._put((_TIMING, time.time_ns(), _plain_values(record)))

    def log_trial(self, metrics: Any, /, **extra: Any) -> None:
        """Log one ``/ilc/trial`` message (see :meth:`McapLogWriter.log_trial`; a missing field raises here)."""
        base = metrics.to_json() if hasattr(metrics, "to_json") else dict(metrics)
        missing = [key for key in ("trial", "sse", "rmse", "max_abs_error") if key not in base]
        if missing:
            raise LogFormatError(f"/ilc/trial message lacks {', '.join(missing)}")
        self._put((_TRIAL, time.time_ns(), _json_values({**base, **extra})))

    def _put(self, item: tuple[Any, ...]) -> None:
        items = self._items
        items.append(item)
        if len(items) >= BATCH:
            self._send(block=len(items) > MAX_BACKLOG)

    # -- between trials and at the end ---------------------------------------------------------------------------

    def end_trial(self, wait: bool = False) -> None:
        """Send the trial to the child, which closes its chunk and syncs the file; ``wait`` blocks until then."""
        self._put((int(WireOp.END_TRIAL),))
        self._send(block=True)
        self._raise_pending()
        if wait:
            self.sync()

    def log_design(self, design: Mapping[str, Any]) -> None:
        """Write the ``foilc_hil.design`` metadata record (in order with everything logged before)."""
        self._put((int(WireOp.METADATA), METADATA_DESIGN, encode_design(design)))

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Write another metadata record (in order with everything logged before)."""
        self._put((int(WireOp.METADATA), name, {str(key): str(value) for key, value in data.items()}))

    def sync(self, timeout: float | None = None) -> bool:
        """Block until the child has written everything logged so far; ``False`` if ``timeout`` expired first."""
        token = time.monotonic_ns()
        self._put((int(WireOp.SYNC), token))
        self._send(block=True)
        deadline = None if timeout is None else time.monotonic() + timeout
        synced = self._error is not None or self._wait_reply(token, deadline)
        self._raise_pending()
        return synced

    def pending(self) -> int:
        """Items not yet sent to the child."""
        return len(self._items)

    def close(self) -> None:
        """Send everything, end the pipe and wait for the child's summary and footer (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._send(block=True)
        finally:
            self._finish_child()
        self._raise_pending()

    @property
    def closed(self) -> bool:
        return self._closed

    # -- internals -----------------------------------------------------------------------------------------------

    def _send(self, *, block: bool) -> None:
        """Send the deque's items as one payload; without ``block``, leave it to a thread already sending."""
        lock = self._send_lock
        if not lock.acquire(blocking=block):
            return
        try:
            if block and len(self._items) > MAX_BACKLOG:
                self.backpressure_waits += 1
            popleft = self._items.popleft
            batch = [popleft() for _ in range(len(self._items))]
            if batch and self._data >= 0:
                self._write(_dumps(batch))
        except (TypeError, ValueError) as exc:  # a value neither marshal nor JSON can hold
            self._error = self._error or f"{self.path}: cannot log {exc}"
        finally:
            lock.release()

    def _write(self, payload: bytes) -> None:
        view = memoryview(framed(payload))
        try:
            while view:
                view = view[os.write(self._data, view) :]
        except OSError as exc:  # the child is gone: drop from now on, say so at the next end_trial/sync/close
            self._error = self._error or f"{self.path}: the log writer process stopped ({exc.strerror or exc})"
            self._close_data()
        except BaseException:
            self._close_data()  # a payload cut by an exception: the child must see its end, not a shifted stream
            raise

    def _close_data(self) -> None:
        if self._data >= 0:
            os.close(self._data)
            self._data = -1

    def _finish_child(self) -> None:
        """End the pipe (the child writes the rest and the footer), wait for it, collect its last replies."""
        self._close_data()
        deadline = time.monotonic() + CLOSE_TIMEOUT
        # its replies until their pipe ends, which is the child exiting: woken at once, where Popen.wait(timeout)
        # polls in sleeps of up to 50 ms (a tenth of a second at the end of every run, measured)
        self._wait_reply(None, deadline)
        try:
            self._process.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
            self._error = self._error or f"{self.path}: the log writer process did not finish in {CLOSE_TIMEOUT} s"
        self._wait_reply(None, time.monotonic())  # read what is left (EOF: the child has exited)
        os.close(self._reply)
        if self._process.returncode and self._error is None and not self._broken:
            self._error = f"{self.path}: the log writer process exited with status {self._process.returncode}"

    def _wait_reply(self, token: int | None, deadline: float | None) -> bool:
        """Read replies until ``token``'s ``SYNCED`` (``True``), the deadline or the pipe's end (``False``)."""
        while True:
            for kind, value in unframed(self._replies):
                if kind == ReplyKind.ERROR:
                    self._error = self._error or str(value)
                elif value == token:
                    return True
            if self._error is not None and token is not None:
                return False
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            ready, _, _ = select.select([self._reply], [], [], wait)
            if not ready:
                return False
            chunk = os.read(self._reply, 65536)
            if not chunk:
                return False
            self._replies += chunk

    def _raise_pending(self) -> None:
        if self._error is None:
            return
        error, self._error = self._error, None
        self._broken = True
        # once broken, the log stays broken: later items are dropped (_data closed) and this is said once
        self._close_data()
        raise LogWriteError(error)


def _spawn(file_fd: int) -> tuple[subprocess.Popen[bytes], int, int]:
    """Start the writer process on ``file_fd``; the write end of its data pipe and the read end of its replies."""
    data_read, data_write = os.pipe()
    reply_read, reply_write = os.pipe()
    with contextlib.suppress(OSError, AttributeError):  # Linux only; the default size works, with less slack
        fcntl.fcntl(data_write, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
    root = str(Path(__file__).resolve().parents[2])  # this checkout's foilc_hil, whatever the installed one
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (root, os.environ.get("PYTHONPATH"))))}
    try:
        process = subprocess.Popen(
            [sys.executable, "-m", "foilc_hil.io.log_child", str(data_read), str(reply_write), str(file_fd)],
            pass_fds=(data_read, reply_write, file_fd),
            stdin=subprocess.DEVNULL,
            env=env,
            start_new_session=True,  # a terminal's Ctrl-C goes to the bench, which closes the log in order
        )
    except OSError as exc:
        for fd in (data_write, reply_read):
            os.close(fd)
        raise LogFormatError(f"cannot start the log writer process: {exc.strerror or exc}") from None
    finally:
        os.close(data_read)
        os.close(reply_write)
    return process, data_write, reply_read


def _plain_values(record: tuple[Any, ...]) -> tuple[Any, ...]:
    """A record's values as marshal holds them: as they are when plain (the bench's floats), else as their JSON."""
    if _PLAIN_TYPES.issuperset(map(type, record)):
        return tuple(record)
    return tuple(_json_values(list(record)))


def _json_values(value: Any) -> Any:
    """``value`` as its JSON document reads back: plain Python values, exactly what the file will hold."""
    return orjson.loads(_encode(value))


def _dumps(batch: list[tuple[Any, ...]]) -> bytes:
    """One payload: ``marshal`` of the items, with a frame's channel as text where it is another object."""
    try:
        return marshal.dumps(batch)
    except ValueError:
        return marshal.dumps([_plain_channel(item) if item[0] == _FRAME else item for item in batch])


def _plain_channel(item: tuple[Any, ...]) -> tuple[Any, ...]:
    fields = item[3]
    channel = fields[10]
    plain = channel if channel is None or isinstance(channel, (str, int)) else str(channel)
    return (*item[:3], (*fields[:10], plain))

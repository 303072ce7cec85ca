"""The MCAP log written by a child process: the loop's process neither encodes JSON nor writes the file.

:class:`ProcessLogWriter` has the logging methods of :class:`~foilc_hil.io.mcap_log.McapLogWriter`. Each call
appends one plain tuple (an opcode, the log time, the values; a frame as its
:func:`~foilc_hil.io.mcap_log.frame_fields`, a trial's samples as the float64 columns of its
:class:`~foilc_hil.io.records.TrialSamples`) to a deque; every :data:`BATCH` items, at every trial's end and at
:meth:`~ProcessLogWriter.sync` the deque goes to the child as one ``marshal`` payload (C code, cheap per item)
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
- The loop never waits for the child. The data pipe is non-blocking: what a full pipe does not take is kept,
  and sent with the next batch. A child that takes nothing for :data:`STALL_TIMEOUT` seconds while bytes wait
  (stopped, hung on a dead NFS or USB disk) has *stalled*: a
  :class:`LogWriteError` naming the log, handed to :attr:`~ProcessLogWriter.on_failure` (``run`` stops the drive
  with it at the next cycle) and raised by the next call that reports errors. Why: a blocking write held the loop's
  thread, and with it a moving axis, for as long as the disk hung (SIGINT and SIGTERM ignored with it).
- Every trial is acknowledged: the child answers each :meth:`~ProcessLogWriter.end_trial` once the trial's chunk
  is written and synced, and :attr:`~ProcessLogWriter.written_trials` lists the trials the file holds. At a
  trial's end the writer waits (up to :data:`STALL_TIMEOUT` without progress) for the acknowledgement of the
  trial before it, so a failed write (disk full) stops the run at the next trial boundary at the latest.
- A write error in the child comes back on a reply pipe, names the file and the OS error, and is raised, as
  :class:`LogWriteError`, by the next :meth:`~ProcessLogWriter.end_trial`, :meth:`~ProcessLogWriter.sync` or
  :meth:`~ProcessLogWriter.close`, never by a per-cycle call; later items are dropped.
- A stalled child is not killed: the pipe is closed, and a child that resumes writes what it has and the footer.
  :meth:`~ProcessLogWriter.close` waits for it only while it makes progress.
"""

from __future__ import annotations

import contextlib
import fcntl
import itertools
import marshal
import os
import select
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Final

import can
import orjson

from foilc_hil.errors import LogFormatError
from foilc_hil.io.log_child import PIPE_BYTES, READ_PAUSE, ReplyKind, WireOp, framed, unframed
from foilc_hil.io.mcap_chunks import compressor
from foilc_hil.io.mcap_log import _ClosingListener, frame_fields
from foilc_hil.io.mcap_writer import _COMPRESSION, Compression, Direction, LogWriteError, _encode, encode_design
from foilc_hil.io.records import SampleRecord, TimingBlock, TimingRecord, TrialSamples
from foilc_hil.io.schemas import METADATA_DESIGN, channel_metadata

__all__ = [
    "BATCH", "MAX_BACKLOG", "MAX_UNSENT_BYTES", "PIPE_BYTES", "READ_PAUSE", "STALL_TIMEOUT", "ProcessLogWriter",
    "WireOp",
]


BATCH: Final = 128
"""Items per payload: a few tens of microseconds of ``marshal`` on whichever thread fills the batch."""
MAX_BACKLOG: Final = 8192
"""Items the deque may hold while another thread's write is blocked on a full pipe, before a producer waits too."""
CLOSE_TIMEOUT: Final = 60.0
"""Seconds :meth:`ProcessLogWriter.close` waits at most for the child to write its backlog and the footer."""
STALL_TIMEOUT: Final = 2.0
"""Seconds the child may take nothing from a pipe holding bytes for it (or leave an acknowledgement unanswered)
before it counts as stalled. Why 2 s: a healthy child reads every :data:`READ_PAUSE`; a trial's chunk and its
``fsync`` took at most tenths of a second on the disks measured, and the pipe holds about a second of a 1 kHz
loop's items besides."""
MAX_UNSENT_BYTES: Final = 16 << 20
"""Bytes the writer keeps for a child whose pipe is full; past them the producer waits until the child has taken
half (a lockstep loop faster than the child is paced by it, and memory stays bounded), for at most
:data:`STALL_TIMEOUT` seconds without progress."""

# the opcodes as plain ints: marshal refuses int subclasses
_FRAME, _SAMPLE, _TRIAL, _TIMING = int(WireOp.FRAME), int(WireOp.SAMPLE), int(WireOp.TRIAL), int(WireOp.TIMING)
_TRIAL_SAMPLES: Final = int(WireOp.TRIAL_SAMPLES)
_TIMING_BLOCK: Final = int(WireOp.TIMING_BLOCK)
_time_ns: Final = time.time_ns  # one global lookup a frame instead of two
#: value types marshal writes as themselves (it writes anything else with a buffer, a numpy scalar for one, as bytes)
_PLAIN_TYPES: Final = frozenset({float, int, bool, type(None)})


# --- the loop's side ------------------------------------------------------------------------------------------


class ProcessLogWriter(_ClosingListener):
    """MCAP logging in a child process (see the module's docstring); same logging methods as
    :class:`~foilc_hil.io.mcap_log.McapLogWriter`, same parameters as
    :class:`~foilc_hil.io.mcap_log.McapLogWriter` (``output`` is a path here), and ``wait`` (see :meth:`started`).

    Values are referenced until their batch is sent: pass floats, or arrays the caller does not mutate afterwards.

    Attributes
    ----------
    on_failure
        Called once, on whichever thread finds it, with the :class:`LogWriteError` of a child that stalled, died
        or failed a write (``run`` stops its loop with it); ``None``: the error is only raised by the next
        :meth:`end_trial`, :meth:`sync` or :meth:`close`.
    stall_timeout
        :data:`STALL_TIMEOUT` unless given.
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
        stall_timeout: float = STALL_TIMEOUT,
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
        # re-entrant: a producer that waits for the child (past MAX_UNSENT_BYTES) drains the pipe under it again
        self._send_lock = threading.RLock()
        self._error: str | None = None
        self._broken = False  # an error was raised: said once, later items are dropped
        self._data_ending = False  # the data pipe is to be ended (at once, or by the send lock's holder: _close_data)
        self._closed = False
        self._replies = bytearray()
        self.backpressure_waits = 0
        self.on_failure: Callable[[LogWriteError], None] | None = None
        self.stall_timeout = stall_timeout
        self.stalled = False  # the child stopped taking what it is sent (see STALL_TIMEOUT)
        self._failure_told = False
        self._unsent = bytearray()  # framed bytes the full pipe did not take yet
        self._blocked_since = 0.0  # when _unsent last became non-empty or last shrank
        self._blocked_cpu: float | None = None  # the child's CPU time when a full pipe was last found stalled
        self._reply_closed = False  # the child's end of the reply pipe is closed: it has exited
        self._tokens = itertools.count(1)  # the acknowledgements asked for (sync, end_trial), in pipe order
        self._acknowledged = 0  # the highest token the child answered
        self._trials_open: list[int] = []  # trial numbers logged since the last end_trial
        self._ending: dict[int, list[int]] = {}  # end_trial token -> its trials, until acknowledged
        self._awaited = 0  # the previous end_trial's token: acknowledged before the next trial's end returns
        self.written_trials: list[int] = []
        """The trials the child has written and synced (acknowledged), in order."""
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
        """Create the file and start the writer process ; ``wait=False``:
        return while the child starts, and call :meth:`started` before the first trial."""
        return cls(output, compression=compression, config_yaml=config_yaml, design=design, fsync=fsync, wait=wait)

    @property
    def failed(self) -> bool:
        """The child stalled, died or failed a write: the file may hold less than was logged, or (a write cut in
        the middle of a trial's end) a trial that was never acknowledged."""
        return self._broken or self._error is not None or self.stalled

    @property
    def pid(self) -> int:
        """The writer process's id."""
        return self._process.pid

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

        Why: built here, the rows would cost the loop's process a record, its check, its tuple and its share of
        ``marshal`` each; sent as columns, a trial is one item.

        """
        axis = None if samples.axis is None else int(samples.axis)
        columns = tuple(column.tobytes() for column in samples.columns())
        latched = samples.latched_column()
        held = None if latched is None else latched.tobytes()  # after the five columns (log_child reads it there)
        self._put((_TRIAL_SAMPLES, time.time_ns(), int(samples.trial), float(samples.sample_time), axis, *columns,
                   held))

    def write_timing(self, record: TimingRecord) -> None:
        """Log one ``/timing`` message (see :meth:`McapLogWriter.write_timing`)."""
        self._put((_TIMING, time.time_ns(), _plain_values(record)))

    def write_timing_block(self, block: TimingBlock) -> None:
        """Log a block of ``/timing`` messages as one item: its columns as bytes, one log time for all (the child
        builds the records with :meth:`TimingBlock.records`, the same documents as :meth:`write_timing`).

        Why: built here, a trial's 6000 records cost the loop's process 55-90 ms of Python in the thread beside its
        settle cycles (:class:`~foilc_hil.io.records.TimingBlock`).
        """
        self._put((_TIMING_BLOCK, time.time_ns(), int(block.first_cycle), int(block.trial), *block.columns()))

    def log_trial(self, metrics: Any, /, **extra: Any) -> None:
        """Log one ``/ilc/trial`` message (see :meth:`McapLogWriter.log_trial`; a missing field raises here)."""
        base = metrics.to_json() if hasattr(metrics, "to_json") else dict(metrics)
        missing = [key for key in ("trial", "sse", "rmse", "max_abs_error") if key not in base]
        if missing:
            raise LogFormatError(f"/ilc/trial message lacks {', '.join(missing)}")
        trial = int(base["trial"])
        if trial not in self._trials_open:  # a run of several axes logs one /ilc/trial per axis
            self._trials_open.append(trial)
        self._put((_TRIAL, time.time_ns(), _json_values({**base, **extra})))

    def _put(self, item: tuple[Any, ...]) -> None:
        items = self._items
        items.append(item)
        if len(items) >= BATCH:
            self._send(block=len(items) > MAX_BACKLOG)

    # -- between trials and at the end ---------------------------------------------------------------------------

    def end_trial(self, wait: bool = False) -> None:
        """Send the trial to the child, which closes its chunk, syncs the file and acknowledges it; then wait for
        the acknowledgement of the trial before (``wait``: of this one), at most :attr:`stall_timeout` seconds
        without progress. Raises the child's error, or :class:`LogWriteError` for a child that stalled."""
        token = next(self._tokens)
        self._ending[token], self._trials_open = self._trials_open, []
        self._put((int(WireOp.END_TRIAL), token))
        self._send(block=True)
        previous, self._awaited = self._awaited, token
        awaited = token if wait else previous
        if awaited and self._data >= 0 and not self._wait_reply(awaited, None, stall=True) and self._error is None:
            self._stall(f"the end of {_trial_span(self._ending.get(awaited, [])) or 'a trial'} was not acknowledged")
        self._raise_pending()

    def log_design(self, design: Mapping[str, Any]) -> None:
        """Write the ``foilc_hil.design`` metadata record (in order with everything logged before)."""
        self._put((int(WireOp.METADATA), METADATA_DESIGN, encode_design(design)))

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Write another metadata record (in order with everything logged before)."""
        self._put((int(WireOp.METADATA), name, {str(key): str(value) for key, value in data.items()}))

    def sync(self, timeout: float | None = None) -> bool:
        """Block until the child has written everything logged so far; ``False`` if ``timeout`` expired first."""
        token = next(self._tokens)
        self._put((int(WireOp.SYNC), token))
        self._send(block=True)
        deadline = None if timeout is None else time.monotonic() + timeout
        synced = self._error is not None or self._wait_reply(token, deadline, stall=True)
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
            if batch and self._data >= 0 and not self._data_ending:
                self._write(_dumps(batch))
            elif self._unsent:
                self._drain()
        except (TypeError, ValueError) as exc:  # a value neither marshal nor JSON can hold
            self._error = self._error or f"{self.path}: cannot log {exc}"
        finally:
            self._release_send_lock()

    def _write(self, payload: bytes) -> None:
        """Queue one framed payload behind what is unsent, and give the pipe what it takes (never waits)."""
        data = framed(payload)
        if not self._unsent:
            self._blocked_since, self._blocked_cpu = time.monotonic(), None
        self._unsent += data
        self._drain()
        if len(self._unsent) > MAX_UNSENT_BYTES and self._data >= 0:
            self.backpressure_waits += 1
            if not self._await(lambda: len(self._unsent) <= MAX_UNSENT_BYTES // 2 or self._data_ending, None):
                self._stall(f"{len(self._unsent)} bytes waited {self.stall_timeout:g} s for it")

    def _drain(self) -> bool:
        """Write what the non-blocking pipe takes of :attr:`_unsent` (``True``: it took some). A child that took
        nothing for :attr:`stall_timeout` seconds and used no CPU time in the last of them has stalled. Called with
        the send lock held (one thread writes the pipe at a time)."""
        unsent = self._unsent
        before = len(unsent)
        try:
            while unsent and not self._data_ending:
                del unsent[: os.write(self._data, unsent)]
        except BlockingIOError:  # the pipe is full: keep the rest for the next batch
            now = time.monotonic()
            if len(unsent) < before:
                self._blocked_since, self._blocked_cpu = now, None
            elif now - self._blocked_since > self.stall_timeout:
                cpu = _cpu_time(self._process.pid)
                if cpu is None or cpu == self._blocked_cpu:
                    self._stall(f"{len(unsent)} bytes waited {now - self._blocked_since:.1f} s for it")
                self._blocked_cpu = cpu  # busy (a long chunk, say): another stall_timeout to take something
        except OSError as exc:  # the child is gone: drop from now on, say so at the next end_trial/sync/close
            self._fail(f"{self.path}: the log writer process stopped ({exc.strerror or exc})")
        return len(unsent) < before

    def _stall(self, what: str) -> None:
        self.stalled = True
        self._fail(
            f"{self.path}: the log writer process (pid {self._process.pid}) stalled: {what}; the log holds "
            f"{_trial_span(self.written_trials) or 'no complete trial'} and is finished if the process resumes"
        )

    def _fail(self, message: str) -> None:
        """The log is broken: drop what is unsent (a payload cut short is dropped by the child), end the pipe (a
        child that resumes finishes the file with what it has) and tell :attr:`on_failure` once."""
        self._error = self._error or message
        self._unsent.clear()
        self._close_data()
        if self.on_failure is not None and not self._failure_told:
            self._failure_told = True
            self.on_failure(LogWriteError(self._error))

    def _close_data(self) -> None:
        """End the data pipe: now, or, while another thread holds the send lock (it may be inside ``os.write`` on
        the descriptor, or waiting for the child to take a full pipe), by that thread as it lets the lock go.

        Why: closed under a writing thread, its write failed with EBADF, and that was reported as the run's error
        ("the log writer process stopped (Bad file descriptor)") instead of the child's own (``No space left on
        device``): 1 of 3 runs of the full-disk test under load. Had the number been reused meanwhile, the write
        would have gone into another file."""
        self._data_ending = True
        if self._send_lock.acquire(blocking=False):
            self._release_send_lock()

    def _release_send_lock(self) -> None:
        """Let the send lock go, ending the data pipe first if that was asked for meanwhile (the lock is held)."""
        try:
            if self._data_ending and self._data >= 0:
                os.close(self._data)
                self._data = -1
        finally:
            self._send_lock.release()

    def _finish_child(self) -> None:
        """Give the pipe what is unsent, end it (the child writes the rest and the footer), wait for the child while
        it makes progress, collect its last replies.

        A child that makes no progress for :attr:`stall_timeout` seconds is left to finish on its own (it is in its
        own session; it writes the footer if it resumes) and said to have stalled: never killed, which would cut a
        file it might still complete."""
        deadline = time.monotonic() + CLOSE_TIMEOUT
        if self._unsent and self._data >= 0 and not self._await(lambda: not self._unsent, deadline):
            self._stall(f"{len(self._unsent)} bytes were left for it at the end of the run")
        self._close_data()
        if not self.stalled and not self._await(lambda: self._reply_closed, deadline):
            self._stall("it did not finish the file")
        if self._reply_closed:  # the child has exited (its end of the reply pipe is closed)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self._process.wait(timeout=CLOSE_TIMEOUT)
        os.close(self._reply)
        if self._process.returncode and self._error is None and not self._broken:
            self._error = f"{self.path}: the log writer process exited with status {self._process.returncode}"

    def _wait_reply(self, token: int, deadline: float | None, *, stall: bool = False) -> bool:
        """Wait until ``token`` is acknowledged (``True``); ``False`` at an error reply, the deadline, the child's
        exit or (``stall``) :attr:`stall_timeout` seconds without progress."""
        done = self._await(lambda: self._acknowledged >= token or self._error is not None, deadline, stall=stall)
        return done and self._acknowledged >= token

    def _await(self, done: Callable[[], bool], deadline: float | None, *, stall: bool = True) -> bool:
        """Read replies and give the pipe what is unsent until ``done()`` (``True``), the deadline, the reply pipe's
        end, or (``stall``) :attr:`stall_timeout` seconds in which the child answered nothing, took no byte and
        used no CPU time (``False``)."""
        progress, cpu = time.monotonic(), _cpu_time(self._process.pid)
        while not done():
            if self._reply_closed:
                return False
            now = time.monotonic()
            waits = [] if deadline is None else [deadline - now]
            if stall:
                waits.append(progress + self.stall_timeout - now)
            if waits and min(waits) <= 0.0:
                seen = _cpu_time(self._process.pid)
                if (deadline is not None and now >= deadline) or (stall and seen == cpu):
                    return False
                progress, cpu = now, seen  # busy (a long chunk, say): not stalled
                continue
            writing = [self._data] if self._unsent and self._data >= 0 and not self._data_ending else []
            try:
                ready, writable, _ = select.select([self._reply], writing, [], None if not waits else min(waits))
            except (OSError, ValueError):  # another thread ended the data pipe meanwhile (a failure)
                continue
            if writable and self._locked_drain():
                progress = time.monotonic()
            if ready and self._read_replies():
                progress = time.monotonic()
        return True

    def _locked_drain(self) -> bool:
        """:meth:`_drain` under the send lock; ``False`` if another thread holds it (that one is writing)."""
        if not self._send_lock.acquire(blocking=False):
            return False
        try:
            return self._data >= 0 and not self._data_ending and self._drain()
        finally:
            self._release_send_lock()

    def _read_replies(self) -> bool:
        """Read the reply pipe once (it is readable) and apply what is whole; ``False`` at its end."""
        chunk = os.read(self._reply, 65536)
        self._replies += chunk
        self._take_replies()
        self._reply_closed = not chunk
        return bool(chunk)

    def _take_replies(self) -> None:
        """Apply the whole replies read so far: errors, and acknowledgements (with the trials they complete)."""
        for kind, value in unframed(self._replies):
            if kind == ReplyKind.ERROR:
                self._error = self._error or str(value)
            else:
                self._acknowledged = max(self._acknowledged, int(value))
                for token in sorted(t for t in self._ending if t <= self._acknowledged):
                    self.written_trials.extend(self._ending.pop(token))

    def _raise_pending(self) -> None:
        if self._error is None:
            return
        error, self._error = self._error, None
        self._broken = True
        # once broken, the log stays broken: later items are dropped (_data closed) and this is said once
        self._close_data()
        raise LogWriteError(error)


def _cpu_time(pid: int) -> float | None:
    """CPU seconds process ``pid`` has run (Linux ``/proc``; ``None`` elsewhere or once it is gone): a stopped
    process, or one asleep in the kernel on a hung disk, uses none."""
    try:
        with open(f"/proc/{pid}/schedstat", "rb") as stat:  # nanoseconds on the CPU, first field
            return int(stat.read().split()[0]) * 1e-9
    except (OSError, ValueError, IndexError):
        return None


def _trial_span(trials: list[int]) -> str:
    if not trials:
        return ""
    if trials == list(range(trials[0], trials[-1] + 1)):
        return f"trial {trials[0]}" if len(trials) == 1 else f"trials {trials[0]}-{trials[-1]}"
    return "trials " + ", ".join(map(str, trials))


def _spawn(file_fd: int) -> tuple[subprocess.Popen[bytes], int, int]:
    """Start the writer process on ``file_fd``; the write end of its data pipe and the read end of its replies."""
    data_read, data_write = os.pipe()
    reply_read, reply_write = os.pipe()
    with contextlib.suppress(OSError, AttributeError):  # Linux only; the default size works, with less slack
        fcntl.fcntl(data_write, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
    os.set_blocking(data_write, False)  # the loop never waits for the child (see the module's docstring)
    root = str(Path(__file__).resolve().parents[2])  # this checkout's foilc_hil, whatever the installed one
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (root, os.environ.get("PYTHONPATH"))))}
    try:
        process = subprocess.Popen(
            [sys.executable, "-m", "foilc_hil.io.log_child", str(data_read), str(reply_write), str(file_fd)],
            pass_fds=(data_read, reply_write, file_fd),
            # nothing of the bench's: a child left stalled must not hold its stdout open (`run --json | jq` waited
            # for it), and its failures come back on the reply pipe
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
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

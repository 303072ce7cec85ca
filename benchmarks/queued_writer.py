"""The writer thread the product logged through before its writer process: :class:`McapLogWriter` behind a queue,
encoding and writing on a background thread of the loop's process. Kept here as ``bench_logging``'s peer (what the
writer process is measured against); the product no longer uses it.
"""

from __future__ import annotations

import enum
import os
import threading
import time
from collections.abc import Mapping
from queue import SimpleQueue
from typing import Any

import can

from foilc_hil.errors import FoilcHilError
from foilc_hil.io.mcap_log import McapLogWriter, _ClosingListener
from foilc_hil.io.mcap_writer import Compression, Direction, LogWriteError
from foilc_hil.io.records import SampleRecord, TimingRecord

__all__ = ["QueuedLogWriter"]


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

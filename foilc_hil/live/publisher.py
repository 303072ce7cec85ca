"""A run's live view: what the loop logs, handed to a :class:`~foilc_hil.live.server.LiveServer` off the loop's path.

Where it takes the run from (:meth:`LivePublisher.attach`, the rig's one hook, ``RunRequest.live``):

- the loop's log sink: every finished trial and every block of ``/timing`` records, beside the MCAP log. The loop
  calls its sink on the between-trial update thread; the live side is one ``put_nowait`` of the record (no copy:
  a trial's arrays are not written again) into a bounded queue. A full queue drops the item, counted
  (:attr:`LiveStats.trials_dropped`); nothing waits.
- the frame tap: a frame is taken only while the ``/can`` budget of the current tick lasts (one comparison per
  frame otherwise: 4 a cycle on the loop's thread); the budget is :attr:`LiveOptions.can_rate` frames a second, and
  zero while no viewer is subscribed to ``/can``.
- the drives: their last feedback (statusword, state, velocity) and controlword, read by the publisher thread every
  :data:`TICK`; ``/drive/state`` is sent at each change seen and every :data:`STATE_PERIOD` otherwise.

One publisher thread builds the JSON (:mod:`foilc_hil.live.messages`: the log's own documents) and hands it to the
server, only for channels a viewer is subscribed to; ``/ilc/sample`` is at most :attr:`LiveOptions.rows` rows of a
trial and :attr:`LiveOptions.row_rate` rows a second (a trial gets what the budget holds when it ends, every
``k``-th row; none when it holds none: :attr:`LiveStats.trials_thinned` counts the trials sent with fewer rows than
they have). The thread shares the loop's GIL: a row costs it about 2 us (0.7 to build its JSON, 1 to 1.5 to hand it
to foxglove-sdk), a round a few tens; :attr:`LiveStats.cpu_seconds` says what it took. The server's threads and the
viewer take tens of microseconds of CPU per message besides (measured): that, on a host without a free core, is what
the budgets bound; ``make bench``'s ``--live`` row says what a lockstep run with a viewer connected loses.
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from types import TracebackType
from typing import TYPE_CHECKING, Any, Final, NamedTuple, Self, cast

from foilc_hil.io.mcap_log import frame_fields
from foilc_hil.io.schemas import TOPIC_CAN, TOPIC_DRIVE_STATE, TOPIC_SAMPLE, TOPIC_TIMING, TOPIC_TRIAL
from foilc_hil.live.messages import (
    DriveState,
    drive_state_document,
    frame_document,
    sample_documents,
    timing_documents,
    trial_document,
)
from foilc_hil.live.options import LiveOptions

if TYPE_CHECKING:
    import can

    from foilc_hil.live.server import LiveServer
    from foilc_hil.loop.bench import TrialLoop
    from foilc_hil.loop.interfaces import LogSink, TrialRecord
    from foilc_hil.loop.scheduler import CycleBlock

__all__ = ["QUEUE_ITEMS", "ROW_SAVE", "STATE_PERIOD", "TICK", "LivePublisher", "LiveSink", "LiveStats", "live_run"]

logger = logging.getLogger(__name__)

TICK: Final = 0.05
"""Seconds between the publisher thread's rounds (frames, drive states, the ``/can`` budget): each round takes the
loop process's GIL for a few tens of microseconds, so they are few (20 a second; a queued trial wakes it at once)."""
STATE_PERIOD: Final = 0.1
"""Seconds between two ``/drive/state`` messages of an axis whose state did not change."""
QUEUE_ITEMS: Final = 16
"""Trials and ``/timing`` blocks waiting for the publisher thread; past them new ones are dropped, counted."""
CLOSE_TIMEOUT: Final = 10.0
ROW_SAVE: Final = 10.0
"""Seconds of ``row_rate`` the row budget saves when trials have no row limit (``--live-rows 0``)."""
_time_ns: Final = time.time_ns


@dataclass
class LiveStats:
    """What a live view published and dropped (``run --json``'s ``live``).

    Attributes
    ----------
    trials, samples, frames, timing, states
        Messages handed to the server: ``/ilc/trial``, ``/ilc/sample``, ``/can``, ``/timing``, ``/drive/state``.
    trials_dropped, timing_dropped
        Trials and ``/timing`` blocks dropped because the publisher's queue was full.
    trials_thinned
        Trials whose rows were sent decimated (or not at all) to keep to ``rows`` and ``row_rate``.
    cpu_seconds
        CPU time the publisher thread used (its share of the loop process's GIL, at most).
    error
        Why the publisher stopped early (the run went on without its live view); empty: it did not.
    """

    trials: int = 0
    samples: int = 0
    frames: int = 0
    timing: int = 0
    states: int = 0
    trials_dropped: int = 0
    timing_dropped: int = 0
    trials_thinned: int = 0
    cpu_seconds: float = 0.0
    error: str = ""

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


class _Trial(NamedTuple):
    record: TrialRecord
    limits: tuple[float, float] | None
    log_time: int


class _Timing(NamedTuple):
    block: CycleBlock


class LiveSink:
    """The live view's ``LogSink`` for one axis's records (``foilc_hil.loop.axes.AxesSink`` splits a run of several
    axes into them, as for the log): each item goes into the publisher's queue, or is dropped, counted.

    Parameters
    ----------
    publisher
        Where the items go.
    limits
        The limits the law clamped to, as the log's sink records them; ``None``: each record's own.
    """

    def __init__(self, publisher: LivePublisher, limits: tuple[float, float] | None) -> None:
        self._publisher = publisher
        self._limits = limits

    def trial_finished(self, record: TrialRecord) -> None:
        self._publisher.offer(_Trial(record, self._limits, _time_ns()))

    def timing(self, block: CycleBlock) -> None:
        self._publisher.offer(_Timing(block))


class _Both:
    """The loop's ``LogSink`` with a live view: the log's sink first (as without it), then the live one."""

    def __init__(self, log: LogSink | None, live: LogSink) -> None:
        self._log = log
        self._live = live

    def trial_finished(self, record: TrialRecord) -> None:
        if self._log is not None:
            self._log.trial_finished(record)
        self._live.trial_finished(record)

    def timing(self, block: CycleBlock) -> None:
        if self._log is not None:
            self._log.timing(block)
        self._live.timing(block)


class LivePublisher:
    """Publishes a run on a :class:`~foilc_hil.live.server.LiveServer` from its own thread (a context manager:
    started on entry, :meth:`close` on exit). ``foilc_hil.loop.rig.run_rig`` calls :meth:`attach` once the loop and
    the drives exist.

    Parameters
    ----------
    server
        The server (owned by the caller).
    options
        ``can_rate``, ``rows`` and ``row_rate`` apply here (:class:`~foilc_hil.live.options.LiveOptions`).
    clock
        ``time.monotonic`` (tests inject one).
    """

    def __init__(self, server: LiveServer, options: LiveOptions, clock: Callable[[], float] = time.monotonic) -> None:
        self._server = server
        self._rows = options.rows
        self._row_rate = options.row_rate
        # rows a trial may take: row_rate a second from the run's start (attach), saved up to `rows` or a second's
        # worth (ten without `rows`): a long realtime trial gets `rows` rows, a lockstep burst of trials is thinned
        self._row_cap = max(options.row_rate, float(options.rows)) if options.rows else ROW_SAVE * options.row_rate
        self._row_credit = 0.0
        self._row_time = clock()
        self._can_rate = options.can_rate
        self._clock = clock
        self.stats = LiveStats()
        self._queue: queue.Queue[_Trial | _Timing] = queue.Queue(maxsize=QUEUE_ITEMS)
        self._frames: deque[tuple[int, str, Any]] = deque()
        self._budget = 0  # /can frames the tap may still hand over in this tick (see log_frame)
        self._credit = 0.0
        self._drives: tuple[Any, ...] = ()
        self._states: dict[int, tuple[DriveState, float]] = {}  # node -> the last state sent, when
        self._previous_sync: float | None = None  # across /timing blocks, as the log's sink keeps it
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._run, name="foilc-hil live view", daemon=True)

    # -- the rig's side ------------------------------------------------------------------------------------------

    def attach(self, loop: TrialLoop, drives: Sequence[Any]) -> None:
        """Feed the view from ``loop`` (its log sink gets the live one beside it), the frame tap of ``drives`` (one
        network: the first drive's tap shows every frame) and their feedback."""
        from foilc_hil.loop.axes import AxesSink, AxisLaws, AxisLimiter
        from foilc_hil.loop.interfaces import echoes_demand
        from foilc_hil.loop.safety import CommandLimiter

        limiter = loop.limiter
        limits = (float(limiter.lower), float(limiter.upper)) if isinstance(limiter, CommandLimiter) else None
        live: LogSink = LiveSink(self, limits)
        if isinstance(loop.law, AxisLaws):  # one record per axis, as the log gets them
            live = AxesSink(cast(Any, live), loop.law, cast(AxisLimiter, limiter), [d.node_id for d in drives],
                            echoes=[echoes_demand(d) for d in drives])
        loop.log = _Both(loop.log, live)
        self._row_time = self._clock()  # the row budget fills from the run's start
        if drives and hasattr(drives[0], "add_frame_listener"):
            drives[0].add_frame_listener(self.log_frame)
        self._drives = tuple(drives)

    def offer(self, item: _Trial | _Timing) -> None:
        """Queue ``item`` for the publisher thread; never waits (a full queue drops it, counted)."""
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            if isinstance(item, _Trial):
                self.stats.trials_dropped += 1
            else:
                self.stats.timing_dropped += 1

    def log_frame(self, msg: can.Message, direction: str) -> None:
        """The frame tap's listener (the loop's thread, and the receive thread): take the frame while this tick's
        ``/can`` budget lasts. Racing updates of the budget from two threads can let one frame more or fewer pass."""
        if self._budget > 0:
            self._budget -= 1
            self._frames.append((_time_ns(), direction, frame_fields(msg)))

    # -- life cycle ----------------------------------------------------------------------------------------------

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        """Publish what is queued, the drives' last states, and stop the thread (idempotent)."""
        self._closing.set()
        if self._thread.is_alive():
            self._thread.join(CLOSE_TIMEOUT)

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    # -- the publisher thread ------------------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            self._rounds()
        except Exception as exc:  # a live view that fails never stops the run: said in the stats and the log
            self.stats.error = f"{type(exc).__name__}: {exc}"
            logger.warning("live view stopped: %s", self.stats.error)
            self._budget = 0
        finally:
            self.stats.cpu_seconds = time.thread_time()

    def _rounds(self) -> None:
        last = self._clock()
        while True:
            closing = self._closing.is_set()
            try:
                item = self._queue.get(timeout=TICK) if not closing else self._queue.get_nowait()
            except queue.Empty:
                item = None
            if item is not None:
                self._publish(item)
            now = self._clock()
            if item is None or now - last >= TICK:
                self._publish_frames()
                self._refill(now - last)
                self._publish_states(now, force=closing and item is None)
                last = now
            if closing and item is None:
                return

    def _publish(self, item: _Trial | _Timing) -> None:
        server = self._server
        if isinstance(item, _Timing):
            if not server.wanted(TOPIC_TIMING):  # no JSON; only the block's last SYNC, for the next block's period
                if len(item.block):
                    self._previous_sync = float(item.block.sync_time[-1])
                return
            documents, self._previous_sync = timing_documents(item.block, self._previous_sync)
            for document in documents:
                server.log(TOPIC_TIMING, document, _time_ns())
            self.stats.timing += len(documents)
            return
        record, limits, log_time = item
        if server.wanted(TOPIC_SAMPLE):
            self._publish_rows(record, log_time)
        if server.wanted(TOPIC_TRIAL):
            server.log(TOPIC_TRIAL, trial_document(record, limits), log_time)
            self.stats.trials += 1

    def _publish_rows(self, record: TrialRecord, log_time: int) -> None:
        """The trial's rows within :attr:`LiveOptions.rows` and the ``row_rate`` budget saved since the last."""
        now = self._clock()
        if self._row_rate > 0:
            self._row_credit = min(self._row_credit + self._row_rate * (now - self._row_time), self._row_cap)
        self._row_time = now
        limit = min(self._rows or math.inf, self._row_credit if self._row_rate > 0 else math.inf)
        rows = len(record.control)
        if limit < rows:
            self.stats.trials_thinned += 1
        if limit < 1:
            return
        documents = sample_documents(record.samples(), 0 if math.isinf(limit) else int(limit))
        self.stats.samples += self._server.log_all(TOPIC_SAMPLE, documents, log_time)
        if self._row_rate > 0:
            self._row_credit -= len(documents)

    def _publish_frames(self) -> None:
        frames = self._frames
        taken = [frames.popleft() for _ in range(len(frames))]
        for log_time, direction, fields in taken:
            self._server.log(TOPIC_CAN, frame_document(fields, cast(Any, direction), log_time), log_time)
        self.stats.frames += len(taken)

    def _refill(self, elapsed: float) -> None:
        """The next tick's ``/can`` budget: ``can_rate`` frames a second, none while nobody watches ``/can``."""
        if self._closing.is_set() or not self._server.wanted(TOPIC_CAN):
            self._budget, self._credit = 0, 0.0
            return
        self._credit = min(self._credit + self._can_rate * max(elapsed, 0.0), max(1.0, 2 * self._can_rate * TICK))
        budget = math.floor(self._credit)
        self._credit -= budget
        self._budget = budget

    def _publish_states(self, now: float, *, force: bool) -> None:
        if not self._drives or not self._server.wanted(TOPIC_DRIVE_STATE):
            return
        for drive in self._drives:
            state = _drive_state(drive)
            if state is None:
                continue
            sent = self._states.get(state.node)
            if force or sent is None or state.changed_from(sent[0]) or now - sent[1] >= STATE_PERIOD:
                self._server.log(TOPIC_DRIVE_STATE, drive_state_document(state), _time_ns())
                self._states[state.node] = (state, now)
                self.stats.states += 1


def _drive_state(drive: Any) -> DriveState | None:
    """A drive's last feedback and controlword (``None`` before its first feedback, or for a drive without)."""
    with contextlib.suppress(Exception):  # a drive being closed: no state this round
        feedback = getattr(drive, "last_feedback", None)
        if feedback is not None:
            controlword = getattr(drive, "controlword", None)
            return DriveState(int(drive.node_id), int(feedback.cycle), int(feedback.state), int(feedback.statusword),
                              None if controlword is None else int(controlword), float(feedback.velocity))
    return None


@contextlib.contextmanager
def live_run(options: LiveOptions, *, name: str, config_yaml: str | None) -> Iterator[LivePublisher]:
    """A run's live view for ``with``: the server started and announced on stderr, a viewer awaited up to
    :attr:`LiveOptions.wait` seconds, the publisher running; on exit the publisher closed (what is queued is
    published) and the server stopped after :attr:`LiveOptions.linger` seconds at most while a viewer is subscribed."""
    import sys

    from foilc_hil.live.server import LiveServer

    with LiveServer(options.address, name=name, config_yaml=config_yaml) as server:
        sys.stderr.write(f"foilc-hil: live view on ws://{_url_host(options.address.host)}:{server.port} "
                         f"(Foxglove: Open connection, Foxglove WebSocket; layout: docs/foxglove-ilc-layout.json)\n")
        if options.wait > 0 and not server.wait_for_viewer(options.wait):
            sys.stderr.write(f"foilc-hil: no viewer subscribed within {options.wait:g} s; starting without one\n")
        try:
            with LivePublisher(server, options) as publisher:
                yield publisher
        finally:
            server.close(options.linger)


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host

"""The bench: learning trials over CAN in a cyclic loop, with safety and logging.

One trial of ``N`` samples runs ``N + 1`` SYNC cycles on the drive's cyclic path::

    cycle i = 0 .. N:  SYNC -> wait TPDO feedback y_i = y(i Ts) -> u_i = law.command(i, y_i) -> clamp -> RPDO

The last cycle (``i = N``) only reads ``y(N Ts)``; its RPDO is a zero command. The trial arrays follow
:mod:`foilc_hil.references` (``output[i] = y((i + 1) Ts)``), so ``output[i] = y_{i+1}``. The drive applies an
RPDO at the next SYNC, so ``u_i`` acts from ``(i + 1) Ts``: a one-cycle transport delay that the design models
with ``input_delay = 1`` (see :func:`foilc_hil.loop.settings.build_design`).

The drive is any :class:`drivers.drive.Drive`: the rig of every run (:mod:`foilc_hil.loop.rig`) hands the loop a
CiA 402 drive on CAN (or the embedded emulator), or, for ``foilc-hil simulate``, in lockstep, a
:class:`~foilc_hil.loop.simulated_drive.SimulatedDrive` (:func:`foilc_hil.loop.simulation.simulate`).

Between trials the axis is brought back to rest over the same cyclic path (zero command, which in CSV/PV is a
braking velocity set-point and in CST lets a stable axis coast down), until ``|y| <= bench.settle_tolerance`` for
``bench.settle_time`` and the phase's last command was latched at its own SYNC (a late one would land in the trial's
first SYNC window, where the record and ``replay --verify`` count the trial's own commands); a settle that does not
finish within
:data:`~foilc_hil.loop.settings.SETTLE_TIMEOUT_FACTOR` x ``settle_time`` (at least
:data:`~foilc_hil.loop.settings.MIN_SETTLE_TIMEOUT` seconds of cycles) raises :class:`~foilc_hil.errors.DriveError`.

Timing modes (:mod:`foilc_hil.loop.scheduler`): ``lockstep`` sends the next SYNC as soon as the command of the
previous one is out; ``realtime`` has each SYNC on an absolute deadline (period ``sample_time``), measures
lateness, feedback latency and missed deadlines, and logs one ``/timing`` record per cycle. In realtime the SYNC
comes from a clock of its own where the drive can (``bench.realtime.sync: clock``, :mod:`drivers.sync_clock`): the
loop then runs on the SYNCs it reads from the bus, each cycle has one period to send its command, and a late one
never delays the next SYNC; else the loop sends each SYNC on its deadline (:class:`DeadlineScheduler`).

The between-trial update (``law.end_trial``, metrics, the trial's log messages, the divergence check) runs in a
helper thread while the next settle phase keeps the cyclic path going, so SYNC never pauses between trials (a
real drive's SYNC-loss supervision would fault on a pause); the next trial starts only after the update is done.

Hot path: the per-trial arrays are allocated before the trial; per cycle the loop only writes into them, calls
the law and the drive, and the frame tap enqueues CAN frames for the log writer thread. ``/ilc/sample``,
``/ilc/trial`` and ``/timing`` messages are built after the trial.

Safety (:mod:`foilc_hil.loop.safety`): commands are clamped to the drive limits and the plant saturation. The
wait for each SYNC's feedback is bounded (:attr:`~foilc_hil.loop.settings.LoopSettings.feedback_timeout`: in
realtime until :data:`COMMAND_MARGIN_FRACTION` of a period before the next deadline, ``bench.watchdog_cycles`` x
:data:`~foilc_hil.loop.settings.LOCKSTEP_FEEDBACK_TIMEOUT` in lockstep, a liveness timeout for a drive in another
process; on the embedded emulator's synchronous bus the drive's answer is in when ``sync`` returns, so
``wait_feedback`` decides at once and no time bound applies at all) -- no further SYNC is sent while
waiting, the drive holds its last command, and realtime feedback that arrives after half a period is counted late.
A wait that expires is a *lost feedback* (``bench.faults``): counted, and the law is given the last good feedback
again (hold); more than ``bench.faults.lost_feedback`` in a row abort with
:class:`~foilc_hil.errors.FeedbackTimeoutError`. Frames that do not decode are the master's to count or raise
(``bench.faults.bad_frame``). EMCY, a fault statusword, the drive's heartbeat leaving NMT OPERATIONAL or a drive
leaving OPERATION ENABLED aborts; non-finite outputs or commands abort; a trial
whose SSE exceeds ``bench.divergence_factor`` x the best SSE so far stops learning and restores the best
feedforward (:class:`~foilc_hil.loop.safety.DivergenceGuard`, the same rule offline: ``simulate`` runs this loop);
SIGINT/SIGTERM stop the loop at the next cycle. Every abort quick-stops the drive first; on every exit path the caller's
``finally`` disables the drive (``safe_stop``) and closes the log.

What ``/ilc/sample`` holds (the contract with ``replay --verify``; layout 2, metadata ``foilc_hil.layout``): row
``i`` of trial ``k`` describes ONE instant, ``t = (i + 1) Ts``: ``output = y_{i+1}`` (exactly the float64 the law
was given at sample ``i + 1``, the held one for a lost feedback), ``reference``, ``error`` and ``E`` are row ``i``
of the trial arrays, so ``error == reference - output`` bit for bit, and ``control = u_i``, the command the drive
applies from ``t`` when its RPDO comes before the SYNC at ``t`` (computed at ``i Ts`` from ``y_i``, the previous
row's output; for row 0 the trial's ``initial_output`` in ``/ilc/trial``). ``latched`` is what the drive did latch
at that SYNC, known from the bus (SYNC from a clock: the loop reads its own RPDO and the SYNCs back in the bus's
order; else the loop sends the SYNC after the RPDO, so it is the command sent), and the law learns from it
(``law.end_trial(..., latched)``: ``u_{k-1}`` is what ran). Where the drive echoes its demand (``drive.demand_echo``:
0x606B / 0x6074 in its TPDO set), the echo in the feedback of SYNC ``i + 1`` is held against row ``i``'s
``latched`` and every sample where they differ is counted (``/ilc/trial`` ``demand_mismatches``; a lost feedback
has no echo and is not counted). ``control`` is the law's command before the bench's
limiter (what the law computed, so ``replay --verify`` can reproduce it bit for bit; the clamped, quantised value
actually sent is kept in :attr:`TrialRecord.applied`, and ``/ilc/trial`` counts the clamped commands in
``clamped``). The law is built with the limiter's limits (``make_law(..., limits=...)``) and clamps internally, so
it learns from the input that was applied (saturation-aware learning, see :mod:`foilc_hil.laws.learning`); the
limiter stays as the safety layer and is normally a no-op. ``/ilc/trial`` records those limits as ``command_limits:
[lower, upper]`` so that ``replay --verify`` rebuilds the same law. The SSE of a trial is the sum of the squared
``error`` fields. Logs written before layout 2 (no ``foilc_hil.layout``) had ``t = i Ts`` and ``output = y_i`` with
the rest at ``(i + 1) Ts``; ``replay --verify`` reads both.
"""

from __future__ import annotations

import collections
import contextlib
import math
import threading
import time
from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from drivers.cia402 import State402
from drivers.realtime import SyncSource, collect_young, demote_current_thread
from foilc_hil.errors import (
    DriveError,
    DriveFaultError,
    FeedbackTimeoutError,
    FoilcHilError,
)
from foilc_hil.loop.interfaces import (
    AxesFeedbackLostError,
    BenchOutcome,
    ClockedDriveLike,
    DriveLike,
    FaultCounts,
    LawLike,
    LimiterLike,
    LogSink,
    TrialRecord,
    WholeTrialRunner,
    echoes_demand,
)
from foilc_hil.loop.safety import (
    DivergenceGuard,
    DivergenceVerdict,
    FeedbackWatchdog,
    StopRequest,
    require_finite,
)
from foilc_hil.loop.scheduler import CycleBlock, DeadlineScheduler, TimingRecorder
from foilc_hil.loop.settings import LoopSettings
from foilc_hil.metrics import NoiseFloorTracker
from foilc_hil.progress import UPDATES_PER_TRIAL, NullProgress, ProgressView
from plant_emulator.device import TimingMode

if TYPE_CHECKING:
    from foilc_hil.loop.stalls import LoopStalls

__all__ = ["TrialLoop"]

#: realtime: feedback arriving later than this fraction of the period after its SYNC counts as late (the command
#: then has less than half a period to reach the drive before the next SYNC)
LATE_FEEDBACK_FRACTION = 0.5
#: realtime: the wait for feedback ends this fraction of a period before the next deadline, leaving time for the
#: timed wait's own wake-up and GIL hand-over (up to ``bench.realtime.switch_interval``), the law, the limiter and
#: the RPDO send to put the command out before the next SYNC latches it
COMMAND_MARGIN_FRACTION = 0.25


@dataclass(frozen=True)
class _RawTrial:
    """What the hot path of one trial produced, before the between-trial update."""

    trial: int
    seen: np.ndarray
    control: np.ndarray
    applied: np.ndarray
    sync_times: np.ndarray
    clamped: int
    feedforward_used: np.ndarray
    faults: FaultCounts
    first_sync: int | None
    latched: np.ndarray
    demand: np.ndarray | None  # (N,): the demand echoed at SYNC i + 1 (NaN: its set lost); None: no echo mapped
    lost_by_axis: np.ndarray | None  # (m,): each axis's lost feedbacks in the trial; None: one axis


#: seconds between the loop's looks at its stop request while it waits for a between-trial update (a stalled log
#: writer can make that wait last the writer's stall timeout: a signal must not)
_UPDATE_POLL = 0.05
#: seconds an abort gives the between-trial update to log its trial before the drive is disabled: the update's
#: own waits for a stalled log writer last up to its stall timeout, and the disable must not wait that long
_UPDATE_GRACE = 0.5


class _TrialUpdateThread:
    """Runs :meth:`TrialLoop._finish_trial` in a thread while the loop settles the axis for the next trial."""

    def __init__(self, loop: TrialLoop, raw: _RawTrial) -> None:
        self._loop = loop
        self._raw = raw
        self._finished: tuple[TrialRecord, DivergenceVerdict] | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._work, name=f"foilc-hil-trial-{raw.trial}-update", daemon=True)

    @classmethod
    def start(cls, loop: TrialLoop, raw: _RawTrial) -> _TrialUpdateThread:
        """Begin the update of the trial ``raw`` in its own thread; in lockstep without settle phases (the simulated
        drive) nothing would run meanwhile, so the update runs at once in the caller's thread (a thread's start and
        hand-over cost more than the update on a loaded host)."""
        update = cls(loop, raw)
        if loop.settings.settle_between_trials or loop.scheduler is not None:
            update._thread.start()
        else:
            update._update()
        return update

    def _work(self) -> None:
        demote_current_thread()  # bulk work: below the cyclic threads (drivers.realtime)
        self._update()

    def _update(self) -> None:
        try:
            self._loop._emit_timing()
            self._finished = self._loop._finish_trial(self._raw)
            collect_young()  # the cyclic garbage of the trial, while the gc is off for the run (drivers.realtime)
        except BaseException as exc:  # handed to the loop's thread by result()
            self._error = exc

    def finish(self, timeout: float) -> None:
        """On the way out of an abort: give the update up to ``timeout`` seconds to finish logging its trial, and
        drop its outcome (the abort is what the run reports)."""
        if self._thread.ident is not None:
            self._thread.join(timeout)

    @property
    def done(self) -> bool:
        """The update has finished (successfully or not)."""
        return not self._thread.is_alive()

    def result(self, stop: StopRequest | None = None) -> tuple[TrialRecord, DivergenceVerdict]:
        """Wait for the update: the trial's record and the divergence verdict; re-raise its error in the caller's
        thread. With ``stop``, a signal or a failure handed to it ends the wait at once (raised as
        :meth:`StopRequest.raise_if_requested` does)."""
        if self._thread.ident is not None:  # started (else it ran in the caller's thread)
            while self._thread.is_alive():
                self._thread.join(_UPDATE_POLL)
                if stop is not None:
                    stop.raise_if_requested()
        if self._error is not None:
            raise self._error
        assert self._finished is not None
        return self._finished


# --- the loop -----------------------------------------------------------------------------------------------------


class TrialLoop:
    """Runs trials of a learning law against a drive.

    Parameters
    ----------
    drive
        Commissioned and enabled (OPERATION ENABLED); the loop only runs the cyclic path and quick-stops on abort.
    law
        The learning law; ``command`` is called once per cycle with a preallocated ``(1,)`` output array (``(m,)``
        for ``m`` axes).
    reference
        One trial's reference, shape ``(N,)`` (:func:`foilc_hil.references.reference_profile`), or ``(N, m)`` for
        ``m`` axes in one loop (:mod:`foilc_hil.loop.axes`): outputs and commands are then ``(m,)`` arrays, the
        drive one SYNC for every axis, and the settle phase waits until every axis is at rest.
    limiter
        Command limits in plant units; ``None``: commands go to the drive as the law computed them (the offline
        simulator, whose plant saturates by itself).
    settings
        Timing and safety settings.
    log
        Receives each finished trial and, in realtime mode, the per-cycle timing records.
    progress
        The stderr view.
    stop
        The SIGINT/SIGTERM flag, polled once per cycle.
    clock, sleep
        ``time.perf_counter`` and ``time.sleep`` (injected in tests: the realtime scheduler waits with them).
    before_trial
        Called with the trial number once the axis has settled, just before the trial's first SYNC. The embedded
        emulator and the simulated drive use it to start their plant's trial (initial condition, a disturbance that
        begins at a given trial, per-trial noise); a real drive has no such hook.
    stalls
        Fault injection (``stall@TRIAL+CYCLE``, :class:`foilc_hil.loop.stalls.LoopStalls`): the samples of each
        trial whose cycle stalls the loop thread alone (``sleep``) between the law's command and its RPDO.
        ``None``: no stall.
    """

    def __init__(
        self,
        drive: DriveLike,
        law: LawLike,
        reference: np.ndarray,
        limiter: LimiterLike | None,
        settings: LoopSettings,
        *,
        log: LogSink | None = None,
        progress: ProgressView | None = None,
        stop: StopRequest | None = None,
        clock: Callable[[], float] = time.perf_counter,
        before_trial: Callable[[int], None] | None = None,
        sleep: Callable[[float], None] = time.sleep,
        stalls: LoopStalls | None = None,
    ) -> None:
        ref = np.asarray(reference, dtype=float)
        if ref.ndim not in (1, 2) or ref.size == 0:
            raise ValueError(f"reference must be a non-empty (N,) array, or (N, m) for m axes, got shape {ref.shape}")
        self.drive = drive
        self.law = law
        self.reference = ref
        self.limiter = limiter
        self.settings = settings
        self.log = log
        self.progress: ProgressView = progress if progress is not None else NullProgress()
        self.stop = stop if stop is not None else StopRequest()
        self._clock = clock
        self._before_trial = before_trial
        self.watchdog = FeedbackWatchdog(settings.feedback_timeout, settings.max_lost_feedback)
        self._held: Any = 0.0  # the last good feedback: what the law is given again for a lost one
        # several axes: each axis's lost feedbacks so far (an axis is held alone, AxesFeedbackLostError); None: one
        self._lost_by_axis = np.zeros(ref.shape[1], dtype=np.int64) if ref.ndim == 2 else None
        self.guard = DivergenceGuard(settings.divergence_factor)
        self._noise_floor = NoiseFloorTracker()
        self.timing = TimingRecorder(settings.mode, settings.sample_time)
        realtime = settings.mode is TimingMode.REALTIME
        self.scheduler = (
            DeadlineScheduler(settings.sample_time, spin_margin=settings.realtime.spin_margin, clock=clock, sleep=sleep)
            if realtime
            else None
        )
        self._command_margin = COMMAND_MARGIN_FRACTION * settings.sample_time
        self._sleep = sleep
        self._stalls = stalls
        # SYNC from a clock (realtime, bench.realtime.sync: clock, a drive that can): the loop runs on the SYNCs it
        # reads from the bus. _latched: what the drive latched at the last SYNC; the liveness bound of the waits
        self._clocked = False
        self._clock_drive: ClockedDriveLike | None = None
        self._latched: Any = 0.0
        self._demand: Any = math.nan  # the demand the last cycle's feedback echoed (NaN: none, or lost)
        self._sync_timeout = settings.watchdog_cycles * settings.lockstep_feedback_timeout
        self.outcome = BenchOutcome()
        # finished realtime blocks (rows, first cycle, phase, trial) whose /timing records are not yet logged: a
        # trial's 6000 records take milliseconds to build, so the update thread logs them, not the loop thread
        self._timing_backlog: collections.deque[tuple[np.ndarray, int, str, int]] = collections.deque()
        self._cycle = 0  # cycles run so far, over the whole run
        self._output_buffer = np.zeros(1 if ref.ndim == 1 else ref.shape[1])
        # one axis: Python floats through the cycle; m axes (an (N, m) reference): (m,) arrays
        self._signal = _SCALAR if ref.ndim == 1 else _VECTOR
        self._feedforward_used = np.zeros(0)
        # the current cycle's measurements, written by _cycle_feedback and read by _finish_cycle
        self._sync_time = self._received = self._latency = 0.0
        self._deadline = self._lateness = math.nan
        self._skipped = 0
        self._late = self._missing = False
        self._missed = False  # the last cycle's command missed the SYNC after its own (it ran one cycle late)
        self._sync_number = 0  # the drive's count of the last SYNC it sent (its frame in the log)
        self._next_trial = 1  # the number the next trial gets (iter_trials continues it)

    # -- public --------------------------------------------------------------------------------------------------

    @property
    def cycles(self) -> int:
        """SYNC cycles run so far (trial and settle phases)."""
        return self._cycle

    def run(self, trials: int) -> BenchOutcome:
        """Run up to ``trials`` trials (:meth:`iter_trials` to the end). Returns the outcome; raises on aborts after
        quick-stopping the drive.

        Raises
        ------
        DriveError
            Feedback watchdog, EMCY, drive fault, heartbeat loss, a settle that never finishes.
        LearningDivergedError
            Non-finite output or command.
        RunInterruptedError
            SIGINT / SIGTERM.
        """
        for _ in self.iter_trials(trials):
            pass
        return self.outcome

    def iter_trials(self, trials: int) -> Generator[TrialRecord, None, None]:
        """Run up to ``trials`` more trials, yielding each one's record once its between-trial update is done.

        Trial ``k``'s record comes after the settle phase before trial ``k + 1`` (the update runs meanwhile, as in
        :meth:`run`), or after the last trial; while the caller holds it no cycle runs (lockstep loses nothing; in
        realtime the drive's SYNC supervision is waiting, so keep the caller's work short). A divergence stop yields
        the diverged trial (learning already stopped, the drive quick-stopped) and ends. Another call continues the
        numbering; after a divergence stop it yields nothing. Raises as :meth:`run` does.
        """
        if trials < 1:
            raise ValueError(f"trials must be >= 1, got {trials}")
        if self.outcome.diverged:
            return
        first, last = self._next_trial, self._next_trial + trials - 1
        if first == 1:
            self.timing.start()
        if self.scheduler is not None:
            self.scheduler.start()
            self._start_clock()
        update: _TrialUpdateThread | None = None
        try:
            for trial in range(first, last + 1):
                # the previous trial's update (law, metrics, log) runs in `update` while the axis settles, so
                # SYNC keeps flowing on its period between trials
                self._settle(trial, update)
                if update is not None:
                    record, verdict = update.result(self.stop)
                    update = None
                    if verdict.diverged:
                        self._stop_learning(verdict)
                    yield record
                    if verdict.diverged:
                        return
                if self._before_trial is not None:
                    self._before_trial(trial)
                raw = self._run_trial(trial, last)
                self._next_trial = trial + 1
                update = _TrialUpdateThread.start(self, raw)
            if update is not None:
                if self.scheduler is not None:  # realtime: the drive watches SYNC until it is stopped
                    self._settle(last, update, phase="final")
                record, verdict = update.result(self.stop)
                update = None
                if verdict.diverged:
                    self._stop_learning(verdict)
                yield record
        except FoilcHilError:  # the drive's, the law's, a signal, the log writer's: the axis stops first
            self._quick_stop()
            raise
        finally:
            if update is not None:
                # an abort during the settle phase: the trial before it did complete, so finish logging it (the
                # writer's waits are bounded: a stalled writer ends the update within its stall timeout)
                update.finish(_UPDATE_GRACE)
            self._stop_clock()
            self._emit_timing()
            self.outcome.clamped_commands = self._clamped_count()
            self.outcome.faults = FaultCounts(self.watchdog.total, self.drive.bad_frames)
            self.outcome.timing = self.timing.summary()

    def _start_clock(self) -> None:
        """Realtime with ``bench.realtime.sync: clock``: SYNC from the drive's clock, when it has one to start
        (:mod:`drivers.sync_clock`); else the loop sends SYNC on its deadlines (the scheduler)."""
        if self.settings.realtime.sync is not SyncSource.CLOCK or not hasattr(self.drive, "start_clock"):
            self.timing.sync_clock = str(SyncSource.LOOP)
            return
        drive = cast(ClockedDriveLike, self.drive)
        name = drive.start_clock(spin_margin=self.settings.realtime.sync_spin)
        self._clocked = name is not None
        self._clock_drive = drive if name is not None else None
        if name is not None:  # the SYNCs so far were the loop's own (enable): the clock's are counted from here
            self._sync_number = drive.syncs_seen
        self.timing.sync_clock = name if name is not None else str(SyncSource.LOOP)

    def _stop_clock(self) -> None:
        """The clock stops with the loop: what follows (the drive's stop) sends its own SYNCs."""
        drive, self._clock_drive = self._clock_drive, None
        self._clocked = False
        if drive is not None:
            with contextlib.suppress(Exception):  # on every exit path, the error being raised is the run's
                drive.stop_clock()

    # -- phases --------------------------------------------------------------------------------------------------

    def _settle(self, trial: int, update: _TrialUpdateThread | None, phase: str = "settle") -> None:
        """Zero command until the axis rests within tolerance for ``settle_time`` (bounded).

        In realtime the phase also lasts until ``update`` (the previous trial's) is done: the drive supervises SYNC,
        so the cyclic path must not pause while the loop thread would wait for it. ``phase="final"`` is the same
        after the last trial (``trial`` is then the last trial's number).
        """
        if not self.settings.settle_between_trials:
            return
        needed = self.settings.settle_cycles
        limit = self.settings.settle_timeout_cycles
        tolerance = self.settings.settle_tolerance
        pending = update if self.scheduler is not None else None
        self.timing.begin_block(min(limit, 4 * needed + 16), phase=phase, trial=trial)
        first_cycle = self._cycle
        at_rest = 0
        try:
            for _ in range(limit):
                y = self._cycle_feedback()
                self.drive.set_target(0.0)
                self._finish_cycle()
                at_rest = at_rest + 1 if self._signal.peak(y) <= tolerance else 0
                # the last settle command must be latched before the trial's first SYNC: one that missed it lands in
                # the trial's first window, where the record and replay --verify count the trial's own N + 1 RPDOs
                if at_rest >= needed and (pending is None or pending.done) and not self._missed:
                    self.outcome.settle_cycles += self._cycle - first_cycle
                    return
        finally:
            self._flush_timing(first_cycle)
        when = "after the last trial" if phase == "final" else f"before trial {trial}"
        raise DriveError(
            f"the axis did not come to rest {when}: |velocity| stayed above "
            f"bench.settle_tolerance {tolerance:g} for {limit} cycles ({limit * self.settings.sample_time:g} s)"
        )

    def _run_trial(self, trial: int, total_trials: int) -> _RawTrial:
        """The trial's N + 1 cycles (hot path); returns the raw arrays."""
        n = self.reference.shape[0]
        width = self.reference.shape[1:]  # () for one axis
        seen = np.empty((n + 1, *width))
        control = np.empty((n, *width))
        applied = np.empty((n, *width))
        latched = np.empty((n, *width))  # what the drive latched at SYNC i + 1 (clocked: from the bus)
        sync_times = np.empty(n + 1)
        # the demand echo of cycle i's feedback (drive.demand_echo): the target latched at the trial's SYNC i
        echo = np.full((n + 1, *width), math.nan) if echoes_demand(self.drive) else None
        stalls = self._stalls.cycles(trial) if self._stalls is not None else {}
        clocked = self._clocked
        self._feedforward_used = np.array(self.law.feedforward, dtype=float, copy=True)
        self.timing.begin_block(n + 1, phase="trial", trial=trial)
        first_cycle = self._cycle
        every = max(1, n // UPDATES_PER_TRIAL)
        self.progress.begin_trial(trial, total_trials, n)
        self.law.begin_trial()
        output_buffer = self._output_buffer
        clamp: Callable[[Any], Any] = self.limiter.clamp if self.limiter is not None else float
        as_command, require = self._signal.command, self._signal.require_finite  # locals: one lookup per trial
        into = self._signal.into
        clamped_before = self._clamped_count()
        lost_before, bad_before = self.watchdog.total, self.drive.bad_frames
        axes_before = None if self._lost_by_axis is None else self._lost_by_axis.copy()
        drive = self.drive
        law = self.law
        try:
            whole = self._run_whole_trial(seen, control, applied, sync_times)
            for i in range(whole, n):  # those left, one by one
                y = self._cycle_feedback()
                if clocked and i:
                    latched[i - 1] = self._latched
                if echo is not None:
                    echo[i] = self._demand
                sync_times[i] = self._sync_time
                seen[i] = y
                output_buffer[into] = y
                u = as_command(law.command(i, output_buffer))
                require(u, "command", self._cycle)
                control[i] = u
                if stalls and i in stalls:  # fault injection: the loop thread alone stalls (the SYNC clock goes on)
                    self._stall(trial, i, stalls[i])
                applied[i] = drive.set_target(clamp(u))
                self._finish_cycle()
                if i % every == 0:
                    self.progress.advance(i)
            y = self._cycle_feedback()  # y(N Ts): closes the trial's output array
            if echo is not None:
                echo[n] = self._demand
            sync_times[n] = self._sync_time
            seen[n] = y
            drive.set_target(0.0)
            self._finish_cycle()
        finally:
            self._flush_timing(first_cycle)
        if clocked:
            latched[n - 1] = self._latched
        else:  # the loop itself sent each SYNC after the cycle's RPDO, on one bus object: every command latched
            latched[:] = applied
        self.progress.advance(n)
        faults = FaultCounts(self.watchdog.total - lost_before, self.drive.bad_frames - bad_before)
        # SYNCs are counted one by one, the trial's N + 1 the last of them (no count where the drive ran it whole)
        first_sync = self._sync_number - n if whole == 0 else None
        return _RawTrial(
            trial, seen, control, applied, sync_times, self._clamped_count() - clamped_before, self._feedforward_used,
            faults, first_sync, latched, None if echo is None else echo[1:],
            None if axes_before is None else cast(np.ndarray, self._lost_by_axis) - axes_before,
        )

    def _run_whole_trial(
        self, seen: np.ndarray, control: np.ndarray, applied: np.ndarray, sync_times: np.ndarray
    ) -> int:
        """Lockstep without a limiter, on a drive with a :data:`WholeTrialRunner`: the trial's sample cycles in one
        call, with the same checks (a stop request, non-finite values) and counts; returns how many ran (0: none).

        Their timing is not measured per cycle (``sync_times`` NaN, one unmeasured ``/timing`` row each); nothing is
        clamped (``applied == control``).
        """
        run_whole_trial: WholeTrialRunner | None = getattr(self.drive, "run_whole_trial", None)
        if self.scheduler is not None or self.limiter is not None or run_whole_trial is None:
            return 0
        self._check_stop()
        ran = run_whole_trial(self.law, seen, control)
        if ran is None:
            return 0
        self.timing.record_unmeasured(ran.cycles)
        self._cycle += ran.cycles
        if ran.failed:
            require_finite(ran.value, ran.failed, self._cycle)
        sync_times[: ran.cycles] = math.nan
        applied[: ran.cycles] = control[: ran.cycles]
        self.watchdog.answered()
        self._held = float(seen[ran.cycles - 1])
        return ran.cycles

    def _finish_trial(self, raw: _RawTrial) -> tuple[TrialRecord, DivergenceVerdict]:
        """Between trials (off the hot path): the law's update, metrics, progress, log, divergence check."""
        n = self.reference.shape[0]
        output = raw.seen[1:].copy()
        update = self.law.end_trial(self.reference, output, raw.latched)  # u_{k-1} is what the drive latched
        shape = (n, *self.reference.shape[1:])
        error = np.asarray(update.error, dtype=float).reshape(shape)
        E = np.asarray(update.E, dtype=float).reshape(shape)
        # the law's metrics (learnable samples counted from its input delay) with the trial-to-trial noise floor
        metrics = self._noise_floor.measured(update.metrics, error)
        record = TrialRecord(
            trial=raw.trial,
            sample_time=self.settings.sample_time,
            reference=self.reference,
            seen=raw.seen,
            control=raw.control,
            applied=raw.applied,
            output=output,
            error=error,
            E=E,
            metrics=metrics,
            sync_times=raw.sync_times,
            clamped=raw.clamped,
            faults=raw.faults,
            first_sync=raw.first_sync,
            latched=raw.latched,
            demand=raw.demand,
            lost_by_axis=raw.lost_by_axis,
        )
        self.outcome.trials.append(metrics)
        mismatches = record.demand_mismatches
        if mismatches is not None:  # the run's total, next to its fault counts
            self.outcome.demand_mismatches = (self.outcome.demand_mismatches or 0) + mismatches
        self.outcome.trial_faults.append(raw.faults)
        self.progress.end_trial(raw.trial, metrics.sse, metrics.rmse, metrics.max_abs_error)
        if self.log is not None:
            self.log.trial_finished(record)
        return record, self.guard.check(raw.trial, metrics.sse, raw.feedforward_used)

    def _stop_learning(self, verdict: DivergenceVerdict) -> None:
        """The divergence guard tripped: restore the best feedforward, stop the axis, say why."""
        self.law.restore(self.guard.best_feedforward())
        self.outcome.stopped = verdict.message
        self.outcome.diverged = True
        self._quick_stop()

    # -- one cycle -----------------------------------------------------------------------------------------------

    def _cycle_feedback(self) -> float:
        """Release (realtime: wait for the deadline), SYNC, and wait for this cycle's feedback (watchdog-bounded)."""
        self._check_stop()
        if self._clocked:
            timeout = self._clocked_sync()
        else:
            if self.scheduler is not None:
                deadline, lateness, skipped = self.scheduler.wait()
            else:
                deadline, lateness, skipped = math.nan, math.nan, 0
            self._sync_number = self.drive.sync()
            sync_time = self._clock()
            self._sync_time = sync_time
            self._deadline, self._lateness, self._skipped = deadline, lateness, skipped
            timeout = self.watchdog.timeout
            if self.scheduler is not None:  # wait no later than the next deadline: a lost feedback costs no deadline
                timeout = max(0.0, self.scheduler.next_deadline - self._command_margin - sync_time)
        try:
            feedback = self.drive.wait_feedback(timeout)
        except FeedbackTimeoutError as exc:
            return self._lost_feedback(exc)
        self.watchdog.answered()
        self._demand = feedback.demand
        received = self._clock()
        self._received = received
        self._missing = False
        self._latency = received - self._sync_time
        self._late = self.scheduler is not None and self._latency > LATE_FEEDBACK_FRACTION * self.settings.sample_time
        if feedback.state != State402.OPERATION_ENABLED:
            raise DriveFaultError(
                f"the drive left OPERATION ENABLED (now {State402(feedback.state).name}) at cycle {self._cycle}"
            )
        y = self._signal.output(feedback.velocity)
        self._signal.require_finite(y, "drive feedback", self._cycle)
        self._held = y
        return y

    def _stall(self, trial: int, sample: int, seconds: float) -> None:
        self._sleep(seconds)
        if self._stalls is not None:
            self._stalls.stalled(trial, sample, self._sync_number)

    def _clocked_sync(self) -> float:
        """SYNC from a clock: the next SYNC read from the bus (its time, deadline and the slots skipped before it,
        as its producer recorded them), what the drive latched at it; returns the bound of the wait for feedback,
        a liveness bound only (the next SYNC on the bus ends the wait first, as a lost feedback)."""
        drive = cast(ClockedDriveLike, self._clock_drive)
        seen = drive.await_sync(self._sync_number, self._sync_timeout)
        self._sync_number = seen.number
        self._sync_time = seen.time if seen.time == seen.time else self._clock()  # NaN: not known, read now
        self._deadline, self._skipped = seen.due, seen.skipped
        self._lateness = seen.time - seen.due
        self._latched = drive.latched
        return self._sync_timeout

    def _check_stop(self) -> None:
        if self.stop.requested:
            self.stop.raise_if_requested()

    def _lost_feedback(self, cause: FeedbackTimeoutError) -> float:
        """This SYNC's wait expired: count it, and hold the last good feedback -- or trip the watchdog."""
        error = self.watchdog.lost(self._cycle, cause)
        self._demand = math.nan  # no echo to compare: the sample is not counted
        if isinstance(cause, AxesFeedbackLostError):
            self._hold_lost_axes(cause)
        elif self._lost_by_axis is not None:  # several axes, none read: every axis held, and counted
            self._lost_by_axis += 1
        self._missing = True
        self._late = False
        self._latency = math.nan
        self._received = self._clock()
        if error is not None:
            self.timing.record(
                self._sync_time, self._deadline, self._lateness, math.nan, math.nan, self._skipped, False, True,
                self._received > self._deadline + self.settings.sample_time,
            )
            raise error from cause
        return self._held

    def _hold_lost_axes(self, cause: AxesFeedbackLostError) -> None:
        """Several axes, some answered: the lost axes' last good feedback is held, the others' fresh answers become
        theirs (and their demand echoes are compared); each axis's losses are counted."""
        lost = cause.lost
        if self._lost_by_axis is not None:
            self._lost_by_axis += lost
        y = self._signal.output(cause.velocity)
        answered = ~lost
        self._signal.require_finite(y[answered], "drive feedback", self._cycle)
        self._held = np.where(lost, self._held, y)
        self._demand = cause.demand

    def _finish_cycle(self) -> None:
        sent = self._clock()
        if self._clocked:  # the command went out after the next SYNC (the bus object's order of sends): missed
            missed = cast(ClockedDriveLike, self._clock_drive).rpdo_sync_count > self._sync_number
        else:  # it went out after the next slot's SYNC should have latched it (NaN deadline: never)
            missed = sent > self._deadline + self.settings.sample_time
        self._missed = missed
        self.timing.record(
            self._sync_time,
            self._deadline,
            self._lateness,
            self._latency,
            sent - self._received,
            self._skipped,
            self._late,
            self._missing,
            missed,
        )
        self._cycle += 1

    def _flush_timing(self, first_cycle: int) -> None:
        phase, trial = self.timing.phase, self.timing.trial
        block = self.timing.finish_block()
        if self.log is not None and self.scheduler is not None:
            self._timing_backlog.append((block, first_cycle, phase, trial))

    def _emit_timing(self) -> None:
        """Log the ``/timing`` records of the finished blocks, in cycle order (the update thread, or the end)."""
        while self.log is not None and self._timing_backlog:
            block, first_cycle, phase, trial = self._timing_backlog.popleft()
            self.log.timing(CycleBlock(block, first_cycle, phase, trial))

    def _clamped_count(self) -> int:
        return self.limiter.clamped_count if self.limiter is not None else 0

    def _quick_stop(self) -> None:
        # best effort on the way out: the caller's finally follows with safe_stop (disable)
        with contextlib.suppress(Exception):
            self.drive.quick_stop()


def _first(values: np.ndarray) -> float:
    return float(values[0])


def _vector(values: Any) -> np.ndarray:
    return np.array(values, dtype=float)


def _peak(values: Any) -> float:
    return float(np.max(np.abs(values)))  # NaN propagates: a NaN axis is never "at rest", never finite


def _require_all_finite(values: Any, what: str, cycle: int) -> None:
    require_finite(_peak(values), what, cycle)


@dataclass(frozen=True)
class _Signals:
    """How the loop handles one cycle's output and command: floats for one axis, ``(m,)`` arrays for several."""

    into: int | slice  # where y goes in the law's input buffer (an int index is the cheaper store)
    output: Callable[[Any], Any]  # the drive's feedback velocity -> y
    command: Callable[[np.ndarray], Any]  # the law's command array -> u
    peak: Callable[[Any], float]  # |y| (the largest over the axes): the settle test
    require_finite: Callable[[Any, str, int], None]


_SCALAR = _Signals(0, float, _first, abs, require_finite)
_VECTOR = _Signals(slice(None), _vector, _vector, _peak, _require_all_finite)

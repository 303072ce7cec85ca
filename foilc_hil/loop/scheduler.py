"""Cycle timing for the bench: absolute deadlines, a hybrid sleep/spin wait, and per-cycle timing records.

Two timing modes drive the SYNC of the CAN loop (see :mod:`foilc_hil.loop.bench`):

``lockstep``
    The next SYNC goes out as soon as the feedback of the previous one is in and the command is sent. The run is
    deterministic and as fast as the bus allows; wall-clock time means nothing (tests, the demo, benchmarks).
``realtime``
    SYNC on a fixed period, on absolute deadlines ``t0 + k * period`` of :func:`time.perf_counter`, so errors do
    not accumulate. By default (``bench.realtime.sync: clock``) a clock of its own sends it
    (:mod:`drivers.sync_clock`: the kernel's broadcast manager on socketcan, a producer thread elsewhere, with the
    same deadlines and policy as below) and the loop runs on the SYNCs it reads from the bus; else the loop sends
    it, released by :class:`DeadlineScheduler`, which sleeps until shortly before each deadline (``time.sleep`` is
    coarse: its wake-up is late by the OS timer slack) and spins the last ``spin_margin`` seconds.

Deadline accounting (documented, counted, never fatal by itself). Cycle ``k`` begins with SYNC ``k`` (due at deadline
``d_k``): it waits for the feedback and sends its command, which the drive latches at the next SYNC (due at
``d_k + period``). Two different things can go wrong:

*missed deadline*
    The cycle's command went out after the next SYNC (SYNC from a clock: after it was sent, in the bus object's order
    of sends; the loop's SYNC: after ``d_k + period``): the drive latched the previous command once more, and the
    log's ``/ilc/sample.latched`` holds what it did latch. Counted once per cycle (``missed_deadlines``, the
    ``/timing`` record's ``missed``), so ``missed_deadlines <= cycles``. The cycle still completes; SYNC from a clock
    goes on regardless, the loop's own SYNC is released as soon as possible (late, or on a later slot).
*skipped deadline*
    A deadline slot on which no SYNC was sent at all: the loop (or the SYNC producer) reached its wait more than a
    period after the slot's deadline (a host stall). No burst of catch-up SYNCs is sent; the loop's cycle is released
    on the next slot still in the future (the producer sends one late SYNC for the latest slot passed), and every slot
    passed over is counted in ``skipped_deadlines`` (any number per stall: a 50 ms stall at 1 kHz skips about 50).
    The drive holds the last command meanwhile (RPDO values persist until replaced).

A cycle released late but before the following slot is neither: its lateness goes into the jitter statistics.

:class:`TimingRecorder` keeps the per-cycle measurements in preallocated arrays (the hot path only writes into
them) and turns them into ``/timing`` records and summary statistics off the hot path.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.realtime import RealtimeConfig, RealtimeReport
from foilc_hil.io.records import TimingBlock
from plant_emulator.device import TimingMode

__all__ = [
    "CycleBlock",
    "CycleTiming",
    "DeadlineScheduler",
    "TimingRecorder",
    "TimingSummary",
]

#: default spin window before each deadline, seconds (``bench.realtime.spin_margin``): covers the wake-up latency of
#: a sleep with the timer slack set to 1 ns (drivers.realtime), measured at tens of microseconds on this machine
DEFAULT_SPIN_MARGIN: float = RealtimeConfig.model_fields["spin_margin"].default


class DeadlineScheduler:
    """Absolute-deadline cycle clock with a hybrid sleep/spin wait.

    Parameters
    ----------
    period
        Cycle period in seconds (the CAN cycle period, ``sample_time``).
    spin_margin
        The last part of each wait, in seconds, is spent spinning on the clock instead of sleeping.
    clock, sleep
        Injected for tests (a fake clock makes every policy decision deterministic).
    """

    def __init__(
        self,
        period: float,
        *,
        spin_margin: float = DEFAULT_SPIN_MARGIN,
        clock: Callable[[], float] = time.perf_counter,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if not (period > 0 and math.isfinite(period)):
            raise ValueError(f"period must be a positive number of seconds, got {period!r}")
        if spin_margin < 0:
            raise ValueError(f"spin_margin must be >= 0, got {spin_margin!r}")
        self.period = float(period)
        self.spin_margin = float(spin_margin)
        self._clock = clock
        self._sleep = sleep
        self._t0 = 0.0
        self._next_index = 0
        self.skipped_deadlines = 0

    def start(self, t0: float | None = None) -> None:
        """Set the time origin: deadline ``k`` is ``t0 + k * period``; the first :meth:`wait` targets ``k = 0``."""
        self._t0 = self._clock() if t0 is None else float(t0)
        self._next_index = 0
        self.skipped_deadlines = 0

    @property
    def next_deadline(self) -> float:
        """The deadline the next :meth:`wait` targets unless it is already past (the current cycle's end)."""
        return self._t0 + self._next_index * self.period

    def deadline(self, index: int) -> float:
        """The absolute time of deadline ``index``."""
        return self._t0 + index * self.period

    def wait(self) -> tuple[float, float, int]:
        """Wait for the next deadline still ahead (skipping any that already passed).

        Returns
        -------
        deadline
            The absolute deadline this cycle was released at.
        lateness
            How late the release is, seconds (``clock() - deadline`` on return, >= 0 up to clock resolution).
        skipped
            How many earlier deadline slots passed without a SYNC (counted into :attr:`skipped_deadlines`).
        """
        index = self._next_index
        deadline = self._t0 + index * self.period
        now = self._clock()
        skipped = 0
        if now >= deadline + self.period:
            # the policy: skip every deadline that has passed except the current slot's own; the cycle waits for
            # the next one ahead instead of sending catch-up SYNCs
            skipped = int((now - deadline) // self.period)
            index += skipped
            deadline = self._t0 + index * self.period
            if now > deadline:
                index += 1
                skipped += 1
                deadline += self.period
            self.skipped_deadlines += skipped
        remaining = deadline - now
        if remaining > self.spin_margin:
            self._sleep(remaining - self.spin_margin)
        now = self._clock()
        while now < deadline:
            now = self._clock()
        self._next_index = index + 1
        return deadline, now - deadline, skipped


@dataclass(frozen=True)
class TimingSummary:
    """Timing statistics of a run (the ``"timing"`` object of ``foilc-hil run --json``).

    Jitter is the release lateness of each cycle (actual SYNC time minus its deadline); in lockstep runs there are
    no deadlines and the jitter fields are ``None``. ``cycle_time`` is the interval between consecutive SYNCs;
    ``compute`` is the bench's own share of a cycle, from the feedback handed to the loop to the command sent
    (law, clamp, RPDO encode and send, log enqueue). ``cycles_per_second`` is ``cycles`` over the time from the
    loop's first cycle (:meth:`TimingRecorder.start`) to the summary. ``missed_deadlines`` (<= ``cycles``) and
    ``skipped_deadlines`` are defined in the module docstring; ``realtime`` is what the host setup applied
    (:class:`drivers.realtime.RealtimeReport`; ``None`` in lockstep). With SYNC from a clock (``sync_clock``) the
    jitter is the producer's lateness of each SYNC against its deadline, and ``cycle_time`` the intervals between
    the SYNCs as the producer sent them.
    """

    mode: TimingMode
    period: float
    cycles: int
    missed_deadlines: int
    skipped_deadlines: int
    late_feedback: int
    missing_feedback: int
    jitter_p50_us: float | None
    jitter_p99_us: float | None
    jitter_max_us: float | None
    cycle_time_p50_us: float | None
    cycle_time_p99_us: float | None
    cycle_time_max_us: float | None
    compute_p50_us: float | None
    compute_p99_us: float | None
    cycles_per_second: float | None
    realtime: RealtimeReport | None = None
    #: where SYNC came from in realtime: ``"thread"`` (a producer thread's clock), ``"bcm"`` (the kernel's broadcast
    #: manager), ``"loop"`` (the loop, on its deadlines); ``None`` in lockstep (the loop, no deadline)
    sync_clock: str | None = None

    def to_json(self) -> dict[str, Any]:
        document = {key: getattr(self, key) for key in self.__dataclass_fields__}
        document["mode"] = str(self.mode)  # the plain string value, as the JSON document has always had it
        document["realtime"] = self.realtime.to_json() if self.realtime is not None else None
        return document


@dataclass(frozen=True, slots=True)
class CycleTiming:
    """One cycle of a block, as :meth:`CycleBlock.records` gives it (``None``: not measured).

    ``sync_time`` and ``deadline`` are ``perf_counter`` seconds; the durations are microseconds. ``sample`` is the
    cycle's index within its block (the trial's sample for ``phase == "trial"``).
    """

    cycle: int
    trial: int
    phase: str
    sample: int
    sync_time: float
    deadline: float | None
    lateness_us: float | None
    feedback_latency_us: float | None
    compute_us: float | None
    skipped_deadlines: int
    late_feedback: bool
    missing_feedback: bool
    missed: bool


@dataclass(frozen=True)
class CycleBlock:
    """A finished block of cycles (:meth:`TimingRecorder.finish_block`'s rows, columns
    :attr:`TimingRecorder.FIELDS`) as the loop hands it to its log: the cycle of row ``k`` is ``first_cycle + k``.

    The log takes its columns whole (:attr:`sync_time`, ...); :meth:`records` is the one definition of a cycle's
    record, for a reader that wants them one by one.
    """

    rows: np.ndarray
    first_cycle: int
    phase: str
    trial: int

    def __len__(self) -> int:
        return int(self.rows.shape[0])

    @property
    def sync_time(self) -> np.ndarray:
        """``perf_counter`` seconds of each cycle's SYNC."""
        return self.rows[:, 0]

    @property
    def lateness_us(self) -> np.ndarray:
        """Each SYNC's lateness after its deadline, microseconds (NaN: not measured)."""
        return self.rows[:, 2] * 1e6

    @property
    def feedback_latency_us(self) -> np.ndarray:
        """SYNC to feedback, microseconds (NaN: none came)."""
        return self.rows[:, 3] * 1e6

    @property
    def missing_feedback(self) -> np.ndarray:
        """Cycles without their feedback (bool)."""
        return self.rows[:, 7] != 0.0

    @property
    def missed(self) -> np.ndarray:
        """Cycles whose command missed its deadline (bool)."""
        return self.rows[:, 8] != 0.0

    def messages(self, previous: float | None) -> tuple[TimingBlock, float | None]:
        """The block's ``/timing`` messages, as columns, and its last SYNC's time (the next block's ``previous``).

        ``previous``: the SYNC time before the block, from which its first ``period_us`` is measured (``None``: the
        run's first block, whose first period is 0). A lateness not measured is 0; a feedback latency not measured
        stays NaN (``null``).
        """
        sync = self.sync_time
        if not len(sync):
            empty = np.empty(0)
            return TimingBlock(self.first_cycle, self.trial, empty, empty, empty, empty.astype(bool),
                               empty.astype(bool)), previous
        before = np.empty_like(sync)
        before[1:] = sync[:-1]
        before[0] = sync[0] if previous is None else previous
        period_us = (sync - before) * 1e6
        if previous is None:
            period_us[0] = 0.0
        lateness = self.lateness_us
        lateness[np.isnan(lateness)] = 0.0  # a fresh array (the property computes it)
        block = TimingBlock(self.first_cycle, self.trial, lateness, period_us, self.feedback_latency_us,
                            self.missed, self.missing_feedback)
        return block, float(sync[-1])

    def records(self) -> Iterator[CycleTiming]:
        """The block's cycles, one record each."""
        first_cycle, phase, trial = self.first_cycle, self.phase, self.trial
        for offset, row in enumerate(self.rows):
            yield CycleTiming(
                cycle=first_cycle + offset,
                trial=trial,
                phase=phase,
                sample=offset,
                sync_time=float(row[0]),
                deadline=None if math.isnan(row[1]) else float(row[1]),
                lateness_us=None if math.isnan(row[2]) else float(row[2] * 1e6),
                feedback_latency_us=None if math.isnan(row[3]) else float(row[3] * 1e6),
                compute_us=None if math.isnan(row[4]) else float(row[4] * 1e6),
                skipped_deadlines=int(row[5]),
                late_feedback=bool(row[6]),
                missing_feedback=bool(row[7]),
                missed=bool(row[8]),
            )


class StreamingDistribution:
    """The distribution of one timing quantity (seconds) in bounded memory, for runs of any length.

    The first :attr:`EXACT_LIMIT` finite values are kept exactly (percentiles as :func:`numpy.percentile`); past
    that they are folded into a histogram of logarithmic bins, each :attr:`RELATIVE_PRECISION` wide, for negative and
    positive values alike (values below 1 ns in magnitude count as zero). Percentiles are then the nearest-rank bin's
    centre, within that relative precision; count and maximum stay exact. Why: keeping every cycle's row made the
    bench's memory grow without bound (about 88 bytes a cycle: GiBs in an 8-hour 1 kHz run).
    """

    EXACT_LIMIT = 1 << 14
    RELATIVE_PRECISION = 1e-3
    _FLOOR = 1e-9
    _CEILING = 1e3
    _BINS = math.ceil(math.log(_CEILING / _FLOOR) / math.log1p(RELATIVE_PRECISION)) + 1

    def __init__(self) -> None:
        # Both arrays are written through at construction (np.full, not np.empty/np.zeros): the pages are then
        # resident from the start, so a long run's memory does not creep up as new bins are first touched.
        self._exact = np.full(self.EXACT_LIMIT, np.nan)
        self._n_exact = 0
        self._counts = np.full(2 * self._BINS + 1, 0, dtype=np.int64)  # [negative bins reversed, zero, positive]
        self._folded = False
        self.count = 0
        self.maximum = -math.inf

    def add(self, values: np.ndarray) -> None:
        """Add the finite entries of ``values`` (called per block, off the hot path)."""
        finite = np.asarray(values, dtype=float)
        finite = finite[np.isfinite(finite)]
        if finite.size == 0:
            return
        self.count += int(finite.size)
        self.maximum = max(self.maximum, float(finite.max()))
        if not self._folded and self._n_exact + finite.size <= self.EXACT_LIMIT:
            self._exact[self._n_exact : self._n_exact + finite.size] = finite
            self._n_exact += int(finite.size)
            return
        if not self._folded:
            self._folded = True
            self._fold(self._exact[: self._n_exact])
            self._n_exact = 0
        self._fold(finite)

    def percentile(self, q: float) -> float | None:
        """The ``q``-th percentile (0..100), or None without values."""
        if self.count == 0:
            return None
        if not self._folded:
            return float(np.percentile(self._exact[: self._n_exact], q))
        rank = max(1, math.ceil(q / 100.0 * self.count))
        index = int(np.searchsorted(np.cumsum(self._counts), rank))
        offset = index - self._BINS
        if offset == 0:
            return 0.0
        centre = self._FLOOR * (1.0 + self.RELATIVE_PRECISION) ** (abs(offset) - 0.5)
        return math.copysign(centre, offset)

    def _fold(self, values: np.ndarray) -> None:
        magnitude = np.clip(np.abs(values), self._FLOOR, self._CEILING)
        bins = 1 + np.floor(np.log(magnitude / self._FLOOR) / math.log1p(self.RELATIVE_PRECISION)).astype(np.int64)
        bins = np.minimum(bins, self._BINS)
        bins[np.abs(values) < self._FLOOR] = 0
        np.add.at(self._counts, self._BINS + np.where(values < 0, -bins, bins), 1)


class TimingRecorder:
    """Per-cycle timing measurements in preallocated arrays, one block per phase (a trial or a settling phase).

    The hot path calls :meth:`record` (writes into arrays, no allocation); :meth:`finish_block` closes the
    block (:class:`CycleBlock`), which the log turns into ``/timing`` messages off the hot path.

    Per cycle: the SYNC send time ``sync_time`` (perf_counter seconds), the deadline (NaN in lockstep), the
    release lateness, the feedback latency (SYNC to TPDO handed to the loop), the cycle's compute time (feedback
    in to command sent), how many deadline slots were skipped before it, whether the feedback was late (after half
    a period) or missing, and whether the cycle missed its deadline (command after the next slot).
    """

    FIELDS = (
        "sync_time", "deadline", "lateness", "feedback_latency", "compute_time", "skipped", "late", "missing", "missed"
    )

    def __init__(self, mode: TimingMode, period: float) -> None:
        self.mode = mode
        self.period = period
        # bounded: a run of any length keeps these four distributions and three counters, not its rows
        self._lateness = StreamingDistribution()
        self._cycle_time = StreamingDistribution()
        self._compute = StreamingDistribution()
        self._cycles = 0
        self._late_feedback = 0
        self._missing_feedback = 0
        self._missed = 0
        self._skipped = 0
        self._current: np.ndarray = np.empty((0, len(self.FIELDS)))
        self._count = 0
        self.phase = ""  # the current block's phase and trial
        self.trial = 0
        self.sync_clock: str | None = None  # TimingSummary.sync_clock, set by the loop
        self._started_at = time.perf_counter()

    def start(self) -> None:
        """Start the clock of ``cycles_per_second`` now, as the loop's first cycle begins.

        Why not at construction: the bench builds its loop before it commissions and enables the drive (SDO writes,
        the CiA 402 walk: 20 to 27 ms of a 0.45 s lockstep run, which are not cycles).
        """
        self._started_at = time.perf_counter()

    def begin_block(self, capacity: int, *, phase: str, trial: int) -> None:
        """Preallocate room for ``capacity`` cycles of the next phase (``"trial"`` or ``"settle"``)."""
        self._current = np.full((max(capacity, 0), len(self.FIELDS)), np.nan)
        self._count = 0
        self.phase = phase
        self.trial = trial

    def record(
        self,
        sync_time: float,
        deadline: float,
        lateness: float,
        feedback_latency: float,
        compute_time: float,
        skipped: int,
        late: bool,
        missing: bool,
        missed: bool,
    ) -> None:
        """Store one cycle (hot path: writes into the preallocated row; grows only past the capacity)."""
        if self._count >= self._current.shape[0]:
            grown = np.full((max(2 * self._current.shape[0], 64), len(self.FIELDS)), np.nan)
            grown[: self._count] = self._current[: self._count]
            self._current = grown
        row = self._current[self._count]
        row[0] = sync_time
        row[1] = deadline
        row[2] = lateness
        row[3] = feedback_latency
        row[4] = compute_time
        row[5] = skipped
        row[6] = 1.0 if late else 0.0
        row[7] = 1.0 if missing else 0.0
        row[8] = 1.0 if missed else 0.0
        self._count += 1

    def record_unmeasured(self, count: int) -> None:
        """Store ``count`` cycles that ran without per-cycle timing (a whole trial in one call): every measurement
        NaN, no flag set."""
        if self._count + count > self._current.shape[0]:
            grown = np.full((self._count + count, len(self.FIELDS)), np.nan)
            grown[: self._count] = self._current[: self._count]
            self._current = grown
        rows = self._current[self._count : self._count + count]
        counts = self.FIELDS.index("skipped")  # the measured times come first, then counts and flags
        rows[:, :counts] = np.nan
        rows[:, counts:] = 0.0
        self._count += count

    def finish_block(self) -> np.ndarray:
        """Close the current block; returns its rows (columns :attr:`FIELDS`)."""
        block = self._current[: self._count].copy()
        self._lateness.add(block[:, 2])
        self._cycle_time.add(np.diff(block[:, 0]))  # intervals between consecutive SYNCs within the block
        self._compute.add(block[:, 4])
        self._cycles += int(block.shape[0])
        self._late_feedback += int(np.sum(block[:, 6]))
        self._missing_feedback += int(np.sum(block[:, 7]))
        self._missed += int(np.sum(block[:, 8]))
        self._skipped += int(np.sum(block[:, 5]))
        self._current = np.empty((0, len(self.FIELDS)))
        self._count = 0
        return block

    def summary(self) -> TimingSummary:
        """Statistics over every finished block (see :class:`StreamingDistribution` for their precision)."""
        cycles = self._cycles
        elapsed = time.perf_counter() - self._started_at
        jitter, cycle_time, compute = (_in_us(d) for d in (self._lateness, self._cycle_time, self._compute))
        return TimingSummary(
            mode=self.mode,
            period=self.period,
            cycles=cycles,
            missed_deadlines=self._missed,
            skipped_deadlines=self._skipped,
            late_feedback=self._late_feedback,
            missing_feedback=self._missing_feedback,
            jitter_p50_us=jitter[0],
            jitter_p99_us=jitter[1],
            jitter_max_us=jitter[2],
            cycle_time_p50_us=cycle_time[0],
            cycle_time_p99_us=cycle_time[1],
            cycle_time_max_us=cycle_time[2],
            compute_p50_us=compute[0],
            compute_p99_us=compute[1],
            cycles_per_second=cycles / elapsed if elapsed > 0 and cycles else None,
            sync_clock=self.sync_clock,
        )


def _in_us(distribution: StreamingDistribution) -> tuple[float | None, float | None, float | None]:
    """p50, p99 and max of ``distribution`` in microseconds (None without values)."""
    if distribution.count == 0:
        return None, None, None
    p50, p99 = distribution.percentile(50.0), distribution.percentile(99.0)
    assert p50 is not None and p99 is not None
    return p50 * 1e6, p99 * 1e6, distribution.maximum * 1e6

"""The realtime trial loop's deadline accounting on a fake clock: missed deadlines, skipped slots, lost feedback.

Every time here is the fake clock's, so the verdicts are exact and no test depends on the machine's speed. The
truths are written from the rule of :mod:`foilc_hil.loop.scheduler`, cycle by cycle, not taken from a run.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from drivers.cia402 import State402
from drivers.drive import Feedback
from foilc_hil.errors import FeedbackTimeoutError
from foilc_hil.loop.bench import COMMAND_MARGIN_FRACTION, TrialLoop
from foilc_hil.loop.interfaces import BenchOutcome
from foilc_hil.loop.scheduler import CycleTiming, TimingSummary
from foilc_hil.loop.settings import LoopSettings
from plant_emulator.device import TimingMode

PERIOD = 0.001
FEEDBACK_LATENCY = 0.0001  # every answered SYNC: 0.1 ms


class FakeClock:
    """Advances by 1 us per reading (so the scheduler's spin ends) and by whatever is slept or scripted."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        self.now += 1e-6
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


class ScriptedDrive:
    """Answers SYNC ``k`` after :data:`FEEDBACK_LATENCY`, except the SYNCs in ``lost`` (never answered: the wait
    takes its whole bound); sending the command of SYNC ``k`` takes ``stalls[k]`` seconds (a host stall)."""

    bad_frames = 0

    def __init__(self, clock: FakeClock, *, lost: set[int], stalls: dict[int, float]) -> None:
        self.clock = clock
        self.lost = lost
        self.stalls = stalls
        self.count = 0
        self.timeouts: list[float] = []

    def sync(self) -> int:
        self.count += 1
        return self.count

    def wait_feedback(self, timeout: float) -> Feedback:
        self.timeouts.append(timeout)
        if self.count in self.lost:
            self.clock.now += timeout
            raise FeedbackTimeoutError(f"no TPDO set answered SYNC {self.count}")
        self.clock.now += FEEDBACK_LATENCY
        return Feedback(self.count, 0x27, State402.OPERATION_ENABLED, 0.0, 0.0, 0, 0.0)

    def set_target(self, value: float) -> float:
        self.clock.now += self.stalls.get(self.count, 0.0)
        return value

    def quick_stop(self) -> None:
        raise AssertionError("nothing in these scripts aborts")


class ZeroLaw:
    """Commands zero; the loop's timing, not learning, is under test."""

    feedforward = np.zeros(10)

    def begin_trial(self) -> None:
        pass

    def command(self, t: int, output: np.ndarray) -> np.ndarray:
        return np.zeros(1)

    def end_trial(self, reference: np.ndarray, output: np.ndarray, applied: np.ndarray | None = None) -> Any:
        from foilc_hil.laws.learning import TrialUpdate
        from foilc_hil.metrics import TrialMetrics

        metrics = TrialMetrics(trial=1, sse=1.0, rmse=0.0, max_abs_error=0.0, rmse_learnable=0.0,
                               max_abs_error_learnable=0.0)
        return TrialUpdate(trial=1, error=reference - output, E=reference - output, metrics=metrics)

    def restore(self, feedforward: np.ndarray) -> None:
        pass


class Sink:
    """Keeps the /timing records the loop logs."""

    def __init__(self) -> None:
        self.records: list[CycleTiming] = []

    def trial_finished(self, record: Any) -> None:
        pass

    def timing(self, block: Any) -> None:
        self.records.extend(block.records())


def _timing(outcome: BenchOutcome) -> TimingSummary:
    assert outcome.timing is not None
    return outcome.timing


def _deadlines(records: list[CycleTiming]) -> list[float]:
    deadlines = [r.deadline for r in records]
    assert all(d is not None for d in deadlines)
    return [float(d or 0.0) for d in deadlines]


def _run(lost: set[int], stalls: dict[int, float]) -> tuple[BenchOutcome, ScriptedDrive, Sink]:
    clock = FakeClock()
    drive = ScriptedDrive(clock, lost=lost, stalls=stalls)
    sink = Sink()
    settings = LoopSettings(sample_time=PERIOD, mode=TimingMode.REALTIME, settle_between_trials=False,
                            max_lost_feedback=2)
    loop = TrialLoop(drive, ZeroLaw(), np.zeros(10), None, settings, log=sink, clock=clock, sleep=clock.sleep)
    return loop.run(1), drive, sink


def test_a_stall_is_one_missed_deadline_and_its_passed_slots_are_skipped() -> None:
    # SYNC 6 (cycle 5, released at 5 ms): its command goes out at about 8.6 ms, after 6 ms -> cycle 5 missed its
    # deadline; the next cycle finds slots 6, 7 and 8 passed (8.6 ms >= 6 + 1 ms) and is released at 9 ms.
    outcome, _, sink = _run(lost=set(), stalls={6: 0.0035})
    timing = _timing(outcome)
    assert timing.cycles == 11
    assert timing.missed_deadlines == 1 <= timing.cycles
    assert timing.skipped_deadlines == 3
    assert [r.missed for r in sink.records] == [cycle == 5 for cycle in range(11)]
    assert [r.skipped_deadlines for r in sink.records] == [3 if cycle == 6 else 0 for cycle in range(11)]
    expected = [0, 1, 2, 3, 4, 5, 9, 10, 11, 12, 13]  # ms: no burst of catch-up SYNCs after the stall
    deadlines = _deadlines(sink.records)
    t0 = deadlines[0]
    assert [d - t0 for d in deadlines] == pytest.approx([k * PERIOD for k in expected])
    assert [r.sync_time - t0 for r in sink.records] == pytest.approx([k * PERIOD for k in expected], abs=2e-5)


def test_a_lost_feedback_ends_its_wait_before_the_next_deadline_and_misses_nothing() -> None:
    outcome, drive, sink = _run(lost={3, 8}, stalls={})
    timing = _timing(outcome)
    assert timing.missing_feedback == 2 and outcome.faults.lost_feedback == 2
    assert timing.missed_deadlines == 0 and timing.skipped_deadlines == 0
    # the wait of every SYNC ended COMMAND_MARGIN_FRACTION of a period before the next deadline
    for record, deadline, timeout in zip(sink.records, _deadlines(sink.records), drive.timeouts, strict=True):
        assert record.sync_time + timeout == pytest.approx(deadline + (1 - COMMAND_MARGIN_FRACTION) * PERIOD)
    assert [r.missing_feedback for r in sink.records] == [r.cycle in (2, 7) for r in sink.records]
    assert all(r.feedback_latency_us is None for r in sink.records if r.missing_feedback)


def test_counts_of_the_log_agree_with_the_summary() -> None:
    outcome, _, sink = _run(lost={2}, stalls={4: 0.0012, 9: 0.0025})
    timing = _timing(outcome)
    assert len(sink.records) == timing.cycles
    assert [r.cycle for r in sink.records] == list(range(timing.cycles))
    assert sum(r.missed for r in sink.records) == timing.missed_deadlines == 2
    assert sum(r.skipped_deadlines for r in sink.records) == timing.skipped_deadlines
    assert sum(r.missing_feedback for r in sink.records) == timing.missing_feedback == 1
    assert max(r.lateness_us for r in sink.records if r.lateness_us is not None) == pytest.approx(timing.jitter_max_us)


def test_lockstep_has_no_deadlines_to_miss() -> None:
    clock = FakeClock()
    drive = ScriptedDrive(clock, lost=set(), stalls={3: 0.5})
    settings = LoopSettings(sample_time=PERIOD, settle_between_trials=False)
    timing = _timing(TrialLoop(drive, ZeroLaw(), np.zeros(10), None, settings, clock=clock, sleep=clock.sleep).run(1))
    assert timing.missed_deadlines == 0 and timing.skipped_deadlines == 0
    assert timing.jitter_p99_us is None and timing.realtime is None
    assert all(math.isclose(t, settings.feedback_timeout) for t in drive.timeouts)


def _settle_then_trial(stalls: dict[int, float]) -> list[CycleTiming]:
    """Trial 1 after a settle phase of three at-rest cycles (nothing pending before the first trial: its length
    depends on the rule alone); the records of the settle phase before it and of the trial."""
    clock = FakeClock()
    drive = ScriptedDrive(clock, lost=set(), stalls=stalls)
    sink = Sink()
    settings = LoopSettings(sample_time=PERIOD, mode=TimingMode.REALTIME, settle_time=3 * PERIOD,
                            max_lost_feedback=2)
    TrialLoop(drive, ZeroLaw(), np.zeros(10), None, settings, log=sink, clock=clock, sleep=clock.sleep).run(1)
    return [r for r in sink.records if r.trial == 1 and r.phase in ("settle", "trial")]


def test_a_trial_never_starts_on_the_sync_its_last_settle_command_missed() -> None:
    # a settle command that missed its SYNC lands in the next SYNC's window: were that the trial's first, the
    # record and replay --verify would count it as the trial's first RPDO. The phase runs one cycle more.
    on_time = _settle_then_trial({})
    assert [r.phase for r in on_time] == ["settle"] * 3 + ["trial"] * 11
    late = _settle_then_trial({3: 1.5 * PERIOD})  # SYNC 3: the third settle cycle's command misses
    assert [r.phase for r in late] == ["settle"] * 4 + ["trial"] * 11
    assert [r.missed for r in late[:4]] == [False, False, True, False]

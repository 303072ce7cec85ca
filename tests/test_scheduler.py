"""DeadlineScheduler policy on a fake clock, and TimingRecorder statistics against numpy recomputation."""

from __future__ import annotations

import numpy as np
import pytest

from foilc_hil.loop.scheduler import DeadlineScheduler, TimingRecorder
from plant_emulator.device import TimingMode


class FakeClock:
    """A clock that advances only when slept on, or by a fixed tick per reading (models spinning)."""

    def __init__(self, tick: float = 0.0) -> None:
        self.now = 0.0
        self.tick = tick
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        self.now += self.tick
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds


def test_on_time_cycles_release_at_absolute_deadlines() -> None:
    clock = FakeClock(tick=1e-6)
    scheduler = DeadlineScheduler(0.001, spin_margin=0.0002, clock=clock, sleep=clock.sleep)
    scheduler.start(t0=0.0)
    releases = []
    for _ in range(5):
        deadline, lateness, skipped = scheduler.wait()
        releases.append(deadline)
        assert skipped == 0
        assert 0.0 <= lateness < 5e-6
        clock.now += 0.0003  # the cycle's work
    assert releases == pytest.approx([0.0, 0.001, 0.002, 0.003, 0.004])
    assert scheduler.missed_deadlines == 0
    # it slept up to the spin margin before each deadline after the first, then spun
    assert all(s == pytest.approx(0.001 - 0.0003 - 0.0002, abs=5e-6) for s in clock.sleeps[1:])


def test_late_within_the_slot_is_lateness_not_a_miss() -> None:
    clock = FakeClock()
    scheduler = DeadlineScheduler(0.001, spin_margin=0.0, clock=clock, sleep=clock.sleep)
    scheduler.start(t0=0.0)
    scheduler.wait()
    clock.now = 0.0016  # overran deadline 1 (0.001) by 0.6 ms, before deadline 2
    deadline, lateness, skipped = scheduler.wait()
    assert deadline == pytest.approx(0.001)
    assert lateness == pytest.approx(0.0006)
    assert skipped == 0
    assert scheduler.missed_deadlines == 0


def test_overrun_skips_passed_deadlines_and_counts_them() -> None:
    clock = FakeClock()
    scheduler = DeadlineScheduler(0.001, spin_margin=0.0, clock=clock, sleep=clock.sleep)
    scheduler.start(t0=0.0)
    scheduler.wait()  # deadline 0
    clock.now = 0.0035  # deadlines 1, 2 and 3 passed
    deadline, lateness, skipped = scheduler.wait()
    assert skipped == 3
    assert deadline == pytest.approx(0.004)  # the next deadline ahead, no catch-up burst
    assert lateness == pytest.approx(0.0)
    assert scheduler.missed_deadlines == 3
    deadline, _, skipped = scheduler.wait()
    assert deadline == pytest.approx(0.005)
    assert skipped == 0


def test_invalid_period_is_refused() -> None:
    with pytest.raises(ValueError, match="period"):
        DeadlineScheduler(0.0)


def test_recorder_summary_matches_numpy() -> None:
    rng = np.random.default_rng(3)
    recorder = TimingRecorder(TimingMode.REALTIME, 0.001)
    lateness = rng.uniform(0, 1e-4, size=300)
    recorder.begin_block(10, phase="trial", trial=1)  # grows past its capacity
    for i, late in enumerate(lateness):
        recorder.record(i * 0.001 + late, i * 0.001, late, 2e-4, 1e-5, 0, i % 50 == 0, i == 7)
    block = recorder.finish_block()
    summary = recorder.summary(missed_deadlines=4)
    assert block.shape == (300, len(TimingRecorder.FIELDS))
    assert summary.cycles == 300
    assert summary.missed_deadlines == 4
    assert summary.late_feedback == 6
    assert summary.missing_feedback == 1
    assert summary.jitter_p99_us == pytest.approx(np.percentile(lateness, 99) * 1e6)
    assert summary.jitter_max_us == pytest.approx(lateness.max() * 1e6)
    intervals = np.diff(np.arange(300) * 0.001 + lateness)
    assert summary.cycle_time_p50_us == pytest.approx(np.median(intervals) * 1e6)
    records = list(recorder.records(block, first_cycle=100))
    assert records[7].missing_feedback is True
    assert records[7].cycle == 107
    assert records[0].lateness_us == pytest.approx(lateness[0] * 1e6)

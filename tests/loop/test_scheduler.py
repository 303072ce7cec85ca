"""DeadlineScheduler policy on a fake clock, and TimingRecorder statistics against numpy recomputation."""

from __future__ import annotations

import numpy as np
import pytest

from foilc_hil.loop.scheduler import CycleBlock, DeadlineScheduler, StreamingDistribution, TimingRecorder
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
    assert scheduler.skipped_deadlines == 0
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
    assert scheduler.skipped_deadlines == 0


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
    assert scheduler.skipped_deadlines == 3
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
        recorder.record(i * 0.001 + late, i * 0.001, late, 2e-4, 1e-5, i % 100 == 1, i % 50 == 0, i == 7, i % 75 == 2)
    block = recorder.finish_block()
    summary = recorder.summary()
    assert block.shape == (300, len(TimingRecorder.FIELDS))
    assert summary.cycles == 300
    assert summary.missed_deadlines == 4  # cycles 2, 77, 152, 227
    assert summary.skipped_deadlines == 3  # cycles 1, 101, 201
    assert summary.late_feedback == 6
    assert summary.missing_feedback == 1
    assert summary.jitter_p99_us == pytest.approx(np.percentile(lateness, 99) * 1e6)
    assert summary.jitter_max_us == pytest.approx(lateness.max() * 1e6)
    intervals = np.diff(np.arange(300) * 0.001 + lateness)
    assert summary.cycle_time_p50_us == pytest.approx(np.median(intervals) * 1e6)
    records = list(CycleBlock(block, 100, "trial", 1).records())
    assert records[7].missing_feedback is True
    assert records[7].cycle == 107
    assert [r.cycle - 100 for r in records if r.missed] == [2, 77, 152, 227]
    assert records[0].lateness_us == pytest.approx(lateness[0] * 1e6)


def test_cycles_per_second_counts_from_the_loops_start_not_the_recorders_construction(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The bench builds its loop (and recorder) before it commissions and enables the drive: that time is not
    cycling, so the rate's clock starts at :meth:`TimingRecorder.start`."""
    clock = FakeClock()
    monkeypatch.setattr("foilc_hil.loop.scheduler.time.perf_counter", clock)
    recorder = TimingRecorder(TimingMode.LOCKSTEP, 0.001)
    clock.sleep(5.0)  # commissioning and the enable
    recorder.start()
    recorder.begin_block(100, phase="trial", trial=1)
    for i in range(100):
        recorder.record(5.0 + i * 0.002, float("nan"), float("nan"), 1e-4, 1e-5, 0, False, False, False)
    recorder.finish_block()
    clock.sleep(0.2)  # 100 cycles in 0.2 s
    assert recorder.summary().cycles_per_second == pytest.approx(500.0)


def test_streaming_distribution_is_exact_then_within_its_precision() -> None:
    rng = np.random.default_rng(11)
    small = rng.uniform(-1e-5, 2e-4, size=1000)
    distribution = StreamingDistribution()
    distribution.add(small)
    for q in (1.0, 50.0, 99.0):
        assert distribution.percentile(q) == np.percentile(small, q)  # exact while it fits
    large = np.concatenate([small, rng.lognormal(-9.0, 1.0, size=60_000), -rng.lognormal(-12.0, 0.5, size=2000)])
    distribution.add(large[small.size :])
    assert distribution.count == large.size and distribution.maximum == large.max()
    for q in (0.5, 1.0, 10.0, 50.0, 90.0, 99.0, 99.9):
        truth = float(np.percentile(large, q, method="inverted_cdf"))  # nearest rank, as the histogram defines it
        found = distribution.percentile(q)
        assert found is not None
        assert abs(found - truth) <= StreamingDistribution.RELATIVE_PRECISION * abs(truth) + 1e-12, (q, found, truth)


def test_timing_memory_stays_bounded_over_a_long_run() -> None:
    """The soak leak: the recorder must not keep a row per cycle (88 bytes a cycle before)."""
    recorder = TimingRecorder(TimingMode.REALTIME, 0.001)

    def size(value: object) -> int:
        if isinstance(value, np.ndarray):
            return int(value.nbytes)
        if isinstance(value, (list, tuple)):
            return 8 * len(value) + sum(size(item) for item in value)
        if isinstance(value, StreamingDistribution):
            return sum(size(item) for item in vars(value).values())
        return 0

    def retained() -> int:  # everything the recorder holds between blocks
        return sum(size(value) for value in vars(recorder).values())

    def run_blocks(blocks: int) -> None:
        for trial in range(blocks):
            recorder.begin_block(1000, phase="trial", trial=trial)
            for i in range(1000):
                recorder.record(i * 1e-3, i * 1e-3, 1e-5 + i * 1e-9, 2e-4, 1e-5, 0, False, False, False)
            recorder.finish_block()

    run_blocks(40)  # past the exact limit: every distribution has switched to its histogram
    after_warm_up = retained()
    run_blocks(40)
    assert retained() == after_warm_up
    assert recorder.summary().cycles == 80_000


def _messages_one_by_one(block: CycleBlock, previous: float | None) -> list[dict[str, object]]:
    """The /timing documents as the sink built them record by record before the columns (the definition: the period
    from the previous SYNC, 0 for the run's first; a lateness not measured is 0; a latency not measured is null)."""
    from foilc_hil.io.records import TimingRecord

    documents = []
    for record in block.records():
        period_us = (record.sync_time - previous) * 1e6 if previous is not None else 0.0
        previous = record.sync_time
        lateness = record.lateness_us if record.lateness_us is not None else 0.0
        documents.append(TimingRecord(record.cycle, record.trial, record.sample, lateness, period_us,
                                      record.feedback_latency_us, record.missed, record.missing_feedback).to_json())
    return documents


@pytest.mark.parametrize("previous", [None, 12.3456789], ids=["first-block", "after-a-block"])
def test_a_blocks_messages_as_columns_are_its_records_bit_for_bit(previous: float | None) -> None:
    rng = np.random.default_rng(5)
    n = 257
    rows = np.column_stack([
        12.5 + np.cumsum(rng.uniform(0.0009, 0.0011, n)),  # sync time
        np.full(n, np.nan), rng.uniform(0, 3e-4, n), rng.uniform(5e-5, 9e-4, n), rng.uniform(1e-5, 3e-4, n),
        rng.integers(0, 2, n), rng.integers(0, 2, n), rng.integers(0, 2, n), rng.integers(0, 2, n),
    ]).astype(float)
    rows[::7, 2] = np.nan  # lateness not measured
    rows[rows[:, 7] == 1.0, 3] = np.nan  # no feedback: no latency
    block = CycleBlock(rows, 4000, "settle", 3)
    messages, last = block.messages(previous)
    got = [record.to_json() for record in messages.records()]
    assert got == _messages_one_by_one(block, previous)
    assert [repr(d["period_us"]) for d in got] == [repr(d["period_us"]) for d in _messages_one_by_one(block, previous)]
    assert last == rows[-1, 0]
    assert any(d["feedback_latency_us"] is None for d in got) and any(d["lateness_us"] == 0.0 for d in got)
    empty, same = CycleBlock(rows[:0], 0, "trial", 1).messages(previous)
    assert list(empty.records()) == [] and same == previous

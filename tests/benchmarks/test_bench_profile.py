"""The lockstep profile's stage timer books exclusive time; its table shows every stage before and after."""

from __future__ import annotations

import threading

from benchmarks.bench_profile import STAGES, StageTimer, markdown


class _Ticks:
    """A clock that advances one second per reading: every interval is a count of readings, known exactly."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        self.now += 1.0
        return self.now


def test_a_stage_books_its_own_time_not_its_callees() -> None:
    timer = StageTimer(clock=_Ticks())
    inner = timer.wrap("inner", lambda: None)

    def outer_body() -> None:
        inner()
        inner()

    outer = timer.wrap("outer", outer_body)
    outer()
    # inner: each call reads the clock twice, one second apart -> 1 s each. outer: from its first reading to its
    # last are 5 readings (its own start, 2 per inner call, its end) = 5 s, minus the 2 s of inner -> 3 s
    assert timer.seconds == {"inner": 2.0, "outer": 3.0}


def test_other_threads_run_untimed() -> None:
    timer = StageTimer(clock=_Ticks())
    results: list[int] = []
    timed = timer.wrap("stage", lambda: results.append(1))
    worker = threading.Thread(target=timed)
    worker.start()
    worker.join()
    assert results == [1] and timer.seconds == {"stage": 0.0}


def test_the_table_has_every_stage_and_both_sides() -> None:
    stages = [stage for stage, _ in STAGES]
    side = {"stage_us": {stage: float(k) for k, stage in enumerate(stages)}, "timed_cycle_us": 99.0,
            "cycle_us": 50.0, "cycle_cpu_us": 40.0}
    lines = markdown({"stages": stages, "before": side, "after": None})
    rows = [line for line in lines if line.startswith("| ") and not line.startswith("| stage")]
    assert len(rows) == len(stages) + 3
    assert rows[3] == f"| {stages[3]} | 3.0 | - |"  # before filled, after absent: shown as such
    assert rows[-1].endswith("| 40.0 | - |")

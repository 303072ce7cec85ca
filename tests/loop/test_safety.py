"""Bench safety logic without CAN: clamping, watchdog, divergence guard, NaN guard, signal flag."""

from __future__ import annotations

import math
import os
import signal
from typing import Any

import numpy as np
import pytest

from foilc_hil.errors import FeedbackTimeoutError, LearningDivergedError
from foilc_hil.loop.safety import CommandLimiter, DivergenceGuard, FeedbackWatchdog, StopRequest, require_finite


def test_limiter_clamps_and_counts() -> None:
    limiter = CommandLimiter.symmetric(300.0, u_max=250.0)  # drive: +-300 plant units; plant saturates at 250
    assert (limiter.lower, limiter.upper) == (-300.0, 250.0)
    assert limiter.clamp(100.0) == 100.0
    assert limiter.clamp(1e6) == 250.0
    assert limiter.clamp(-1e6) == -300.0
    assert limiter.clamp(math.inf) == 250.0
    assert limiter.clamped_count == 3


def test_limiter_refuses_nan_and_bad_limits() -> None:
    limiter = CommandLimiter(-1.0, 1.0)
    with pytest.raises(LearningDivergedError, match="NaN"):
        limiter.clamp(float("nan"))
    with pytest.raises(ValueError, match="below"):
        CommandLimiter(1.0, 1.0)


def test_watchdog_tolerates_max_lost_in_a_row_then_trips() -> None:
    watchdog = FeedbackWatchdog(0.010, 2)
    assert watchdog.timeout == pytest.approx(0.010)
    assert watchdog.lost(40) is None and watchdog.lost(41) is None
    watchdog.answered()  # an answered SYNC ends the run of losses
    assert watchdog.lost(43) is None and watchdog.lost(44) is None
    assert not watchdog.tripped
    error = watchdog.lost(45, FeedbackTimeoutError("no TPDO set answered SYNC 45"))
    assert isinstance(error, FeedbackTimeoutError)
    assert watchdog.tripped and watchdog.total == 5
    assert "3 consecutive SYNCs" in str(error) and "cycle 45" in str(error) and "SYNC 45" in str(error)
    with pytest.raises(ValueError, match="lost"):
        FeedbackWatchdog(0.001, -1)
    with pytest.raises(ValueError, match="timeout"):
        FeedbackWatchdog(0.0, 1)


def test_watchdog_with_no_tolerance_trips_at_the_first_loss() -> None:
    error = FeedbackWatchdog(0.1, 0).lost(7)
    assert error is not None and "1 consecutive SYNCs" in str(error)


def test_divergence_guard_keeps_best_feedforward() -> None:
    guard = DivergenceGuard(10.0)
    first = guard.check(1, 100.0, np.array([1.0, 2.0]))
    assert first.is_best and not first.diverged
    second = guard.check(2, 40.0, np.array([3.0, 4.0]))
    assert second.is_best
    third = guard.check(3, 399.0, np.array([5.0, 6.0]))  # worse, below 10 x 40
    assert not third.diverged and not third.is_best
    fourth = guard.check(4, 401.0, np.array([7.0, 8.0]))
    assert fourth.diverged
    assert "trial 4" in fourth.message and "trial 2" in fourth.message
    np.testing.assert_array_equal(guard.best_feedforward(), [3.0, 4.0])
    assert guard.check(5, math.nan, np.zeros(2)).diverged


def test_best_feedforward_is_a_copy_not_an_alias() -> None:
    guard = DivergenceGuard(2.0)
    feedforward = np.array([1.0])
    guard.check(1, 1.0, feedforward)
    feedforward[0] = 99.0
    assert guard.best_feedforward()[0] == 1.0


def test_require_finite() -> None:
    require_finite(1.0, "output", 3)
    with pytest.raises(LearningDivergedError, match=r"non-finite output .* cycle 7"):
        require_finite(math.inf, "output", 7)


def test_stop_request_turns_sigint_into_a_flag_and_restores_the_handler() -> None:
    before = signal.getsignal(signal.SIGINT)
    with StopRequest() as stop:
        assert not stop.requested
        os.kill(os.getpid(), signal.SIGINT)
        assert stop.requested
        assert stop.signal_name == "SIGINT"
        # a second Ctrl-C or a SIGTERM during the stop is counted, never raised: the stop must finish and report
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.repeated == 2 and stop.signal_name == "SIGINT"
    assert signal.getsignal(signal.SIGINT) is before


# --- the trial loop's safety reactions, on an in-memory drive (no CAN) ------------------------------------------


class _InMemoryDrive:
    """ZOH first-order axis answering each SYNC at once, with the CAN loop's one-cycle command delay."""

    bad_frames = 0  # no bus: nothing to decode

    def __init__(self, *, output_override: float | None = None, fault_at_cycle: int | None = None) -> None:
        self.a_d = math.exp(-1.23 * 0.01)
        self.b_d = (1.0 - self.a_d) / 1.23 * 1.68
        self.y = 0.0
        self.active = 0.0
        self.pending = 0.0
        self.count = 0
        self.output_override = output_override
        self.fault_at_cycle = fault_at_cycle
        self.quick_stops = 0

    def sync(self) -> int:
        self.count += 1
        self.y = self.a_d * self.y + self.b_d * self.active
        self.active = self.pending
        return self.count

    def wait_feedback(self, timeout: float) -> Any:
        from drivers.cia402 import State402
        from drivers.drive import Feedback

        state = State402.OPERATION_ENABLED
        if self.fault_at_cycle is not None and self.count >= self.fault_at_cycle:
            state = State402.FAULT
        y = self.y if self.output_override is None or self.count < 50 else self.output_override
        return Feedback(self.count, 0x27, state, y, 0.0, 0, 0.0)

    def set_target(self, value: float) -> float:
        self.pending = value
        return value

    def quick_stop(self) -> None:
        self.quick_stops += 1


def _loop(drive: _InMemoryDrive, gain: float, factor: float = 3.0) -> Any:
    from foilc_hil.laws.learning import PType
    from foilc_hil.loop.bench import TrialLoop
    from foilc_hil.loop.settings import LoopSettings
    from tests.support.designs import p_type_design

    a_d, b_d = drive.a_d, drive.b_d
    A = np.array([[a_d, b_d], [0.0, 0.0]])
    B = np.array([[0.0], [1.0]])
    C = np.array([[1.0, 0.0]])
    law = PType(p_type_design(A, B, C, gain, sample_time=0.01, input_delay=1), 100)
    settings = LoopSettings(sample_time=0.01, settle_time=0.01, settle_tolerance=1e9, divergence_factor=factor)
    return TrialLoop(drive, law, np.ones(100), CommandLimiter(-1e9, 1e9), settings), law


def test_loop_stops_learning_that_diverges_and_restores_the_best_feedforward() -> None:
    drive = _InMemoryDrive()
    loop, law = _loop(drive, gain=-40.0)  # the wrong sign: every update makes the error grow
    outcome = loop.run(10)
    assert outcome.diverged
    assert "diverged" in (outcome.stopped or "")
    sse = [m.sse for m in outcome.trials]
    assert len(sse) < 10
    best = min(sse[:-1])
    assert sse[-1] > 3.0 * best  # the trial that tripped the guard
    assert all(later <= 3.0 * min(sse[: i + 1]) for i, later in enumerate(sse[1:-1], start=1))
    # the law now holds the feedforward that produced the best trial (trial 1: zeros)
    np.testing.assert_array_equal(law.feedforward, np.zeros_like(law.feedforward))
    assert drive.quick_stops == 1


def test_loop_aborts_on_non_finite_feedback_after_quick_stop() -> None:
    drive = _InMemoryDrive(output_override=math.nan)
    loop, _ = _loop(drive, gain=1.0)
    with pytest.raises(LearningDivergedError, match="non-finite drive feedback"):
        loop.run(3)
    assert drive.quick_stops == 1


def test_loop_aborts_when_the_drive_leaves_operation_enabled() -> None:
    from foilc_hil.errors import DriveFaultError

    drive = _InMemoryDrive(fault_at_cycle=150)
    loop, _ = _loop(drive, gain=1.0)
    with pytest.raises(DriveFaultError, match="FAULT"):
        loop.run(5)
    assert drive.quick_stops == 1
    assert len(loop.outcome.trials) == 1  # trial 1 (cycles 2..102) completed before the fault

"""Bench safety logic without CAN: clamping, watchdog, divergence guard, NaN guard, signal flag."""

from __future__ import annotations

import math
import os
import signal

import numpy as np
import pytest

from foilc_hil.errors import FeedbackTimeoutError, LearningDivergedError
from foilc_hil.safety import CommandLimiter, DivergenceGuard, FeedbackWatchdog, StopRequest, require_finite


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


def test_watchdog_timeout_and_message() -> None:
    watchdog = FeedbackWatchdog(5, 0.002)
    assert watchdog.timeout == pytest.approx(0.010)
    assert not watchdog.tripped
    error = watchdog.trip(42, FeedbackTimeoutError("no TPDO set answered SYNC 42"))
    assert isinstance(error, FeedbackTimeoutError)
    assert watchdog.tripped
    assert "5 cycles" in str(error) and "cycle 42" in str(error) and "SYNC 42" in str(error)
    with pytest.raises(ValueError, match="limit"):
        FeedbackWatchdog(0, 0.001)


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
        with pytest.raises(KeyboardInterrupt):  # a second Ctrl-C is not swallowed
            os.kill(os.getpid(), signal.SIGINT)
    assert signal.getsignal(signal.SIGINT) is before

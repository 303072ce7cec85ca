"""Safety logic of the bench, free of CAN so it is unit-tested on its own.

- :class:`CommandLimiter` clamps every command to the drive's limits (and the plant's actuator saturation).
- :class:`FeedbackWatchdog` counts SYNCs whose feedback did not arrive within the bound and trips after more than
  ``bench.faults.lost_feedback`` of them in a row.
- :class:`DivergenceGuard` compares each trial's SSE with the best so far and trips when it exceeds
  ``bench.divergence_factor`` times the best; it keeps the best trial's feedforward so the bench can restore it.
  It is the one divergence rule: ``foilc-hil run`` and ``foilc-hil simulate`` run the same loop and so the same
  guard. A disturbance that appears after the error has converged raises the SSE by a jump the factor must exceed.
- :func:`require_finite` is the NaN/inf guard for outputs and commands.
- :class:`StopRequest` turns SIGINT/SIGTERM into a flag the loop polls once per cycle, so a Ctrl-C never
  interrupts the loop between a SYNC and its command: the loop then quick-stops the drive itself.

What the bench does when one of them trips (quick stop, disable, close the log, exit code) is in
:mod:`foilc_hil.loop.bench`.
"""

from __future__ import annotations

import math
import signal
import threading
from collections.abc import Callable
from dataclasses import dataclass
from types import FrameType, TracebackType
from typing import Any

import numpy as np

from foilc_hil.errors import FeedbackTimeoutError, FoilcHilError, LearningDivergedError, RunInterruptedError

__all__ = [
    "CommandLimiter",
    "DivergenceGuard",
    "DivergenceVerdict",
    "FeedbackWatchdog",
    "StopRequest",
    "require_finite",
]


class CommandLimiter:
    """Clamp commands to ``[lower, upper]`` (plant units).

    Parameters
    ----------
    lower, upper
        The command limits. ``lower < upper`` and both finite.
    """

    def __init__(self, lower: float, upper: float) -> None:
        if not (math.isfinite(lower) and math.isfinite(upper)):
            raise ValueError(f"command limits must be finite, got [{lower!r}, {upper!r}]")
        if lower >= upper:
            raise ValueError(f"command lower limit {lower!r} must be below the upper limit {upper!r}")
        self.lower = float(lower)
        self.upper = float(upper)
        self.clamped_count = 0

    @classmethod
    def symmetric(cls, drive_limit: float, *, u_min: float | None = None, u_max: float | None = None) -> CommandLimiter:
        """Limits from the drive's ``|target| <= drive_limit`` (``drive.velocity_limit`` / ``torque_limit``, in plant
        units: the master clamps before scaling) intersected with the plant's saturation ``[u_min, u_max]``."""
        if not drive_limit > 0:
            raise ValueError(f"drive limit must be positive, got {drive_limit!r}")
        lower, upper = -float(drive_limit), float(drive_limit)
        if u_min is not None:
            lower = max(lower, u_min)
        if u_max is not None:
            upper = min(upper, u_max)
        return cls(lower, upper)

    def clamp(self, value: float) -> float:
        """``value`` clamped to the limits; counts how often clamping was active. NaN is refused, not clamped."""
        if value != value:  # NaN compares unequal; clamping it would hide a broken law
            raise LearningDivergedError("the learning law produced a NaN command")
        if value > self.upper:
            self.clamped_count += 1
            return self.upper
        if value < self.lower:
            self.clamped_count += 1
            return self.lower
        return value


class FeedbackWatchdog:
    """The feedback watchdog: counts SYNCs that went unanswered and trips after too many in a row.

    The bench waits for each SYNC's feedback at most :attr:`timeout`; a wait that expires is a *lost feedback*
    (:meth:`lost`): the law is given the last good feedback again (hold) and the cycle goes on. ``max_lost``
    consecutive lost feedbacks are tolerated; one more trips the watchdog. Any answered SYNC (:meth:`answered`)
    resets the run of losses.

    Parameters
    ----------
    timeout
        How long one SYNC's feedback may take, seconds: the period in realtime, ``bench.watchdog_cycles`` x the
        lockstep per-cycle allowance in lockstep (lockstep has no deadline, so a slow answer is not a lost one).
    max_lost
        ``bench.faults.lost_feedback`` (>= 0): consecutive lost feedbacks tolerated.
    """

    def __init__(self, timeout: float, max_lost: int) -> None:
        if not (timeout > 0 and math.isfinite(timeout)):
            raise ValueError(f"watchdog timeout must be positive, got {timeout!r}")
        if max_lost < 0:
            raise ValueError(f"tolerated lost feedbacks must be >= 0, got {max_lost!r}")
        self.timeout = float(timeout)
        self.max_lost = int(max_lost)
        self.consecutive = 0
        self.total = 0
        self.tripped = False

    def answered(self) -> None:
        """A SYNC was answered: the run of lost feedbacks ends."""
        self.consecutive = 0

    def lost(self, cycle: int, cause: BaseException | None = None) -> FeedbackTimeoutError | None:
        """Count a lost feedback at ``cycle``; the error to raise when that makes too many in a row, else ``None``."""
        self.consecutive += 1
        self.total += 1
        if self.consecutive <= self.max_lost:
            return None
        self.tripped = True
        detail = f": {cause}" if cause is not None and str(cause) else ""
        return FeedbackTimeoutError(
            f"watchdog: {self.consecutive} consecutive SYNCs without feedback from the drive (each waited "
            f"{self.timeout:.3g} s; bench.faults.lost_feedback tolerates {self.max_lost}) at cycle {cycle}; "
            f"quick stop commanded{detail}"
        )


@dataclass(frozen=True)
class DivergenceVerdict:
    """What :meth:`DivergenceGuard.check` found for one trial."""

    diverged: bool
    is_best: bool
    best_trial: int
    best_sse: float
    message: str = ""


class DivergenceGuard:
    """Stops learning that makes the error grow.

    A trial diverges when its SSE is not finite or exceeds ``factor`` times the best SSE seen so far. The guard
    keeps a copy of the feedforward that produced the best trial, for :meth:`best_feedforward`.

    Parameters
    ----------
    factor
        ``bench.divergence_factor`` (> 1).
    """

    def __init__(self, factor: float) -> None:
        if not factor > 1:
            raise ValueError(f"divergence factor must be > 1, got {factor!r}")
        self.factor = float(factor)
        self.best_sse = math.inf
        self.best_trial = 0
        self._best_feedforward: np.ndarray | None = None

    def check(self, trial: int, sse: float, feedforward_used: np.ndarray) -> DivergenceVerdict:
        """Judge trial ``trial`` whose SSE is ``sse``, run with ``feedforward_used`` (copied when best)."""
        if not math.isfinite(sse):
            return DivergenceVerdict(
                True, False, self.best_trial, self.best_sse, f"trial {trial}: the tracking error is not finite"
            )
        if self.best_trial and sse > self.factor * self.best_sse:
            return DivergenceVerdict(
                True,
                False,
                self.best_trial,
                self.best_sse,
                f"learning diverged: trial {trial} SSE {sse:.6g} > {self.factor:g} x best SSE {self.best_sse:.6g} "
                f"(trial {self.best_trial}); learning stopped, best feedforward restored",
            )
        is_best = sse < self.best_sse
        if is_best:
            self.best_sse = float(sse)
            self.best_trial = trial
            self._best_feedforward = np.array(feedforward_used, dtype=float, copy=True)
        return DivergenceVerdict(False, is_best, self.best_trial, self.best_sse)

    def best_feedforward(self) -> np.ndarray:
        """The feedforward of the best trial so far (a copy)."""
        if self._best_feedforward is None:
            raise LearningDivergedError("no trial has completed yet, there is no feedforward to restore")
        return self._best_feedforward.copy()


def require_finite(value: float, what: str, cycle: int) -> None:
    """NaN/inf guard. Raises :class:`LearningDivergedError` naming ``what`` (e.g. ``"command"``) and the cycle."""
    if not math.isfinite(value):
        raise LearningDivergedError(f"non-finite {what} ({value!r}) at cycle {cycle}")


class StopRequest:
    """SIGINT/SIGTERM as a flag polled by the loop (a context manager installing the handlers).

    Inside the context, the first SIGINT or SIGTERM sets :attr:`requested` (and :attr:`signal_name`); the loop
    checks it once per cycle and stops the drive itself. Later signals are counted (:attr:`repeated`) and change
    nothing: the stop already under way (the quick stop, the disable read back, the log closed) must finish and be
    reported. Why not the default behaviour for a second signal: a ``KeyboardInterrupt`` raised inside the stop lost
    its report (``drive_stop: null``, no trials) and, across processes, ended python-can's receive thread in a
    traceback. Every wait of the stop is bounded, so nothing wedges; ``SIGKILL`` still ends the process (the drive's
    heartbeat consumer then stops the axis). Outside the main thread signals cannot be handled; the context then
    does nothing and the flag can only be set with :meth:`request`.
    """

    def __init__(self) -> None:
        self.requested = False
        self.signal_name = ""
        self.failure: FoilcHilError | None = None
        self.repeated = 0  # signals after the first: counted, not acted on
        self._previous: dict[int, Callable[[int, FrameType | None], Any] | int | None] = {}

    def request(self, reason: str = "stop requested") -> None:
        """Ask the loop to stop (what the signal handler does)."""
        self.requested = True
        self.signal_name = reason

    def fail(self, error: FoilcHilError) -> None:
        """Stop the loop with ``error`` at its next cycle: a failure found on another thread (the log writer's),
        raised on the loop's as any other abort (the drive quick-stopped first). The first failure is kept."""
        if self.failure is None:
            self.failure = error
        self.request(type(error).__name__)

    def raise_if_requested(self) -> None:
        """Raise the failure handed to :meth:`fail`, or :class:`RunInterruptedError` for a signal."""
        if not self.requested:
            return
        if self.failure is not None:
            raise self.failure
        raise RunInterruptedError(f"interrupted by {self.signal_name}; quick stop commanded")

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.requested:
            self.repeated += 1
            return
        self.request(signal.Signals(signum).name)

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._previous[signum] = signal.getsignal(signum)
                signal.signal(signum, self._handle)
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous if previous is not None else signal.SIG_DFL)
        self._previous.clear()

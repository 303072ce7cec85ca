"""The trial loop's settings and what a run derives from its config for the loop: :class:`LoopSettings` (from
``sample_time`` and ``bench:``, :func:`loop_settings`), the command limits (:func:`command_limiter`) and the design
for the CAN loop's delay (:func:`build_design`, :data:`CAN_INPUT_DELAY`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from drivers.realtime import BenchRealtimeConfig
from foilc_hil.loop.safety import CommandLimiter
from plant_emulator.device import TimingMode

if TYPE_CHECKING:
    from foilc_hil.config import Config
    from foilc_hil.design.record import Design

__all__ = [
    "CAN_INPUT_DELAY",
    "LOCKSTEP_FEEDBACK_TIMEOUT",
    "MIN_SETTLE_TIMEOUT",
    "SETTLE_TIMEOUT_FACTOR",
    "LoopSettings",
    "build_design",
    "command_limiter",
    "loop_settings",
]

#: the settle phase gives up after this many times ``bench.settle_time`` ...
SETTLE_TIMEOUT_FACTOR = 20.0
#: ... but never sooner than this many seconds of cycles
MIN_SETTLE_TIMEOUT = 5.0
#: lockstep over a wall-clock bus (a drive in another process): how long to wait for one cycle's TPDO feedback before
#: counting it missing (seconds); a liveness timeout, not a deadline. Unused on a synchronous bus (nothing to wait for)
LOCKSTEP_FEEDBACK_TIMEOUT = 0.1


@dataclass(frozen=True)
class LoopSettings:
    """Timing and safety settings of the loop (from ``bench:`` and ``sample_time``)."""

    sample_time: float  # seconds per cycle: the SYNC period, the deadline scheduler's and the trial records' period
    mode: TimingMode = TimingMode.LOCKSTEP
    watchdog_cycles: int = 5
    divergence_factor: float = 10.0
    settle_time: float = 0.5
    settle_tolerance: float = 1.0
    lockstep_feedback_timeout: float = LOCKSTEP_FEEDBACK_TIMEOUT
    #: ``bench.faults.lost_feedback``: consecutive lost feedbacks tolerated (the law holds the last good one)
    max_lost_feedback: int = 3
    #: False when the drive itself starts every trial at rest (the simulated drive resets its plant in
    #: ``before_trial``): no settle phase between trials
    settle_between_trials: bool = True
    #: ``bench.realtime``: the host setup of a realtime run (its ``spin_margin`` is the scheduler's)
    realtime: BenchRealtimeConfig = field(default_factory=BenchRealtimeConfig)

    @property
    def settle_cycles(self) -> int:
        """Consecutive at-rest cycles that count as settled (at least one)."""
        return max(1, math.ceil(self.settle_time / self.sample_time - 1e-9))

    @property
    def feedback_timeout(self) -> float:
        """The bound of one SYNC's wait for feedback: at most the period in realtime (the wait ends
        :data:`~foilc_hil.loop.bench.COMMAND_MARGIN_FRACTION` of a period before the next deadline),
        ``watchdog_cycles`` x the lockstep allowance in lockstep (no deadline there: only an expired bound makes a
        lost feedback)."""
        if self.mode is TimingMode.REALTIME:
            return self.sample_time
        return self.watchdog_cycles * self.lockstep_feedback_timeout

    @property
    def settle_timeout_cycles(self) -> int:
        return math.ceil(max(SETTLE_TIMEOUT_FACTOR * self.settle_time, MIN_SETTLE_TIMEOUT) / self.sample_time)


#: the CAN loop applies a command one SYNC after it is computed (the drive latches RPDOs at the next SYNC)
CAN_INPUT_DELAY = 1


def build_design(config: Config, law: str, n_samples: int) -> Design:
    """The design of ``law`` for the bench's CAN loop (:func:`foilc_hil.design.pipeline.build_design`)."""
    from foilc_hil.design.pipeline import build_design as pipeline_design

    return pipeline_design(config, law, n_samples, input_delay=CAN_INPUT_DELAY)


def command_limiter(config: Config) -> CommandLimiter:
    """Limits of the command in plant units: the drive's limit for the mode, and the plant's saturation."""
    drive = config.drive
    saturation = config.plant.saturation
    limit = drive.torque_limit if drive.mode == "cst" else drive.velocity_limit
    return CommandLimiter.symmetric(limit, u_min=saturation.u_min, u_max=saturation.u_max)


def loop_settings(config: Config, mode: TimingMode | None = None, *,
                  settle_between_trials: bool = True) -> LoopSettings:
    """The loop's settings from ``sample_time`` and the ``bench:`` section; ``mode`` overrides ``bench.mode``."""
    bench = config.bench
    return LoopSettings(
        sample_time=config.sample_time,
        mode=TimingMode(mode or bench.mode),
        watchdog_cycles=bench.watchdog_cycles,
        divergence_factor=bench.divergence_factor,
        settle_time=bench.settle_time,
        settle_tolerance=bench.settle_tolerance,
        max_lost_feedback=bench.faults.lost_feedback,
        settle_between_trials=settle_between_trials,
        realtime=bench.realtime,
    )

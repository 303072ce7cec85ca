"""What the trial loop talks to and what it produces: the protocols of its drive, law, limiter and log
(:class:`DriveLike`, :class:`ClockedDriveLike`, :class:`LawLike`, :class:`LimiterLike`, :class:`LogSink`; a drive's
whole trial, :class:`WholeTrial`), and its records (:class:`TrialRecord`, :class:`FaultCounts`,
:class:`BenchOutcome`). The loop is :class:`foilc_hil.loop.bench.TrialLoop`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from drivers.cia402 import State402
from foilc_hil.errors import FeedbackTimeoutError
from foilc_hil.io.records import TrialSamples
from foilc_hil.laws.learning import TrialUpdate
from foilc_hil.loop.scheduler import CycleBlock, TimingSummary
from foilc_hil.metrics import TrialMetrics

__all__ = [
    "AxesFeedbackLostError",
    "BenchOutcome",
    "ClockedDriveLike",
    "DriveLike",
    "FaultCounts",
    "FeedbackLike",
    "LawLike",
    "LimiterLike",
    "LogSink",
    "TrialRecord",
    "WholeTrial",
    "WholeTrialRunner",
    "echoes_demand",
]


class AxesFeedbackLostError(FeedbackTimeoutError):
    """Some axes' TPDO sets did not answer a SYNC; the others did (:meth:`foilc_hil.loop.axes.AxisGroup.wait_feedback`).

    The loop holds the last good feedback of the ``lost`` axes alone and gives the law the others' fresh answers:
    one axis's lost set must not make every axis learn from a held value.

    Attributes
    ----------
    velocity, demand
        ``(m,)``: each axis's answer; NaN where ``lost``.
    lost
        ``(m,)`` bool: the axes whose set did not answer.
    """

    def __init__(self, message: str, velocity: np.ndarray, demand: np.ndarray, lost: np.ndarray) -> None:
        super().__init__(message)
        self.velocity, self.demand, self.lost = velocity, demand, lost


# --- what the loop talks to (drivers.drive.Drive, foilc_hil.laws.learning, foilc_hil.io.mcap_log) ---------------


def echoes_demand(drive: object) -> bool:
    """The drive's TPDO set carries its demand echo (``drive.demand_echo``): a CiA 402 drive's cyclic path says so,
    an axis group for its axes; any other drive (the simulated one) has none. The one place the loop, the axis group,
    the rig and the live view ask it."""
    cyclic = getattr(drive, "cyclic", None)
    return bool(getattr(cyclic if cyclic is not None else drive, "echoes_demand", False))


class FeedbackLike(Protocol):
    """What the loop reads of one SYNC's answer: a :class:`~drivers.drive.Feedback`, or several axes' at once
    (``velocity`` then an ``(m,)`` array, :mod:`foilc_hil.loop.axes`)."""

    @property
    def state(self) -> State402: ...

    @property
    def velocity(self) -> Any: ...

    @property
    def demand(self) -> Any: ...  # the demand echo (NaN: none), ``(m,)`` for several axes


class LimiterLike(Protocol):
    """The command limiter the loop clamps with (:class:`~foilc_hil.loop.safety.CommandLimiter`, or one per axis)."""

    def clamp(self, value: Any) -> Any: ...

    @property
    def clamped_count(self) -> int: ...


class DriveLike(Protocol):
    """The subset of ``drivers.drive.Drive`` the trial loop uses (several axes: values are ``(m,)`` arrays)."""

    def sync(self) -> int: ...

    def wait_feedback(self, timeout: float) -> FeedbackLike: ...

    def set_target(self, value: Any) -> Any: ...

    def quick_stop(self) -> None: ...

    @property
    def bad_frames(self) -> int: ...


class ClockedDriveLike(DriveLike, Protocol):
    """A drive whose network can take SYNC from a clock (:class:`drivers.cia402_master.Cia402Drive`,
    :class:`~foilc_hil.loop.axes.AxisGroup`): the realtime loop then runs on the SYNCs it reads from the bus."""

    def start_clock(self, *, spin_margin: float) -> str | None: ...

    def stop_clock(self) -> None: ...

    def await_sync(self, after: int, timeout: float) -> Any: ...

    @property
    def latched(self) -> Any: ...

    @property
    def rpdo_sync_count(self) -> int: ...

    @property
    def syncs_seen(self) -> int: ...


class LawLike(Protocol):
    """The subset of ``foilc_hil.laws.learning.LearningLaw`` the loop uses."""

    def begin_trial(self) -> None: ...

    def command(self, t: int, output: np.ndarray) -> np.ndarray: ...

    def end_trial(
        self, reference: np.ndarray, output: np.ndarray, applied: np.ndarray | None = None
    ) -> TrialUpdate: ...

    @property
    def feedforward(self) -> np.ndarray: ...

    def restore(self, feedforward: np.ndarray) -> None: ...


@dataclass(frozen=True)
class WholeTrial:
    """What a drive's ``run_whole_trial(law, seen, control)`` ran (:data:`WholeTrialRunner`).

    Attributes
    ----------
    cycles
        Cycles completed (``N``: all of the trial's samples; the trial's last cycle is the loop's own).
    failed
        ``""``, or what was not finite in cycle ``cycles``, where it stopped (``"drive feedback"``, ``"command"``,
        as :func:`~foilc_hil.loop.safety.require_finite` names them).
    value
        That value.
    """

    cycles: int
    failed: str = ""
    value: float = math.nan


#: A drive's ``run_whole_trial(law, seen, control)``, offered by a drive that can run a trial's sample cycles in one
#: call (the simulated drive's compiled trial, :mod:`foilc_hil.loop.trial_kernel`); the loop asks for it in lockstep
#: without a limiter. It runs cycles ``0 .. N-1``: writes ``seen[0 .. N-1]`` (each one's feedback) and ``control``
#: (``law``'s command in each); ``None``: nothing ran (the loop runs them one by one).
WholeTrialRunner = Callable[[object, np.ndarray, np.ndarray], WholeTrial | None]


class LogSink(Protocol):
    """Where finished trials go (an adapter over ``foilc_hil.io.mcap_log``); called off the hot path."""

    def trial_finished(self, record: TrialRecord) -> None: ...

    def timing(self, block: CycleBlock) -> None: ...


# --- results ------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FaultCounts:
    """Faults the policy counted instead of aborting (``bench.faults``), over one trial or a whole run.

    Attributes
    ----------
    lost_feedback
        SYNCs whose TPDO set did not arrive within the wait's bound; the law was given the last good feedback.
    bad_frames
        Frames from the drive that did not decode (``bench.faults.bad_frame: count``).
    """

    lost_feedback: int = 0
    bad_frames: int = 0

    def to_json(self) -> dict[str, int]:
        return {"lost_feedback": self.lost_feedback, "bad_frames": self.bad_frames}


@dataclass(frozen=True)
class TrialRecord:
    """One completed trial, as logged."""

    trial: int
    sample_time: float
    reference: np.ndarray  # (N,)
    seen: np.ndarray  # (N + 1,): y_i the law was given at cycle i (y_N only read)
    control: np.ndarray  # (N,): the law's command u_i (clamped by the law itself), before the limiter
    applied: np.ndarray  # (N,): what was sent to the drive (plant units)
    output: np.ndarray  # (N,): trial output array, output[i] = y_{i+1}
    error: np.ndarray  # (N,)
    E: np.ndarray  # (N,) the law's learning signal: FOILC's fractional PD function of the error, else the error
    metrics: TrialMetrics
    sync_times: np.ndarray  # (N + 1,) perf_counter time of each SYNC
    clamped: int = 0  # commands of this trial the limiter clamped
    faults: FaultCounts = field(default_factory=FaultCounts)  # lost feedbacks, bad frames in the trial
    axis: int | None = None  # the axis's node id in a run of several axes (``axes:``); None: the only axis
    command_limits: tuple[float, float] | None = None  # this axis's limits when they are not the sink's
    first_sync: int | None = None  # the drive's count of the trial's first SYNC (its frame in /can); None: no bus
    #: (N,): what the drive latched at SYNC i + 1 (``/ilc/sample.latched``); None: not known (not logged)
    latched: np.ndarray | None = None
    #: (N,): the demand the drive echoed in the TPDO set answering SYNC i + 1 (``drive.demand_echo``), in the units of
    #: ``latched``; NaN where that set was lost; None: no echo mapped
    demand: np.ndarray | None = None
    #: (m,): each axis's lost feedbacks in the trial, for a run of several axes (an axis is held alone,
    #: :class:`AxesFeedbackLostError`); None: one axis (``faults.lost_feedback`` is its count)
    lost_by_axis: np.ndarray | None = None

    @property
    def demand_mismatches(self) -> int | None:
        """Samples whose echoed demand is not ``latched`` (``/ilc/trial.demand_mismatches``); None: no echo mapped.

        A sample whose TPDO set was lost (NaN) has no echo to compare: it is not counted.
        """
        if self.demand is None or self.latched is None:
            return None
        echoed = np.asarray(self.demand, dtype=float)
        return int(np.count_nonzero(~np.isnan(echoed) & (echoed != np.asarray(self.latched, dtype=float))))

    def samples(self) -> TrialSamples:
        """The ``/ilc/sample`` messages of this trial as columns, layout :data:`~foilc_hil.io.schemas.SAMPLE_LAYOUT`
        (module docstring): row ``i`` describes the instant ``(i + 1) Ts``, ``output[i] = y((i + 1) Ts)`` (so
        ``error[i] = reference[i] - output[i]`` exactly) and ``control[i] = u_i``, sent after SYNC ``i`` and applied
        by the drive from SYNC ``i + 1`` if its RPDO came before it: ``latched[i]`` is what the drive did latch."""
        return TrialSamples(int(self.trial), float(self.sample_time), self.reference, self.output, self.control,
                            self.error, self.E, self.axis, self.latched)


@dataclass
class BenchOutcome:
    """What a run produced: per-trial metrics, timing, and why it stopped early (``None``: it did not)."""

    trials: list[TrialMetrics] = field(default_factory=list)
    timing: TimingSummary | None = None
    stopped: str | None = None
    diverged: bool = False
    clamped_commands: int = 0
    settle_cycles: int = 0
    faults: FaultCounts = field(default_factory=FaultCounts)  # over the whole run, settle phases included
    trial_faults: list[FaultCounts] = field(default_factory=list)  # per completed trial
    #: samples of the run's trials whose echoed demand was not the latched command (``drive.demand_echo``); None:
    #: no echo mapped
    demand_mismatches: int | None = None

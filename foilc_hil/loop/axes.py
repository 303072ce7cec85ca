"""Several axes on one bus in one trial loop: the composite drive, law, limiter and log sink of an ``axes:`` run.

:class:`~foilc_hil.loop.bench.TrialLoop` stays the only trial loop. For ``m`` axes it runs on an ``(N, m)``
reference, and the objects here put the ``m`` axes behind its ``DriveLike`` / ``LawLike`` protocols with ``(m,)``
vectors for outputs and commands:

- :class:`AxisGroup`: the :class:`~drivers.cia402_master.Cia402Drive` of every axis on one
  :class:`~drivers.network.DriveNetwork`. One cycle is ONE SYNC (every drive's cycle begins with it), every axis's
  TPDO set collected, then every axis's RPDO sent: all within the same SYNC period. A fault of any axis quick-stops
  every axis (the loop's abort path calls :meth:`AxisGroup.quick_stop`); :func:`foilc_hil.loop.rig.run_rig` then
  safe-stops each drive and reports one :class:`~drivers.drive.StopReport` per axis, read back from each drive.
- :class:`AxisLaws`: one :class:`~foilc_hil.laws.learning.LearningLaw` per axis, each designed and certified on its
  own model (:func:`foilc_hil.loop.settings.build_design` of the axis's config, :func:`foilc_hil.config.axis_configs`).
- :class:`AxisLimiter`: one :class:`~foilc_hil.loop.safety.CommandLimiter` per axis.
- :class:`AxesSink`: splits each finished trial into one record per axis; every ``/ilc/sample`` and ``/ilc/trial``
  message carries ``axis`` (the node id) -- docs/interface-additions.md.

Injected faults (``inject:``) act on the axis their ``axis`` names (its frames, its emulated drive), the first
axis without one (:func:`drivers.faults.split_by_axis`). A precomputed ``RunRequest.design`` is refused (exit 2):
it is one axis's design, and each axis is designed on its own model.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any, cast

import numpy as np

from drivers.cia402 import State402
from drivers.drive import StopReport
from foilc_hil.errors import DriveFaultError, FeedbackTimeoutError
from foilc_hil.laws.learning import TrialUpdate
from foilc_hil.loop.interfaces import AxesFeedbackLostError, FaultCounts, TrialRecord, echoes_demand
from foilc_hil.loop.log_sink import McapSink
from foilc_hil.loop.safety import CommandLimiter
from foilc_hil.loop.scheduler import CycleBlock
from foilc_hil.metrics import TrialMetrics, trial_metrics

__all__ = ["AxesFeedback", "AxesSink", "AxisGroup", "AxisLaws", "AxisLimiter", "AxisOutcome"]


@dataclass(frozen=True, slots=True)
class AxesFeedback:
    """Every axis's answer to one SYNC: ``velocity`` and ``demand`` (each axis's demand echo, NaN where it has none)
    are ``(m,)`` in axis order; ``state`` OPERATION_ENABLED (an axis in any other state is raised by
    :meth:`AxisGroup.wait_feedback`)."""

    cycle: int
    state: State402
    velocity: np.ndarray
    demand: np.ndarray


class AxisGroup:
    """The drives of several axes on one :class:`~drivers.network.DriveNetwork`, as one ``DriveLike``.

    Parameters
    ----------
    drives
        Connected, configured and enabled :class:`~drivers.cia402_master.Cia402Drive` objects sharing one network
        (``Cia402Drive.on_network``), in axis order.
    clock
        Seconds, monotonic: the clock of :meth:`wait_feedback`'s one deadline (the drives' own wait clock).
    """

    def __init__(self, drives: Sequence[Any], clock: Callable[[], float] = time.monotonic) -> None:
        if not drives:
            raise ValueError("an axis group needs at least one drive")
        self.drives = tuple(drives)
        self._clock = clock
        self._velocity = np.zeros(len(self.drives))
        self._demand = np.full(len(self.drives), np.nan)
        self._applied = np.zeros(len(self.drives))

    def sync(self) -> int:
        """One SYNC for every axis: any member's sync begins the cycle on all of them (``DriveNetwork.sync``)."""
        return cast(int, self.drives[0].sync())

    def wait_feedback(self, timeout: float) -> AxesFeedback:
        """Every axis's TPDO set answering the last SYNC, all within ``timeout`` from now.

        One deadline for the group, not ``timeout`` per axis: a realtime loop hands in the time left until its next
        deadline, and an axis whose answer is late must not let the next axis's wait run past it (an axis whose
        answer is in returns it at once, whatever time is left).

        Raises what a drive raises (its own stop commanded), :class:`~foilc_hil.errors.DriveFaultError` naming the
        node for an axis that left OPERATION ENABLED, and, where some axes' sets did not answer (each drive's
        :class:`~foilc_hil.errors.FeedbackTimeoutError`), :class:`AxesFeedbackLostError` with every axis read: the
        others' answers in it, so that only the lost axes are held.
        """
        velocity, demand = self._velocity, self._demand
        cycle = 0
        clock = self._clock
        deadline = clock() + timeout
        lost: np.ndarray | None = None
        first: FeedbackTimeoutError | None = None
        for k, drive in enumerate(self.drives):
            left = deadline - clock() if k else timeout
            try:
                feedback = drive.wait_feedback(left if left > 0.0 else 0.0)
            except FeedbackTimeoutError as exc:  # this axis alone: the others are still read
                if lost is None:
                    lost, first = np.zeros(len(self.drives), dtype=bool), exc
                lost[k] = True
                velocity[k] = demand[k] = np.nan
                continue
            if feedback.state is not State402.OPERATION_ENABLED:
                raise DriveFaultError(f"node {drive.node_id} left OPERATION ENABLED (now {feedback.state.name}) at "
                                      f"SYNC {feedback.cycle}")
            velocity[k] = feedback.velocity
            demand[k] = feedback.demand
            cycle = feedback.cycle
        if lost is not None:
            raise AxesFeedbackLostError(str(first), velocity.copy(), demand.copy(), lost) from first
        return AxesFeedback(cycle, State402.OPERATION_ENABLED, velocity.copy(), demand.copy())

    def set_target(self, value: Any) -> np.ndarray:
        """Send every axis's RPDO (``value``: ``(m,)``, or one number for all); returns what each drive sent."""
        applied = self._applied
        if type(value) is not np.ndarray or value.shape != applied.shape:  # the loop's own (m,) array: as it is
            value = np.broadcast_to(np.asarray(value, dtype=float), applied.shape)
        for k, (drive, target) in enumerate(zip(self.drives, value.tolist(), strict=True)):  # floats, one call
            applied[k] = drive.set_target(target)
        return applied.copy()

    # -- SYNC from a clock (realtime): one clock for the one network, every axis's RPDO echo ------------------

    def start_clock(self, *, spin_margin: float = 0.0) -> str | None:
        """SYNC from a clock on the axes' one network (every drive's RPDO echo routed); the clock's name, or None
        where the network cannot (no cyclic receiver)."""
        first = self.drives[0]
        net = first.link.net
        if net.receiver is None:
            return None
        echoes = {cob: callback for drive in self.drives for cob, callback in drive.cyclic.clock_routes().items()}
        return cast(str, net.start_clock(first.sample_time, echoes, spin_margin=spin_margin).name)

    def stop_clock(self) -> None:
        self.drives[0].stop_clock()

    def await_sync(self, after: int, timeout: float) -> Any:
        return self.drives[0].await_sync(after, timeout)

    @property
    def latched(self) -> np.ndarray:
        """What each axis's drive latched at the last SYNC read from the bus, ``(m,)``."""
        return np.array([drive.latched for drive in self.drives])

    @property
    def echoes_demand(self) -> bool:
        """Some axis's TPDOs carry its demand echo (``drive.demand_echo``; the others' are NaN, never counted)."""
        return any(echoes_demand(drive) for drive in self.drives)

    @property
    def syncs_seen(self) -> int:
        return cast(int, self.drives[0].syncs_seen)

    @property
    def rpdo_sync_count(self) -> int:
        """The SYNCs sent when the last axis's RPDO (the cycle's last) went out."""
        return cast(int, self.drives[-1].rpdo_sync_count)

    def quick_stop(self) -> None:
        """Quick-stop EVERY axis, each tried even when another fails; then raise the first failure."""
        failures: list[Exception] = []
        for drive in self.drives:
            try:
                drive.quick_stop()
            except Exception as exc:  # the other axes must still be stopped
                failures.append(exc)
        if failures:
            raise failures[0]

    @property
    def bad_frames(self) -> int:
        """Frames that did not decode, over every axis."""
        return sum(drive.bad_frames for drive in self.drives)


class AxisLaws:
    """One learning law per axis behind the loop's ``LawLike``: ``(m,)`` outputs in, ``(m,)`` commands out.

    The metrics of a trial (:attr:`TrialUpdate.metrics`) are over every axis and sample (the divergence guard's
    SSE); each axis's own update is :attr:`updates` (the last trial's) and its metrics :attr:`history`.
    """

    def __init__(self, laws: Sequence[Any]) -> None:
        if not laws:
            raise ValueError("an axis group needs at least one law")
        self.laws = tuple(laws)
        self._inputs = [np.zeros(1) for _ in self.laws]
        self._commands = np.zeros(len(self.laws))
        self.updates: tuple[TrialUpdate, ...] = ()
        self.history: list[list[TrialMetrics]] = [[] for _ in self.laws]

    def begin_trial(self) -> None:
        for law in self.laws:
            law.begin_trial()

    def command(self, t: int, output: np.ndarray) -> np.ndarray:
        commands = self._commands
        for k, law in enumerate(self.laws):
            axis_input = self._inputs[k]
            axis_input[0] = output[k]
            commands[k] = law.command(t, axis_input)[0]
        return commands

    def end_trial(self, reference: np.ndarray, output: np.ndarray, applied: np.ndarray | None = None) -> TrialUpdate:
        """Every axis's between-trial update (``applied``: ``(N, m)``, each axis's column the input it ran); the
        returned one stacks their errors column by column."""
        updates = tuple(law.end_trial(reference[:, k], output[:, k], None if applied is None else applied[:, k])
                        for k, law in enumerate(self.laws))
        self.updates = updates
        for k, update in enumerate(updates):
            self.history[k].append(update.metrics)
        error = np.column_stack([np.asarray(update.error, dtype=float).reshape(-1) for update in updates])
        E = np.column_stack([np.asarray(update.E, dtype=float).reshape(-1) for update in updates])
        first = min(min(law.input_delay for law in self.laws), error.shape[0] - 1)
        return TrialUpdate(updates[0].trial, error, E, trial_metrics(updates[0].trial, error, first_learnable=first))

    @property
    def feedforward(self) -> np.ndarray:
        return np.column_stack([np.asarray(law.feedforward, dtype=float).reshape(-1) for law in self.laws])

    def restore(self, feedforward: np.ndarray) -> None:
        for k, law in enumerate(self.laws):
            law.restore(feedforward[:, k].reshape(np.shape(law.feedforward)))


class AxisLimiter:
    """One :class:`~foilc_hil.loop.safety.CommandLimiter` per axis, clamping an ``(m,)`` command."""

    def __init__(self, limiters: Sequence[CommandLimiter]) -> None:
        self.limiters = tuple(limiters)
        self._out = np.zeros(len(self.limiters))

    def clamp(self, value: np.ndarray) -> np.ndarray:
        out = self._out
        for k, limiter in enumerate(self.limiters):
            out[k] = limiter.clamp(float(value[k]))
        return out

    @property
    def clamped_count(self) -> int:
        return sum(limiter.clamped_count for limiter in self.limiters)


class AxesSink:
    """The loop's ``LogSink`` for several axes: each finished trial as one record per axis, ``axis`` = node id;
    ``echoes``: which axes' drives echo their demand (``AxisGroup.drives[k].echoes_demand``)."""

    def __init__(self, sink: McapSink, laws: AxisLaws, limiter: AxisLimiter, node_ids: Sequence[int], *,
                 echoes: Sequence[bool] = ()) -> None:
        self._sink = sink
        # which axes echo their demand (drive.demand_echo): the others' records get no demand_mismatches (default:
        # every axis, as far as the loop's record has a demand column at all)
        self._echoes = tuple(echoes) or (True,) * len(node_ids)
        self._laws = laws
        self._limiter = limiter
        self._node_ids = tuple(node_ids)
        self._clamped = [0] * len(self._node_ids)  # each axis's clamp count after the previous trial

    def trial_finished(self, record: TrialRecord) -> None:
        for k, node in enumerate(self._node_ids):
            limiter = self._limiter.limiters[k]
            clamped, self._clamped[k] = limiter.clamped_count - self._clamped[k], limiter.clamped_count
            update = self._laws.updates[k]
            self._sink.trial_finished(replace(
                record, reference=record.reference[:, k], seen=record.seen[:, k], control=record.control[:, k],
                applied=record.applied[:, k], output=record.output[:, k], error=record.error[:, k],
                E=record.E[:, k], metrics=update.metrics, clamped=clamped, axis=node, faults=self._faults(record, k),
                command_limits=(limiter.lower, limiter.upper),
                latched=None if record.latched is None else record.latched[:, k],
                demand=None if record.demand is None or not self._echoes[k] else record.demand[:, k],
            ))

    @staticmethod
    def _faults(record: TrialRecord, k: int) -> FaultCounts:
        """Axis ``k``'s faults: its own lost feedbacks (an axis is held alone), the bus's bad frames."""
        if record.lost_by_axis is None:
            return record.faults
        return replace(record.faults, lost_feedback=int(record.lost_by_axis[k]))

    def timing(self, block: CycleBlock) -> None:
        self._sink.timing(block)


# --- a whole run over several axes ------------------------------------------------------------------------------


@dataclass(frozen=True)
class AxisOutcome:
    """One axis of a run: its node id, its own trial metrics and the stop read back from its drive."""

    node_id: int
    trials: list[TrialMetrics]
    drive_stop: StopReport | None
    design: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        return {
            "node_id": self.node_id,
            "trials": [metrics.to_json() for metrics in self.trials],
            "drive_stop": self.drive_stop.to_json() if self.drive_stop is not None else None,
            "design": self.design,
        }

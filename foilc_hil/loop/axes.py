"""Several axes on one bus in one trial loop: the composite drive, law, limiter and log sink of an ``axes:`` run.

:class:`~foilc_hil.loop.bench.TrialLoop` stays the only trial loop. For ``m`` axes it runs on an ``(N, m)``
reference, and the objects here put the ``m`` axes behind its ``DriveLike`` / ``LawLike`` protocols with ``(m,)``
vectors for outputs and commands:

- :class:`AxisGroup`: the :class:`~drivers.cia402_master.Cia402Drive` of every axis on one
  :class:`~drivers.network.DriveNetwork`. One cycle is ONE SYNC (every drive's cycle begins with it), every axis's
  TPDO set collected, then every axis's RPDO sent: all within the same SYNC period. A fault of any axis quick-stops
  every axis (the loop's abort path calls :meth:`AxisGroup.quick_stop`); :func:`run_axes` then safe-stops each
  drive and reports one :class:`~drivers.drive.StopReport` per axis, read back from each drive.
- :class:`AxisLaws`: one :class:`~foilc_hil.laws.learning.LearningLaw` per axis, each designed and certified on its
  own model (:func:`foilc_hil.loop.bench.build_design` of the axis's config, :func:`foilc_hil.config.axis_configs`).
- :class:`AxisLimiter`: one :class:`~foilc_hil.loop.safety.CommandLimiter` per axis.
- :class:`AxesSink`: splits each finished trial into one record per axis; every ``/ilc/sample`` and ``/ilc/trial``
  message carries ``axis`` (the node id) -- docs/interface-additions.md.

Injected faults (``inject:``) act on the axis their ``axis`` names (its frames, its emulated drive), the first
axis without one (:func:`drivers.faults.split_by_axis`). A precomputed ``RunRequest.design`` is refused (exit 2):
it is one axis's design, and each axis is designed on its own model.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, cast

import numpy as np

from drivers.cia402 import State402
from drivers.drive import StopReport
from drivers.faults import FaultyBus, Injection, InjectionReport, require_actions, split_by_axis
from drivers.realtime import RealtimeSession
from foilc_hil.errors import DriveFaultError, FoilcHilError
from foilc_hil.laws.learning import TrialUpdate
from foilc_hil.loop.bench import (
    BenchOutcome,
    LoopSettings,
    McapSink,
    RunReport,
    RunRequest,
    TrialLoop,
    TrialRecord,
    build_design,
    command_limiter,
    cyclic_receiver,
    logged_trials,
    loop_settings,
    realtime_session,
    stop_error,
    trial_hook,
)
from foilc_hil.loop.safety import CommandLimiter, StopRequest
from foilc_hil.metrics import TrialMetrics, trial_metrics

__all__ = ["AxesFeedback", "AxesRunReport", "AxesSink", "AxisGroup", "AxisLaws", "AxisLimiter", "AxisOutcome",
           "run_axes"]


@dataclass(frozen=True, slots=True)
class AxesFeedback:
    """Every axis's answer to one SYNC: ``velocity`` is ``(m,)`` in axis order; ``state`` OPERATION_ENABLED (an
    axis in any other state is raised by :meth:`AxisGroup.wait_feedback`)."""

    cycle: int
    state: State402
    velocity: np.ndarray


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
        self._applied = np.zeros(len(self.drives))

    def sync(self) -> int:
        """One SYNC for every axis: any member's sync begins the cycle on all of them (``DriveNetwork.sync``)."""
        return cast(int, self.drives[0].sync())

    def wait_feedback(self, timeout: float) -> AxesFeedback:
        """Every axis's TPDO set answering the last SYNC, all within ``timeout`` from now.

        One deadline for the group, not ``timeout`` per axis: a realtime loop hands in the time left until its next
        deadline, and an axis whose answer is late must not let the next axis's wait run past it (an axis whose
        answer is in returns it at once, whatever time is left).

        Raises what a drive raises (its own stop commanded; a timeout as the drive's
        :class:`~foilc_hil.errors.FeedbackTimeoutError`), and :class:`~foilc_hil.errors.DriveFaultError` naming
        the node for an axis that left OPERATION ENABLED.
        """
        velocity = self._velocity
        cycle = 0
        clock = self._clock
        deadline = clock() + timeout
        for k, drive in enumerate(self.drives):
            left = deadline - clock() if k else timeout
            feedback = drive.wait_feedback(left if left > 0.0 else 0.0)
            if feedback.state is not State402.OPERATION_ENABLED:
                raise DriveFaultError(f"node {drive.node_id} left OPERATION ENABLED (now {feedback.state.name}) at "
                                      f"SYNC {feedback.cycle}")
            velocity[k] = feedback.velocity
            cycle = feedback.cycle
        return AxesFeedback(cycle, State402.OPERATION_ENABLED, velocity.copy())

    def set_target(self, value: Any) -> np.ndarray:
        """Send every axis's RPDO (``value``: ``(m,)``, or one number for all); returns what each drive sent."""
        applied = self._applied
        if type(value) is not np.ndarray or value.shape != applied.shape:  # the loop's own (m,) array: as it is
            value = np.broadcast_to(np.asarray(value, dtype=float), applied.shape)
        for k, (drive, target) in enumerate(zip(self.drives, value.tolist(), strict=True)):  # floats, one call
            applied[k] = drive.set_target(target)
        return applied.copy()

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

    def end_trial(self, reference: np.ndarray, output: np.ndarray) -> TrialUpdate:
        """Every axis's between-trial update; the returned one stacks their errors column by column."""
        updates = tuple(law.end_trial(reference[:, k], output[:, k]) for k, law in enumerate(self.laws))
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
    """The loop's ``LogSink`` for several axes: each finished trial as one record per axis, ``axis`` = node id."""

    def __init__(self, sink: McapSink, laws: AxisLaws, limiter: AxisLimiter, node_ids: Sequence[int]) -> None:
        self._sink = sink
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
                E=record.E[:, k], metrics=update.metrics, clamped=clamped, axis=node,
                command_limits=(limiter.lower, limiter.upper),
            ))

    def timing(self, records: Iterator[Any]) -> None:
        self._sink.timing(records)


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


@dataclass(frozen=True)
class AxesRunReport:
    """A run of several axes: the run as a whole (``trials``: every axis's errors together) and each axis."""

    run: RunReport
    axes: list[AxisOutcome] = field(default_factory=list)

    @property
    def outcome(self) -> BenchOutcome:
        return self.run.outcome

    def to_json(self) -> dict[str, Any]:
        return {**self.run.to_json(), "axes": [axis.to_json() for axis in self.axes]}


@dataclass(frozen=True)
class _AxesPlan:
    """What an ``axes:`` run will do, decided before anything is opened."""

    law_kind: str
    trials: int
    bus: Any
    configs: tuple[Any, ...]
    designs: tuple[Any, ...]
    reference: np.ndarray  # (N, m)
    laws: AxisLaws
    limiter: AxisLimiter
    settings: LoopSettings
    injections: dict[int, tuple[Injection, ...]]  # node id -> the faults injected on that axis

    @property
    def node_ids(self) -> tuple[int, ...]:
        return tuple(config.drive.node_id for config in self.configs)


def _plan_axes(request: RunRequest) -> _AxesPlan:
    """Each axis's design (on its own model), law and limits; one reference column per axis."""
    from foilc_hil.config import axis_configs
    from foilc_hil.errors import ConfigError, InputError
    from foilc_hil.laws.learning import make_law
    from foilc_hil.references import reference_profile

    config = request.config
    if request.design is not None:
        # one Design is one axis's model; applying it to every axis would run the others on the wrong model
        raise InputError("design: a precomputed design is one axis's; an axes: run designs each axis on its own model")
    configs = axis_configs(config)
    law_kind = request.law or config.law.kind
    bus = request.bus if request.bus is not None else config.bus
    require_actions(config.inject, emulator=bus.interface == "embedded")
    injections = split_by_axis(config.inject, [axis.drive.node_id for axis in configs])
    columns = [reference_profile(axis.reference, config.sample_time) for axis in configs]
    lengths = {column.shape[0] for column in columns}
    if len(lengths) != 1:
        raise ConfigError(f"every axis's trial must have the same number of samples (one SYNC clock), got "
                          f"{[column.shape[0] for column in columns]}", key="axes.reference")
    n_samples = lengths.pop()
    kinds = [request.law or axis.law.kind for axis in configs]
    designs = tuple(build_design(axis, kind, n_samples) for axis, kind in zip(configs, kinds, strict=True))
    limiters = [command_limiter(axis) for axis in configs]
    laws = [make_law(design, axis.law, n_samples, limits=(limiter.lower, limiter.upper))
            for design, axis, limiter in zip(designs, configs, limiters, strict=True)]
    return _AxesPlan(law_kind=law_kind, trials=request.trials or config.trials, bus=bus, configs=configs,
                     designs=designs, reference=np.column_stack(columns), laws=AxisLaws(laws),
                     limiter=AxisLimiter(limiters), settings=loop_settings(config, request.mode),
                     injections=injections)


def _log_axes(writer: Any, plan: _AxesPlan) -> None:
    """Each axis's own config and design, for ``replay --verify`` and ``report`` of one axis."""
    from foilc_hil.config import dump_config
    from foilc_hil.io.mcap_log import encode_design
    from foilc_hil.io.schemas import METADATA_AXIS_PREFIX

    for node, axis, design in zip(plan.node_ids, plan.configs, plan.designs, strict=True):
        writer.add_metadata(f"{METADATA_AXIS_PREFIX}.{node}.config", {"yaml": dump_config(axis)})
        writer.add_metadata(f"{METADATA_AXIS_PREFIX}.{node}.design", encode_design(design.to_json()))


def _start_emulators(stack: contextlib.ExitStack, plan: _AxesPlan, threaded: bool) -> tuple[Any, list[Any]]:
    """``interface: embedded``: one emulated drive per axis (its own plant) on ONE in-process channel."""
    if plan.bus.interface != "embedded":
        return plan.bus, []
    from plant_emulator.embedded import CHANNEL_PREFIX, EmbeddedEmulator

    channel = f"{CHANNEL_PREFIX}-axes-{id(plan):x}"
    emulators = [stack.enter_context(EmbeddedEmulator.from_config(axis, channel=channel, threaded=threaded))
                 for axis in plan.configs]
    return emulators[0].bus_config, emulators


def _open_axes(stack: contextlib.ExitStack, plan: _AxesPlan, config: Any, bus_cfg: Any, sink: McapSink | None,
               stops: dict[int, StopReport], emulators: list[Any]) -> tuple[AxisGroup, list[FaultyBus]]:
    """The bus (wrapped in each faulted axis's ``inject:``), one network, one master per axis (each safe-stopped on
    exit)."""
    from drivers.bus import open_bus
    from drivers.cia402_master import Cia402Drive
    from drivers.network import DriveNetwork
    from foilc_hil.config import BadFramePolicy
    from plant_emulator.faults import emulator_actions

    bus = open_bus(bus_cfg)
    stack.callback(bus.shutdown)
    faulty: list[FaultyBus] = []
    for node, injections in plan.injections.items():
        # one wrapper per faulted axis, nested: each sees every SYNC (its clock) and classifies its own node's frames
        k = plan.node_ids.index(node)
        actions = emulator_actions(emulators[k].drive) if emulators else {}
        bus = FaultyBus(bus, injections, node_id=node, actions=actions)
        stack.callback(bus.shutdown)
        faulty.append(bus)
    # one receiver for every axis: one socket, one poll (the drives' waits share one deadline)
    network = DriveNetwork(bus, cyclic_receiver(stack, plan.settings, bus_cfg) if not faulty else None)
    stack.callback(network.close)
    if sink is not None:
        network.tap.add_listener(cast("Callable[[Any, str], None]", sink.writer.log_frame))
    drives = []
    for axis in plan.configs:
        drive = Cia402Drive.on_network(network, axis.drive, sample_time=config.sample_time)
        drive.fatal_bad_frames = config.bench.faults.bad_frame is BadFramePolicy.ABORT
        stack.callback(drive.close)
        drives.append(drive)
    # LIFO: every drive is safe-stopped (and its state read back) before any is closed and before the log closes
    for drive in drives:
        stack.callback(_record_stop, stops, drive)
    return AxisGroup(drives), faulty


def _record_stop(stops: dict[int, StopReport], drive: Any) -> None:
    """Safe-stop one axis's drive and keep what its statusword confirmed."""
    stops[drive.node_id] = drive.safe_stop()


def _commission_axes(
    group: AxisGroup, plan: _AxesPlan, sink: McapSink | None, session: RealtimeSession | None
) -> None:
    """Connect every axis, enter the realtime ``session`` (if any), configure every axis, log each axis's mapping
    (the first's also as the single-axis record), then enable every axis."""
    from drivers.cia402_master import pdo_plan
    from foilc_hil.io.pdo_mapping import encode_pdo_mapping
    from foilc_hil.io.schemas import METADATA_AXIS_PREFIX, METADATA_PDO_MAPPING

    for drive in group.drives:
        drive.connect()
    if session is not None:  # as bench._commission: after connect, so the one CAN receive thread exists to be raised
        session.__enter__()
    for drive, axis in zip(group.drives, plan.configs, strict=True):
        drive.configure(axis.drive.operation_mode, axis.sample_time)
    if sink is not None:
        for k, (drive, axis) in enumerate(zip(group.drives, plan.configs, strict=True)):
            mapping = pdo_plan(axis.drive.operation_mode, drive.node_id, drive.od)
            record = encode_pdo_mapping(mapping.rpdos, mapping.tpdos)
            sink.writer.add_metadata(f"{METADATA_AXIS_PREFIX}.{drive.node_id}.pdo_mapping", record)
            if k == 0:  # readers of one axis (older tools) find the first axis's where they always did
                sink.writer.add_metadata(METADATA_PDO_MAPPING, record)
        sink.ready()  # the writer process, started while the drives were commissioned (bench.run_bench's order)
    for drive in group.drives:
        drive.enable()


def run_axes(request: RunRequest) -> AxesRunReport:
    """``foilc-hil run`` for a config with ``axes:``: every axis in one trial loop, one SYNC per cycle.

    On every exit path every drive ends safe-stopped, read back per axis; aborts propagate as
    :class:`~foilc_hil.errors.FoilcHilError` with one ``drive_stops`` entry per axis in their facts.
    """
    from foilc_hil.config import dump_config
    from foilc_hil.io.log_process import ProcessLogWriter
    from foilc_hil.progress import make_progress

    config = request.config
    plan = _plan_axes(request)
    stops: dict[int, StopReport] = {}
    loops: list[TrialLoop] = []
    sinks: list[McapSink] = []
    try:
        with _confirmed_stops(stops, plan.node_ids), contextlib.ExitStack() as stack:
            sink = None
            if request.out is not None:
                # a child process writes, as for one axis (bench._open_log): a writer thread here would take the
                # loop's GIL for every frame it encodes, and a realtime loop waits for it at its deadlines
                writer = ProcessLogWriter.open(request.out, config_yaml=dump_config(config),
                                               design=plan.designs[0].to_json(), wait=False)
                stack.callback(writer.close)
                _log_axes(writer, plan)
                sink = McapSink(writer, None)
                sinks.append(sink)
            bus_cfg, emulators = _start_emulators(stack, plan, threaded=bool(config.inject))
            # the host setup of bench.realtime, as for one axis (bench.run_bench): undone after every axis's
            # confirmed stop (LIFO); without it the loop ran at normal priority behind the emulators' FIFO threads
            session = realtime_session(stack, plan.settings)
            group, faulty = _open_axes(stack, plan, config, bus_cfg, sink, stops, emulators)
            progress = make_progress(request.title or f"{plan.law_kind.upper()} on {len(plan.configs)} axes",
                                     quiet=request.quiet)
            stack.callback(progress.close)
            stop = stack.enter_context(StopRequest())
            if sink is not None:
                sink.stop_on_failure(stop)
            log = AxesSink(sink, plan.laws, plan.limiter, plan.node_ids) if sink is not None else None
            loop = TrialLoop(group, plan.laws, plan.reference, plan.limiter, plan.settings, log=log,
                             progress=progress, stop=stop, before_trial=trial_hook([*emulators, *faulty], None))
            loops.append(loop)
            _commission_axes(group, plan, sink, session)
            outcome = loop.run(plan.trials)
            if session is not None and outcome.timing is not None:
                outcome.timing = replace(outcome.timing, realtime=session.report)
    except FoilcHilError as exc:
        ran = loops[0].outcome.trials if loops else []
        done = logged_trials(ran, sinks)
        exc.partial = {"law": plan.law_kind, "trials": [metrics.to_json() for metrics in done], "trials_run": len(ran),
                       "stopped": str(exc).splitlines()[0] if str(exc) else type(exc).__name__,
                       "log": str(request.out) if request.out is not None else "",
                       "drive_stop": _worst(stops, plan.node_ids).to_json() if stops else None,
                       "axes": [axis.to_json() for axis in _axis_outcomes(plan, stops)]}
        raise
    outcome.trials = logged_trials(outcome.trials, sinks)
    injected: list[InjectionReport] = [report for wrapper in faulty for report in wrapper.reports()]
    run = RunReport(law=plan.law_kind, outcome=outcome, log=str(request.out) if request.out is not None else "",
                    design=_design_summary(plan.designs[0]), bus=f"{bus_cfg.interface}:{bus_cfg.channel}",
                    cycles=loop.cycles, drive_stop=_worst(stops, plan.node_ids), injected=injected)
    return AxesRunReport(run, _axis_outcomes(plan, stops))


def _design_summary(design: Any) -> dict[str, Any]:
    return {"kp": design.kp, "r": design.r, "input_delay": design.input_delay, "gain_scale": design.gain_scale,
            "certificates": design.to_json().get("certificates", {})}


def _axis_outcomes(plan: _AxesPlan, stops: dict[int, StopReport]) -> list[AxisOutcome]:
    return [AxisOutcome(node, list(plan.laws.history[k]), stops.get(node), _design_summary(plan.designs[k]))
            for k, node in enumerate(plan.node_ids)]


def _worst(stops: dict[int, StopReport], node_ids: Sequence[int]) -> StopReport:
    """The ``drive_stop`` of the run as a whole: the first axis not confirmed disabled (or faulted), else the first."""
    reports = [stops[node] for node in node_ids if node in stops]
    for report in reports:
        if not report.confirmed or report.faults or report.state is State402.FAULT:
            return report
    return reports[0] if reports else StopReport(commanded=False, confirmed=False)


@contextlib.contextmanager
def _confirmed_stops(stops: dict[int, StopReport], node_ids: Sequence[int]) -> Iterator[None]:
    """Every axis's stop, read back: noted on an error that ends the run; an error (exit 1) for a run that otherwise
    succeeded but left any axis unconfirmed or faulted."""
    try:
        yield
    except FoilcHilError as exc:
        exc.facts = {**(exc.facts or {}), "drive_stops": {str(node): stops[node].to_json() for node in stops}}
        for node in node_ids:
            if node in stops:
                exc.add_note(stops[node].describe(node))
        raise
    for node in node_ids:
        report = stops.get(node, StopReport(commanded=False, confirmed=False))
        error = stop_error(report, node, f"node {node}")
        if error is not None:
            error.facts = {"drive_stops": {str(n): r.to_json() for n, r in stops.items()}}
            raise error

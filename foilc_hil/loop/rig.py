"""One run, one rig: the plan and the wiring of every run of the trial loop: ``foilc-hil run`` (one axis or
several), the demo, the Python API's ``Bench`` and ``simulate``, ``foilc-hil simulate`` and the robustness Monte
Carlo.

:func:`plan_run` decides everything before anything is opened (each axis's design on its own model, its law and
limits, the reference, the loop's settings). What answers the loop's SYNC is the plan's :class:`DriveKind`:

- ``DriveKind.CAN``: a CiA 402 drive over CAN, on a bus or the embedded emulator. :func:`run_rig` opens what the
  plan needs, in this order, each closed in reverse on every exit path (``contextlib.ExitStack``):

  1. the log (:class:`~foilc_hil.io.log_process.ProcessLogWriter`: a child process writes; started here, waited
     for before the enable);
  2. the embedded emulator, one emulated drive per axis on one in-process channel (``bus.interface: embedded``);
  3. the realtime host setup (``bench.realtime``), undone after the confirmed stops;
  4. the bus (wrapped in each faulted axis's ``inject:``), one :class:`~drivers.network.DriveNetwork` and one
     :class:`~drivers.cia402_master.Cia402Drive` per axis, each safe-stopped (read back) before any is closed and
     before the log closes;
  5. the stop request (SIGINT, SIGTERM, a failed log writer), the progress view and the one
     :class:`~foilc_hil.loop.bench.TrialLoop`.

  One axis is the one-member case of the same code: a single drive is a one-member network (as
  ``Cia402Drive.open`` makes it), and the loop is handed the axis's own drive, law and limiter (scalar signals);
  several axes are handed to it behind :mod:`foilc_hil.loop.axes`' composites (``(m,)`` vectors).
- ``DriveKind.SIMULATED``: the plant's physics behind a :class:`~foilc_hil.loop.simulated_drive.SimulatedDrive`,
  no bus, one axis, in lockstep: the log is written in this process (the trials are short and there is no cycle to
  keep), the drive resets its plant before each trial (no settle phase), the law clamps to the bench's limits and
  the loop has no limiter of its own (so the drive may run a trial's sample cycles in one compiled call,
  ``SimulatedDrive.run_whole_trial``), and no signal handler is installed (the Monte Carlo runs it on Dask's worker
  threads).
"""

from __future__ import annotations

import contextlib
import enum
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Protocol, cast

import numpy as np

from drivers.cia402 import State402
from drivers.cyclic_rx import CyclicReceive, CyclicReceiver, open_cyclic_receiver
from drivers.drive import StopReport
from drivers.faults import LOOP_KINDS, FaultyBus, Injection, InjectionReport, require_actions, split_by_axis
from drivers.realtime import RealtimeSession
from foilc_hil.errors import DriveError, DriveFaultError, DriveNotStoppedError, FoilcHilError, InputError
from foilc_hil.loop.axes import AxesSink, AxisGroup, AxisLaws, AxisLimiter, AxisOutcome
from foilc_hil.loop.bench import TrialLoop
from foilc_hil.loop.interfaces import BenchOutcome, LawLike, LimiterLike, echoes_demand
from foilc_hil.loop.log_sink import McapSink, logged_trials
from foilc_hil.loop.safety import CommandLimiter, StopRequest
from foilc_hil.loop.settings import CAN_INPUT_DELAY, LoopSettings, command_limiter, loop_settings
from foilc_hil.loop.stalls import LoopStalls
from foilc_hil.progress import ProgressView
from plant_emulator.device import TimingMode

if TYPE_CHECKING:
    from drivers.cia402_master import Cia402Drive
    from drivers.config import BusConfig
    from foilc_hil.config import Config
    from foilc_hil.design.record import Design
    from foilc_hil.io.log_process import ProcessLogWriter
    from foilc_hil.laws.learning import LearningLaw
    from foilc_hil.loop.simulated_drive import SimulatedDrive
    from plant_emulator.embedded import EmbeddedEmulator

__all__ = ["AxisPlan", "DriveKind", "Rig", "RunPlan", "RunReport", "RunRequest", "plan_axis", "plan_run", "run_rig"]


class LiveView(Protocol):
    """A live view of a run (``foilc_hil.live.publisher.LivePublisher``, a rank above the loop)."""

    def attach(self, loop: TrialLoop, drives: Sequence[Any]) -> None: ...


class DriveKind(enum.StrEnum):
    """What answers the loop's SYNC (module docstring)."""

    CAN = "can"  # a CiA 402 drive over CAN: a bus, or the embedded emulator (run, the demo, Bench)
    SIMULATED = "simulated"  # the plant's physics behind SimulatedDrive, no bus (simulate, robustness)


@dataclass(frozen=True)
class RunRequest:
    """What ``foilc-hil run`` asks for.

    Attributes
    ----------
    config
        The resolved :class:`foilc_hil.config.Config` (with ``axes:``, a run of several axes).
    out
        The MCAP file to write; ``None``: no log (benchmarks measuring the loop without logging).
    law
        ``foilc``, ``ioilc``, ``p-type``, ``noilc`` or ``gradient``; ``None``: each axis's ``law.kind``.
    trials
        ``None``: ``config.trials``.
    mode
        ``None``: ``config.bench.mode``.
    bus
        A ``drivers.config.BusConfig``; ``None`` or ``interface: embedded``: the in-process emulator.
    quiet
        No progress view on stderr.
    design
        A precomputed :class:`foilc_hil.design.record.Design` (the demo reuses one; one axis only: each axis of
        several is designed on its own model); ``None``: designed with ``input_delay = 1`` (the CAN loop).
    progress
        The view to report to instead of the stderr one ``quiet`` decides (the demo's runs, in worker processes,
        forward to the parent's view).
    live
        A live view (``foilc_hil.live.publisher.LivePublisher``, ``run --live``): its ``attach(loop, drives)`` is
        called once the loop exists; it sees what the log sees and never holds the loop. ``None``: none.
    drive
        What answers the SYNC: a drive over CAN (``bus``, ``mode``, ``live`` apply), or the simulated plant.
    input_delay
        Cycles between the law's command and the plant applying it, for a design made here (and checked against a
        given one): ``None`` is :data:`~foilc_hil.loop.settings.CAN_INPUT_DELAY`, the only delay of the CAN loop;
        the simulated drive runs any (0: the ideal loop).
    """

    config: Config
    out: str | os.PathLike[str] | None
    law: str | None = None
    trials: int | None = None
    mode: TimingMode | None = None
    bus: BusConfig | None = None
    quiet: bool = True
    design: Design | None = None
    title: str = ""
    progress: ProgressView | None = None
    live: LiveView | None = None
    drive: DriveKind = DriveKind.CAN
    input_delay: int | None = None


@dataclass(frozen=True)
class RunReport:
    """What a run produced (the ``foilc-hil run --json`` document is :meth:`to_json`).

    ``design`` is the first axis's; ``axes`` lists every axis of a run of several (empty for one axis) and
    ``drive_stop`` is then the worst of their stops."""

    law: str
    outcome: BenchOutcome
    log: str
    design: dict[str, Any]
    bus: str
    cycles: int
    drive_stop: StopReport
    injected: list[InjectionReport] = field(default_factory=list)  # what each ``inject:`` fault did
    axes: list[AxisOutcome] = field(default_factory=list)
    stop_lines: list[str] = field(default_factory=list)  # each drive's stop as read back, one line per axis

    def to_json(self) -> dict[str, Any]:
        timing = self.outcome.timing.to_json() if self.outcome.timing is not None else {}
        document = {
            "drive_stop": self.drive_stop.to_json(),
            "law": self.law,
            "trials": [metrics.to_json() for metrics in self.outcome.trials],
            "timing": timing,
            "log": self.log,
            "design": self.design,
            "bus": self.bus,
            "clamped_commands": self.outcome.clamped_commands,
            "settle_cycles": self.outcome.settle_cycles,
            "stopped": self.outcome.stopped,
            "faults": {
                **self.outcome.faults.to_json(),
                "trials": [faults.to_json() for faults in self.outcome.trial_faults],
                "injected": [report.to_json() for report in self.injected],
            },
        }
        if self.outcome.demand_mismatches is not None:  # drive.demand_echo: the run's total (absent without it)
            faults = document["faults"]
            assert isinstance(faults, dict)
            faults["demand_mismatches"] = self.outcome.demand_mismatches
        if self.axes:
            document["axes"] = [axis.to_json() for axis in self.axes]
        return document


# --- the plan ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AxisPlan:
    """One axis of a run: its own config (``foilc_hil.config.axis_configs``), design, law and limits."""

    config: Config
    design: Design
    law: LearningLaw
    limiter: CommandLimiter

    @property
    def node_id(self) -> int:
        return int(self.config.drive.node_id)


@dataclass(frozen=True)
class RunPlan:
    """What a run will do, decided before anything is opened."""

    law_kind: str
    trials: int
    bus: BusConfig
    config: Config
    axes: tuple[AxisPlan, ...]
    law: LawLike  # what the loop calls: the axis's own law, or every axis's behind one (m,) law (AxisLaws)
    limiter: LimiterLike | None  # the axis's limiter, or AxisLimiter; None: the simulated drive (the law clamps)
    reference: np.ndarray  # (N,) for one axis, (N, m) for m
    settings: LoopSettings
    title: str
    injections: dict[int, tuple[Injection, ...]]  # node id -> the faults injected on that axis's bus or emulator
    stalls: LoopStalls | None = None  # the loop's own injections (stall@...): they stall every axis's one loop
    drive: DriveKind = DriveKind.CAN

    @property
    def node_ids(self) -> tuple[int, ...]:
        return tuple(axis.node_id for axis in self.axes)

    @property
    def several(self) -> bool:
        return len(self.axes) > 1


def plan_run(request: RunRequest) -> RunPlan:
    """Resolve the request against its config: each axis's design (tuned and synthesized unless given), law and
    limits, and the reference (one column per axis). Bad input (an output directory that does not exist, an
    injection naming no axis, axes whose trials differ in length) is found here, before the (possibly slow)
    design."""
    from foilc_hil.config import axis_configs
    from foilc_hil.errors import ConfigError
    from foilc_hil.io.mcap_writer import check_log_path
    from foilc_hil.references import reference_profile

    config = request.config
    simulated = request.drive is DriveKind.SIMULATED
    trials = config.trials if request.trials is None else request.trials
    if trials < 1:
        raise ConfigError(f"must be >= 1, got {trials}", key="trials")
    input_delay = _input_delay(request)
    if request.out is not None:
        check_log_path(request.out)  # before the (possibly slow) design
    # the simulated drive runs the document's own plant (simulate reads no axes:)
    configs = tuple(axis_configs(config)) if config.axes and not simulated else (config,)
    if request.design is not None and len(configs) > 1:
        # one Design is one axis's model; applying it to every axis would run the others on the wrong model
        raise InputError("design: a precomputed design is one axis's; an axes: run designs each axis on its own model")
    law_kind = request.law or config.law.kind
    bus = request.bus if request.bus is not None else config.bus
    injections, stalls = ({}, None) if simulated else _injections(config, configs, bus)
    columns = [reference_profile(axis.reference, config.sample_time) for axis in configs]
    lengths = [column.shape[0] for column in columns]
    if len(set(lengths)) != 1:
        raise ConfigError(f"every axis's trial must have the same number of samples (one SYNC clock), got "
                          f"{lengths}", key="axes.reference")
    kinds = [request.law or axis.law.kind for axis in configs]
    axes = tuple(plan_axis(axis, kind, lengths[0], design=request.design, input_delay=input_delay)
                 for axis, kind in zip(configs, kinds, strict=True))
    if simulated and (axes[0].law.n_inputs != 1 or axes[0].law.n_outputs != 1):
        raise ConfigError(f"the trial loop drives one axis; the law is {axes[0].law.n_outputs}x"
                          f"{axes[0].law.n_inputs}", key="plant")
    return RunPlan(
        law_kind=law_kind,
        trials=trials,
        bus=bus,
        config=config,
        axes=axes,
        law=axes[0].law if len(axes) == 1 else AxisLaws([axis.law for axis in axes]),
        limiter=None if simulated else axes[0].limiter if len(axes) == 1 else AxisLimiter([a.limiter for a in axes]),
        reference=columns[0] if len(axes) == 1 else np.column_stack(columns),
        settings=(loop_settings(config, TimingMode.LOCKSTEP, settle_between_trials=False) if simulated
                  else loop_settings(config, request.mode)),
        title=request.title or _title(law_kind, len(axes), None if simulated else bus),
        injections=injections,
        stalls=stalls,
        drive=request.drive,
    )


def _input_delay(request: RunRequest) -> int:
    """The loop's transport delay the design is made for (:attr:`RunRequest.input_delay`)."""
    if request.input_delay is None:
        return CAN_INPUT_DELAY
    if request.input_delay < 0:
        raise InputError(f"input_delay: must be >= 0, got {request.input_delay}")
    if request.drive is DriveKind.CAN and request.input_delay != CAN_INPUT_DELAY:
        raise InputError(f"input_delay: the CAN loop's is {CAN_INPUT_DELAY} (a drive latches its RPDO at the next "
                         f"SYNC), got {request.input_delay}")
    return request.input_delay


def _injections(config: Config, configs: Sequence[Config],
                bus: BusConfig) -> tuple[dict[int, tuple[Injection, ...]], LoopStalls | None]:
    """The faults ``inject:`` puts on each axis's bus or emulator (node id -> faults), and the loop's own stalls."""
    require_actions(config.inject, emulator=bus.interface == "embedded")
    injections = split_by_axis(config.inject, [axis.drive.node_id for axis in configs])  # a stray axis: exit 2
    kept = {node: on_bus for node, faults in injections.items()
            if (on_bus := tuple(i for i in faults if i.kind not in LOOP_KINDS))}
    return kept, LoopStalls.of(config.inject)


def _title(law_kind: str, axes: int, bus: BusConfig | None) -> str:
    """The progress view's title: the law, the axes and what runs them (``bus`` ``None``: the simulated plant)."""
    if bus is None:
        where = "the simulated plant"
    else:
        where = "the embedded emulator" if bus.interface == "embedded" else f"{bus.interface}:{bus.channel}"
    several = f" on {axes} axes" if axes > 1 else ""
    return f"{law_kind.upper()}{several} on {where}"


def plan_axis(config: Config, kind: str, n_samples: int, *, design: Design | None = None,
              input_delay: int = CAN_INPUT_DELAY) -> AxisPlan:
    """One axis of a run: its design (:func:`foilc_hil.design.pipeline.build_design` for ``input_delay``, or
    ``design`` checked against the axis), its law of ``n_samples`` samples and the bench's command limits.

    The law clamps to the limiter's limits and learns from what is applied; the limiter stays as the safety layer.
    Why the limits offline too: a sample whose error no command can remove (the demo's first samples: the reference
    asks for more acceleration than the torque limit gives) is integrated trial after trial. Unclamped, the learned
    command there grew by about 3,000 rpm a trial (93,700 rpm at trial 30 on the demo axis), a command the bench
    would never send; clamped, the law learns from what is applied, as on the bench.

    Raises
    ------
    ConfigError
        ``design`` is of another law, or looks ahead over fewer samples than the plant's own delay.
    """
    from foilc_hil.design.pipeline import build_design, model_delay_samples
    from foilc_hil.errors import ConfigError
    from foilc_hil.laws.learning import make_law

    if design is None:
        design = build_design(config, kind, n_samples, input_delay=input_delay)
    elif design.law != kind and not (kind == "ioilc" and design.kp == 0):
        raise ConfigError(f"the design is for law {design.law!r}, not {kind!r}", key="law.kind")
    elif design.input_delay < model_delay_samples(config):
        # The design's input_delay is the whole delay its law looks ahead over (transport + the plant's own); the
        # drive adds only the difference, which cannot be negative. Running the law anyway would time every update
        # against samples the plant has not answered yet.
        raise ConfigError(
            f"is {model_delay_samples(config)} sample(s), more than the design's input_delay "
            f"{design.input_delay}: re-synthesize the design for this plant",
            key="plant.delay",
        )
    limiter = command_limiter(config)
    law = make_law(design, config.law, n_samples, limits=(limiter.lower, limiter.upper))
    return AxisPlan(config, design, law, limiter)


# --- the rig -----------------------------------------------------------------------------------------------------


def run_rig(request: RunRequest) -> RunReport:
    """Run learning trials over CAN on one axis or several: commission each drive, run the loop, and leave every
    drive safe-stopped (read back) and the log closed.

    Aborts propagate as :class:`~foilc_hil.errors.FoilcHilError` subclasses (after the log is closed), with what
    the run had done in ``partial`` (``--json``'s error document) and each drive's stop in ``facts``; a divergence
    stop does not raise -- the report's ``outcome.stopped`` says why and ``outcome.diverged`` is set.
    """
    rig = Rig(request)
    with rig:
        rig.loop.run(rig.plan.trials)
    return rig.report()


class Rig:
    """The rig's stack, open between ``__enter__`` and ``__exit__``: what :func:`run_rig` runs its trials in, and
    ``foilc_hil.Bench`` its caller's, trial by trial (:meth:`TrialLoop.iter_trials`).

    ``__enter__`` plans (:func:`plan_run`), then opens the log, the emulators, the realtime session, the bus and
    the drives, and commissions and enables every drive, everything registered to be undone in reverse;
    ``__exit__`` undoes it on every path: every drive safe-stopped (read back) before any is closed and before the
    log closes, the truth about the stops told (an error for an unconfirmed or faulted stop), and an error that
    ends the run given what it had done in ``partial``.
    """

    def __init__(self, request: RunRequest) -> None:
        self.request = request
        self.plan = plan_run(request)
        self.stops: dict[int, StopReport] = {}
        self.sinks: list[McapSink] = []
        self._loop: TrialLoop | None = None
        self._session: RealtimeSession | None = None
        self._faulty: list[FaultyBus] = []
        self.emulators: list[EmbeddedEmulator] = []  # the embedded emulators, one per axis; [] on a bus
        self.drives: list[Cia402Drive] = []  # the masters, one per axis ([] for the simulated drive)
        self._bus = ""
        self._open = contextlib.ExitStack()

    @property
    def loop(self) -> TrialLoop:
        """The one trial loop (the rig is open)."""
        if self._loop is None:
            raise InputError("the rig is not open: use it in a with block")
        return self._loop

    def __enter__(self) -> Rig:
        if self.plan.drive is DriveKind.SIMULATED:
            return self._enter_simulated()
        plan, request = self.plan, self.request
        with contextlib.ExitStack() as outer:
            outer.enter_context(self._partial_on_error())
            outer.enter_context(_truth_about_the_stops(self.stops, plan.node_ids))
            stack = outer.enter_context(contextlib.ExitStack())
            # first in, last out: from here to the closed log a signal is a stop request, never an exception that
            # would cut the stop short (a second Ctrl-C during the disable lost the stop report)
            stop = stack.enter_context(StopRequest())
            sink = _open_log(stack, request, plan)
            self.sinks.extend([sink] if sink is not None else [])
            bus_cfg, self.emulators = _start_emulators(stack, plan)
            self._bus = f"{bus_cfg.interface}:{bus_cfg.channel}"
            # undone only after the confirmed stops (LIFO): restoring the host (the garbage collector first of all)
            # takes a tenth of a second, which must not pass between the loop's last SYNC and the stop
            self._session = realtime_session(stack, plan.settings)
            self.drives, self._faulty = _open_drives(stack, plan, bus_cfg, sink, self.stops, self.emulators)
            progress = request.progress or _progress(plan, request.quiet)
            stack.callback(progress.close)
            if sink is not None:
                sink.stop_on_failure(stop)
            # the loop and the host setup before the drives are enabled: from its first SYNC in OPERATIONAL a drive
            # supervises SYNC, so nothing slow may run between the enable's last SYNC and the loop's first
            hook = trial_hook([*self.emulators, *self._faulty])
            self._loop = _trial_loop(plan, self.drives, sink, progress, stop, hook=hook)
            if request.live is not None:  # beside the log sink and on the frame tap; a rank above: duck-typed
                request.live.attach(self._loop, self.drives)
            _commission(self.drives, plan, sink, self._session)
            self._open = outer.pop_all()
        return self

    def _enter_simulated(self) -> Rig:
        """The simulated drive's rig: the log, the drive (enabled) and the loop; nothing to stop or to report."""
        with contextlib.ExitStack() as stack:
            sink = _open_log(stack, self.request, self.plan)
            self.sinks.extend([sink] if sink is not None else [])
            drive = _simulated_drive(self.plan)
            progress = self.request.progress or _progress(self.plan, self.request.quiet)
            stack.callback(progress.close)
            # no signal handlers: simulate never installed any (and the Monte Carlo runs on Dask's worker threads)
            self._loop = _trial_loop(self.plan, [drive], sink, progress, StopRequest(), hook=drive.begin_trial)
            drive.enable()
            self._open = stack.pop_all()
        return self

    def __exit__(self, *exc: Any) -> bool:
        outcome = self._loop.outcome if self._loop is not None else None
        if exc[0] is None and outcome is not None and self._session is not None and outcome.timing is not None:
            outcome.timing = replace(outcome.timing, realtime=self._session.report)
        return bool(self._open.__exit__(*exc))

    @contextlib.contextmanager
    def _partial_on_error(self) -> Iterator[None]:
        """An error that ends the run carries what the run had done (``--json``'s error document)."""
        plan, request = self.plan, self.request
        try:
            yield
        except FoilcHilError as exc:
            ran = self._loop.outcome.trials if self._loop is not None else []
            exc.partial = {
                "law": plan.law_kind,
                "trials": [metrics.to_json() for metrics in logged_trials(ran, self.sinks)],
                "trials_run": len(ran),
                "stopped": str(exc).splitlines()[0] if str(exc) else type(exc).__name__,
                "log": str(request.out) if request.out is not None else "",
                "drive_stop": _worst(self.stops, plan.node_ids).to_json() if self.stops else None,
            }
            if plan.several:
                exc.partial["axes"] = [axis.to_json() for axis in _axis_outcomes(plan, self.stops)]
            raise

    def report(self) -> RunReport:
        """What the run produced (the rig closed): the trials its log holds, every drive's stop."""
        plan, loop = self.plan, self.loop
        loop.outcome.trials = logged_trials(loop.outcome.trials, self.sinks)
        return RunReport(
            law=plan.law_kind, outcome=loop.outcome, log=str(self.request.out) if self.request.out is not None else "",
            design=_design_summary(plan.axes[0].design), bus=self._bus, cycles=loop.cycles,
            drive_stop=_worst(self.stops, plan.node_ids),
            injected=[*(report for wrapper in self._faulty for report in wrapper.reports()),
                      *(plan.stalls.reports() if plan.stalls is not None else [])],
            axes=_axis_outcomes(plan, self.stops) if plan.several else [],
            stop_lines=[self.stops[node].describe(node) for node in plan.node_ids if node in self.stops],
        )


def _progress(plan: RunPlan, quiet: bool) -> ProgressView:
    from foilc_hil.progress import make_progress

    return make_progress(plan.title, quiet=quiet)


def _trial_loop(plan: RunPlan, drives: Sequence[Cia402Drive] | Sequence[SimulatedDrive], sink: McapSink | None,
                progress: ProgressView, stop: StopRequest, hook: Callable[[int], None] | None) -> TrialLoop:
    """The one loop: on the axis's own drive, law and limiter, or on the ``(m,)`` composites of several axes."""
    law, limiter = plan.law, plan.limiter
    if not plan.several:
        return TrialLoop(drives[0], law, plan.reference, limiter, plan.settings, log=sink, progress=progress,
                         stop=stop, before_trial=hook, stalls=plan.stalls)
    echoes = [echoes_demand(drive) for drive in drives]
    log = (AxesSink(sink, cast(AxisLaws, law), cast(AxisLimiter, limiter), plan.node_ids, echoes=echoes)
           if sink is not None else None)
    return TrialLoop(AxisGroup(drives), law, plan.reference, limiter, plan.settings, log=log, progress=progress,
                     stop=stop, before_trial=hook, stalls=plan.stalls)


def _simulated_drive(plan: RunPlan) -> SimulatedDrive:
    """The plant's physics behind the drive interface; the law looks ahead over the transport delay and the plant's
    own delay, the drive adds only the transport."""
    from foilc_hil.design.pipeline import model_delay_samples
    from foilc_hil.loop.simulated_drive import SimulatedDrive
    from plant_emulator.physics import build_plant

    config, law = plan.config, plan.axes[0].law
    transport = law.input_delay - model_delay_samples(config)
    return SimulatedDrive(build_plant(config.plant), sample_time=config.sample_time, input_delay=transport)


def _open_log(stack: contextlib.ExitStack, request: RunRequest, plan: RunPlan) -> McapSink | None:
    """The log, written by a child process (a writer thread here would take the loop's GIL for every frame it
    encodes); not waited for here: the child imports while the drives are commissioned (``McapSink.ready``). The
    simulated drive's is written in this process (no cycle to keep, no frames)."""
    from foilc_hil.config import dump_config
    from foilc_hil.io.log_process import ProcessLogWriter

    if request.out is None:
        return None
    limiter = plan.axes[0].limiter
    if plan.drive is DriveKind.SIMULATED:
        from foilc_hil.io.mcap_log import McapLogWriter

        simulated = McapLogWriter(request.out, config_yaml=dump_config(plan.config),
                                  design=plan.axes[0].design.to_json(), fsync=False)
        stack.callback(simulated.close)
        # /ilc/trial records the limits the law clamped to (replay --verify rebuilds the law with them)
        return McapSink(simulated, (limiter.lower, limiter.upper))
    writer = ProcessLogWriter.open(request.out, config_yaml=dump_config(plan.config),
                                   design=plan.axes[0].design.to_json(), wait=False)
    stack.callback(writer.close)
    if plan.several:
        _log_axes(writer, plan)
        # each axis's /ilc/trial carries its own limits (AxesSink)
        return McapSink(writer, None)
    return McapSink(writer, (limiter.lower, limiter.upper))


def _log_axes(writer: ProcessLogWriter, plan: RunPlan) -> None:
    """Each axis's own config and design, for ``replay --verify`` and ``report`` of one axis."""
    from foilc_hil.config import dump_config
    from foilc_hil.io.mcap_log import encode_design
    from foilc_hil.io.schemas import METADATA_AXIS_PREFIX

    for axis in plan.axes:
        writer.add_metadata(f"{METADATA_AXIS_PREFIX}.{axis.node_id}.config", {"yaml": dump_config(axis.config)})
        writer.add_metadata(f"{METADATA_AXIS_PREFIX}.{axis.node_id}.design", encode_design(axis.design.to_json()))


def _start_emulators(stack: contextlib.ExitStack, plan: RunPlan) -> tuple[BusConfig, list[EmbeddedEmulator]]:
    """``interface: embedded``: one emulated drive per axis (its own plant) on ONE in-process channel; returns the
    bus to open and the emulators. Injected faults act through a wrapper of the master's bus, which needs frames to
    pass its send and recv: the emulators then run threaded."""
    if plan.bus.interface != "embedded":
        return plan.bus, []
    from plant_emulator.embedded import CHANNEL_PREFIX, EmbeddedEmulator

    threaded = bool(plan.config.inject)
    channel = f"{CHANNEL_PREFIX}-axes-{id(plan):x}" if plan.several else None
    emulators = [stack.enter_context(EmbeddedEmulator.from_config(axis.config, channel=channel, threaded=threaded))
                 for axis in plan.axes]
    return emulators[0].bus_config, emulators


def _open_drives(stack: contextlib.ExitStack, plan: RunPlan, bus_cfg: BusConfig, sink: McapSink | None,
                 stops: dict[int, StopReport],
                 emulators: list[EmbeddedEmulator]) -> tuple[list[Cia402Drive], list[FaultyBus]]:
    """The bus (wrapped in each faulted axis's ``inject:``), one network, one master per axis (each safe-stopped on
    exit, its state read back)."""
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
        stack.callback(bus.shutdown)  # before the inner bus's: frames still held back go out first
        faulty.append(bus)
    # one receiver for every axis: one socket, one poll; injected faults act on the master's bus object, which a
    # second receiver would bypass
    network = DriveNetwork(bus, cyclic_receiver(stack, plan.settings, bus_cfg) if not faulty else None)
    stack.callback(network.close)
    if sink is not None:  # the master passes "tx" or "rx", the writer's Direction
        network.tap.add_listener(cast("Callable[[Any, str], None]", sink.writer.log_frame))
    drives = []
    for axis in plan.axes:
        drive = Cia402Drive.on_network(network, axis.config.drive, sample_time=plan.config.sample_time)
        drive.fatal_bad_frames = plan.config.bench.faults.bad_frame is BadFramePolicy.ABORT
        stack.callback(drive.close)
        drives.append(drive)
    # LIFO: every drive is safe-stopped (and its state read back) before any is closed and before the log closes
    for drive in drives:
        stack.callback(_record_stop, stops, drive)
    return drives, faulty


def _record_stop(stops: dict[int, StopReport], drive: Cia402Drive) -> None:
    """Safe-stop one axis's drive and keep what its statusword confirmed."""
    stops[drive.node_id] = drive.safe_stop()


def _commission(drives: Sequence[Cia402Drive], plan: RunPlan, sink: McapSink | None,
                session: RealtimeSession | None) -> None:
    """Connect every drive, enter the realtime ``session`` (if any: after connect, so the CAN receive thread exists
    to be raised; before the heartbeats are configured and SYNC is watched), configure every drive (NMT
    OPERATIONAL), log each PDO mapping, wait for the log writer, then enable every drive: the loop's first SYNC
    follows at once."""
    for drive in drives:
        drive.connect()
    if session is not None:
        session.__enter__()
    for drive, axis in zip(drives, plan.axes, strict=True):
        drive.configure(axis.config.drive.operation_mode)
    if sink is not None:
        _log_mappings(sink, drives, plan)
        sink.ready()
    for drive in drives:
        drive.enable()


def _log_mappings(sink: McapSink, drives: Sequence[Cia402Drive], plan: RunPlan) -> None:
    """Log the PDO mapping ``configure`` installed on each axis (``export --format dbc`` reads it): the first axis's
    also as the single-axis record, where readers of one axis find it."""
    from drivers.cia402_master import pdo_plan
    from foilc_hil.io.pdo_mapping import encode_pdo_mapping
    from foilc_hil.io.schemas import METADATA_AXIS_PREFIX, METADATA_PDO_MAPPING

    for k, (drive, axis) in enumerate(zip(drives, plan.axes, strict=True)):
        # the layouts of configure's preflight: the same function of the mode, the node and the drive's EDS
        mapping = pdo_plan(axis.config.drive.operation_mode, drive.node_id, drive.od,
                           demand_echo=axis.config.drive.demand_echo)
        record = encode_pdo_mapping(mapping.rpdos, mapping.tpdos)
        if plan.several:
            sink.writer.add_metadata(f"{METADATA_AXIS_PREFIX}.{drive.node_id}.pdo_mapping", record)
        if k == 0:
            sink.writer.add_metadata(METADATA_PDO_MAPPING, record)


def cyclic_receiver(stack: contextlib.ExitStack, settings: LoopSettings,
                    bus_cfg: BusConfig) -> CyclicReceiver | None:
    """Realtime with ``bench.realtime.cyclic_receive: loop``: the loop thread receives the TPDOs itself
    (:mod:`drivers.cyclic_rx`; closed on ``stack``). The caller leaves it out under injected faults: they act on the
    master's bus object, which a second one would bypass."""
    realtime = settings.realtime
    if settings.mode is not TimingMode.REALTIME or realtime.cyclic_receive is not CyclicReceive.LOOP:
        return None
    receiver = open_cyclic_receiver(bus_cfg, realtime.receive_spin)
    if receiver is not None:
        stack.callback(receiver.close)
    return receiver


def trial_hook(owners: Sequence[Any]) -> Callable[[int], None] | None:
    """What starts a trial besides the loop: the embedded emulators' physics and the injected faults' clock."""
    hooks = [hook for hook in (getattr(owner, "begin_trial", None) for owner in owners) if hook]
    if not hooks:
        return None

    def begin_trial(trial: int) -> None:
        for hook in hooks:
            hook(trial)

    return begin_trial


def realtime_session(stack: contextlib.ExitStack, settings: LoopSettings) -> RealtimeSession | None:
    """Realtime runs: the host setup ``bench.realtime`` (drivers.realtime), its exit registered on ``stack`` now;
    the caller enters it (exiting a session never entered changes nothing)."""
    if settings.mode is not TimingMode.REALTIME:
        return None
    session = RealtimeSession(settings.realtime)
    stack.push(session)
    return session


def stop_error(report: StopReport, node_id: int, subject: str) -> DriveError | None:
    """The error a run ends with when its stop of drive ``node_id`` (``subject`` in the message) was not confirmed
    or found the drive faulted; ``None`` when the drive is confirmed stopped and healthy."""
    if not report.confirmed:
        return DriveNotStoppedError(report.describe(node_id))
    if report.faults or report.state is State402.FAULT:
        reported = "; ".join(report.faults) or "a fault statusword"
        return DriveFaultError(f"{subject} reported {reported} at the end of the run; {report.describe(node_id)}")
    return None


# --- the report and the truth about the stops ---------------------------------------------------------------------


def _design_summary(design: Design) -> dict[str, Any]:
    return {"kp": design.kp, "r": design.r, "input_delay": design.input_delay, "gain_scale": design.gain_scale,
            "certificates": design.to_json().get("certificates", {})}


def _axis_outcomes(plan: RunPlan, stops: dict[int, StopReport]) -> list[AxisOutcome]:
    history = cast(AxisLaws, plan.law).history
    return [AxisOutcome(axis.node_id, list(history[k]), stops.get(axis.node_id), _design_summary(axis.design))
            for k, axis in enumerate(plan.axes)]


def _worst(stops: dict[int, StopReport], node_ids: Sequence[int]) -> StopReport:
    """The run's one ``drive_stop``: the first axis not confirmed disabled (or faulted), else the first axis's."""
    reports = [stops[node] for node in node_ids if node in stops]
    for report in reports:
        if not report.confirmed or report.faults or report.state is State402.FAULT:
            return report
    return reports[0] if reports else StopReport(commanded=False, confirmed=False)


@contextlib.contextmanager
def _truth_about_the_stops(stops: dict[int, StopReport], node_ids: Sequence[int]) -> Iterator[None]:
    """Say what each final stop really reached: a note per axis on an error that ends the run (and every axis's
    stop in its facts), and an error (exit 1) for a run that otherwise succeeded but left a drive unconfirmed or
    faulted."""
    try:
        yield
    except FoilcHilError as exc:
        if stops:
            exc.facts = {**(exc.facts or {}), "drive_stop": _worst(stops, node_ids).to_json()}
            if len(node_ids) > 1:
                exc.facts["drive_stops"] = {str(node): stops[node].to_json() for node in stops}
        for node in node_ids:
            if node not in stops:
                continue
            exc.add_note(stops[node].describe(node))
            also = [fault for fault in stops[node].faults if fault != str(exc)]  # the same error again says nothing
            if also:
                exc.add_note("the drive also reported: " + "; ".join(also))
        raise
    for node in node_ids:
        report = stops.get(node, StopReport(commanded=False, confirmed=False))
        error = stop_error(report, node, "the drive" if len(node_ids) == 1 else f"node {node}")
        if error is not None:
            error.facts = {"drive_stop": report.to_json()}
            if len(node_ids) > 1:
                error.facts["drive_stops"] = {str(n): r.to_json() for n, r in stops.items()}
            raise error

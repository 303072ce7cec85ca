"""Offline learning trials: the bench's trial loop on a simulated drive, over the one physics code path.

:func:`simulate` runs :class:`~foilc_hil.loop.bench.TrialLoop` -- the loop ``foilc-hil run`` runs over CAN -- in
lockstep on a :class:`~foilc_hil.loop.simulated_drive.SimulatedDrive`, which puts
``plant_emulator.physics.build_plant(config.plant)`` behind the bench's drive interface with a transport delay of
the law's ``input_delay`` cycles (1: the SYNC-driven CAN loop; 0: the ideal loop). Each trial: the drive resets
the plant for trial ``k`` (initial condition, disturbance armed from ``disturbance.start_trial``), then for
``t = 0 .. N-1`` the law gets the measured output ``y(t Ts)`` and returns ``u(t)``, and finally the trial arrays
(values at ``(i + 1) Ts``, see :mod:`foilc_hil.references`) go to
:meth:`~foilc_hil.laws.learning.LearningLaw.end_trial`. The divergence rule, the per-sample log and the metrics are
the bench's. No plant dynamics and no trial loop are written here.

The tables of ``docs/paper-reproduction.md`` (every law over seeds) are generated outside the package, by
``python -m benchmarks.reproduction``.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from foilc_hil.design.record import jsonable
from foilc_hil.errors import ConfigError, LearningDivergedError
from foilc_hil.metrics import TrialMetrics

if TYPE_CHECKING:
    from foilc_hil.config import Config
    from foilc_hil.design.record import Design
    from foilc_hil.laws.learning import LearningLaw
    from foilc_hil.loop.bench import McapSink, TrialRecord
    from foilc_hil.loop.scheduler import CycleTiming

__all__ = [
    "SimulationResult",
    "build_law",
    "plot_simulation",
    "simulate",
]

@dataclass
class SimulationResult:
    """Everything a simulation produced.

    Attributes
    ----------
    law
        ``foilc``, ``ioilc`` or ``p-type``.
    metrics
        One :class:`~foilc_hil.metrics.TrialMetrics` per completed trial.
    time
        ``(i + 1) Ts``, ``(N,)``: the instants of the trial arrays.
    reference
        ``(N, p)``.
    outputs, errors, learned
        ``(K, N, p)`` per completed trial: ``y``, ``e`` and ``E`` at ``(i + 1) Ts``.
    controls
        ``(K, N, m)``: the command ``u(i)`` issued in sample ``i``.
    feedback
        ``(K, N, p)``: the output the law saw in sample ``i`` (``y(i Ts)``).
    certificates
        The design's certificates (2D laws) or the P-type lifted-map certificates.
    design
        The design the 2D laws ran with (``None`` for P-type).
    stopped
        Empty, or why the run stopped early (learning diverged).
    seconds
        Wall-clock time of the trial loop.
    """

    law: str
    metrics: list[TrialMetrics]
    time: np.ndarray
    reference: np.ndarray
    outputs: np.ndarray
    controls: np.ndarray
    errors: np.ndarray
    learned: np.ndarray
    feedback: np.ndarray
    certificates: dict[str, Any] = field(default_factory=dict)
    design: Design | None = None
    stopped: str = ""
    seconds: float = 0.0

    def to_json(self) -> dict[str, Any]:
        """The ``simulate --json`` document: ``{"law", "trials": [...]}`` plus ``certificates``/``stopped``."""
        document: dict[str, Any] = {"law": self.law, "trials": [m.to_json() for m in self.metrics]}
        document["certificates"] = jsonable(self.certificates)
        if self.design is not None:
            document["design"] = {
                "kp": self.design.kp,
                "r": self.design.r,
                "gain_scale": self.design.gain_scale,
                "gamma": self.design.gamma,
                "P": self.design.P.tolist(),
                "input_delay": self.design.input_delay,
            }
        if self.stopped:
            document["stopped"] = self.stopped
        return document


# --- design and law ---------------------------------------------------------------------------------------------


def build_law(
    config: Config, law: str, n_samples: int, *, design: Design | None = None, input_delay: int = 0
) -> tuple[LearningLaw, Design | None, dict[str, Any]]:
    """The law ``law`` for ``config`` with its design and certificates (:mod:`foilc_hil.design.pipeline`), clamping
    to the bench's command limits (:func:`~foilc_hil.loop.bench.command_limiter`) as ``run`` builds it.

    Why the limits offline too: a sample whose error no command can remove (the demo's first samples: the reference
    asks for more acceleration than the torque limit gives) is integrated trial after trial. Unclamped, the learned
    command there grew by about 3,000 rpm a trial (93,700 rpm at trial 30 on the demo axis), a command the bench
    would never send; clamped, the law learns from what is applied, as on the bench.
    """
    from foilc_hil.design.pipeline import build_design, model_delay_samples
    from foilc_hil.laws.learning import make_law
    from foilc_hil.loop.bench import command_limiter

    if design is None:
        design = build_design(config, law, n_samples, input_delay=input_delay)
    elif design.law != law and not (law == "ioilc" and design.kp == 0):
        raise ConfigError(f"the design is for law {design.law!r}, not {law!r}", key="law.kind")
    elif design.input_delay < model_delay_samples(config):
        # The design's input_delay is the whole delay its law looks ahead over (transport + the plant's own); the
        # simulated drive adds only the difference, which cannot be negative. Running the law anyway would time
        # every update against samples the plant has not answered yet.
        raise ConfigError(
            f"is {model_delay_samples(config)} sample(s), more than the design's input_delay "
            f"{design.input_delay}: re-synthesize the design for this plant",
            key="plant.delay",
        )
    certificates = {} if design.certificates is None else design.certificates.to_json()
    limiter = command_limiter(config)
    return make_law(design, config.law, n_samples, limits=(limiter.lower, limiter.upper)), design, certificates


# --- the trial loop: the bench's, on a simulated drive ----------------------------------------------------------


def simulate(
    config: Config,
    *,
    law: str,
    trials: int,
    design: Design | None = None,
    input_delay: int = 0,
    out: str | Path | None = None,
) -> SimulationResult:
    """Run ``trials`` learning trials of ``law`` offline on ``build_plant(config.plant)``.

    The trials run in the bench's :class:`~foilc_hil.loop.bench.TrialLoop`, in lockstep, on a
    :class:`~foilc_hil.loop.simulated_drive.SimulatedDrive` whose transport delay is the law's input delay; the
    drive resets the plant before each trial, so there is no settle phase. The law clamps to the bench's command
    limits (:func:`build_law`); the drive has none of its own (the plant's ``saturation`` acts inside the plant).

    Parameters
    ----------
    config
        The whole configuration (plant, reference, sample time, tuning, synthesis, law, bench).
    law
        ``foilc``, ``ioilc`` or ``p-type``.
    trials
        Number of trials.
    design
        A ready design (skips tuning and synthesis).
    input_delay
        Samples between issuing ``u(t)`` and the plant applying it (1 emulates a SYNC-driven CAN loop, 0 is the
        ideal loop); the design is made for the same delay.
    out
        Optional MCAP file (layout of ``docs/interface.md``).

    Returns
    -------
    SimulationResult
        If learning diverges the run stops after that trial and ``stopped`` says why: non-finite values, or the
        bench's rule (:class:`~foilc_hil.loop.safety.DivergenceGuard`): a trial's SSE above
        ``bench.divergence_factor`` times the best SSE so far.
    """
    from foilc_hil.references import trial_samples

    if trials < 1:
        raise ConfigError(f"must be >= 1, got {trials}", key="trials")
    n = trial_samples(config.reference, config.sample_time)
    learning_law, used_design, certificates = build_law(config, law, n, design=design, input_delay=input_delay)
    if learning_law.n_inputs != 1 or learning_law.n_outputs != 1:
        raise ConfigError(
            f"the trial loop drives one axis; the law is {learning_law.n_outputs}x{learning_law.n_inputs}", key="plant"
        )
    started = time.perf_counter()
    with contextlib.ExitStack() as stack:
        limits = learning_law.limits
        log = _open_log(stack, out, config, used_design, limits) if out is not None else None
        collector = _TrialCollector(log)
        stopped = _run_trials(config, learning_law, trials, collector)
    return _result(config, law, collector.records, certificates, used_design, stopped, time.perf_counter() - started)


class _TrialCollector:
    """The loop's log sink offline: keeps every finished trial (the result's arrays) and passes it to the log."""

    def __init__(self, log: McapSink | None) -> None:
        self.log = log
        self.records: list[TrialRecord] = []

    def trial_finished(self, record: TrialRecord) -> None:
        self.records.append(record)
        if self.log is not None:
            self.log.trial_finished(record)

    def timing(self, records: Iterator[CycleTiming]) -> None:
        if self.log is not None:
            self.log.timing(records)


def _run_trials(config: Config, law: LearningLaw, trials: int, collector: _TrialCollector) -> str:
    """The bench's trial loop on a simulated drive, in lockstep; returns why it stopped early (``""``: it did not)."""
    from foilc_hil.design.pipeline import model_delay_samples
    from foilc_hil.loop.bench import TrialLoop, loop_settings
    from foilc_hil.loop.simulated_drive import SimulatedDrive
    from foilc_hil.references import reference_profile
    from plant_emulator.device import TimingMode
    from plant_emulator.physics import build_plant

    # the law looks ahead over the transport delay and the plant's own delay; the drive adds only the transport
    transport = law.input_delay - model_delay_samples(config)
    drive = SimulatedDrive(build_plant(config.plant), sample_time=config.sample_time, input_delay=transport)
    loop = TrialLoop(
        drive,
        law,
        reference_profile(config.reference, config.sample_time),
        None,
        loop_settings(config, TimingMode.LOCKSTEP, settle_between_trials=False),
        log=collector,
        before_trial=drive.begin_trial,
    )
    drive.enable()
    try:
        return loop.run(trials).stopped or ""
    except LearningDivergedError as exc:  # a non-finite output or command: the trials before it are the result
        return str(exc)


def _result(
    config: Config,
    law: str,
    records: Sequence[TrialRecord],
    certificates: dict[str, Any],
    design: Design | None,
    stopped: str,
    seconds: float,
) -> SimulationResult:
    """The per-trial arrays of the finished trials, as ``(K, N, 1)`` (one output, one input)."""
    from foilc_hil.references import reference_profile, sample_times

    ts = config.sample_time
    reference = reference_profile(config.reference, ts)
    n = reference.shape[0]

    def stacked(rows: list[np.ndarray]) -> np.ndarray:
        return np.array(rows, dtype=float).reshape(len(rows), n, 1)

    return SimulationResult(
        law=law,
        metrics=[record.metrics for record in records],
        time=sample_times(config.reference, ts),
        reference=reference[:, None],
        outputs=stacked([record.output for record in records]),
        controls=stacked([record.control for record in records]),
        errors=stacked([record.error for record in records]),
        learned=stacked([record.E for record in records]),
        # y_i the law saw at sample i: the first N of the trial's N + 1 feedbacks (the last closes the output array)
        feedback=stacked([record.seen[:-1] for record in records]),
        certificates=certificates,
        design=design,
        stopped=stopped,
        seconds=seconds,
    )


def _open_log(
    stack: contextlib.ExitStack, out: str | Path, config: Config, design: Design | None,
    limits: tuple[float, float] | None,
) -> McapSink:
    from foilc_hil.config import dump_config
    from foilc_hil.io.mcap_log import McapLogWriter
    from foilc_hil.loop.bench import McapSink

    writer = McapLogWriter(
        out,
        config_yaml=dump_config(config),
        design=design.to_json() if design is not None else None,
        fsync=False,
    )
    stack.callback(writer.close)
    return McapSink(writer, limits)  # /ilc/trial records the limits the law clamped to (replay --verify uses them)


# --- plots ------------------------------------------------------------------------------------------------------


def plot_simulation(result: SimulationResult, out_dir: str | Path) -> list[Path]:
    """Write ``outputs.png``, ``control.png``, ``error.png`` and ``sse.png`` (matplotlib, Agg) into ``out_dir``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory = Path(out_dir)
    directory.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    t = result.time
    panels = (
        ("outputs.png", "output y", result.outputs, True),
        ("control.png", "control u", result.controls, False),
        ("error.png", "tracking error e", result.errors, False),
    )
    colors = plt.get_cmap("viridis")
    count = max(len(result.metrics), 1)
    for name, label, data, with_reference in panels:
        fig, ax = plt.subplots(figsize=(8, 4.5))
        for k in range(data.shape[0]):
            ax.plot(t, data[k, :, 0], color=colors(k / max(count - 1, 1)), lw=1.0, label=f"trial {k + 1}")
        if with_reference:
            ax.plot(t, result.reference[:, 0], "k--", lw=1.0, label="reference")
        ax.set_xlabel("time [s]")
        ax.set_ylabel(label)
        ax.set_title(f"{result.law}: {label} by trial")
        ax.grid(True, alpha=0.3)
        if data.shape[0] <= 12:
            ax.legend(fontsize="small", ncol=2)
        path = directory / name
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.semilogy([m.trial for m in result.metrics], [max(m.sse, 1e-300) for m in result.metrics], "o-")
    ax.set_xlabel("trial")
    ax.set_ylabel("SSE")
    ax.set_title(f"{result.law}: sum of squared errors")
    ax.grid(True, which="both", alpha=0.3)
    path = directory / "sse.png"
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)
    return written

"""Offline learning trials: the bench's trial loop on a simulated drive, over the one physics code path.

:func:`simulate` runs :class:`~foilc_hil.loop.bench.TrialLoop` -- the loop ``foilc-hil run`` runs over CAN -- in
lockstep on a :class:`~foilc_hil.loop.simulated_drive.SimulatedDrive`, which puts
``plant_emulator.physics.build_plant(config.plant)`` behind the bench's drive interface with a transport delay of
the law's ``input_delay`` cycles (1: the SYNC-driven CAN loop; 0: the ideal loop). Each trial: the drive resets
the plant for trial ``k`` (initial condition, disturbance armed from ``disturbance.start_trial``), then for
``t = 0 .. N-1`` the law gets the measured output ``y(t Ts)`` and returns ``u(t)``, and finally the trial arrays
(values at ``(i + 1) Ts``, see :mod:`foilc_hil.references`) go to
:meth:`~foilc_hil.laws.learning.LearningLaw.end_trial`. The divergence rule, the per-sample log and the metrics are
the bench's. The rig of every run wires it (:mod:`foilc_hil.loop.rig`, ``DriveKind.SIMULATED``): no plant
dynamics, no trial loop and no wiring are written here.

The tables of ``docs/paper-reproduction.md`` (every law over seeds) are generated outside the package, by
``python -m benchmarks.reproduction``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from foilc_hil.design.json_fields import jsonable
from foilc_hil.errors import LearningDivergedError
from foilc_hil.metrics import TrialMetrics

if TYPE_CHECKING:
    from foilc_hil.config import Config
    from foilc_hil.design.record import Design
    from foilc_hil.loop.interfaces import TrialRecord

__all__ = [
    "SimulationResult",
    "plot_simulation",
    "simulate",
]

@dataclass
class SimulationResult:
    """Everything a simulation produced.

    Attributes
    ----------
    law
        ``foilc``, ``ioilc``, ``p-type``, ``noilc`` or ``gradient``.
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


# --- the trial loop: the bench's, on a simulated drive, through the one rig ---------------------------------------


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
    :class:`~foilc_hil.loop.simulated_drive.SimulatedDrive` whose transport delay is the law's input delay, wired
    by the rig of every run (:class:`~foilc_hil.loop.rig.Rig`, ``DriveKind.SIMULATED``); the drive resets the plant
    before each trial, so there is no settle phase. The law clamps to the bench's command limits
    (:func:`~foilc_hil.loop.rig.plan_axis`); the drive has none of its own (the plant's ``saturation`` acts inside
    the plant).

    Parameters
    ----------
    config
        The whole configuration (plant, reference, sample time, tuning, synthesis, law, bench).
    law
        ``foilc``, ``ioilc``, ``p-type``, ``noilc`` or ``gradient``.
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
    from foilc_hil.loop.rig import DriveKind, Rig, RunRequest

    rig = Rig(RunRequest(config=config, out=out, law=law, trials=trials, design=design, drive=DriveKind.SIMULATED,
                         input_delay=input_delay))
    started = time.perf_counter()
    records: list[TrialRecord] = []
    try:
        with rig:
            records.extend(rig.loop.iter_trials(rig.plan.trials))
        stopped = rig.loop.outcome.stopped or ""
    except LearningDivergedError as exc:  # a non-finite output or command: the trials before it are the result
        stopped = str(exc)
    used = rig.plan.axes[0].design
    certificates = {} if used.certificates is None else used.certificates.to_json()
    return _result(config, law, records, certificates, used, stopped, time.perf_counter() - started)


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

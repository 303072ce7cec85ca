"""The paper's claims over seeds: every law run on the same plant under many seeds, each seed moving what the paper
leaves to chance (issue 26, target 9).

A seed moves, on a copy of the config (:func:`seeded_config`):

- the sensor noise's realisation (``plant.noise_seed``; the noise's size is the config's ``plant.output_noise`` or,
  where the config has none, a fixed fraction of the reference range, so that there is a realisation to move);
- the phase of the time-varying parameters: ``plant.variation.a/b.phase`` of a first-order plant's sines
  (``Delta a(t) = 0.1 sin(t + phase)``), ``plant.pmsm.drift.phase`` of a PMSM's inertia drift;
- the phase of the disturbance (``plant.disturbance.phase``, sine or square wave).

The phases are drawn uniformly on ``[0, 2 pi)`` from the seed alone, so seed ``s`` is the same plant for every law:
the laws are compared seed by seed (:mod:`benchmarks.verdicts`). A law is designed once, on the nominal model,
which no seed changes; only its runs are repeated. Runs are the offline bench loop
(:func:`foilc_hil.loop.simulation.simulate`), no network.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from foilc_hil.config import Config, LawKind
from foilc_hil.errors import FoilcHilError

__all__ = [
    "LawStudy",
    "PlantStudy",
    "RunFigures",
    "SeedDraw",
    "StudySettings",
    "moved_signals",
    "run_figures",
    "run_study",
    "seed_draw",
    "seeded_config",
]


@dataclass(frozen=True)
class SeedDraw:
    """The phases (rad) seed ``seed`` gives; each applies only where the config has that signal."""

    seed: int
    variation_a: float
    variation_b: float
    drift: float
    disturbance: float


def seed_draw(seed: int) -> SeedDraw:
    """The phases of ``seed``: uniform on ``[0, 2 pi)``, from a generator of the seed alone (not of the config)."""
    a, b, drift, disturbance = np.random.default_rng([26, int(seed)]).uniform(0.0, 2.0 * math.pi, 4)
    return SeedDraw(int(seed), float(a), float(b), float(drift), float(disturbance))


def seeded_config(config: Config, seed: int, noise: float) -> Config:
    """``config`` with seed ``seed``'s noise realisation (std ``noise``) and phases (:func:`seed_draw`)."""
    draw = seed_draw(seed)
    plant = config.plant
    updates: dict[str, object] = {"noise_seed": draw.seed, "output_noise": float(noise)}
    variation = plant.variation
    moved = {}
    for name, phase in (("a", draw.variation_a), ("b", draw.variation_b)):
        signal = getattr(variation, name)
        if signal.kind == "sine":
            moved[name] = signal.model_copy(update={"phase": phase})
    if moved:
        updates["variation"] = variation.model_copy(update=moved)
    if plant.model == "pmsm" and plant.pmsm.drift.amplitude > 0:
        drift = plant.pmsm.drift.model_copy(update={"phase": draw.drift})
        updates["pmsm"] = plant.pmsm.model_copy(update={"drift": drift})
    if plant.disturbance.kind in ("sine", "square"):
        updates["disturbance"] = plant.disturbance.model_copy(update={"phase": draw.disturbance})
    return config.model_copy(update={"plant": plant.model_copy(update=updates)})


def moved_signals(config: Config) -> list[str]:
    """What a seed moves on ``config`` besides the noise, in words (the page says it)."""
    plant = config.plant
    moved = [f"the phase of Delta {name}(t)" for name in ("a", "b") if getattr(plant.variation, name).kind == "sine"]
    if plant.model == "pmsm" and plant.pmsm.drift.amplitude > 0:
        moved.append("the phase of the inertia drift (`pmsm.drift.phase`)")
    if plant.disturbance.kind in ("sine", "square"):
        moved.append(f"the phase of the {plant.disturbance.kind} disturbance (`plant.disturbance.phase`)")
    return moved


@dataclass(frozen=True)
class StudySettings:
    """How many seeds and trials, the tolerance and the noise of one plant's study."""

    seeds: tuple[int, ...]
    trials: int
    tolerance: float
    noise: float
    disturbance_trial: int
    laws: tuple[LawKind, ...]


@dataclass(frozen=True)
class RunFigures:
    """The figures of one law's run on one seed (errors over the learnable samples, ``TrialMetrics``).

    Trials that never reach the tolerance count as one past the last trial (``reached`` says whether they did).
    ``disturbance_jump`` is the SSE the disturbance trial adds to the trial before it: the disturbance's share,
    where the SSE of the disturbance trial itself also holds the noise every trial has.
    """

    trials_to_tolerance: float
    reached: bool
    rmse_trial_3: float
    transient_sse: float
    disturbance_sse: float
    disturbance_jump: float
    recovery_trials: float
    recovered: bool
    final_rmse: float
    sse_by_trial: tuple[float, ...]
    stopped: str


def run_figures(rmse: Sequence[float], sse: Sequence[float], settings: StudySettings, stopped: str) -> RunFigures:
    """The figures from a run's learnable RMSE and SSE per trial (a run that stopped early has fewer trials: the
    figures of the trials it did not run are NaN)."""
    trials, start, tol = settings.trials, settings.disturbance_trial, settings.tolerance

    def at(values: Sequence[float], trial: int) -> float:
        return float(values[trial - 1]) if len(values) >= trial else math.nan

    reached = next((k + 1 for k, value in enumerate(rmse) if value < tol), None)
    recovery = next((k + 1 - start for k in range(start - 1, len(rmse)) if rmse[k] < tol), None)
    transient = [at(sse, trial) for trial in range(2, start)]
    return RunFigures(
        trials_to_tolerance=float(trials + 1 if reached is None else reached),
        reached=reached is not None,
        rmse_trial_3=at(rmse, 3),
        transient_sse=float(sum(transient)),
        disturbance_sse=at(sse, start),
        disturbance_jump=at(sse, start) - at(sse, start - 1),
        recovery_trials=float(trials - start + 1 if recovery is None else recovery),
        recovered=recovery is not None,
        final_rmse=at(rmse, trials),
        sse_by_trial=tuple(float(value) for value in sse),
        stopped=stopped,
    )


@dataclass(frozen=True)
class LawStudy:
    """One law over the seeds: its design (once) and its runs (one per seed, in the order of the seeds)."""

    law: LawKind
    runs: tuple[RunFigures, ...]
    design_seconds: float
    run_seconds: float
    kp: float | None = None
    r: float | None = None
    spectral_radius: float | None = None
    norm_2: float | None = None
    gamma: float | None = None
    gain_scale: float | None = None
    refused: str = ""


@dataclass(frozen=True)
class PlantStudy:
    """Every law over the seeds on one plant, and the wall time it took."""

    config: Config
    settings: StudySettings
    laws: tuple[LawStudy, ...]
    seconds: float

    def law(self, kind: LawKind) -> LawStudy | None:
        """The study of ``kind``, if it ran."""
        return next((law for law in self.laws if law.law is kind and not law.refused), None)


def _learnable(errors: np.ndarray, first: int) -> tuple[list[float], list[float]]:
    """Learnable RMSE and SSE per trial from the ``(K, N, p)`` errors (samples from ``first`` on)."""
    part = errors[:, first:, :]
    sse = np.sum(part * part, axis=(1, 2))
    return [float(v) for v in np.sqrt(sse / (part.shape[1] * part.shape[2]))], [float(v) for v in sse]


def _study_law(config: Config, law: LawKind, settings: StudySettings, n_samples: int) -> LawStudy:
    """Design ``law`` once, then run it on every seed."""
    from foilc_hil.design.pipeline import build_design
    from foilc_hil.loop.simulation import simulate

    began = time.perf_counter()
    try:
        design = build_design(config, law, n_samples, input_delay=0)
    except FoilcHilError as exc:  # an infeasible or uncertified design is a result too: the page reports it
        return LawStudy(law, (), time.perf_counter() - began, 0.0, refused=f"{type(exc).__name__}: {exc}")
    design_seconds = time.perf_counter() - began
    first = min(design.input_delay, n_samples - 1)  # the first error sample an input can move (TrialMetrics' rule)
    runs = []
    began = time.perf_counter()
    for seed in settings.seeds:
        result = simulate(seeded_config(config, seed, settings.noise), law=law, trials=settings.trials, design=design)
        rmse, sse = _learnable(result.errors, first)
        runs.append(run_figures(rmse, sse, settings, result.stopped))
    certificates = {} if design.certificates is None else design.certificates.to_json()

    def number(key: str) -> float | None:
        value = certificates.get(key)
        return float(value) if isinstance(value, (int, float)) else None

    return LawStudy(
        law, tuple(runs), design_seconds, time.perf_counter() - began, kp=design.kp, r=design.r,
        spectral_radius=number("spectral_radius"), norm_2=number("norm_2"), gamma=design.gamma,
        gain_scale=design.gain_scale,
    )


def run_study(
    config: Config, settings: StudySettings, progress: Callable[[str], None] | None = None
) -> PlantStudy:
    """Every law of ``settings`` on every seed of ``settings`` on ``config``'s plant."""
    from foilc_hil.references import trial_samples

    began = time.perf_counter()
    n_samples = trial_samples(config.reference, config.sample_time)
    laws = []
    for law in settings.laws:
        laws.append(_study_law(config, law, settings, n_samples))
        if progress is not None:
            done = laws[-1]
            progress(f"{law}: design {done.design_seconds:.1f} s, {len(done.runs)} runs {done.run_seconds:.1f} s")
    return PlantStudy(config, settings, tuple(laws), time.perf_counter() - began)

"""The robustness Monte Carlo that runs trials: every law over plants drawn from the uncertainty set, on Dask.

``foilc-hil robustness`` designs each law once on the nominal configuration (the one pipeline, ``build_design``),
then runs it with :func:`~foilc_hil.loop.simulation.simulate` -- the bench's trial loop on the one physics code
path -- on every drawn plant, and reports per draw the certificate of the drawn (frozen) plant, the trials to
tolerance, the final RMSE, the noise floor and whether learning diverged; then the distributions over the draws.

The uncertainty set
-------------------
For a ``first_order`` plant the set is the variation box of ``plant.variation``: ``|Delta a| <= A_a``,
``|Delta b| <= A_b`` (the configured amplitudes, whatever their kind). Draw ``i`` (its own generator
``numpy.random.default_rng([seed, i])``, so a draw does not depend on how the draws are split into tasks) takes

- a frozen offset ``Delta = f A`` per parameter, ``f`` uniform on ``[-1, 1]`` (``a`` shifts every mode, ``b`` every
  non-zero entry, as in :mod:`plant_emulator.physics.first_order`);
- a time-varying part: a seeded random walk (``kind: random_walk``, the configured rate) bounded by the rest of the
  box, ``(1 - |f|) A``, so ``|Delta(t)| <= A`` always;
- the disturbance ``plant.disturbance`` with its amplitude scaled by a factor uniform on ``[-1, 1]``;
- the sensor noise ``plant.output_noise`` (or ``--noise``) with the draw's own seed (``plant.seed``).

The corners of the box come first (frozen, no walk, the full disturbance, the configured seed), so the worst
frozen plant is always among the draws. A ``pmsm`` plant has no box: its draws are the seeded parameter spread
(``pmsm.spread``, by ``plant.seed``), the disturbance and the noise.

Per draw
--------
- **Certificate**: the spectral radius and induced 2-norm of the lifted trial-to-trial map of the law as it runs
  (:func:`foilc_hil.design.robustness.certify_draws`) on the drawn frozen plant, discretised like the design model.
  It covers the frozen part only (a time-varying ``Delta(t)`` has no trial-invariant lifted map); a ``pmsm`` draw
  reports the design model's nominal certificate.
- **Trials to tolerance**: the first trial whose ``rmse_learnable`` is below the tolerance (``None``: never).
- **Final RMSE**: the last completed trial's ``rmse_learnable``.
- **Noise floor**: the RMS of the per-trial :func:`~foilc_hil.metrics.noise_floor` over the last third of the trials
  (at least one; ``docs/robustness.md``).
- **Diverged**: the run stopped early (the bench's divergence rule, or a non-finite output or command).

Execution
---------
One ``dask.delayed`` task per law's design and one per chunk of draws and law, computed on the
``dask.distributed`` client given (a ``LocalCluster`` or a running cluster's scheduler); the configuration and each
design are single shared nodes of the graph. The result does not depend on the number of workers.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from foilc_hil.config import Config, LawKind
from foilc_hil.design.lifted import LawStructure
from foilc_hil.design.map_norms import CONTRACTION_LIMIT
from foilc_hil.design.pipeline import build_design, design_model
from foilc_hil.design.record import Design
from foilc_hil.design.robustness import DrawCertificate, Perturbation, certify_draws, running_law
from foilc_hil.errors import InputError
from foilc_hil.loop.simulation import simulate
from foilc_hil.progress import step
from plant_emulator.config import ParameterVariation, VariationConfig
from plant_emulator.linear import continuous_model

__all__ = [
    "QUANTILES",
    "DrawOutcome",
    "LawRobustness",
    "MonteCarloSettings",
    "PlantDraw",
    "RobustnessReport",
    "draw_plants",
    "drawn_config",
    "plot_robustness",
    "run_draws",
    "run_robustness",
]

#: Quantiles of every per-draw figure reported (besides the worst).
QUANTILES = (0.5, 0.9, 0.99)
#: Chunks per worker and law: enough to balance the load, few enough that the scheduler's overhead stays small. A
#: chunk no longer carries a per-chunk cost (the NOILC gain and its Gram matrix are kept per process), so the last
#: chunk a worker runs alone is short: 16 gives about 8 s of NOILC work per chunk at 1,000 draws on 2 workers (4: 33 s).
CHUNKS_PER_WORKER = 16
#: The per-draw figures summarised (their distributions, quantiles and plots).
FIGURES = ("norm_2", "spectral_radius", "trials_to_tolerance", "final_rmse", "noise_floor")


@dataclass(frozen=True)
class MonteCarloSettings:
    """What every draw runs: ``trials`` trials, the sensor noise ``noise``, tolerance on ``rmse_learnable``."""

    samples: int
    seed: int
    trials: int
    noise: float
    tolerance: float
    input_delay: int = 1

    def __post_init__(self) -> None:
        for name, value in (("--samples", self.samples), ("--seed", self.seed), ("--input-delay", self.input_delay)):
            if value < 0:
                raise InputError(f"{name}: must be >= 0, got {value}")
        if self.trials < 2:
            raise InputError(f"--trials: must be >= 2 (the noise floor compares trials), got {self.trials}")
        if not (math.isfinite(self.noise) and self.noise >= 0):
            raise InputError(f"--noise: must be a finite number >= 0, got {self.noise}")
        if not (math.isfinite(self.tolerance) and self.tolerance > 0):
            raise InputError(f"--tolerance: must be a finite number > 0, got {self.tolerance}")


@dataclass(frozen=True)
class PlantDraw:
    """One plant of the uncertainty set (module notes); ``vertex``: a corner of the variation box."""

    index: int
    vertex: bool
    delta_a: float
    delta_b: float
    walk_a: float
    walk_b: float
    disturbance_scale: float
    seed: int

    def to_json(self) -> dict[str, Any]:
        """``{"index", "vertex", "delta_a", "delta_b", "walk_a", "walk_b", "disturbance_scale", "seed"}``."""
        return {
            "index": self.index,
            "vertex": self.vertex,
            "delta_a": self.delta_a,
            "delta_b": self.delta_b,
            "walk_a": self.walk_a,
            "walk_b": self.walk_b,
            "disturbance_scale": self.disturbance_scale,
            "seed": self.seed,
        }


def _box(variation: VariationConfig) -> float:
    return 0.0 if variation.kind == "none" else float(variation.amplitude)


def draw_plants(config: Config, samples: int, seed: int) -> list[PlantDraw]:
    """The corners of the variation box (``first_order`` plants with a box), then ``samples`` seeded random draws."""
    plant = config.plant
    box_a, box_b = _box(plant.variation.a), _box(plant.variation.b)
    draws: list[PlantDraw] = []
    if plant.model == "first_order" and (box_a > 0 or box_b > 0):
        corners = sorted(set(itertools.product((-box_a, box_a), (-box_b, box_b))))
        draws = [PlantDraw(i, True, da, db, 0.0, 0.0, 1.0, plant.seed) for i, (da, db) in enumerate(corners)]
    if plant.model != "first_order":
        box_a = box_b = 0.0
    start = len(draws)
    for i in range(samples):
        rng = np.random.default_rng([seed, i])
        fa, fb, scale = rng.uniform(-1.0, 1.0, 3)
        plant_seed = int(rng.integers(0, 2**31))
        draws.append(
            PlantDraw(
                start + i, False, float(fa * box_a), float(fb * box_b), float((1 - abs(fa)) * box_a),
                float((1 - abs(fb)) * box_b), float(scale), plant_seed,
            )
        )
    return draws


def _walk(variation: VariationConfig, amplitude: float) -> VariationConfig:
    if amplitude <= 0:
        return VariationConfig()
    return VariationConfig(kind="random_walk", amplitude=amplitude, frequency=variation.frequency)


def drawn_config(config: Config, draw: PlantDraw, noise: float) -> Config:
    """``config`` with its plant replaced by ``draw`` (module notes) and sensor noise ``noise``."""
    plant = config.plant
    scaled = plant.disturbance.amplitude * draw.disturbance_scale
    disturbance = plant.disturbance.model_copy(update={"amplitude": scaled})
    updates: dict[str, Any] = {"seed": draw.seed, "output_noise": noise, "disturbance": disturbance}
    if plant.model == "first_order":
        model = continuous_model(plant)
        a = model.a + draw.delta_a * np.eye(model.n_states)
        b = model.b + draw.delta_b * (model.b != 0)
        updates |= {
            "a": a.tolist(),
            "b": b.tolist(),
            "c": model.c.tolist(),
            "num": None,
            "den": None,
            "variation": ParameterVariation(
                a=_walk(plant.variation.a, draw.walk_a), b=_walk(plant.variation.b, draw.walk_b)
            ),
        }
    return config.model_copy(update={"plant": plant.model_copy(update=updates)})


@dataclass(frozen=True)
class DrawOutcome:
    """One law on one drawn plant: its certificate and what its trials did."""

    draw: PlantDraw
    spectral_radius: float
    norm_2: float
    trials_to_tolerance: int | None
    final_rmse: float
    noise_floor: float
    diverged: bool
    trials: int

    @property
    def monotonic(self) -> bool:
        """The frozen plant's map is certified monotonic in l2."""
        return self.spectral_radius < 1.0 and self.norm_2 <= CONTRACTION_LIMIT

    def to_json(self) -> dict[str, Any]:
        """The draw's ``to_json()`` plus ``spectral_radius``, ``norm_2``, ``trials_to_tolerance``, ``final_rmse``,
        ``noise_floor``, ``diverged``, ``trials`` (completed)."""
        return {
            **self.draw.to_json(),
            "spectral_radius": _finite_or_none(self.spectral_radius),
            "norm_2": _finite_or_none(self.norm_2),
            "trials_to_tolerance": self.trials_to_tolerance,
            "final_rmse": _finite_or_none(self.final_rmse),
            "noise_floor": _finite_or_none(self.noise_floor),
            "diverged": self.diverged,
            "trials": self.trials,
        }


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _frozen_perturbations(config: Config, design: Design, draws: Sequence[PlantDraw]) -> list[Perturbation]:
    """Each draw's frozen plant as a perturbation of the design model (zero for a ``pmsm`` plant: no box)."""
    model = design.model
    out = []
    for draw in draws:
        if config.plant.model == "first_order":
            drawn, _ = design_model(drawn_config(config, draw, 0.0), input_delay=design.input_delay)
            out.append(Perturbation(draw.index, draw.vertex, drawn.A - model.A, drawn.B - model.B))
        else:
            out.append(Perturbation(draw.index, draw.vertex, np.zeros_like(model.A), np.zeros_like(model.B)))
    return out


def _outcome(
    config: Config, design: Design, draw: PlantDraw, certificate: DrawCertificate, settings: MonteCarloSettings
) -> DrawOutcome:
    """The trials of ``design``'s law on ``draw``, with the draw's ``certificate``."""
    result = simulate(
        drawn_config(config, draw, settings.noise), law=design.law, trials=settings.trials, design=design,
        input_delay=design.input_delay,
    )
    rmse = [m.rmse_learnable for m in result.metrics]
    floors = [m.noise_floor for m in result.metrics if m.noise_floor is not None]
    last = floors[-max(1, settings.trials // 3) :]
    finished = bool(rmse) and all(math.isfinite(value) for value in rmse)
    return DrawOutcome(
        draw,
        certificate.spectral_radius,
        certificate.norm_2,
        trials_to_tolerance=next((k for k, value in enumerate(rmse, 1) if value < settings.tolerance), None),
        final_rmse=rmse[-1] if finished else math.inf,
        noise_floor=float(np.sqrt(np.mean(np.square(last)))) if last and finished else math.inf,
        diverged=bool(result.stopped) or not finished,
        trials=len(rmse),
    )


def run_draws(
    config: Config, design: Design, law: LawStructure, draws: Sequence[PlantDraw], settings: MonteCarloSettings
) -> list[DrawOutcome]:
    """Certify and run ``design``'s law on each draw; one Dask task runs this on a chunk (certified together: a
    NOILC gain is built once per chunk)."""
    certificates = certify_draws(design, law, _frozen_perturbations(config, design, draws))
    return [
        _outcome(config, design, draw, certificate, settings)
        for draw, certificate in zip(draws, certificates, strict=True)
    ]


def _quantiles(values: np.ndarray) -> dict[str, float | None]:
    """``{"worst", "0.5", "0.9", "0.99"}`` (a non-finite value, e.g. tolerance never reached, is ``None``)."""
    ordered = np.where(np.isnan(values), math.inf, values)  # not nan_to_num: it would turn inf into the largest float
    points = {"worst": float(np.max(ordered))}
    # inverted_cdf: an observed value, so a tolerance never reached (inf) stays inf instead of being interpolated
    points |= {f"{q:g}": float(np.quantile(ordered, q, method="inverted_cdf")) for q in QUANTILES}
    return {key: _finite_or_none(value) for key, value in points.items()}


@dataclass(frozen=True)
class LawRobustness:
    """One law over all the draws, with its design's own worst case (nominal and vertices) for comparison."""

    law: LawKind
    design_spectral_radius: float
    design_norm_2: float
    outcomes: tuple[DrawOutcome, ...]

    def values(self, figure: str) -> np.ndarray:
        """``figure`` (one of :data:`FIGURES`) per draw; a tolerance never reached is ``inf``."""
        raw = [getattr(outcome, figure) for outcome in self.outcomes]
        return np.array([math.inf if value is None else value for value in raw], dtype=float)

    def rate(self, name: str) -> float:
        """The fraction of draws that ``diverged``, ``reached`` the tolerance or are certified ``monotonic``."""
        if name == "reached":
            hits = [outcome.trials_to_tolerance is not None for outcome in self.outcomes]
        else:
            hits = [bool(getattr(outcome, name)) for outcome in self.outcomes]
        return sum(hits) / len(hits)

    def to_json(self) -> dict[str, Any]:
        """``{"law", "design", <figure>: {"worst", "0.5", "0.9", "0.99"}, "divergence_rate", "reached_rate",
        "monotonic_rate", "per_draw"}``."""
        return {
            "law": self.law.value,
            "design": {"spectral_radius": self.design_spectral_radius, "norm_2": self.design_norm_2},
            **{figure: _quantiles(self.values(figure)) for figure in FIGURES},
            "divergence_rate": self.rate("diverged"),
            "reached_rate": self.rate("reached"),
            "monotonic_rate": self.rate("monotonic"),
            "per_draw": [outcome.to_json() for outcome in self.outcomes],
        }


@dataclass(frozen=True)
class RobustnessReport:
    """Every law over the same draws (the ``robustness --json`` document)."""

    settings: MonteCarloSettings
    n_samples: int
    vertices: int
    draws: int
    laws: tuple[LawRobustness, ...]
    workers: int
    seconds: float

    def to_json(self) -> dict[str, Any]:
        """``{"seed", "samples", "vertices", "draws", "trials", "n_samples", "noise", "tolerance", "input_delay",
        "workers", "seconds", "laws": [LawRobustness.to_json()]}``."""
        s = self.settings
        return {
            "seed": s.seed,
            "samples": s.samples,
            "vertices": self.vertices,
            "draws": self.draws,
            "trials": s.trials,
            "n_samples": self.n_samples,
            "noise": s.noise,
            "tolerance": s.tolerance,
            "input_delay": s.input_delay,
            "workers": self.workers,
            "seconds": self.seconds,
            "laws": [law.to_json() for law in self.laws],
        }


def _chunks(draws: list[PlantDraw], count: int) -> list[list[PlantDraw]]:
    size = max(1, math.ceil(len(draws) / max(1, count)))
    return [draws[i : i + size] for i in range(0, len(draws), size)]


def run_robustness(
    config: Config, laws: Sequence[LawKind], settings: MonteCarloSettings, *, client: Any, workers: int
) -> RobustnessReport:
    """Design every law in ``laws`` for ``config``, then run each on the drawn plants, all on the Dask ``client``.

    Parameters
    ----------
    client
        A ``dask.distributed.Client`` (a local cluster or a running one).
    workers
        Workers the draws are split for (:data:`CHUNKS_PER_WORKER` chunks per worker and law); the result does not
        depend on it.

    Raises
    ------
    foilc_hil.errors.InfeasibleDesignError
        A law cannot be designed (exit 3).
    """
    import dask

    from foilc_hil.references import trial_samples

    if workers < 1:
        raise InputError(f"--workers: must be >= 1, got {workers}")
    started = time.perf_counter()
    n_samples = trial_samples(config.reference, config.sample_time)
    draws = draw_plants(config, settings.samples, settings.seed)
    shared_config, shared_settings = dask.delayed(config, pure=True), dask.delayed(settings, pure=True)
    # The designs are tasks too: they run side by side (NOILC's takes tens of seconds at 2000 samples), and each
    # law's draws start as soon as its own design is done.
    design_nodes = [
        dask.delayed(build_design, pure=True)(shared_config, law, n_samples, input_delay=settings.input_delay)
        for law in laws
    ]
    tasks = []
    for node in design_nodes:
        running = dask.delayed(running_law, pure=True)(shared_config, node, n_samples)
        chunks = _chunks(draws, CHUNKS_PER_WORKER * workers)
        run = dask.delayed(run_draws, pure=True)
        tasks.append([run(shared_config, node, running, chunk, shared_settings) for chunk in chunks])
    runs = len(laws) * len(draws)
    with step(f"robustness: {len(laws)} designs, then {len(laws)} laws x {len(draws)} plants ({runs} runs) in Dask"):
        designs, results = dask.compute(design_nodes, tasks, scheduler=client)
    summaries = []
    for design, chunks in zip(designs, results, strict=True):
        assert design.certificates is not None  # every built design is certified
        outcomes = tuple(outcome for chunk in chunks for outcome in chunk)
        summaries.append(
            LawRobustness(design.law, design.certificates.spectral_radius, design.certificates.norm_2, outcomes)
        )
    return RobustnessReport(
        settings, n_samples, sum(d.vertex for d in draws), len(draws), tuple(summaries), workers,
        time.perf_counter() - started,
    )


# --- plots ------------------------------------------------------------------------------------------------------

#: (figure, axis label, logarithmic axis) of the ECDF plots.
_ECDF_PLOTS = (
    ("norm_2", "certified induced 2-norm of the trial map (frozen plant)", False),
    ("final_rmse", "final learnable RMSE", True),
    ("noise_floor", "noise floor (RMS trial-to-trial error / sqrt 2)", True),
)


def plot_robustness(report: RobustnessReport, out_dir: str | Path) -> list[Path]:
    """Write ``ecdf_<figure>.png`` per figure of :data:`_ECDF_PLOTS` and ``hist_trials_to_tolerance.png`` (one
    line or bar set per law; matplotlib, Agg) into ``out_dir``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory = Path(out_dir)
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for figure, label, logarithmic in _ECDF_PLOTS:
        fig, ax = plt.subplots(figsize=(7, 4.2))
        for law in report.laws:
            values = np.sort(law.values(figure)[np.isfinite(law.values(figure))])
            if values.size:
                ax.step(values, np.arange(1, values.size + 1) / len(law.outcomes), where="post", label=str(law.law))
        if logarithmic:
            ax.set_xscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("fraction of draws")
        ax.set_title(f"ECDF over {report.draws} plants ({report.settings.trials} trials each)")
        ax.grid(True, alpha=0.3)
        ax.legend()
        written.append(_save(fig, directory / f"ecdf_{figure}.png"))
    fig, ax = plt.subplots(figsize=(7, 4.2))
    never = report.settings.trials + 1
    bins = [k + 0.5 for k in range(never + 1)]
    series = [np.where(np.isfinite(law.values("trials_to_tolerance")), law.values("trials_to_tolerance"), never)
              for law in report.laws]
    ax.hist(series, bins=bins, label=[str(law.law) for law in report.laws])
    ax.set_xlabel(f"first trial within tolerance ({never}: not reached in {report.settings.trials})")
    ax.set_ylabel("draws")
    ax.set_title(f"Trials to tolerance over {report.draws} plants")
    ax.legend()
    written.append(_save(fig, directory / "hist_trials_to_tolerance.png"))
    return written


def _save(fig: Any, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

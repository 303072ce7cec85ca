"""Robustness Monte Carlo: a designed law certified on plants drawn from its uncertainty set, on Dask.

The design's certificates (:mod:`foilc_hil.design.certificates`) are taken at the nominal plant and the uncertainty
vertices (frozen ``Delta``). This module asks how the law does over the whole set: it draws plants
``A + G1 Delta1 H1``, ``B + G2 Delta2 H2`` with ``||Delta_i||_2 <= 1`` and certifies the law as it runs on each
(the spectral radius and induced 2-norm of the lifted trial-to-trial map, the same functions the design uses), and
reports the distribution: the worst draw, quantiles, the fractions certified asymptotic and monotonic.

Draws
-----
Every vertex of :func:`~foilc_hil.design.models.uncertainty_vertices` is a draw (so the worst case can be compared
with the design's own vertex certificates), followed by ``samples`` random draws. Random draw ``i`` takes, per
independent channel, ``Delta = u M / ||M||_2`` with ``M`` standard normal and ``u`` uniform on ``[0, 1]`` (for a
scalar channel: uniform on ``[-1, 1]``), from its own generator ``numpy.random.default_rng([seed, i])``: a draw
does not depend on how the draws are split into tasks, so the result is the same whatever the worker count.

Execution
---------
The draws are certified in chunks, one ``dask.delayed`` task each, and computed with the scheduler given: a
``dask.distributed.Client`` (a local cluster or a real one), or a local scheduler name (``"synchronous"``,
``"threads"``). The design is one shared node of the graph (sent once per worker, not once per task).

Module order: after :mod:`foilc_hil.design.pipeline` (it certifies the designs the pipeline builds).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from foilc_hil.config import Config, LawKind
from foilc_hil.design.certificates import (
    CONTRACTION_LIMIT,
    LawStructure,
    LoopPlant,
    map_certificate,
    matrix_certificate,
)
from foilc_hil.design.gradient import lifted_gain
from foilc_hil.design.models import Uncertainty, uncertainty_vertices
from foilc_hil.design.noilc import trial_map
from foilc_hil.design.pipeline import law_structure
from foilc_hil.design.record import Design
from foilc_hil.errors import InputError

__all__ = [
    "QUANTILES",
    "DrawCertificate",
    "Perturbation",
    "RobustnessResult",
    "certify_draws",
    "draw_perturbations",
    "robustness",
    "running_law",
]

#: Quantiles of the per-draw certificates reported (besides the worst).
QUANTILES = (0.5, 0.9, 0.99)
#: Chunks per worker: enough to balance the load, few enough that the scheduler's overhead stays small.
CHUNKS_PER_WORKER = 4


@dataclass(frozen=True)
class Perturbation:
    """One plant of the uncertainty set, ``A + delta_a``, ``B + delta_b``; ``vertex``: an uncertainty vertex."""

    index: int
    vertex: bool
    delta_a: np.ndarray
    delta_b: np.ndarray


@dataclass(frozen=True)
class DrawCertificate:
    """The lifted trial map of the law on one drawn plant."""

    index: int
    vertex: bool
    spectral_radius: float
    norm_2: float
    norm_2_method: str

    @property
    def monotonic(self) -> bool:
        """Certified monotonic in l2 (as :mod:`foilc_hil.design.certificates` decides it)."""
        return self.spectral_radius < 1.0 and self.norm_2 <= CONTRACTION_LIMIT

    def to_json(self) -> dict[str, Any]:
        """``{"index", "vertex", "spectral_radius", "norm_2", "norm_2_method"}``."""
        return {
            "index": self.index,
            "vertex": self.vertex,
            "spectral_radius": self.spectral_radius,
            "norm_2": self.norm_2,
            "norm_2_method": self.norm_2_method,
        }


def _random_delta(rows: int, cols: int, rng: np.random.Generator) -> np.ndarray:
    """A point of the unit spectral-norm ball: a random direction scaled by a uniform radius."""
    direction = rng.standard_normal((rows, cols))
    norm = float(np.linalg.norm(direction, 2))
    return rng.uniform(0.0, 1.0) * direction / norm if norm > 0 else np.zeros((rows, cols))


def _random_perturbation(uncertainty: Uncertainty, index: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random draw ``index`` (its own generator, ``default_rng([seed, index])``)."""
    rng = np.random.default_rng([seed, index])
    n, m = uncertainty.G1.shape[0], uncertainty.H2.shape[1]
    dA, dB = np.zeros((n, n)), np.zeros((n, m))
    for kind, G, H in uncertainty.channels():
        term = G @ _random_delta(G.shape[1], H.shape[0], rng) @ H
        if kind == "state":
            dA = dA + term
        else:
            dB = dB + term
    return dA, dB


def draw_perturbations(uncertainty: Uncertainty, samples: int, seed: int) -> list[Perturbation]:
    """The vertices of ``uncertainty``, then ``samples`` seeded random draws (module notes).

    Raises
    ------
    InputError
        ``samples`` or ``seed`` negative.
    """
    if samples < 0:
        raise InputError(f"--samples: must be >= 0, got {samples}")
    if seed < 0:
        raise InputError(f"--seed: must be >= 0, got {seed}")
    draws = [Perturbation(i, True, dA, dB) for i, (dA, dB) in enumerate(uncertainty_vertices(uncertainty))]
    start = len(draws)
    for i in range(samples):
        dA, dB = _random_perturbation(uncertainty, i, seed)
        draws.append(Perturbation(start + i, False, dA, dB))
    return draws


def certify_draws(design: Design, law: LawStructure, draws: Sequence[Perturbation]) -> list[DrawCertificate]:
    """Certify ``design``'s law (as it runs: ``law``) on each drawn plant; one Dask task runs this on a chunk."""
    model = design.model
    gain = lifted_gain(design, law.n_samples)  # NOILC, gradient: their dense map; the others: per sample
    results = []
    for draw in draws:
        A, B = model.A + draw.delta_a, model.B + draw.delta_b
        if gain is not None:
            matrix, kind = trial_map(A, B, model, gain, law)
            certificate = matrix_certificate(matrix, kind)
        else:
            certificate = map_certificate(LoopPlant(A, B, model.measured_output, design.p1, design.p2), law)
        results.append(
            DrawCertificate(
                draw.index, draw.vertex, certificate.spectral_radius, certificate.norm_2, certificate.norm_2_method
            )
        )
    return results


@dataclass(frozen=True)
class RobustnessResult:
    """The distribution of the law's certificates over the drawn plants.

    ``design_norm_2``/``design_spectral_radius`` are the design's own worst case (nominal and vertices), for
    comparison with :meth:`worst` over the draws.
    """

    law: LawKind
    seed: int
    samples: int
    vertices: int
    n_samples: int
    draws: tuple[DrawCertificate, ...]
    design_spectral_radius: float
    design_norm_2: float

    def _values(self, key: str) -> np.ndarray:
        return np.array([getattr(draw, key) for draw in self.draws], dtype=float)

    def worst(self, key: str) -> DrawCertificate:
        """The draw with the largest ``key`` (``spectral_radius`` or ``norm_2``; a non-finite value is largest)."""
        values = np.nan_to_num(self._values(key), nan=math.inf)
        return self.draws[int(np.argmax(values))]

    def quantiles(self, key: str) -> dict[str, float]:
        """``{"0.5": ..., "0.9": ..., "0.99": ...}`` of ``key`` over the draws (linear interpolation)."""
        values = self._values(key)
        return {f"{q:g}": float(np.quantile(values, q)) for q in QUANTILES}

    @property
    def fraction_monotonic(self) -> float:
        """Fraction of the draws certified monotonic (2-norm below one)."""
        return sum(draw.monotonic for draw in self.draws) / len(self.draws)

    @property
    def fraction_asymptotic(self) -> float:
        """Fraction of the draws with spectral radius below one."""
        return sum(draw.spectral_radius < 1.0 for draw in self.draws) / len(self.draws)

    def to_json(self) -> dict[str, Any]:
        """The ``robustness --json`` document (``docs/interface-additions.md``)."""
        summary = {}
        for key in ("spectral_radius", "norm_2"):
            worst = self.worst(key)
            summary[key] = {"worst": getattr(worst, key), "worst_draw": worst.index, "quantiles": self.quantiles(key)}
        return {
            "law": self.law.value,
            "seed": self.seed,
            "samples": self.samples,
            "vertices": self.vertices,
            "draws": len(self.draws),
            "n_samples": self.n_samples,
            "design": {"spectral_radius": self.design_spectral_radius, "norm_2": self.design_norm_2},
            **summary,
            "fraction_asymptotic": self.fraction_asymptotic,
            "fraction_monotonic": self.fraction_monotonic,
            "per_draw": [draw.to_json() for draw in self.draws],
        }


def running_law(config: Config, design: Design, n_samples: int) -> LawStructure:
    """How ``design``'s law runs for ``config`` (Q-filter, fractional memory, input delay), with the design's own
    ``kp``, ``r`` (a co-designed or tuned FOILC is not tuned again)."""
    base = law_structure(config, LawKind.IOILC, n_samples, input_delay=design.input_delay)  # IOILC: never tuned
    return replace(base, kp=design.kp, r=design.r)


def _chunks(draws: list[Perturbation], count: int) -> list[list[Perturbation]]:
    size = max(1, math.ceil(len(draws) / max(1, count)))
    return [draws[i : i + size] for i in range(0, len(draws), size)]


def robustness(
    design: Design,
    law: LawStructure,
    *,
    samples: int,
    seed: int,
    scheduler: Any = "synchronous",
    workers: int = 1,
) -> RobustnessResult:
    """Certify ``design`` (law as it runs: ``law``) on its vertices and ``samples`` random plants, with Dask.

    Parameters
    ----------
    scheduler
        A ``dask.distributed.Client``, or a local Dask scheduler name (``"synchronous"``, ``"threads"``).
    workers
        Workers the draws are split for (chunks of ``CHUNKS_PER_WORKER`` per worker); threads of the
        ``"threads"`` scheduler. The result does not depend on it.
    """
    import dask

    if workers < 1:
        raise InputError(f"--workers: must be >= 1, got {workers}")
    draws = draw_perturbations(design.uncertainty, samples, seed)
    shared = dask.delayed(design, pure=True), dask.delayed(law, pure=True)
    chunks = _chunks(draws, CHUNKS_PER_WORKER * workers)
    tasks = [dask.delayed(certify_draws, pure=True)(*shared, chunk) for chunk in chunks]
    if scheduler == "threads":  # a pool of our own, shut down here (dask's default pool outlives the call)
        with ThreadPoolExecutor(workers) as pool:
            results = dask.compute(*tasks, scheduler="threads", pool=pool)
    else:
        results = dask.compute(*tasks, scheduler=scheduler)
    certificates = design.certificates
    assert certificates is not None  # every built design is certified
    return RobustnessResult(
        law=design.law,
        seed=seed,
        samples=samples,
        vertices=sum(draw.vertex for draw in draws),
        n_samples=law.n_samples,
        draws=tuple(draw for chunk in results for draw in chunk),
        design_spectral_radius=certificates.spectral_radius,
        design_norm_2=certificates.norm_2,
    )

"""A designed law certified on plants of its uncertainty set: the per-draw certificates of the robustness Monte Carlo.

The design's certificates (:mod:`foilc_hil.design.certificates`) are taken at the nominal plant and the uncertainty
vertices (frozen ``Delta``). :func:`certify_draws` certifies the law as it runs (the spectral radius and induced
2-norm of the lifted trial-to-trial map, the same functions the design uses) on other plants ``A + delta_a``,
``B + delta_b`` of the design model: :mod:`foilc_hil.loop.robustness` draws them from the uncertainty set, runs the
law's trials on each, and reports the distributions (``foilc-hil robustness``).

Module order: after :mod:`foilc_hil.design.pipeline` (it certifies the designs the pipeline builds).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from foilc_hil.config import Config, LawKind
from foilc_hil.design.certificate_record import PlantCertificate
from foilc_hil.design.certificates import map_certificate
from foilc_hil.design.error_map import FftOperand, block_toeplitz_product
from foilc_hil.design.gradient import lifted_gain
from foilc_hil.design.lifted import LawStructure, LoopPlant, markov_blocks
from foilc_hil.design.map_norms import CONTRACTION_LIMIT, UNIT_ROUNDOFF, bounded_matrix_certificate
from foilc_hil.design.models import DiscreteModel
from foilc_hil.design.noilc import trial_map
from foilc_hil.design.pipeline import law_structure
from foilc_hil.design.rational_map import RATIONAL_METHOD, GainGram, rational_norm_bound
from foilc_hil.design.record import Design

__all__ = ["DrawCertificate", "Perturbation", "certify_draws", "running_law"]


@dataclass(frozen=True)
class Perturbation:
    """One plant of the uncertainty set, ``A + delta_a``, ``B + delta_b`` of the design model; ``vertex``: a corner
    of the set."""

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


def certify_draws(design: Design, law: LawStructure, draws: Sequence[Perturbation]) -> list[DrawCertificate]:
    """Certify ``design``'s law (as it runs: ``law``) on each drawn plant; one Dask task runs this on a chunk.

    A lifted law (NOILC, gradient) is certified by :func:`_lifted_certificate`: its dense map bounded by a Cholesky
    test (``docs/robustness.md``); the others by the Toeplitz path of
    :func:`~foilc_hil.design.certificates.map_certificate`.
    """
    model = design.model
    gain = lifted_gain(design, law.n_samples)  # NOILC, gradient: their dense map; the others: per sample
    # the gain's Gram matrix, once per process (the Q-filter's input map is formed densely: no Gram)
    gram = None if gain is None or law.q_filter is not None else GainGram.shared(gain)
    # the gain's FFT for the fallback of _lifted_certificate: once for the chunk, and only if a draw needs it
    operand = None if gain is None else functools.cache(lambda: FftOperand.of(gain, law.n_samples - law.lead))
    results = []
    for draw in draws:
        A, B = model.A + draw.delta_a, model.B + draw.delta_b
        if gain is not None and operand is not None:
            certificate = _lifted_certificate(A, B, model, gain, law, gram, operand)
        else:
            certificate = map_certificate(LoopPlant(A, B, model.measured_output, design.p1, design.p2), law)
        results.append(
            DrawCertificate(
                draw.index, draw.vertex, certificate.spectral_radius, certificate.norm_2, certificate.norm_2_method
            )
        )
    return results


def _lifted_certificate(
    A: np.ndarray, B: np.ndarray, model: DiscreteModel, gain: np.ndarray, law: LawStructure, gram: GainGram | None,
    operand: Callable[[], FftOperand],
) -> PlantCertificate:
    """The certificate of a lifted law's map at plant ``(A, B)``: :func:`~foilc_hil.design.noilc.trial_map`'s map.

    The error map ``T = I - G L`` (``G`` lower block-Toeplitz) is bounded first through the plant's transfer
    function (:func:`~foilc_hil.design.rational_map.rational_norm_bound`: ``T T^T`` from the gain's ``gram`` in
    ``O(k L^2)``, one Cholesky test); where that is not a certificate, ``T`` is formed by FFT (no dense ``G`` and no
    ``O(L^3)`` product; ``operand()``: ``L`` transformed, once per chunk) with its rounding bound, for
    :func:`~foilc_hil.design.map_norms.bounded_matrix_certificate`. With a Q-filter (``gram`` is ``None``), the
    input map as ``trial_map`` forms it."""
    if gram is None:
        matrix, kind = trial_map(A, B, model, gain, law)
        return bounded_matrix_certificate(matrix, kind)
    bound = rational_norm_bound(A, B, model.measured_output, law.lead, gram)
    if bound is not None and bound <= CONTRACTION_LIMIT:
        return PlantCertificate("", "error", bound, bound, RATIONAL_METHOD, "upper bound: the induced 2-norm")
    length = law.n_samples - law.lead
    blocks = markov_blocks(A, B, model.measured_output, law.lead, length)
    product, error = block_toeplitz_product(blocks, operand())
    product *= -1.0
    diagonal = np.arange(product.shape[0])
    product[diagonal, diagonal] += 1.0  # T = I - G L, in place; the subtraction rounds by at most u |T| entrywise
    error += UNIT_ROUNDOFF * float(np.linalg.norm(product))
    return bounded_matrix_certificate(product, "error", error)


def running_law(config: Config, design: Design, n_samples: int) -> LawStructure:
    """How ``design``'s law runs for ``config`` (Q-filter, fractional memory, input delay), with the design's own
    ``kp``, ``r`` (a co-designed or tuned FOILC is not tuned again)."""
    base = law_structure(config, LawKind.IOILC, n_samples, input_delay=design.input_delay)  # IOILC: never tuned
    return replace(base, kp=design.kp, r=design.r)

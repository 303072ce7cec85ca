"""Norm-optimal ILC (Amann–Owens), lifted: the baseline an ILC engineer compares a new law with.

Each trial minimises ``||e_k||_Q^2 + ||u_k - u_{k-1}||_R^2`` on the lifted plant, which gives

    u_k = u_{k-1} + L e_{k-1},    L = (G^T Q G + R)^-1 G^T Q,

with ``G`` the lifted nominal plant from the inputs ``u[0..N-d-1]`` to the error samples they can move,
``e[d..N-1]`` (block lower-triangular Toeplitz with blocks ``C_measured A^(j + d) B``; the first ``d`` samples never
change and the last ``d`` inputs move nothing, as for every law here). ``Q = q I``, ``R = r I``.

Certificates
------------
The trial-to-trial error map is ``T = I - G_v L`` at each plant ``G_v`` (nominal and uncertainty vertices): with a
Q-filter the input map ``M = Q_f - L S G_y`` instead (:mod:`foilc_hil.design.certificates` notes). Both are
dense (``L`` is not Toeplitz); :func:`~foilc_hil.design.certificates.matrix_certificate` computes their spectral
radius and induced 2-norm with the same code as every other law's. On the nominal plant
``T = r (q G G^T + r I)^-1`` is symmetric with eigenvalues ``r / (r + q sigma_i^2)`` in ``(0, 1)``: monotonic by
construction, fastest where the plant gain ``sigma_i`` is large. The vertices measure its robustness.

The weight ``r`` is set relative to the plant, ``r = r_relative ||G||_2^2 q`` (``law.noilc.r_relative``), so one
default fits plants of any gain: the direction of the largest plant gain contracts by
``r_relative / (1 + r_relative)`` per trial.

Module order: after :mod:`foilc_hil.design.certificates`, before :mod:`foilc_hil.design.lmi`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from foilc_hil.config import FractionalMemory, LawKind, NoilcConfig
from foilc_hil.design.certificates import (
    CONTRACTION_LIMIT,
    LawStructure,
    dense_block_toeplitz,
    markov_blocks,
    matrix_certificate,
)
from foilc_hil.design.models import DiscreteModel, Uncertainty, uncertainty_vertices
from foilc_hil.design.record import Bounds, CertificateAction, Certificates, Design, NoilcWeights, PlantCertificate
from foilc_hil.errors import InputError
from foilc_hil.progress import as_step

__all__ = ["certify_lifted", "certify_noilc", "lifted_plant", "noilc_gain", "noilc_weights", "trial_map"]

#: ``r`` recorded by a NOILC design: the law has no fractional term.
UNUSED_ORDER = 1.0


def lifted_plant(A: np.ndarray, B: np.ndarray, C_measured: np.ndarray, n_samples: int, lead: int) -> np.ndarray:
    """``G`` (``(L p) x (L m)``, ``L = N - lead``): inputs ``u[0..L-1]`` to the errors they move, ``y[lead..N-1]``."""
    length = n_samples - lead
    if length < 1:
        raise InputError(f"n_samples: must exceed the input delay {lead}, got {n_samples}")
    return dense_block_toeplitz(markov_blocks(A, B, C_measured, lead, length))


def noilc_weights(model: DiscreteModel, config: NoilcConfig, n_samples: int) -> NoilcWeights:
    """The absolute weights of ``law.noilc`` on ``model`` for trials of ``n_samples`` (module notes)."""
    G = lifted_plant(model.A, model.B, model.measured_output, n_samples, model.input_delay)
    scale = float(np.linalg.norm(G, 2)) ** 2
    return NoilcWeights(q=config.q, r=config.r_relative * scale * config.q, r_relative=config.r_relative)


def noilc_gain(model: DiscreteModel, weights: NoilcWeights, n_samples: int) -> np.ndarray:
    """``L = (q G^T G + r I)^-1 q G^T``, ``(L m) x (L p)``: the lifted learning gain (module notes)."""
    G = lifted_plant(model.A, model.B, model.measured_output, n_samples, model.input_delay)
    normal = weights.q * (G.T @ G) + weights.r * np.eye(G.shape[1])
    return np.asarray(np.linalg.solve(normal, weights.q * G.T), dtype=float)


def trial_map(
    A: np.ndarray, B: np.ndarray, model: DiscreteModel, gain: np.ndarray, law: LawStructure
) -> tuple[np.ndarray, str]:
    """The map the law runs on at plant ``(A, B)``: the error map, or with a Q-filter the input map."""
    n, lead = law.n_samples, law.lead
    C = model.measured_output
    if law.q_filter is None:
        return np.eye(gain.shape[1]) - lifted_plant(A, B, C, n, lead) @ gain, "error"
    m, p = model.n_inputs, model.n_outputs
    # u_k = Q_f u_{k-1} + L_full e_{k-1}, e = y_r - G_y u: L_full acts on e[lead:] and fills u[:N-lead].
    full = np.zeros((n * m, n * p))
    full[: (n - lead) * m, lead * p :] = gain
    G_y = dense_block_toeplitz(markov_blocks(A, B, C, 0, n))
    return np.kron(law.q_filter, np.eye(m)) - full @ G_y, "input (Q-filter)"


def certify_lifted(
    model: DiscreteModel,
    uncertainty: Uncertainty,
    gain: np.ndarray,
    law: LawStructure,
    *,
    require_monotonic: bool,
    kind: LawKind,
    addition: Mapping[str, Any],
) -> Design:
    """The design of a lifted feedforward law ``u_k = u_{k-1} + L e_{k-1}`` (NOILC, gradient): certificates of
    its dense map (:func:`trial_map`) at the nominal plant and every vertex; ``addition`` is what its certificates
    add (``{"noilc": weights}``, ``{"gradient": step}``). Nothing is rescaled: the certificates report the map as
    it is (like P-type's)."""
    if law.lead != model.input_delay:
        raise InputError(f"law: its lead {law.lead} must be the model's input delay {model.input_delay}")
    plants = [("nominal", model.A, model.B)]
    plants += [
        (f"vertex {i}", model.A + dA, model.B + dB) for i, (dA, dB) in enumerate(uncertainty_vertices(uncertainty), 1)
    ]
    entries: list[PlantCertificate] = []
    for name, A_v, B_v in plants:
        matrix, map_kind = trial_map(A_v, B_v, model, gain, law)
        entries.append(matrix_certificate(matrix, map_kind).named(name))
    radius = max(entry.spectral_radius for entry in entries)
    norm = max(entry.norm_2 for entry in entries)
    bounds = Bounds(radius, norm)
    certificates = Certificates(
        spectral_radius=radius,
        norm_2=norm,
        monotonic_required=require_monotonic,
        n_samples=law.n_samples,
        lead=law.lead,
        fractional_memory=FractionalMemory(law.fractional_memory),
        filter_first_weight=1.0,
        naive_without_filter=bounds,
        designed=bounds,
        vertices=len(entries) - 1,
        q_filter=law.q_filter is not None,
        action=CertificateAction.NONE,
        gain_scale=1.0,
        asymptotic=radius < 1.0,
        monotonic=radius < 1.0 and norm <= CONTRACTION_LIMIT,
        plants=tuple(entries),
        **addition,
    )
    P = np.zeros((model.n_inputs, model.n_states + model.n_outputs))
    return Design(
        law=kind,
        model=model,
        uncertainty=uncertainty,
        P=P,
        kp=0.0,
        r=UNUSED_ORDER,
        certificates=certificates,
    )


@as_step("NOILC gain and certificates")
def certify_noilc(
    model: DiscreteModel,
    uncertainty: Uncertainty,
    config: NoilcConfig,
    law: LawStructure,
    *,
    require_monotonic: bool,
) -> Design:
    """The NOILC design for ``model``: its weights, and certificates of the law as it runs (nominal, vertices)."""
    weights = noilc_weights(model, config, law.n_samples)
    gain = noilc_gain(model, weights, law.n_samples)
    return certify_lifted(
        model,
        uncertainty,
        gain,
        law,
        require_monotonic=require_monotonic,
        kind=LawKind.NOILC,
        addition={"noilc": weights},
    )

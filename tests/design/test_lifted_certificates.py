"""The certificates of the lifted laws (NOILC, gradient ILC) on long trials, by the structured test: against dense
SVDs and eigenvalues of maps built here from the plant's numbers, with and without a Q-filter, and against simulated
trials on the nominal plant."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from foilc_hil.config import load_config
from foilc_hil.design.certificate_record import BoundClaim, CertificateMethod, MonotoneVerdict, NoilcWeights
from foilc_hil.design.noilc import DENSE_LIMIT, STRUCTURED_METHOD, noilc_update, plant_operator
from foilc_hil.design.pipeline import build_design
from foilc_hil.design.qfilter import QFilter
from foilc_hil.design.record import Design
from foilc_hil.design.trial_operator import TrialOperator
from foilc_hil.loop.simulation import simulate
from tests.support.fuzz_settings import fuzz_settings
from tests.support.lifted_reference import config_plants, lifted, random_model

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
N = 201  # 200 learnable samples (paper_sim; 199 on the demo axis, whose drive lags a sample more): structured
PAPER = {
    "reference.profile": "piecewise",
    "reference.segments": [{"duration": 1.5, "start": 1.0}, {"duration": 0.5, "start": 0.0}],
    "plant.uncertainty.G1": 0.006,  # wider than shipped: vertex maps well apart from the nominal one
}
CASES = [("paper_sim.yaml", PAPER), ("demo.yaml", {"reference.time_scale": 0.04})]


def _dense_update(design: Design, G: np.ndarray) -> np.ndarray:
    """The law's ``L`` from the normal equations (NOILC) or ``beta G^T`` (gradient), with the recorded scale."""
    certificates = design.certificates
    assert certificates is not None
    if certificates.noilc is not None:
        w = certificates.noilc
        return np.asarray(w.scale * np.linalg.solve(w.q * G.T @ G + w.r * np.eye(G.shape[1]), w.q * G.T))
    assert certificates.gradient is not None
    return np.asarray(certificates.gradient.beta * G.T)


@pytest.mark.parametrize(("config_name", "overrides"), CASES, ids=["paper_sim", "demo-axis"])
@pytest.mark.parametrize("law", ["noilc", "gradient"])
def test_structured_certificates_bound_the_dense_maps(config_name: str, overrides: dict[str, Any], law: str) -> None:
    """At every plant: ``||T||_2 <= norm_2 <= ||T||_2 (1 + 2e-6)`` (the bisection's tolerance and the rounding
    margin) and ``rho(T) <= spectral_radius``, ``T = I - G_v L`` dense."""
    config = load_config(CONFIGS / config_name, overrides)
    design = build_design(config, law, N, input_delay=1)
    assert design.certificates is not None
    _, plants = config_plants(config, 1, N)
    assert plants[0].shape[0] > DENSE_LIMIT  # the structured path, not the dense one
    L = _dense_update(design, plants[0])
    for G_v, certificate in zip(plants, design.certificates.plants, strict=True):
        T = np.eye(G_v.shape[0]) - G_v @ L
        norm = float(np.linalg.norm(T, 2))
        assert STRUCTURED_METHOD in certificate.norm_2_method and certificate.proof is not None
        assert certificate.proof.method is CertificateMethod.STRUCTURED and certificate.proof.norm_2 is BoundClaim.UPPER
        assert norm <= certificate.norm_2 <= norm * (1 + 2e-6), certificate.plant
        assert max(abs(np.linalg.eigvals(T))) <= certificate.spectral_radius * (1 + 1e-12)
        assert norm < 1 and certificate.proof.monotone is MonotoneVerdict.MONOTONE  # these designs are monotonic


@pytest.mark.parametrize("phase", ["zero", "causal"])
@pytest.mark.parametrize("law", ["noilc", "gradient"])
def test_the_q_filter_input_map_is_certified_structurally(phase: str, law: str) -> None:
    """With a Q-filter (order 2, 20 rad/s: the update is rescaled to be monotonic), the input map
    ``M = Q - s L_full G_y`` on all ``N`` inputs, dense here from the filter's own matrix and the plant's numbers."""
    q_filter = {"cutoff": 20.0, "order": 2, "phase": phase}
    config = load_config(CONFIGS / "paper_sim.yaml", {**PAPER, "law.q_filter": q_filter})
    design = build_design(config, law, N, input_delay=1)
    assert design.certificates is not None and design.certificates.monotonic
    model, plants = config_plants(config, 1, N)
    d = model.input_delay
    _, whole = config_plants(config, 1, N, whole=True)  # G_y: u[0..N-1] -> y[0..N-1]
    Q = QFilter(20.0, 2, config.sample_time, phase).matrix(N)
    L = _dense_update(design, plants[0])
    for G_y, certificate in zip(whole, design.certificates.plants, strict=True):
        learning = np.zeros((N, N))
        learning[: N - d] = L @ G_y[d:]  # L acts on e[d:] = (G_y u)[d:] and fills u[:N-d]
        M = Q - learning
        norm = float(np.linalg.norm(M, 2))
        assert certificate.map == "input (Q-filter)" and STRUCTURED_METHOD in certificate.norm_2_method
        assert norm <= certificate.norm_2 <= norm * (1 + 2e-6), certificate.plant


@given(seed=st.integers(0, 2**32 - 1), length=st.integers(3, 60), states=st.integers(1, 3),
       delay=st.integers(0, 2), perturbation=st.floats(0.0, 0.5))
@fuzz_settings(25)
def test_the_similar_map_has_the_trial_maps_spectrum(seed: int, length: int, states: int, delay: int,
                                                      perturbation: float) -> None:
    """``X = I - left G_v right`` (NOILC's ``I - q (G Fi)^T G_v Fi``) is similar to ``I - L G_v`` through ``right``
    (``right X = (I - L G_v) right``, ``right`` invertible), whose spectrum is that of the trial map ``I - G_v L``;
    on the nominal plant ``X`` is symmetric with norm ``r / (r + q sigma_min(G)^2)``, the spectral radius. (The
    eigenvalues themselves are too ill-conditioned on these non-normal maps to compare beyond about 1e-7.)"""
    rng = np.random.default_rng(seed)
    model = random_model(rng, states, 1, delay)
    G = lifted(model.A, model.B, model.measured_output, delay, length)
    sigma = np.linalg.svd(G, compute_uv=False)
    q, r = 1.0, 1e-2 * float(sigma[0]) ** 2
    update = noilc_update(model, NoilcWeights(q, r, 1e-2), length + delay)
    A_v = model.A.copy()
    A_v[: states, : states] *= 1.0 - perturbation
    G_v = plant_operator(A_v, model.B, model.measured_output, length + delay, delay)
    similar = TrialOperator.identity(length, 1).plus(update.left.product(G_v.product(update.right)).scaled(-1.0))
    right = update.right.dense()
    assert np.all(np.abs(np.diag(right)) > 0)  # lower triangular: invertible
    swapped = np.eye(length) - update.dense() @ G_v.dense()
    np.testing.assert_allclose(right @ similar.dense(), swapped @ right, atol=1e-10 * float(np.abs(right).max()))
    G_nominal = plant_operator(model.A, model.B, model.measured_output, length + delay, delay)
    nominal = TrialOperator.identity(length, 1).plus(update.left.product(G_nominal.product(update.right)).scaled(-1))
    assert np.linalg.norm(nominal.dense(), 2) == pytest.approx(r / (r + q * sigma[-1] ** 2), rel=1e-8)


@pytest.mark.parametrize("law", ["noilc", "gradient"])
@pytest.mark.parametrize("q_filter", [None, {"cutoff": 20.0, "order": 2}], ids=["no-filter", "q-filter"])
def test_simulated_trials_contract_by_at_most_the_certified_norm(law: str, q_filter: dict[str, Any] | None) -> None:
    """On the nominal plant (no variation, disturbance or noise) the trial-to-trial map is the certified nominal map:
    the learnable error (without a Q-filter) or the input's change (with one) shrinks each trial by at most the
    nominal certificate's norm."""
    overrides: dict[str, Any] = {
        **PAPER, "plant.variation": {}, "plant.disturbance": {"kind": "none"}, "law.q_filter": q_filter,
    }
    config = load_config(CONFIGS / "paper_sim.yaml", overrides)
    design = build_design(config, law, N, input_delay=1)
    assert design.certificates is not None and design.certificates.monotonic
    nominal = design.certificates.plants[0]
    result = simulate(config, law=law, trials=6, design=design, input_delay=1)
    d = design.input_delay
    if q_filter is None:
        sizes = [float(np.linalg.norm(errors[d:])) for errors in result.errors]
    else:
        sizes = [float(np.linalg.norm(b - a)) for a, b in itertools.pairwise(result.controls)]
    assert all(later <= nominal.norm_2 * earlier * (1 + 1e-9) + 1e-12 for earlier, later in itertools.pairwise(sizes))
    assert sizes[-1] < sizes[0]  # and it does learn

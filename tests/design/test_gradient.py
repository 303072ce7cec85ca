"""Gradient ILC (``--law gradient``): its step, its certificate recomputed here with numpy on a lifted map built from
the plant's formula (not the code under test), one learning step by hand, and monotonic convergence on paper_sim."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from foilc_hil.config import LawKind, load_config
from foilc_hil.design.gradient import gradient_step, gradient_update
from foilc_hil.design.noilc import plant_norm
from foilc_hil.design.pipeline import build_design
from foilc_hil.design.record import Design
from foilc_hil.laws.learning import Gradient, make_law
from foilc_hil.loop.simulation import simulate
from tests.support.fuzz_settings import fuzz_settings
from tests.support.lifted_reference import config_plants, lifted, random_model

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
#: paper_sim's plant, variation and uncertainty on a 0.8 s trial.
SHORT = {
    "reference.profile": "piecewise",
    "reference.segments": [{"duration": 0.5, "start": 1.0}, {"duration": 0.3, "start": 0.0}],
}
H = 0.01


def _lifted(a: float, b: float, n: int) -> np.ndarray:
    """The lifted ZOH plant of ``x' = a x + b u``, ``y = x``, written out from its formula (Markov parameters
    ``A^(i-j) B``)."""
    A, B = math.exp(a * H), b * (math.exp(a * H) - 1.0) / a
    return np.array([[A ** (i - j) * B if i >= j else 0.0 for j in range(n)] for i in range(n)])


def _vertex_plants(n: int) -> list[np.ndarray]:
    """The lifted plants at paper_sim's four vertices, ``A +- G1 H1``, ``B +- G2 H2`` (0.001, 0.0016)."""
    A, B = math.exp(-1.23 * H), 1.68 * (math.exp(-1.23 * H) - 1.0) / -1.23
    plants = []
    for dA, dB in itertools.product((-0.001, 0.001), (-0.0016, 0.0016)):
        Av, Bv = A + dA, B + dB
        plants.append(np.array([[Av ** (i - j) * Bv if i >= j else 0.0 for j in range(n)] for i in range(n)]))
    return plants


def test_gradient_certificate_recomputed_from_the_lifted_map() -> None:
    n = 80
    design = build_design(load_config(CONFIGS / "paper_sim.yaml", SHORT), "gradient", n, input_delay=0)
    certificates = design.certificates
    assert design.law is LawKind.GRADIENT and certificates is not None and certificates.gradient is not None
    G = _lifted(-1.23, 1.68, n)
    singular = np.linalg.svd(G, compute_uv=False)
    beta = 1.0 / singular[0] ** 2  # the middle of the monotonic range (0, 2 / ||G||^2)
    assert certificates.gradient.beta == pytest.approx(beta, rel=1e-10)
    # nominal: T = I - beta G G^T, eigenvalues 1 - beta sigma_i^2: norm = radius = 1 - (sigma_min / sigma_max)^2
    nominal = certificates.plants[0]
    expected = 1.0 - (singular[-1] / singular[0]) ** 2
    assert nominal.plant == "nominal"
    assert nominal.norm_2 == pytest.approx(expected, rel=1e-9)
    assert nominal.spectral_radius == pytest.approx(expected, rel=1e-9)
    # vertices: T_v = I - G_v beta G^T, its induced 2-norm by SVD and radius by eigenvalues, here
    norms = sorted(np.linalg.norm(np.eye(n) - Gv @ (beta * G.T), 2) for Gv in _vertex_plants(n))
    radii = sorted(np.max(np.abs(np.linalg.eigvals(np.eye(n) - Gv @ (beta * G.T)))) for Gv in _vertex_plants(n))
    np.testing.assert_allclose(sorted(p.norm_2 for p in certificates.plants[1:]), norms, rtol=1e-8)
    np.testing.assert_allclose(sorted(p.spectral_radius for p in certificates.plants[1:]), radii, rtol=1e-8)
    assert max(norms) < 1 and certificates.monotonic and certificates.norm_2 == pytest.approx(max(expected, *norms))


def test_gradient_law_applies_beta_g_transpose() -> None:
    """One learning step by hand: ``u_2 = u_1 + beta G^T e_1``."""
    n = 30
    config = load_config(CONFIGS / "paper_sim.yaml", SHORT)
    design = build_design(config, "gradient", n, input_delay=0)
    law = make_law(design, config.law, n)
    assert isinstance(law, Gradient)
    law.begin_trial()
    for t in range(n):
        law.command(t, np.zeros(1))
    error = np.linspace(1.0, 0.0, n)
    law.end_trial(error, np.zeros(n))
    law.begin_trial()
    u = np.array([law.command(t, np.zeros(1))[0] for t in range(n)])
    G = _lifted(-1.23, 1.68, n)
    np.testing.assert_allclose(u, G.T @ error / np.linalg.norm(G, 2) ** 2, rtol=1e-9, atol=1e-14)
    assert Design.from_json(design.to_json()).to_json() == design.to_json()


@given(seed=st.integers(0, 2**32 - 1), length=st.integers(2, 150), states=st.integers(1, 3),
       channels=st.integers(1, 2), delay=st.integers(0, 2))
@fuzz_settings(40)
def test_the_step_and_the_adjoint_pass_are_the_dense_ones(seed: int, length: int, states: int, channels: int,
                                                          delay: int) -> None:
    """``||G||_2`` (the structured test, bisected) against the SVD to 1e-11, and the update ``beta G^T e`` (one
    adjoint pass) against the dense product to 1e-12 relative, on random stable plants behind ``delay`` samples."""
    rng = np.random.default_rng(seed)
    model = random_model(rng, states, channels, delay)
    G = lifted(model.A, model.B, model.measured_output, delay, length)
    sigma = float(np.linalg.norm(G, 2))
    assert plant_norm(model, length + delay) == pytest.approx(sigma, rel=1e-11)
    step = gradient_step(model, length + delay)
    assert step.beta == pytest.approx(1.0 / sigma**2, rel=3e-11)
    error = rng.standard_normal((length, channels))
    truth = step.beta * G.T @ error.ravel()
    got = gradient_update(model, step, length + delay).apply(error).ravel()
    assert np.linalg.norm(got - truth) <= 1e-12 * np.linalg.norm(truth)


@pytest.mark.slow
@pytest.mark.parametrize("config_name", ["paper_sim.yaml", "demo.yaml"])
def test_gradient_law_update_at_2000_samples_is_the_dense_one(config_name: str) -> None:
    """The law as it runs on a shipped config at N = 2000 behind the CAN loop's delay: one learning step
    ``u_2 = u_1 + beta G^T e_1`` against the dense product on the lifted plant built here (1e-9 relative, 2-norm
    and max-abs; ``beta`` is the recorded step, checked against the SVD above)."""
    n = 2000
    config = load_config(CONFIGS / config_name)
    design = build_design(config, "gradient", n, input_delay=1)
    assert design.certificates is not None and design.certificates.gradient is not None
    beta = design.certificates.gradient.beta
    model, plants = config_plants(config, 1, n)
    d, G = model.input_delay, plants[0]
    law = make_law(design, config.law, n)
    law.begin_trial()
    for t in range(n):
        law.command(t, np.zeros(1))
    error = np.cos(np.linspace(0.0, 30.0, n)) * np.linspace(1.0, 0.2, n)
    law.end_trial(error, np.zeros(n))
    law.begin_trial()
    u = np.array([law.command(t, np.zeros(1))[0] for t in range(n)])
    truth = beta * G.T @ error[d:]
    assert np.linalg.norm(u[: n - d] - truth) <= 1e-9 * np.linalg.norm(truth)
    assert np.max(np.abs(u[: n - d] - truth)) <= 1e-9 * np.max(np.abs(truth))
    np.testing.assert_array_equal(u[n - d :], 0.0)


def test_gradient_converges_monotonically_on_paper_sim() -> None:
    """The SSE falls every trial (before the disturbance of trial 5), and the trial map's certificate, recomputed
    above, says it must on every frozen vertex plant."""
    config = load_config(CONFIGS / "paper_sim.yaml", SHORT)
    result = simulate(config, law="gradient", trials=4, input_delay=0)
    assert result.design is not None and result.design.certificates is not None
    assert result.design.certificates.monotonic
    sse = [metric.sse for metric in result.metrics]
    assert all(later < earlier for earlier, later in itertools.pairwise(sse)), sse
    assert sse[-1] < 0.5 * sse[0]

"""The Q-filtered input map's certificates (foilc_hil.design.qmap) against dense truths and against simulation.

Every number is checked against an independent computation: the dense map of ``error_map.dense_input_map`` (its
own lifted plant, fractional matrix and ``QFilter.matrix``), LAPACK's SVD and eigenvalues, and trials of the law
run sample by sample on the plant.
"""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from foilc_hil.config import Config, FractionalMemory, LawConfig, QFilterConfig, QFilterPhase, load_config
from foilc_hil.design import qmap
from foilc_hil.design.certificate_record import BoundClaim, CertificateMethod, MonotoneVerdict
from foilc_hil.design.certificates import certify_as_given
from foilc_hil.design.error_map import dense_input_map
from foilc_hil.design.lifted import LawStructure, LoopPlant, law_filter_matrix
from foilc_hil.design.map_norms import CONTRACTION_LIMIT
from foilc_hil.design.models import DiscreteModel, Uncertainty, augment_input_delay, discretize
from foilc_hil.design.pipeline import build_design
from foilc_hil.design.qfilter import QFilter
from foilc_hil.design.record import Design
from foilc_hil.laws.learning import make_law
from plant_emulator.linear import ContinuousModel
from tests.support.designs import plain_design

TS = 0.01


def _model(seed: int, states: int, lead: int) -> DiscreteModel:
    """A stable random single-input single-output plant with ``lead`` samples of input delay in its state."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((states, states))
    A *= rng.uniform(0.3, 0.95) / max(1e-9, float(np.max(np.abs(np.linalg.eigvals(A)))))
    B = rng.standard_normal((states, 1))
    C = rng.standard_normal((1, states))
    base = DiscreteModel(A, B, C, TS)
    return augment_input_delay(base, lead)[0] if lead else base


def _dense(loop: LoopPlant, law: LawStructure, scale: float) -> np.ndarray:
    assert law.q_filter is not None
    F = law_filter_matrix(law.kp, law.r, law.sample_time, law.n_samples, law.lead, str(law.fractional_memory))
    return dense_input_map(
        loop.A, loop.B, loop.C_measured, loop.p1, scale * loop.p2, F, law.q_filter.matrix(), law.lead
    )


def _toeplitz_norm(smap: qmap.StructuredInputMap, scale: float) -> float:
    """``||T_N(a0 - s a1)||_2`` densely (the finite section the symbol bound is about)."""
    from scipy.linalg import toeplitz

    a = (smap.a0 - scale * smap.a1)[:, 0, 0]
    n = smap.n_samples
    return float(np.linalg.norm(toeplitz(a[n - 1 :], a[n - 1 :: -1]), 2))


def _block_triangular_radius(M: np.ndarray, channels: int) -> float:
    """The spectral radius of a block lower-triangular ``M`` (checked: its block-upper part is zero) from its diagonal
    blocks: LAPACK's eigenvalues of the whole far-from-normal matrix are off by far more (0.895 for 0.475 on the
    two-channel map below)."""
    block = np.arange(M.shape[0]) // channels
    assert not np.any(M[block[:, None] < block[None, :]])
    diagonal = [M[i : i + channels, i : i + channels] for i in range(0, M.shape[0], channels)]
    return max(float(np.max(np.abs(np.linalg.eigvals(d)))) for d in diagonal)


@st.composite
def _cases(draw: st.DrawFn) -> tuple[LoopPlant, LawStructure, float]:
    seed = draw(st.integers(0, 10_000))
    states, lead = draw(st.integers(1, 3)), draw(st.integers(0, 2))
    model = _model(seed, states, lead)
    rng = np.random.default_rng(seed + 1)
    markov = float((model.measured_output @ np.linalg.matrix_power(model.A, lead) @ model.B)[0, 0])
    kp = draw(st.sampled_from([0.0, 0.02, 0.1]))
    r = draw(st.floats(0.2, 0.9))
    weight = 1.0 + kp * TS**-r
    p1 = 0.3 * rng.standard_normal((1, model.n_states)) * draw(st.sampled_from([0.0, 1.0]))
    while max(abs(np.linalg.eigvals(model.A + model.B @ p1))) > 0.98:  # a stable loop within the trial
        p1 = 0.5 * p1
    p2 = np.array([[draw(st.floats(0.2, 1.2)) / (markov * weight if abs(markov) > 1e-3 else weight)]])
    n = draw(st.integers(80, 180))
    q = QFilter(
        draw(st.floats(0.02, 0.45)) * math.pi / TS,
        draw(st.sampled_from([1, 2, 4])),
        TS,
        draw(st.sampled_from(list(QFilterPhase))),
    ).on(n)
    memory = draw(st.sampled_from(list(FractionalMemory)))
    law = LawStructure(kp, r, TS, n, lead, memory, q)
    return LoopPlant(model.A, model.B, model.measured_output, p1, p2), law, draw(st.sampled_from([1.0, 0.3, 0.05]))


@pytest.mark.slow
@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_cases())
def test_the_certificate_brackets_the_dense_norm_and_radius(case: tuple[LoopPlant, LawStructure, float]) -> None:
    """On random plants, gains, filters (order 1, 2, 4; 2-45 % of Nyquist; both phases) and memories: the operator
    is the dense map, the 2-norm's bracket holds the SVD's value, an upper bound is within 2e-4 of the larger of
    that value and the symbol's bound (which bounds the dense Toeplitz section), a lower bound never exceeds it,
    and the spectral radius is LAPACK's (causal filter: exact) or at least it (zero phase)."""
    loop, law, scale = case
    smap = qmap.structured_input_map(loop, law)
    assert smap is not None
    M = _dense(loop, law, scale)
    x = np.random.default_rng(0).standard_normal((1, 1, law.n_samples))
    rows, columns = float(np.abs(M).sum(axis=1).max()), float(np.abs(M).sum(axis=0).max())
    np.testing.assert_allclose(smap.apply(scale, x)[0, 0], M @ x[0, 0], rtol=0, atol=1e-10 * rows)
    np.testing.assert_allclose(smap.adjoint(scale, x)[0, 0], M.T @ x[0, 0], rtol=0, atol=1e-10 * columns)
    exact, radius = float(np.linalg.norm(M, 2)), float(np.max(np.abs(np.linalg.eigvals(M))))
    bracket = smap.norm(scale)
    assert bracket.lower <= exact * (1 + 1e-9) and exact <= bracket.upper
    assert _toeplitz_norm(smap, scale) <= bracket.tau * (1 + 1e-12)
    assert bracket.upper <= max(exact, bracket.tau) * (1 + 2e-4)
    certificate = qmap.input_map_certificate(smap, scale)
    proof = certificate.proof
    assert proof is not None and proof.method in (CertificateMethod.SYMBOL, CertificateMethod.STRUCTURED)
    if proof.norm_2 is BoundClaim.LOWER:
        assert certificate.norm_2 <= exact * (1 + 1e-9) and proof.monotone is MonotoneVerdict.NOT_MONOTONE
    else:
        assert exact <= certificate.norm_2 <= max(exact, bracket.tau) * (1 + 2e-4)
    if proof.monotone is MonotoneVerdict.MONOTONE:
        assert exact <= CONTRACTION_LIMIT
    if proof.monotone is MonotoneVerdict.INCONCLUSIVE:
        assert certificate.norm_2_method.startswith("inconclusive at bound")
    if law.q_filter is not None and law.q_filter.phase is QFilterPhase.CAUSAL:
        assert proof.spectral_radius is BoundClaim.EXACT and smap.triangular
        assert certificate.spectral_radius == pytest.approx(_block_triangular_radius(M, 1), rel=1e-8, abs=1e-12)
    else:
        assert radius <= certificate.spectral_radius * (1 + 1e-9)


def _edge_case(n: int) -> tuple[LoopPlant, LawStructure]:
    """A map whose 2-norm is its edge's (above the symbol's sup): two samples of delay, state feedback, a small
    learning gain and a zero-phase filter (the demo's structure at 1 ms)."""
    base = discretize(ContinuousModel(np.array([[-100.2]]), np.array([[100.2]]), np.array([[1.0]])), 0.001)
    model = augment_input_delay(base, 2)[0]
    p1 = np.array([[-7.96, -0.84, -0.92]])
    p2 = np.array([[2.42 * 0.05]])
    q = QFilter(0.2 * math.pi / 0.001, 2, 0.001).on(n)
    law = LawStructure(0.0319, 0.635, 0.001, n, 2, FractionalMemory.CONTROLLABLE, q)
    return LoopPlant(model.A, model.B, model.measured_output, p1, p2), law


def test_an_edge_above_the_symbol_is_found_and_the_exact_mode_pins_it() -> None:
    loop, law = _edge_case(250)
    smap = qmap.structured_input_map(loop, law)
    assert smap is not None
    M = _dense(loop, law, 1.0)
    exact = float(np.linalg.norm(M, 2))
    fast = qmap.input_map_certificate(smap, 1.0)
    assert fast.norm_2_symbol is not None and exact > fast.norm_2_symbol * (1 + 1e-4)  # the edge dominates
    assert fast.proof is not None and fast.proof.method is CertificateMethod.STRUCTURED
    assert exact <= fast.norm_2 <= exact * (1 + 2e-4)
    pinned = qmap.input_map_certificate(smap, 1.0, exact=True)
    assert pinned.proof is not None and pinned.proof.norm_2 is BoundClaim.EXACT
    assert pinned.norm_2 == pytest.approx(exact, rel=5e-9)
    # dense (the trial is short enough): LAPACK's eigenvalues of the operator's own matrix; those of this
    # far-from-normal map are ill-conditioned, so two dense matrices equal to rounding agree only to about 1e-4
    assert pinned.proof.spectral_radius is BoundClaim.EXACT
    assert pinned.spectral_radius == pytest.approx(float(np.max(np.abs(np.linalg.eigvals(M)))), rel=1e-3)


def test_a_map_without_the_structure_is_not_certified_by_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """The structure check can fail: without the zero-phase pass's end corner in the known co-ranges,
    ``(I - P_U) E (I - P_V)`` is not zero and the map is refused (certificates then say "inconclusive")."""
    loop, law = _edge_case(300)
    assert qmap.structured_input_map(loop, law) is not None
    real = qmap._corner_spaces

    def without_end(*args: object) -> tuple[np.ndarray, np.ndarray]:
        U, V = real(*args)  # type: ignore[arg-type]
        return U, V[:0]

    monkeypatch.setattr(qmap, "_corner_spaces", without_end)
    assert qmap.structured_input_map(loop, law) is None


def test_an_unstable_in_trial_loop_is_not_monotone_by_a_lower_bound() -> None:
    """``A + B p1`` unstable: the map has no structured form (its entries grow like the loop's powers); a power
    iteration on the exact operator still proves it is not monotone, below the dense norm."""
    model = _model(5, 3, 2)
    p1 = 0.3 * np.ones((1, model.n_states))
    assert max(abs(np.linalg.eigvals(model.A + model.B @ p1))) > 1.0
    loop = LoopPlant(model.A, model.B, model.measured_output, p1, np.array([[0.1]]))
    law = LawStructure(0.0, 0.5, TS, 200, 2, FractionalMemory.CONTROLLABLE, QFilter(20.0, 2, TS).on(200))
    assert qmap.structured_input_map(loop, law) is None
    certificate = qmap.unstructured_certificate(loop, law)
    assert certificate.proof is not None and certificate.proof.monotone is MonotoneVerdict.NOT_MONOTONE
    assert 1.0 < certificate.norm_2 <= float(np.linalg.norm(_dense(loop, law, 1.0), 2)) * (1 + 1e-9)


def _simulate(
    design_A: np.ndarray, design_B: np.ndarray, C: np.ndarray, law: object, reference: np.ndarray, trials: int
) -> list[np.ndarray]:
    """Trials of ``law`` on the plant ``(A, B, C)`` from rest, sample by sample; the commands of each trial."""
    commands = []
    n = reference.shape[0]
    for _ in range(trials):
        law.begin_trial()  # type: ignore[attr-defined]
        x = np.zeros(design_A.shape[0])
        outputs, issued = np.zeros((n, 1)), np.zeros((n, 1))
        for t in range(n):
            issued[t] = law.command(t, C @ x)  # type: ignore[attr-defined]
            x = design_A @ x + design_B @ issued[t]
            outputs[t] = C @ x
        law.end_trial(reference, outputs)  # type: ignore[attr-defined]
        commands.append(issued)
    return commands


@pytest.mark.parametrize("phase", list(QFilterPhase))
def test_a_monotone_certificate_bounds_the_growth_of_the_input_from_trial_to_trial(phase: QFilterPhase) -> None:
    """FOILC with state feedback and a Q-filter, certified on a trial beyond the dense limit (the structured path),
    then run: ``u_(k+1) - u_k = M (u_k - u_(k-1))``, so each trial's input change is at most the certified 2-norm
    times the previous one's."""
    n, kp, r = 700, 0.05, 0.6
    model = discretize(ContinuousModel(np.array([[-1.23]]), np.array([[1.68]]), np.array([[1.0]])), TS)
    P = np.array([[-0.3, 0.6 * 1.23 / 1.68 / (1 + kp * TS**-r)]])
    section = QFilterConfig(cutoff=0.2 * math.pi / TS, order=2, phase=phase)
    q_filter = QFilter.of(section, TS)
    law_structure = LawStructure(kp, r, TS, n, 0, FractionalMemory.CONTROLLABLE, q_filter.on(n))
    certificates = certify_as_given(model, Uncertainty.none(1, 1), P, law_structure, require_monotonic=True)
    nominal = certificates.plants[0]
    assert certificates.monotonic and nominal.proof is not None and n > 600  # beyond the dense limit
    assert nominal.proof.method in (CertificateMethod.SYMBOL, CertificateMethod.STRUCTURED)
    design = plain_design(
        model.A, model.B, model.C, P, kp=kp, r=r, sample_time=TS, certificates=certificates, q_filter=q_filter
    )
    law = make_law(design, LawConfig(q_filter=section), n)
    t = np.arange(1, n + 1) * TS
    reference = np.column_stack([np.sin(2 * t) + 0.5 * np.sign(np.sin(7 * t))])
    inputs = _simulate(model.A, model.B, model.C, law, reference, trials=7)
    changes = [float(np.linalg.norm(inputs[k] - inputs[k - 1])) for k in range(1, len(inputs))]
    assert changes[0] > 0
    for before, after in itertools.pairwise(changes[1:]):  # from trial 2 on: trial 1 only measured
        assert after <= nominal.norm_2 * before * (1 + 1e-9)


def _paper_config(n: int, phase: str, *, exact: bool = False) -> Config:
    """The paper's plant (10 ms) with a P-type law, a Q-filter at 20 % of Nyquist and trials of ``n`` samples."""
    return load_config(
        None,
        {
            "plant.a": -1.23,
            "plant.b": 1.68,
            "sample_time": TS,
            "reference.profile": "piecewise",
            "reference.segments": [{"duration": n * TS, "start": 1.0}],
            "law.kind": "p-type",
            "law.q_filter": {"cutoff": 0.2 * math.pi / TS, "order": 2, "phase": phase},
            "synthesis.exact_certificates": exact,
        },
    )


def test_the_proof_reads_back_from_the_design_record() -> None:
    design = build_design(_paper_config(700, "causal"), "p-type", 700, input_delay=1)
    assert design.certificates is not None
    proofs = [plant.proof for plant in design.certificates.plants]
    assert all(proof is not None for proof in proofs)
    again = Design.from_json(json.loads(json.dumps(design.to_json())))
    assert again.certificates is not None
    assert [plant.proof for plant in again.certificates.plants] == proofs
    assert json.dumps(again.to_json()) == json.dumps(design.to_json())


@pytest.mark.slow
def test_the_exact_mode_from_the_config_gives_the_dense_radius_of_a_zero_phase_map() -> None:
    """``synthesis.exact_certificates``: the zero-phase map's spectral radius densely (the fast mode bounds it by the
    2-norm), and the 2-norm's bracket around the dense SVD's value."""
    n = 700
    fast = build_design(_paper_config(n, "zero"), "p-type", n, input_delay=1)
    exact = build_design(_paper_config(n, "zero", exact=True), "p-type", n, input_delay=1)
    assert fast.certificates is not None and exact.certificates is not None
    fast_nominal, exact_nominal = fast.certificates.plants[0], exact.certificates.plants[0]
    assert fast_nominal.proof is not None and fast_nominal.proof.spectral_radius is BoundClaim.UPPER
    assert exact_nominal.proof is not None and exact_nominal.proof.spectral_radius is BoundClaim.EXACT
    law = LawStructure(
        0.0, 1.0, TS, n, exact.input_delay, FractionalMemory.CONTROLLABLE, QFilter(0.2 * math.pi / TS, 2, TS).on(n)
    )
    M = _dense(LoopPlant(exact.A, exact.B, exact.measured_output, exact.p1, exact.p2), law, 1.0)
    assert exact_nominal.spectral_radius == pytest.approx(float(np.max(np.abs(np.linalg.eigvals(M)))), rel=1e-3)
    assert exact_nominal.spectral_radius < fast_nominal.spectral_radius
    assert float(np.linalg.norm(M, 2)) <= exact_nominal.norm_2 <= float(np.linalg.norm(M, 2)) * (1 + 1e-4)


@pytest.mark.parametrize("phase", list(QFilterPhase))
def test_two_channels_against_the_dense_map(phase: QFilterPhase) -> None:
    """Two inputs and two outputs (block symbols, the per-frequency SVD of the symbol's bound, block circulant
    preconditioner): the same agreement with the dense map as one channel."""
    rng = np.random.default_rng(3)
    A = rng.standard_normal((3, 3))
    A *= 0.8 / float(np.max(np.abs(np.linalg.eigvals(A))))
    model = augment_input_delay(DiscreteModel(A, rng.standard_normal((3, 2)), rng.standard_normal((2, 3)), TS), 1)[0]
    markov = model.measured_output @ model.A @ model.B
    p1 = 0.02 * rng.standard_normal((2, model.n_states))
    assert max(abs(np.linalg.eigvals(model.A + model.B @ p1))) < 1.0
    loop = LoopPlant(model.A, model.B, model.measured_output, p1, 0.3 * np.linalg.inv(markov))
    n = 150
    q = QFilter(60.0, 2, TS, phase).on(n)
    law = LawStructure(0.05, 0.6, TS, n, 1, FractionalMemory.CONTROLLABLE, q)
    smap = qmap.structured_input_map(loop, law)
    assert smap is not None
    F = law_filter_matrix(0.05, 0.6, TS, n, 1)  # per channel: dense_input_map repeats it over the outputs
    M = dense_input_map(loop.A, loop.B, loop.C_measured, p1, loop.p2, F, q.matrix(), 1)
    x = rng.standard_normal((1, 2, n))
    flat = x[0].T.ravel()  # sample-major, as the dense map
    np.testing.assert_allclose(smap.apply(1.0, x)[0].T.ravel(), M @ flat, atol=1e-10 * np.abs(M).sum(axis=1).max())
    exact = float(np.linalg.norm(M, 2))
    bracket = smap.norm(1.0)
    assert bracket.lower <= exact * (1 + 1e-9) and exact <= bracket.upper <= max(exact, bracket.tau) * (1 + 2e-4)
    if phase is QFilterPhase.CAUSAL:
        assert qmap.triangular_radius(smap, 1.0) == pytest.approx(_block_triangular_radius(M, 2), rel=1e-8)

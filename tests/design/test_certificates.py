"""Lifted trial-to-trial map of the law as it runs, checked against brute-force trial-by-trial simulation."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from foilc_hil.config import DivergentFilterPolicy, FractionalMemory
from foilc_hil.design.certificates import certify, map_certificate
from foilc_hil.design.error_map import (
    FftOperand,
    block_toeplitz_product,
    dense_error_map,
    dense_input_map,
    lifted_error_map,
)
from foilc_hil.design.fractional import FractionalPD
from foilc_hil.design.lifted import LawStructure, LoopPlant, dense_block_toeplitz
from foilc_hil.design.lmi import solve_lmi
from foilc_hil.design.map_norms import (
    CHOLESKY_METHOD,
    CONTRACTION_LIMIT,
    DENSE_LIMIT,
    bounded_matrix_certificate,
    matrix_norm_bound,
)
from foilc_hil.design.models import DiscreteModel, Uncertainty, augment_input_delay, discretize
from foilc_hil.design.qfilter import QFilter
from foilc_hil.design.qmap import structured_input_map
from foilc_hil.errors import ConvergenceCertificateError
from plant_emulator.linear import ContinuousModel
from tests.design.test_synthesis import _mimo

pytestmark = pytest.mark.filterwarnings("ignore:Solution may be inaccurate")


def _run_trials(
    A: np.ndarray,
    B: np.ndarray,
    C: np.ndarray,
    p1: np.ndarray,
    p2: np.ndarray,
    fpd: FractionalPD,
    reference: np.ndarray,
    lead: int,
    trials: int,
    Q: np.ndarray | None = None,
    memory: str = "trial",
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Plain loops: trial 1 only measures; then u_k(t) = ff(t) + p1 (x_k(t) - x_{k-1}(t)) + p2 E_{k-1}[t + lead],
    ff = u_{k-1} (or Q u_{k-1}); e[i] = r[i] - C x(i + 1). Returns the errors and inputs of every trial.

    ``memory="trial"``: E = fpd(e) over the whole trial; ``"controllable"``: E[lead:] = zero-history fpd(e[lead:]).
    """
    zero = FractionalPD(fpd.kp, fpd.r, fpd.h, history="zero")

    def learning_signal(e: np.ndarray) -> np.ndarray:
        if memory == "trial":
            return np.column_stack([fpd.apply(e[:, j]) for j in range(e.shape[1])])
        out = e.copy()
        out[lead:] = np.column_stack([zero.apply(e[lead:, j]) for j in range(e.shape[1])])
        return out

    n_samples, m = reference.shape[0], B.shape[1]
    feedforward = np.zeros((n_samples, m))
    x_prev: np.ndarray | None = None
    E_prev: np.ndarray | None = None
    errors, inputs = [], []
    for _ in range(trials):
        x = np.zeros(A.shape[0])
        states, us, ys = [], [], []
        for t in range(n_samples):
            states.append(x.copy())
            u = feedforward[t].copy()
            if x_prev is not None and E_prev is not None:
                u += p1 @ (x - x_prev[t])
                if t + lead < n_samples:
                    u += p2 @ E_prev[t + lead]
            us.append(u)
            x = A @ x + B @ u
            ys.append(C @ x)
        e = reference - np.array(ys)
        E = learning_signal(e)
        u_trial = np.array(us)
        errors.append(e)
        inputs.append(u_trial)
        x_prev, E_prev = np.array(states), E
        feedforward = u_trial if Q is None else Q @ u_trial
    return errors, inputs


def _plant(n: int, m: int, p: int, seed: int, lead: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, n))
    A *= 0.8 / max(abs(np.linalg.eigvals(A)))  # stable: lifted maps stay well scaled over long trials
    B = rng.standard_normal((n, m))
    C = rng.standard_normal((p, n))
    if lead:
        augmented, _ = augment_input_delay(DiscreteModel(A, B, C, 0.05), lead)
        return augmented.A, augmented.B, augmented.measured_output
    return A, B, C


CASES = [
    # n, m, p, lead, kp, r
    (1, 1, 1, 0, 0.3, 0.6),
    (1, 1, 1, 0, 0.05, 1.4),
    (2, 1, 1, 1, 0.2, 0.8),
    (2, 1, 1, 2, 0.1, 1.2),
    (3, 2, 2, 0, 0.2, 0.7),
    (3, 2, 2, 1, 0.0, 1.0),
]


def _law_operator(kp: float, r: float, h: float, n_samples: int, lead: int, memory: FractionalMemory) -> np.ndarray:
    """The law's E = F e as a dense matrix, built from FractionalPD (the operator tested in test_fractional)."""
    if memory == "trial":
        return FractionalPD(kp, r, h).matrix(n_samples)
    F = np.eye(n_samples)
    F[lead:, lead:] = FractionalPD(kp, r, h, history="zero").matrix(n_samples - lead)
    return F


MEMORIES = list(FractionalMemory)


@pytest.mark.parametrize("memory", MEMORIES)
@pytest.mark.parametrize(("n", "m", "p", "lead", "kp", "r"), CASES)
def test_lifted_map_matches_brute_force_trials(
    n: int, m: int, p: int, lead: int, kp: float, r: float, memory: FractionalMemory
) -> None:
    A, B, C = _plant(n, m, p, seed=n + 10 * lead, lead=lead)
    rng = np.random.default_rng(5)
    p1 = 0.1 * rng.standard_normal((m, A.shape[0]))
    p2 = 0.05 * rng.standard_normal((m, p))
    h, n_samples = 0.05, 40
    reference = np.cumsum(rng.standard_normal((n_samples, p)), axis=0) * 0.1
    errors, _ = _run_trials(A, B, C, p1, p2, FractionalPD(kp, h=h, r=r), reference, lead, trials=5, memory=memory)
    T = lifted_error_map(LoopPlant(A, B, C, p1, p2), LawStructure(kp, r, h, n_samples, lead, memory))
    for k in range(2, 5):
        before = (errors[k - 1] - errors[k - 2])[lead:].ravel()
        after = (errors[k] - errors[k - 1])[lead:].ravel()
        scale = max(1.0, float(np.max(np.abs(after))))
        assert float(np.max(np.abs(T.matvec(before) - after))) <= 1e-9 * scale
        # The first `lead` error samples never change.
        np.testing.assert_allclose(errors[k][:lead], errors[0][:lead], atol=1e-12)


@pytest.mark.parametrize("memory", MEMORIES)
@pytest.mark.parametrize(("n", "m", "p", "lead", "kp", "r"), CASES)
def test_fast_operator_matches_the_dense_second_method(
    n: int, m: int, p: int, lead: int, kp: float, r: float, memory: FractionalMemory
) -> None:
    A, B, C = _plant(n, m, p, seed=3, lead=lead)
    rng = np.random.default_rng(9)
    p1 = 0.1 * rng.standard_normal((m, A.shape[0]))
    p2 = 0.05 * rng.standard_normal((m, p))
    h, n_samples = 0.05, 30
    T = lifted_error_map(LoopPlant(A, B, C, p1, p2), LawStructure(kp, r, h, n_samples, lead, memory))
    full = dense_error_map(A, B, C, p1, p2, _law_operator(kp, r, h, n_samples, lead, memory), lead)
    np.testing.assert_allclose(full[: lead * p, :], np.eye(n_samples * p)[: lead * p], atol=1e-15)
    sub = full[lead * p :, lead * p :]
    np.testing.assert_allclose(T.to_dense(), sub, atol=1e-10 * max(1.0, float(np.max(np.abs(sub)))))
    x, y = rng.standard_normal(T.size), rng.standard_normal(T.size)
    assert float(np.dot(T.matvec(x), y)) == pytest.approx(float(np.dot(x, T.rmatvec(y))), rel=1e-9, abs=1e-9)


def test_spectral_radius_is_read_off_the_block_triangular_structure() -> None:
    A, B, C = _plant(3, 2, 2, seed=4)
    rng = np.random.default_rng(2)
    p1, p2 = 0.1 * rng.standard_normal((2, 3)), 0.3 * rng.standard_normal((2, 2))
    kp, r, h, n_samples = 0.1, 1.3, 0.05, 30
    T = lifted_error_map(LoopPlant(A, B, C, p1, p2), LawStructure(kp, r, h, n_samples, 0, FractionalMemory.TRIAL))
    dense = dense_error_map(A, B, C, p1, p2, FractionalPD(kp, r, h).matrix(n_samples))
    # Dense eigvals of a defective triangular matrix are inaccurate; read the blocks from the dense matrix instead.
    k = 4 * 2  # the leading samples where the Caputo corrections sit
    assert np.all(dense[:k, k:] == 0)
    strictly_upper = np.triu(dense[k:, k:], 1)
    for i in range(0, dense.shape[0] - k, 2):  # only the 2x2 diagonal blocks may stick above the diagonal
        strictly_upper[i, i + 1] = 0.0
    assert np.all(strictly_upper == 0)
    diagonal_blocks = [dense[k + i : k + i + 2, k + i : k + i + 2] for i in range(0, dense.shape[0] - k, 2)]
    expected = max(max(abs(np.linalg.eigvals(blk))) for blk in [dense[:k, :k], *diagonal_blocks])
    assert T.spectral_radius() == pytest.approx(expected, rel=1e-10)


@pytest.mark.slow
@pytest.mark.parametrize("memory", MEMORIES)
def test_iterative_norm_matches_dense_svd(memory: FractionalMemory) -> None:
    model = discretize(ContinuousModel(np.array([[-1.23]]), np.array([[1.68]]), np.array([[1.0]])), 0.01)
    p1, p2 = -model.A / model.B, 0.3 / model.B
    n_samples = DENSE_LIMIT + 200
    result = map_certificate(
        LoopPlant(model.A, model.B, model.C, p1, p2), LawStructure(0.05, 0.8, 0.01, n_samples, 0, memory)
    )
    dense = dense_error_map(model.A, model.B, model.C, p1, p2, _law_operator(0.05, 0.8, 0.01, n_samples, 0, memory))
    exact = float(np.linalg.norm(dense, 2))
    if result.norm_2_method == "upper bound (truncated Toeplitz symbol)":
        assert exact <= result.norm_2 <= exact + 1e-3  # rigorous, and tight
    else:
        assert result.norm_2_method == "svds"
        assert result.norm_2 == pytest.approx(exact, rel=1e-7)
    assert result.spectral_radius < 1


@pytest.mark.parametrize("memory", MEMORIES)
@pytest.mark.parametrize(("n_samples", "seed"), [(60, 0), (300, 1), (900, 2)])
def test_symbol_bound_is_an_upper_bound_of_the_exact_norm(memory: FractionalMemory, n_samples: int, seed: int) -> None:
    """The fast certificate against a dense SVD of the same map: never below it, and close to it."""
    rng = np.random.default_rng(seed)
    a, b = -rng.uniform(0.5, 5.0), rng.uniform(0.5, 3.0)
    model = discretize(ContinuousModel(np.array([[a]]), np.array([[b]]), np.array([[1.0]])), 0.01)
    p1, p2 = -model.A / model.B, rng.uniform(0.1, 0.9) / model.B
    kp, r = rng.uniform(0.0, 0.3), rng.uniform(0.1, 1.2)
    loop = LoopPlant(model.A, model.B, model.C, p1, p2)
    T = lifted_error_map(loop, LawStructure(kp, r, 0.01, n_samples, 0, memory))
    exact = float(np.linalg.norm(T.to_dense(), 2))
    bound = T.symbol_upper_bound()
    assert exact <= bound
    assert bound <= T.norm_upper_bound() + 1e-12  # never looser than the triangle inequality it replaces
    if memory is FractionalMemory.CONTROLLABLE:  # pure Toeplitz: the finite section approaches the symbol's sup
        assert bound <= exact + 0.05


def test_symbol_bound_holds_for_several_outputs() -> None:
    model = _mimo()
    rng = np.random.default_rng(5)
    p2 = 0.3 * np.linalg.pinv(model.C @ model.B)
    loop = LoopPlant(model.A, model.B, model.C, np.zeros((model.B.shape[1], model.A.shape[0])), p2)
    for n_samples in (40, 200):
        kp, r = rng.uniform(0.0, 0.2), rng.uniform(0.2, 0.9)
        T = lifted_error_map(loop, LawStructure(kp, r, model.sample_time, n_samples, 0, FractionalMemory.CONTROLLABLE))
        assert float(np.linalg.norm(T.to_dense(), 2)) <= T.symbol_upper_bound()


@pytest.mark.slow
@pytest.mark.parametrize("memory", MEMORIES)
def test_q_filter_input_map_matches_brute_force_and_the_operator(memory: FractionalMemory) -> None:
    A, B, C = _plant(2, 1, 1, seed=8)
    kp, r, h, n_samples = 0.1, 0.7, 0.05, 40
    first_weight = 1 + kp * h**-r
    p1, p2 = np.array([[0.05, -0.02]]), 0.5 / (C @ B * first_weight)  # a convergent law
    q_filter = QFilter(cutoff=20.0, order=2, sample_time=h)
    Q = q_filter.matrix(n_samples)
    rng = np.random.default_rng(1)
    reference = np.cumsum(rng.standard_normal((n_samples, 1)), axis=0) * 0.1
    _, inputs = _run_trials(A, B, C, p1, p2, FractionalPD(kp, r, h), reference, 0, trials=5, Q=Q, memory=memory)
    M = dense_input_map(A, B, C, p1, p2, _law_operator(kp, r, h, n_samples, 0, memory), Q)
    for k in range(2, 5):
        before = (inputs[k - 1] - inputs[k - 2]).ravel()
        after = (inputs[k] - inputs[k - 1]).ravel()
        np.testing.assert_allclose(M @ before, after, atol=1e-10 * max(1.0, float(np.max(np.abs(after)))))
    # The structured operator agrees with the dense map, forward and adjoint.
    law = LawStructure(kp, r, h, n_samples, 0, memory, q_filter.on(n_samples))
    structured = structured_input_map(LoopPlant(A, B, C, p1, p2), law)
    assert structured is not None
    x, y = rng.standard_normal((1, 1, n_samples)), rng.standard_normal((1, 1, n_samples))
    np.testing.assert_allclose(structured.apply(1.0, x)[0, 0], M @ x[0, 0], atol=1e-10 * np.max(np.abs(M @ x[0, 0])))
    np.testing.assert_allclose(
        structured.adjoint(1.0, y)[0, 0], M.T @ y[0, 0], atol=1e-10 * np.max(np.abs(M.T @ y[0, 0]))
    )
    # On a trial beyond the dense limit the certificate brackets the dense 2-norm and bounds the radius.
    n_large = DENSE_LIMIT + 100
    fast = map_certificate(
        LoopPlant(A, B, C, p1, p2), LawStructure(kp, r, h, n_large, 0, memory, q_filter.on(n_large))
    )
    M_large = dense_input_map(A, B, C, p1, p2, _law_operator(kp, r, h, n_large, 0, memory), q_filter.matrix(n_large))
    assert fast.map == "input (Q-filter)" and fast.proof is not None
    exact = float(np.linalg.norm(M_large, 2))
    if fast.proof.norm_2 == "lower bound":
        assert fast.norm_2 <= exact * (1 + 1e-9)
    else:
        assert exact <= fast.norm_2 <= exact * (1 + 1e-3)
    assert max(abs(np.linalg.eigvals(M_large))) <= fast.spectral_radius * (1 + 1e-9)


def _paper_model(ts: float) -> DiscreteModel:
    return discretize(ContinuousModel(np.array([[-1.23]]), np.array([[1.68]]), np.array([[1.0]])), ts)


# the law's default memory in the inner loop, both in `make test`
@pytest.mark.parametrize("memory", [pytest.param(memory, marks=() if memory is FractionalMemory.CONTROLLABLE
                                                 else pytest.mark.slow) for memory in MEMORIES])
def test_rescale_fixes_a_filter_that_breaks_the_naive_gain_and_refuse_raises(memory: FractionalMemory) -> None:
    model = _paper_model(0.01)
    unc = Uncertainty.none(1, 1)
    P = solve_lmi(model, unc, tau=0.868, theta=0.868).P
    kp, r, n_samples = 0.05, 0.8, 300
    fpd_matrix = _law_operator(kp, r, 0.01, n_samples, 0, memory)
    designed = dense_error_map(model.A, model.B, model.C, P[:, :1], P[:, 1:], fpd_matrix)
    naive = dense_error_map(model.A, model.B, model.C, P[:, :1], P[:, 1:], np.eye(n_samples))
    assert np.linalg.norm(naive, 2) < 1  # the LMI gain is fine without the filter ...
    assert max(abs(np.diag(designed))) > 1  # ... and diverges with it (triangular: the diagonal is the spectrum)
    with pytest.raises(ConvergenceCertificateError, match="refuse"):
        certify(model, unc, P, LawStructure(kp, r, 0.01, n_samples, 0, memory), policy=DivergentFilterPolicy.REFUSE)
    outcome = certify(
        model, unc, P, LawStructure(kp, r, 0.01, n_samples, 0, memory), policy=DivergentFilterPolicy.RESCALE
    )
    assert outcome.certificates.fractional_memory == memory
    assert 0 < outcome.gain_scale < 1
    assert outcome.certificates.action == "rescale"
    assert outcome.certificates.monotonic is True
    np.testing.assert_allclose(outcome.P[:, 1:], outcome.gain_scale * P[:, 1:])
    np.testing.assert_array_equal(outcome.P[:, :1], P[:, :1])
    rescaled = dense_error_map(model.A, model.B, model.C, outcome.P[:, :1], outcome.P[:, 1:], fpd_matrix)
    assert np.linalg.norm(rescaled, 2) < 1
    assert outcome.certificates.norm_2 == pytest.approx(np.linalg.norm(rescaled, 2), rel=1e-9)
    assert outcome.certificates.largest_admissible_scale is not None
    assert outcome.certificates.largest_admissible_scale >= outcome.gain_scale


@pytest.mark.slow
def test_r_above_one_has_no_monotonic_certificate() -> None:
    model = _paper_model(0.01)
    unc = Uncertainty.none(1, 1)
    P = solve_lmi(model, unc, tau=0.868, theta=0.868).P
    kp, r, n_samples = 2.6315, 1.0778, 200
    with pytest.raises(ConvergenceCertificateError, match="monotonically"):
        certify(model, unc, P, LawStructure(kp, r, 0.01, n_samples, 0, FractionalMemory.TRIAL))
    outcome = certify(
        model, unc, P, LawStructure(kp, r, 0.01, n_samples, 0, FractionalMemory.TRIAL), require_monotonic=False
    )
    assert outcome.certificates.monotonic is False
    assert outcome.certificates.spectral_radius < 1
    rescaled = dense_error_map(
        model.A, model.B, model.C, outcome.P[:, :1], outcome.P[:, 1:], FractionalPD(kp, r, 0.01).matrix(n_samples)
    )
    assert np.linalg.norm(rescaled, 2) > 1
    assert outcome.certificates.growth_bound is not None
    assert outcome.certificates.growth_bound.bound >= 1


@pytest.mark.slow
def test_certify_covers_uncertainty_vertices_and_mimo() -> None:
    model = _mimo()
    unc = Uncertainty(0.01 * np.eye(3), np.eye(3), 0.01 * model.B, np.eye(2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        P = solve_lmi(model, unc, tau=0.868, theta=0.868).P
    outcome = certify(model, unc, P, LawStructure(0.0, 1.0, model.sample_time, 60))
    assert outcome.certificates.vertices > 0
    assert len(outcome.certificates.plants) == outcome.certificates.vertices + 1
    assert all(entry.spectral_radius < 1 for entry in outcome.certificates.plants)
    assert outcome.certificates.monotonic is True


@pytest.mark.parametrize("memory", MEMORIES)
@pytest.mark.parametrize(("n", "m", "p", "lead", "kp", "r"), CASES)
def test_norm_upper_bound_bounds_the_dense_norm(
    n: int, m: int, p: int, lead: int, kp: float, r: float, memory: FractionalMemory
) -> None:
    A, B, C = _plant(n, m, p, seed=11, lead=lead)
    rng = np.random.default_rng(4)
    p1 = 0.1 * rng.standard_normal((m, A.shape[0]))
    p2 = 0.05 * rng.standard_normal((m, p))
    T = lifted_error_map(LoopPlant(A, B, C, p1, p2), LawStructure(kp, r, 0.05, 30, lead, memory))
    dense_norm = float(np.linalg.norm(T.to_dense(), 2))
    assert T.norm_upper_bound() >= dense_norm * (1 - 1e-12)
    assert T.symbol_norm() <= T.norm_upper_bound() * (1 + 1e-12)


# --- the Cholesky norm bound of dense maps (per-draw NOILC certificates) -----------------------------------------


def _decaying_map(size: int, seed: int) -> np.ndarray:
    """``I - G L``-like: identity minus a lower-triangular Toeplitz with decaying random taps times a dense matrix."""
    rng = np.random.default_rng(seed)
    taps = 0.3 * rng.standard_normal(size) * 0.97 ** np.arange(size)
    from scipy.linalg import toeplitz

    G = toeplitz(taps, np.zeros(size))
    return np.eye(size) - G @ (0.05 * rng.standard_normal((size, size)) / np.sqrt(size))


@pytest.mark.slow
@pytest.mark.parametrize(("size", "seed"), [(30, 1), (60, 2), (DENSE_LIMIT + 50, 3)])
def test_cholesky_norm_bound_is_above_numpys_norm_and_tight(size: int, seed: int) -> None:
    T = _decaying_map(size, seed)
    exact = float(np.linalg.svd(T, compute_uv=False)[0])  # LAPACK SVD: a second method
    bound = matrix_norm_bound(T)
    assert bound is not None and exact <= bound <= exact * (1 + 1e-3)
    if size <= DENSE_LIMIT:  # the LAPACK estimate is at or below the exact value: the first gap succeeds
        assert bound <= exact * (1 + 1e-7)
    # an admitted rounding error of the matrix is added to the bound
    assert matrix_norm_bound(T, 1e-3) == pytest.approx(bound + 1e-3, rel=1e-12)
    certificate = bounded_matrix_certificate(T, "error")
    if bound <= CONTRACTION_LIMIT:
        assert certificate.norm_2_method == CHOLESKY_METHOD and certificate.norm_2 == bound
        assert certificate.spectral_radius >= float(np.max(np.abs(np.linalg.eigvals(T))))
    else:  # no certificate from the bound: the exact dense path decides
        assert certificate.norm_2 == pytest.approx(exact, rel=1e-9)


def test_cholesky_norm_bound_is_not_fooled_by_a_low_estimate() -> None:
    """A map whose norm comes from one corner entry (far from Toeplitz): the symbol estimate of the middle column
    misses it, so the first gaps fail and a later, larger one must hold -- never a bound below the norm."""
    size = DENSE_LIMIT + 10
    T = 0.5 * np.eye(size)
    T[0, -1] = 0.9
    exact = float(np.linalg.norm(T, 2))
    bound = matrix_norm_bound(T)
    assert bound is None or bound >= exact
    certificate = bounded_matrix_certificate(T, "error")
    assert certificate.norm_2 >= exact * (1 - 1e-12)
    assert matrix_norm_bound(np.full((3, 3), np.nan)) is None


def test_block_toeplitz_product_matches_the_dense_product_within_its_bound() -> None:
    rng = np.random.default_rng(7)
    for rows, cols in ((1, 1), (2, 3)):
        blocks = rng.standard_normal((50, rows, cols)) * 0.9 ** np.arange(50)[:, None, None]
        X = rng.standard_normal((50 * cols, 17))
        product, error = block_toeplitz_product(blocks, X)
        dense = dense_block_toeplitz(blocks) @ X
        assert product.shape == dense.shape
        assert np.linalg.norm(product - dense) <= error and 0 < error < 1e-10
        # X transformed once, for many left factors: the same product and bound
        operand = FftOperand.of(X, 50)
        for scale in (1.0, -0.5):
            again, bound = block_toeplitz_product(blocks * scale, operand)
            assert np.linalg.norm(again - dense * scale) <= bound and bound == pytest.approx(error * abs(scale))
        with pytest.raises(ValueError, match="blocks"):
            block_toeplitz_product(blocks[:40], operand)

"""Trial operators (``foilc_hil.design.trial_operator``): the state-space algebra and the structured norm test against
dense matrices built here, on random plants (hypothesis) and on the lifted laws' own trial maps."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from foilc_hil.design.models import DiscreteModel, augment_input_delay
from foilc_hil.design.noilc import plant_operator, plant_realization
from foilc_hil.design.trial_operator import ROUNDING_MARGIN, TrialOperator
from tests.support.fuzz_settings import fuzz_settings


def _stable(rng: np.random.Generator, n: int, radius: float) -> np.ndarray:
    A = rng.standard_normal((n, n))
    return np.asarray(A * (radius / max(abs(np.linalg.eigvals(A)))))


def _causal(rng: np.random.Generator, n: int, m: int, p: int, length: int) -> tuple[TrialOperator, np.ndarray]:
    """A random causal system and its lifted matrix written out from the Markov parameters ``D, C A^k B``."""
    A, B = _stable(rng, n, 0.9), rng.standard_normal((n, m))
    C, D = rng.standard_normal((p, n)), rng.standard_normal((p, m))
    blocks = [D] + [C @ np.linalg.matrix_power(A, k) @ B for k in range(length - 1)]
    dense = np.zeros((length * p, length * m))
    for i in range(length):
        for j in range(i + 1):
            dense[i * p : (i + 1) * p, j * m : (j + 1) * m] = blocks[i - j]
    return TrialOperator.causal(A, B, C, D, length), dense


@given(seed=st.integers(0, 2**32 - 1), length=st.integers(2, 40), n=st.integers(1, 3), m=st.integers(1, 2),
       p=st.integers(1, 2))
@fuzz_settings(25)
def test_products_transposes_and_sums_are_the_dense_ones(seed: int, length: int, n: int, m: int, p: int) -> None:
    rng = np.random.default_rng(seed)
    G, G_dense = _causal(rng, n, m, p, length)
    H, H_dense = _causal(rng, 2, p, m, length)
    np.testing.assert_allclose(G.transpose().dense(), G_dense.T, atol=1e-12 * np.abs(G_dense).max())
    # products of causal and anticausal factors in both orders, then of those (mixed) with each other: every
    # cross term of the product rule, with inputs and outputs of different widths
    first = G.transpose().product(H.transpose()).product(H.product(G))  # G^T H^T H G: m -> m
    second = H.product(G).product(G.transpose().product(H.transpose()))  # H G G^T H^T: m -> m
    mixed = first.product(second)
    truth = (G_dense.T @ H_dense.T @ H_dense @ G_dense) @ (H_dense @ G_dense @ G_dense.T @ H_dense.T)
    scale = float(np.abs(truth).max())
    np.testing.assert_allclose(mixed.dense(), truth, atol=1e-11 * scale)
    summed = mixed.plus(TrialOperator.identity(length, m).scaled(-0.5))
    np.testing.assert_allclose(summed.dense(), truth - 0.5 * np.eye(length * m), atol=1e-11 * scale)
    np.testing.assert_allclose(mixed.transpose().dense(), truth.T, atol=1e-11 * scale)


@given(seed=st.integers(0, 2**32 - 1), length=st.integers(2, 60), n=st.integers(1, 3), delay=st.integers(0, 3),
       shifted=st.booleans())
@fuzz_settings(25)
def test_the_plant_operator_is_the_lifted_plant(seed: int, length: int, n: int, delay: int, shifted: bool) -> None:
    """``G`` (blocks ``C A^(j + d) B``) of a delay-augmented model, on the plant block alone when the model is laid
    out as the augmentation lays it out, and on the whole model (``C A^d``) when a perturbation breaks that."""
    rng = np.random.default_rng(seed)
    plant = DiscreteModel(_stable(rng, n, 0.95), rng.standard_normal((n, 1)), rng.standard_normal((1, n)), 0.01)
    model, _ = augment_input_delay(plant, delay)
    A = model.A.copy()
    if not shifted and delay:
        A[-1, 0] += 0.01  # a perturbation in a delay row: the model is no longer the shift
    C = model.measured_output
    truth = np.zeros((length, length))
    for i in range(length):
        for j in range(i + 1):
            truth[i, j] = (C @ np.linalg.matrix_power(A, i - j + delay) @ model.B)[0, 0]
    G = plant_operator(A, model.B, C, length + delay, delay)
    np.testing.assert_allclose(G.dense(), truth, atol=1e-12 * np.abs(truth).max())
    reduced = plant_realization(A, model.B, C, delay).A.shape[0]
    assert reduced == (n if shifted or not delay else n + delay)


@given(seed=st.integers(0, 2**32 - 1), length=st.integers(5, 120), n=st.integers(1, 3), channels=st.integers(1, 2),
       gain=st.floats(0.1, 3.0))
@fuzz_settings(30)
def test_the_norm_bound_brackets_the_singular_value(seed: int, length: int, n: int, channels: int,
                                                    gain: float) -> None:
    """``lower <= ||T||_2 <= upper`` with the dense SVD's ``||T||_2`` for ``T = I - gain G_v G^T`` (gradient ILC's
    map at a plant ``G_v``), and the upper bound within the bisection's tolerance and the rounding margin."""
    rng = np.random.default_rng(seed)
    G, G_dense = _causal(rng, n, channels, channels, length)
    V, V_dense = _causal(rng, n, channels, channels, length)
    step = gain / float(np.linalg.norm(G_dense, 2)) ** 2
    T = TrialOperator.identity(length, channels).plus(V.product(G.transpose()).scaled(-step))
    truth = float(np.linalg.norm(np.eye(length * channels) - step * V_dense @ G_dense.T, 2))
    bound = T.norm_bound(1e-10)
    assert bound.lower <= truth * (1 + 1e-12)
    assert truth <= bound.upper <= truth * (1 + 2e-10 + ROUNDING_MARGIN)
    assert T.lanczos_lower() <= truth * (1 + 1e-12)
    assert T.below(truth * (1 + 1e-8)) and not T.below(truth * (1 - 1e-8))


def test_an_overflowing_operator_has_no_bound() -> None:
    """A plant that grows past the floating-point range over the trial: no test passes, the bound is infinite."""
    G = TrialOperator.causal(np.array([[1e3]]), np.ones((1, 1)), np.ones((1, 1)), np.ones((1, 1)), 200)
    bound = G.norm_bound()
    assert bound.upper == np.inf
    assert not G.below(1e300)


def test_the_norm_test_needs_a_square_operator() -> None:
    G = TrialOperator.causal(np.eye(1), np.ones((1, 2)), np.ones((1, 1)), np.ones((1, 2)), 5)
    with pytest.raises(Exception, match="square"):
        G.below(1.0)

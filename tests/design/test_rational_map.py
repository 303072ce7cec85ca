"""The transfer-function bound of a lifted law's error map (``foilc_hil.design.rational_map``) against independent
references: the gain's Gram matrix against exact rational arithmetic, ``||D^-1||`` and ``||I - G L||`` against
LAPACK's SVD of dense matrices built here from the plant's Markov parameters."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest

from foilc_hil.design.rational_map import GainGram, _inverse_norm, rational_norm_bound


def test_the_gain_gram_is_within_its_bound_of_the_exact_product() -> None:
    rng = np.random.default_rng(3)
    # rows of very different scales and entries far below their row's largest: the slices must stay exact
    L = rng.standard_normal((12, 12)) * np.logspace(-8, 6, 12)[:, None] * rng.choice([1.0, 1e-9], (12, 12))
    gram = GainGram.of(L)
    exact = [[sum(Fraction(L[i, k]) * Fraction(L[j, k]) for k in range(12)) for j in range(12)] for i in range(12)]
    deviation = math.sqrt(sum(float(Fraction(gram.P[i, j]) - exact[i][j]) ** 2 for i in range(12) for j in range(12)))
    assert deviation <= gram.error
    assert gram.error < 1e-14 * float(np.linalg.norm(L @ L.T))  # about the rounding of the result only
    assert np.array_equal(gram.P, gram.P.T)
    assert GainGram.shared(L) is GainGram.shared(L)


def test_the_inverse_norm_bounds_the_dense_inverse_and_refuses_an_unstable_denominator() -> None:
    for denominator in ([-0.95], [-1.5, 0.56], [0.3, -0.2, 0.05]):
        d = np.array(denominator)
        D = np.eye(300)
        for i, coefficient in enumerate(d, start=1):
            D += coefficient * np.eye(300, k=-i)
        exact = float(np.linalg.norm(np.linalg.inv(D), 2))
        assert exact <= _inverse_norm(d, 300) <= exact * 1.5
    assert _inverse_norm(np.array([-1.2]), 2000) == math.inf


def _markov(A: np.ndarray, B: np.ndarray, C: np.ndarray, lead: int, length: int) -> np.ndarray:
    """The lower-triangular Toeplitz matrix of ``C A^(j + lead) B``, by plain powers."""
    taps = [float((C @ np.linalg.matrix_power(A, j + lead) @ B)[0, 0]) for j in range(length)]
    return np.array([[taps[i - j] if i >= j else 0.0 for j in range(length)] for i in range(length)])


@pytest.mark.parametrize("lead", [0, 1])
def test_the_bound_is_above_the_exact_norm_and_close_to_it(lead: int) -> None:
    """A NOILC gain of a nominal plant, certified on perturbed plants of one and three states."""
    rng = np.random.default_rng(11)
    length = 240
    plants = [
        (np.array([[0.95, 0.03], [0.0, 0.0]]), np.array([[0.0], [1.0]]), np.array([[1.0, 0.0]])),
        (np.array([[0.9, 0.1, 0.0], [-0.1, 0.8, 0.05], [0.0, 0.0, 0.5]]), np.array([[0.0], [0.1], [1.0]]),
         np.array([[1.0, 0.0, 0.2]])),
    ]
    for A, B, C in plants:
        G = _markov(A, B, C, lead, length)
        L = np.linalg.solve(G.T @ G + 1e-3 * np.eye(length), G.T)
        gram = GainGram.of(L)
        for _ in range(3):
            A_v = A * (1.0 + 0.03 * rng.uniform(-1, 1))
            B_v = B * (1.0 + 0.05 * rng.uniform(-1, 1))
            exact = float(np.linalg.norm(np.eye(length) - _markov(A_v, B_v, C, lead, length) @ L, 2))
            bound = rational_norm_bound(A_v, B_v, C, lead, gram)
            assert bound is not None
            assert exact <= bound <= exact + 1e-8


def test_no_bound_for_several_outputs_and_a_rigorous_one_for_an_unstable_plant() -> None:
    gram = GainGram.of(np.eye(50))
    assert rational_norm_bound(np.eye(2) * 0.5, np.ones((2, 1)), np.eye(2), 0, gram) is None
    A = np.array([[1.3]])
    bound = rational_norm_bound(A, np.ones((1, 1)), np.ones((1, 1)), 0, gram)
    exact = float(np.linalg.norm(np.eye(50) - _markov(A, np.ones((1, 1)), np.ones((1, 1)), 0, 50), 2))
    assert bound is not None and exact <= bound

"""A lifted law's error map on a drawn plant, bounded through the plant's transfer function: no ``O(L^3)`` Gram.

The robustness Monte Carlo certifies NOILC's dense map ``T = I - G L`` (``G``: the drawn plant's lower-triangular
Toeplitz Markov matrix, ``L``: the law's lifted gain) on every draw. :func:`~foilc_hil.design.certificates.
matrix_norm_bound` forms ``T`` and its Gram matrix (a symmetric rank-``L`` update, ``L^3`` flops) before its Cholesky
test; here the Gram matrix is formed in ``O(k L^2)`` from what every draw shares, and only the Cholesky test is cubic.

The identity
------------
A single-input single-output plant of ``k`` states has Markov parameters ``h_j = C A^(j + d) B`` that satisfy its
characteristic polynomial's recurrence: with ``det(z I - A) = z^k + d_1 z^(k-1) + ... + d_k``, ``sum_i d_i h_(j-i) = 0``
for ``j >= k`` (Cayley-Hamilton). As lower-triangular Toeplitz matrices, ``D G = N`` with ``D = Toeplitz(1, d_1, ..,
d_k)`` and ``N = Toeplitz(nu_0, .., nu_(k-1))`` both banded, so ``G = D^-1 N`` and, with ``Q = G L`` and the gain's
own ``P = L L^T`` (the same for every draw: formed once),

    T T^T = I - Q - Q^T + D^-1 N P N^T D^-T,

every term a banded product or a banded triangular solve (:func:`_filter_rows`). ``T T^T`` has the eigenvalues of
``T^T T``, so its Cholesky test bounds ``||T||_2`` (:func:`~foilc_hil.design.map_norms.gram_norm_bound`).

Rigour
------
Every rounding is bounded and added to the Gram matrix's error (2-norm, by Frobenius norms), as
:func:`~foilc_hil.design.map_norms.matrix_norm_bound` does for its own:

* ``P``: the gain split row by row into slices of ``beta`` bits (Ozaki et al., Numer. Algorithms 59, 2012), whose
  products BLAS computes EXACTLY (every partial sum is an integer multiple of the slices' unit below ``2^53``), the
  products of small slices left out and bounded, the kept ones summed with ``gamma_5`` (:class:`GainGram`);
* the banded solves: each output is one recursive sum of at most ``2 k`` products, so the computed ``Y`` solves
  ``(D + dD) Y = (N + dN) X`` with ``|dD| <= gamma_2k |D|``, ``|dN| <= gamma_2k |N|`` (Higham, Accuracy and Stability,
  sec. 3.1 and 8.1), and ``||Y - D^-1 N X||_F <= ||D^-1||_2 gamma_2k (|nu|_1 ||X||_F + |d|_1 ||Y||_F)``;
* ``||D^-1 N||_2 <= sum |h_j| + ||D^-1||_2 ||E||_2`` (``E`` below) where a product by ``D^-1 N`` carries an error on;
* ``||D^-1||_2 <= sum |g_j| / (1 - sum |r_j|)`` from a computed impulse response ``g`` of ``1 / d`` and the
  rigorously bounded residual ``r`` of ``D g = e_0`` (``D^-1 = Toeplitz(g) (I + Toeplitz(r))^-1``);
* the assembly of ``T T^T`` (three additions per entry, ``gamma_3``), its upper triangle mirrored (``sqrt 2``);
* the model: ``G`` is the Markov matrix of the blocks the certificates take as given (:func:`~foilc_hil.design.
  lifted.markov_blocks`), which satisfy the recurrence only to rounding: ``D G = N + E`` with ``E`` the
  Toeplitz matrix of the recurrence's residual (bounded entry by entry), so ``||T - T'||_2 <= ||D^-1||_2 ||E||_2
  ||L||_F`` for the map ``T' = I - D^-1 N L`` the Cholesky test certifies; that is added to the bound.

The result is a rigorous upper bound on the norm of the same map :func:`~foilc_hil.design.robustness.
_lifted_certificate` certified by FFT, within about 1e-9 of it on paper_sim's NOILC draws; where the bound is not
below one, or a plant is not single-input single-output, ``None``: the caller takes the dense path.

Module order: after :mod:`foilc_hil.design.certificates` (whose Cholesky test it feeds), before
:mod:`foilc_hil.design.robustness` (its caller).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from foilc_hil.design.lifted import markov_blocks
from foilc_hil.design.map_norms import UNIT_ROUNDOFF, gram_norm_bound, rounding_gamma

__all__ = ["RATIONAL_METHOD", "GainGram", "rational_norm_bound"]

#: Slices of the gain kept in its exact Gram products (pairs ``(a, b)`` with ``a + b <= 4``: ``1-1, 1-2, 1-3, 2-2``).
GAIN_SLICES = 3
#: ``norm_2_method`` of a certificate from :func:`rational_norm_bound`.
RATIONAL_METHOD = "upper bound (Cholesky of rho^2 I - T T^T, T T^T from the plant's transfer function)"
#: Gain Gram matrices kept per process (:meth:`GainGram.shared`): a robustness worker certifies one or two gains.
SHARED_GRAMS = 2
#: Relative slack on every norm computed in floating point for an error bound (their own rounding, far below it).
NORM_SLACK = 1e-10


@njit(cache=True)
def _filter_rows(numerator: np.ndarray, denominator: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``Y = D^-1 N X`` along axis 0 (``D = Toeplitz(1, denominator)``, ``N = Toeplitz(numerator)``, both lower
    triangular and banded): ``Y[t] = sum_i numerator[i] X[t - i] - sum_i denominator[i] Y[t - 1 - i]``, every entry
    ONE recursive sum in that order (the rounding bound of the module notes), vectorised across the columns."""
    n, columns = X.shape
    Y = np.zeros((n, columns))
    for t in range(n):
        row = Y[t]
        for i in range(min(numerator.shape[0], t + 1)):
            weight = numerator[i]
            source = X[t - i]
            for c in range(columns):
                row[c] += weight * source[c]
        for i in range(min(denominator.shape[0], t)):
            weight = denominator[i]
            source = Y[t - 1 - i]
            for c in range(columns):
                row[c] -= weight * source[c]
    return Y


@njit(cache=True)
def _assemble(Q: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """The symmetric ``I - Q - Q^T + Z`` from ``Z``'s upper triangle: ``((delta_ij - Q_ij) - Q_ji) + Z_ij`` for
    ``i <= j``, mirrored."""
    n = Q.shape[0]
    M = np.empty((n, n))
    for i in range(n):
        for j in range(i, n):
            value = ((1.0 if i == j else 0.0) - Q[i, j]) - Q[j, i]
            M[i, j] = value + Z[i, j]
    for i in range(n):
        for j in range(i):
            M[i, j] = M[j, i]
    return M


# At import, compiled or loaded from numba's cache (C-contiguous float64, as the callers pass): not inside a draw.
# Both kinds of X: a gain's Gram matrix that came through dask's serialisation is a read-only array (its own
# machine code), and left to the first draw that overload was compiled in every worker process of a fresh install.
_filter_rows(np.ones(1), np.ones(1), np.ones((2, 2)))
_filter_rows(np.ones(1), np.ones(1), np.lib.stride_tricks.as_strided(np.ones((2, 2)), writeable=False))
_assemble(np.ones((2, 2)), np.ones((2, 2)))


def _frobenius(X: np.ndarray) -> float:
    return float(np.linalg.norm(X)) * (1.0 + NORM_SLACK)


def _slices(X: np.ndarray, bits: int) -> tuple[list[np.ndarray], np.ndarray]:
    """``X = sum(slices) + rest`` EXACTLY, each slice's row ``i`` an integer multiple of ``2^(e_i - bits)`` of
    magnitude at most ``2^e_i + 2^(e_i - bits)`` (Rump, Ogita, Oishi, SIAM J. Sci. Comput. 31, 2008, Lemma 3.3:
    ``q = fl((sigma + x) - sigma)`` with ``sigma = 2^(e + 53 - bits)``, ``|x| <= 2^e``, is exact, and so is
    ``x - q``)."""
    rest = np.array(X, dtype=float, copy=True)
    slices = []
    for _ in range(GAIN_SLICES):
        peak = np.max(np.abs(rest), axis=1, keepdims=True)
        exponent = np.ceil(np.log2(np.where(peak > 0, peak, 1.0)))
        sigma = np.exp2(exponent + (53 - bits))
        part = (sigma + rest) - sigma
        part[(peak == 0)[:, 0]] = 0.0
        slices.append(part)
        rest = rest - part
    return slices, rest


@dataclass(frozen=True)
class GainGram:
    """``P = L L^T`` of a lifted gain, to within ``error`` (2-norm, rigorous), with ``||L||_F``; one per gain."""

    gain: np.ndarray
    P: np.ndarray
    error: float
    frobenius: float
    p_frobenius: float

    @classmethod
    def shared(cls, gain: np.ndarray) -> GainGram:
        """:meth:`of` ``gain``, kept per process for the same array (``lifted_gain`` shares one per design): every
        chunk of a robustness run on a worker reuses it."""
        for kept in _SHARED:
            if kept.gain is gain:
                return kept
        made = cls.of(gain)
        _SHARED.insert(0, made)
        del _SHARED[SHARED_GRAMS:]
        return made

    @classmethod
    def of(cls, gain: np.ndarray) -> GainGram:
        """The exact slice products of the module notes (four BLAS products, about a second at 2000 samples)."""
        L = np.asarray(gain, dtype=float)
        peaks = np.max(np.abs(L), axis=1)
        if not (np.all(np.isfinite(L)) and np.all((peaks == 0) | ((peaks > 2.0**-300) & (peaks < 2.0**300)))):
            # the slices' units would underflow (or sigma overflow): no exact products, no bound
            return cls(L, L @ L.T, math.inf, _frobenius(L), math.inf)
        bits = (53 - math.ceil(math.log2(max(2, L.shape[1]))) - 1) // 2  # n (2^bits + 1)^2 < 2^53: exact sums
        (L1, L2, L3), rest = _slices(L, bits)
        P11, P22 = L1 @ L1.T, L2 @ L2.T  # exact (syrk, symmetric)
        P12, P13 = L1 @ L2.T, L1 @ L3.T  # exact
        P = ((P11 + P22) + (P12 + P12.T)) + (P13 + P13.T)  # each sum symmetric: P is exactly symmetric
        summed = rounding_gamma(5) * (_frobenius(P11) + _frobenius(P22) + 2.0 * _frobenius(P12) + 2.0 * _frobenius(P13))
        norms = [_frobenius(part) for part in (L, L2, L3, rest)]
        # left out: L2 L3^T + L3 L2^T + L3 L3^T + (L - rest) rest^T + rest L^T
        dropped = 2.0 * norms[1] * norms[2] + norms[2] ** 2 + 2.0 * (norms[0] + norms[3]) * norms[3]
        return cls(L, P, (summed + dropped) * (1.0 + NORM_SLACK), norms[0], _frobenius(P))


_SHARED: list[GainGram] = []


def _inverse_norm(denominator: np.ndarray, length: int) -> float:
    """A rigorous upper bound on ``||D^-1||_2``, ``D = Toeplitz(1, denominator)`` of ``length`` rows (``inf`` when
    the residual test fails: an unstable plant's response growing past the floating-point range)."""
    impulse = np.zeros((length, 1))
    impulse[0, 0] = 1.0
    g = _filter_rows(np.ones(1), denominator, impulse)[:, 0]
    d = np.concatenate([[1.0], denominator])
    residual = np.convolve(d, g)[:length]
    residual[0] -= 1.0
    k = d.shape[0]
    bound = np.abs(residual) + 2.0 * rounding_gamma(k + 1) * np.convolve(np.abs(d), np.abs(g))[:length]
    r = float(np.sum(bound)) * (1.0 + rounding_gamma(length))
    if not (math.isfinite(r) and r < 0.5):
        return math.inf
    return float(np.sum(np.abs(g))) * (1.0 + rounding_gamma(length)) / (1.0 - r) * (1.0 + NORM_SLACK)


def rational_norm_bound(A: np.ndarray, B: np.ndarray, C: np.ndarray, lead: int, gram: GainGram) -> float | None:
    """A RIGOROUS upper bound on ``||I - G L||_2`` for ``G`` the lower-triangular Toeplitz matrix of
    :func:`~foilc_hil.design.lifted.markov_blocks` ``(A, B, C, lead)`` and ``L = gram.gain`` (module notes);
    ``None`` when the plant is not single-input single-output, ``D^-1`` is not bounded, or no Cholesky test passes."""
    L = gram.gain
    length = L.shape[0]
    if not math.isfinite(gram.error) or B.shape[1] != 1 or C.shape[0] != 1 or L.shape != (length, length):
        return None
    h = markov_blocks(A, B, C, lead, length)[:, 0, 0]
    if not np.all(np.isfinite(h)):
        return None
    d = np.poly(A)  # monic, degree k
    k = A.shape[0]
    convolved = np.convolve(d, h)[:length]
    nu = convolved[:k].copy()
    # E = D G - N: the recurrence's residual, every entry bounded (the first k are fl of the same sum: 0 + rounding)
    residual = np.abs(np.concatenate([np.zeros(k), convolved[k:]]))
    residual += 2.0 * rounding_gamma(k + 1) * np.convolve(np.abs(d), np.abs(h))[:length]
    model = float(np.sum(residual)) * (1.0 + rounding_gamma(length))
    inverse = _inverse_norm(d[1:], length)
    if not math.isfinite(inverse):
        return None
    denominator = np.ascontiguousarray(d[1:])
    nu1, d1 = float(np.sum(np.abs(nu))), float(np.sum(np.abs(d[1:])))
    solve = rounding_gamma(2 * k + 1)
    Q = _filter_rows(nu, denominator, np.ascontiguousarray(L))
    Y = _filter_rows(nu, denominator, gram.P)
    Z = _filter_rows(nu, denominator, np.ascontiguousarray(Y.T))  # D^-1 N P N^T D^-T (P symmetric)
    q, y, z = _frobenius(Q), _frobenius(Y), _frobenius(Z)
    error_q = inverse * solve * (nu1 * gram.frobenius + d1 * q)
    error_y = inverse * solve * (nu1 * gram.p_frobenius + d1 * y)
    # ||D^-1 N||_2 <= ||G||_2 + ||D^-1 E||_2 <= sum |h_j| + ||D^-1|| ||E||: far below ||D^-1|| |nu|_1
    plant = float(np.sum(np.abs(h))) * (1.0 + rounding_gamma(length)) + inverse * model
    error_z = inverse * solve * (nu1 * y + d1 * z) + plant * error_y + plant**2 * gram.error
    assembly = rounding_gamma(3) * (math.sqrt(length) + 2.0 * q + z)
    gram_error = math.sqrt(2.0) * (2.0 * error_q + error_z + assembly) * (1.0 + NORM_SLACK)
    M = _assemble(Q, Z)
    # the estimate: the symbol sup of T's middle column, as matrix_norm_bound's (T = I - Q)
    column = -Q[:, length // 2]  # T's middle column, for the estimate of the Cholesky tests
    column[length // 2] += 1.0
    bound = gram_norm_bound(M, gram_error, column)
    if bound is None:
        return None
    mismatch = inverse * model * gram.frobenius * (1.0 + NORM_SLACK)
    return math.nextafter(bound + mismatch * (1.0 + 2.0 * UNIT_ROUNDOFF), math.inf)

"""Finite Toeplitz sections on signals, and the rigorous bound of a two-sided symbol: the pieces the structured
certificate of :mod:`foilc_hil.design.qmap` is built from.

Signals are ``(columns, channels, samples)`` arrays, time on the last (contiguous) axis. :class:`CausalToeplitz`
and :class:`ToeplitzSection` multiply them by a causal or a two-sided block Toeplitz finite section by FFT (and by
its transpose); :func:`inner`, :func:`project_out` and :func:`orthonormalize` are the inner products and
orthonormal bases of such signals; :class:`SectionSymbol` bounds ``sup |a0 - s a1|`` over the unit circle, for
every scale ``s`` at once, rigorously (:func:`~foilc_hil.design.lifted.grid_bound`): the 2-norm of
``T_N(a0 - s a1)`` is at most that, for every trial length.

Module order: after :mod:`foilc_hil.design.lifted`, before :mod:`foilc_hil.design.norm_test` and
:mod:`foilc_hil.design.qmap`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from foilc_hil.design.lifted import SYMBOL_GRID_CAP, SYMBOL_GRID_CAP_MIMO, grid_bound, symbol_grid

__all__ = [
    "CausalToeplitz",
    "SectionSymbol",
    "ToeplitzSection",
    "flat",
    "inner",
    "orthonormalize",
    "project_out",
    "wrapped",
]


def _fft_length(n: int) -> int:
    """The FFT length of a linear convolution of two ``n``-sample signals (``next_fast_len(2n - 1)``)."""
    from scipy.fft import next_fast_len

    return int(next_fast_len(2 * n - 1, real=True))


def _mix(spectrum: np.ndarray, signals: np.ndarray) -> np.ndarray:
    """Per-frequency block products: ``spectrum`` ``(r, c, F)`` times ``signals`` ``(K, c, F)`` -> ``(K, r, F)``."""
    if spectrum.shape[0] == spectrum.shape[1] == 1:
        return signals * spectrum[0]
    return np.einsum("rcf,kcf->krf", spectrum, signals)


@dataclass(frozen=True)
class CausalToeplitz:
    """A causal block Toeplitz finite section ``y[t] = sum_(j <= t) blocks[t - j] x[j]`` by FFT."""

    spectrum: np.ndarray  # (rows, cols, F) of the blocks (L, rows, cols)
    n_samples: int
    nfft: int

    @classmethod
    def of(cls, blocks: np.ndarray) -> CausalToeplitz:
        """The section of ``blocks`` (``(L, rows, cols)``), transformed once."""
        from scipy.fft import rfft

        n = blocks.shape[0]
        nfft = _fft_length(n)
        return cls(rfft(np.ascontiguousarray(blocks.transpose(1, 2, 0)), n=nfft, axis=-1), n, nfft)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """``T x`` for ``(K, cols, N)`` signals."""
        from scipy.fft import irfft, rfft

        mixed = _mix(self.spectrum, rfft(x, n=self.nfft, axis=-1))
        return np.asarray(irfft(mixed, n=self.nfft, axis=-1)[..., : self.n_samples])

    def adjoint(self, y: np.ndarray) -> np.ndarray:
        """``T^T y``: the transposed blocks on the time-reversed signal, reversed back."""
        from scipy.fft import irfft, rfft

        mixed = _mix(self.spectrum.transpose(1, 0, 2), rfft(y[..., ::-1], n=self.nfft, axis=-1))
        return np.asarray(irfft(mixed, n=self.nfft, axis=-1)[..., : self.n_samples][..., ::-1])


@dataclass(frozen=True)
class ToeplitzSection:
    """``T_N(a)``: ``T[i, j] = a_(i - j)`` for two-sided block coefficients ``a_k``, ``|k| < N``, stored as
    ``(2N - 1, m, m)`` with ``a_k`` at index ``k + N - 1``; products by FFT on ``(K, m, N)`` signals."""

    coefficients: np.ndarray
    spectrum: np.ndarray  # (m, m, F)
    nfft: int

    @classmethod
    def of(cls, coefficients: np.ndarray) -> ToeplitzSection:
        """The section of ``coefficients``, transformed once."""
        from scipy.fft import next_fast_len, rfft

        nfft = int(next_fast_len(coefficients.shape[0], real=True))
        spectrum = rfft(np.ascontiguousarray(coefficients.transpose(1, 2, 0)), n=nfft, axis=-1)
        return cls(coefficients, spectrum, nfft)

    @property
    def n_samples(self) -> int:
        """``N``."""
        return (self.coefficients.shape[0] + 1) // 2

    def apply(self, x: np.ndarray) -> np.ndarray:
        """``T x``: a circular convolution of length ``>= 2N - 1`` leaves outputs ``N-1 .. 2N-2`` un-aliased."""
        from scipy.fft import irfft, rfft

        n = self.n_samples
        mixed = _mix(self.spectrum, rfft(x, n=self.nfft, axis=-1))
        return np.asarray(irfft(mixed, n=self.nfft, axis=-1)[..., n - 1 : 2 * n - 1])

    def adjoint(self, y: np.ndarray) -> np.ndarray:
        """``T^T y = J T_N(a^T) J y`` (``J`` reverses time)."""
        from scipy.fft import irfft, rfft

        n = self.n_samples
        mixed = _mix(self.spectrum.transpose(1, 0, 2), rfft(y[..., ::-1], n=self.nfft, axis=-1))
        return np.asarray(irfft(mixed, n=self.nfft, axis=-1)[..., n - 1 : 2 * n - 1][..., ::-1])

    def l1(self) -> float:
        """``sum_k ||a_k||_F``: bounds ``||T||`` and the FFT products' rounding."""
        return float(np.sum(np.linalg.norm(self.coefficients.reshape(self.coefficients.shape[0], -1), axis=1)))


def flat(x: np.ndarray) -> np.ndarray:
    """``(K, m, N)`` signals as the columns of an ``(m N) x K`` matrix."""
    return x.reshape(x.shape[0], x.shape[1] * x.shape[2]).T


def inner(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``X^T Y`` for ``(K, m, N)`` and ``(L, m, N)`` signals (``K x L``), by ``einsum``."""
    return np.asarray(np.einsum("kat,lat->kl", x, y))


def project_out(basis: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``(I - P_basis) x`` for an orthonormal ``basis`` (both ``(K, m, N)``)."""
    if basis.shape[0] == 0:
        return x
    return x - np.einsum("kl,kat->lat", inner(basis, x), basis)


def orthonormalize(W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Q``, ``R`` with ``Q`` orthonormal (``(kq, m, N)``) and ``W = R^T``-combinations of it: ``W_j = sum_i R[i, j]
    Q_i`` to rounding, by two passes of the Gram matrix's eigen-decomposition (directions below ``1e-26`` of the
    largest eigenvalue dropped: a change of ``W`` of at most ``1e-13`` of its norm, inside
    :data:`~foilc_hil.design.qmap.ROUNDING_MARGIN`). ``einsum`` instead of a threaded QR
    (:func:`~foilc_hil.design.lifted.vector_norm`)."""
    Q, R = W, np.eye(W.shape[0])
    for _ in range(2):
        values, vectors = np.linalg.eigh(inner(Q, Q))
        kept = values > 1e-26 * max(float(values[-1]), 0.0) if values.size else values > 0
        if not np.any(kept):
            return W[:0], np.zeros((0, W.shape[0]))
        values, vectors = values[kept], vectors[:, kept]
        Q = np.einsum("kj,kat->jat", vectors / np.sqrt(values), Q)
        R = (np.sqrt(values)[:, None] * vectors.T) @ R
    return Q, R


def _centered_moments(coefficients: np.ndarray) -> tuple[float, float, float]:
    """``S_j = sum_k |k|^j ||a_k||_2`` over ``|k| < N`` (two-sided, at ``k + N - 1``): the widening of the symbol's
    grid sup (:func:`~foilc_hil.design.lifted.grid_bound` holds for any integer indices)."""
    length = coefficients.shape[0]
    lag = np.abs(np.arange(length) - (length - 1) // 2).astype(float)
    if coefficients.shape[1] == coefficients.shape[2] == 1:
        magnitudes = np.abs(coefficients[:, 0, 0])
    else:
        magnitudes = np.linalg.norm(coefficients, ord=2, axis=(1, 2))
    return float(np.sum(magnitudes)), float(np.sum(lag * magnitudes)), float(np.sum(lag * lag * magnitudes))


def wrapped(coefficients: np.ndarray, points: int) -> np.ndarray:
    """Two-sided coefficients folded onto ``points >= N`` (``a_k`` at ``k mod points``): their DFT is the symbol
    at the ``points``-th roots of unity (``points = N``: the lags ``k`` and ``k - N`` share a point)."""
    length = coefficients.shape[0]
    n = (length + 1) // 2
    out = np.zeros((points, *coefficients.shape[1:]))
    out[:n] = coefficients[n - 1 :]
    out[points - (n - 1) :] += coefficients[: n - 1]
    return out


@dataclass(frozen=True)
class SectionSymbol:
    """The symbol ``a0 - s a1`` on a grid, for every scale ``s`` in ``[0, 1]`` at once (single channel: the three
    real arrays of ``|a0 - s a1|^2 = |a0|^2 - 2 s Re(a0 a1*) + s^2 |a1|^2``; several: the complex blocks)."""

    grid: int
    moments0: tuple[float, float, float]
    moments1: tuple[float, float, float]
    parts: tuple[np.ndarray, ...]

    @classmethod
    def of(cls, a0: np.ndarray, a1: np.ndarray) -> SectionSymbol:
        """The symbol of ``a0 - s a1`` on a grid fine enough for :func:`~foilc_hil.design.lifted.grid_bound`."""
        from scipy.fft import fft, rfft

        m0, m1 = _centered_moments(a0), _centered_moments(a1)
        joint = (m0[0] + m1[0], m0[1] + m1[1], m0[2] + m1[2])
        length = a0.shape[0]
        if a0.shape[1] == 1:
            grid = symbol_grid(length, joint, SYMBOL_GRID_CAP)
            # real coefficients: |a| is even in theta, half the grid (rfft) covers it
            s0, s1 = rfft(wrapped(a0, grid)[:, 0, 0]), rfft(wrapped(a1, grid)[:, 0, 0])
            parts: tuple[np.ndarray, ...] = (np.abs(s0) ** 2, np.real(s0 * np.conj(s1)), np.abs(s1) ** 2)
        else:
            grid = max(SYMBOL_GRID_CAP_MIMO, 1 << math.ceil(math.log2(length)))
            parts = (fft(wrapped(a0, grid), axis=0), fft(wrapped(a1, grid), axis=0))
        return cls(grid, m0, m1, parts)

    def bound(self, scale: float) -> tuple[float, float]:
        """A rigorous bound on ``sup |a0 - s a1|`` (the 2-norm of ``T_N(a0 - s a1)`` is at most that), and the
        grid frequency of the peak."""
        mom = tuple(a + scale * b for a, b in zip(self.moments0, self.moments1, strict=True))
        moments3 = (mom[0], mom[1], mom[2])
        if len(self.parts) == 3:
            values = self.parts[0] - 2.0 * scale * self.parts[1] + scale * scale * self.parts[2]
            peak_index = int(np.argmax(values))
            peak = math.sqrt(max(0.0, float(values[peak_index])))
            return grid_bound(peak, self.grid, moments3), 2.0 * math.pi * peak_index / self.grid
        singular = np.linalg.svd(self.parts[0] - scale * self.parts[1], compute_uv=False)[:, 0]
        peak_index = int(np.argmax(singular))
        widened = float(singular[peak_index]) + moments3[1] * math.pi / self.grid
        return min(widened, moments3[0]), 2.0 * math.pi * peak_index / self.grid

"""Convergence certificates of the learning law AS IT RUNS: the lifted trial-to-trial map (errata item 4).

Theorem 1 certifies the Roesser model (18), in which the learning gain multiplies ``E`` as if ``E`` were the
error. The law that runs multiplies the Grünwald–Letnikov-discretised ``E = (I + kp D^r) e``, whose newest
sample carries the weight ``1 + kp h^-r`` (hundreds to thousands at millisecond steps), so a gain certified on
(18) can diverge once the filter is switched on. This module certifies the law with the filter (and the
input delay, and an optional Q-filter) on whole trials.

The lifted map
--------------
Sample alignment is that of :mod:`foilc_hil.references`: a trial issues ``u[i] = u(i Ts)``, ``i = 0..N-1``;
``x[i] = x(i Ts)``; ``e[i] = e((i+1) Ts)`` is the first error sample ``u[i]`` moves (relative degree one). With
``d`` cycles of input delay (state ``z = [x; u(t-d); ...; u(t-1)]``, measured output ``C_measured z``), ``u[i]``
first moves ``e[i + d]`` and the law is

    u_k[i] = u_{k-1}[i] + p1 (z_k[i] - z_{k-1}[i]) + p2 E_{k-1}[i + d]      (E[j] = 0 for j >= N),
    E = F e  acting on each output channel, with F the law's operator (``law.fractional_memory``):
      "controllable" (default): F = diag(I_d, F_c), F_c = FractionalPD(kp, r, h, history="zero").matrix(N - d),
                                a pure lower-triangular Toeplitz operator on e[d:] (zero history before it);
      "trial" (paper-literal):  F = FractionalPD(kp, r, h).matrix(N), Caputo over the whole trial.

The first ``d`` error samples cannot be moved by any input (they repeat every trial), so the trial-to-trial map
acts on ``e~ = e[d:]`` (``L = N - d`` samples). Writing ``A_cl = A + B p1``, the learning update
``du = u_k - u_{k-1}`` obeys ``dz[i+1] = A_cl dz[i] + B p2 E'[i]`` and ``de[j] = -C_measured dz[j + 1]``, so

    e~_k - e~* = T (e~_{k-1} - e~*),   T = I - H F',
    H = block lower-triangular Toeplitz with blocks h_j = C_measured A_cl^(j + d) B p2  (j = 0..L-1),
    F' = F[d:, d:]  (only columns >= d matter: the first d error samples never change) -- F_c itself in
                    "controllable" mode, where this is also the whole affine part: E[d:] depends on e[d:] only,
                    so the law's fixed point e~* = 0 (in "trial" mode F[d:, :d] e[:d] is a constant offset
                    that moves the fixed point to a nonzero Mittag-Leffler-like tail; the map T of differences
                    is still exact).

``T`` is the map of the law as it runs: an exact identity on trial-to-trial error differences (the tests check
it against a brute-force trial-by-trial simulation), not a bound.

With a Q-filter (zero-phase, an ``N x N`` matrix ``Q``; as :mod:`foilc_hil.laws.learning` runs it, the feedforward
stored for the next trial is ``Q u_{k-1}``, so ``u_k = Q u_{k-1} + P2 S E_{k-1} + P1 (z_k - z_{k-1})``) the error
recursion does not close; the map acts on the input instead:

    u_k - u* = M (u_{k-1} - u*),  M = R (Q - P2 S F Gy - P1 Gz),  R = (I - P1 Gz)^-1,

with ``Gz``, ``Gy`` the lifted input-to-state and input-to-output maps and ``S`` the ``d``-sample advance.

What is exact and what is estimated
-----------------------------------
* Spectral radius of ``T`` (asymptotic convergence): EXACT. In "controllable" mode ``F'`` is lower-triangular
  Toeplitz, so ``T`` is block lower-triangular Toeplitz and its eigenvalues are those of ``I - h_0 w_0``. In
  "trial" mode ``F`` is lower-triangular Toeplitz except its first few columns (the Caputo correction for
  ``e(0)`` and, for ``r > 1``, ``e'(0)``), which makes ``T`` block lower triangular with one small leading block;
  the eigenvalues are those of that block and of the diagonal block
  ``I - h_0 w_0`` (``w_0 = 1 + kp h^-r``). The Toeplitz-plus-columns decomposition of ``F`` is verified on a
  random probe against ``FractionalPD.apply``; if it does not hold, ``T`` is built densely instead.
* Induced 2-norm of ``T`` (monotonic convergence in l2): computed by ARPACK (``scipy.sparse.linalg.svds``) with
  FFT matrix-vector products, to a relative tolerance of 1e-8 -- an iterative estimate of the exact finite-trial
  norm, not a bound. For trials short enough (``L p <= DENSE_LIMIT``) it is a dense SVD instead; if ARPACK does
  not converge, a dense SVD up to ``DENSE_FALLBACK_LIMIT`` rows, else no certificate. When the spectral radius
  is already ``>= 1`` the norm is not needed for the verdict: ``norm_2`` is then a lower bound (the larger of
  the radius and a short power iteration).
* ``norm_2_symbol``: the sup over a frequency grid of the Toeplitz symbol of ``T`` (the long-trial limit of the
  2-norm of the Toeplitz part), for information.
* With a Q-filter: spectral radius by ARPACK ``eigs`` (an estimate; dense ``eigvals`` for small trials), 2-norm
  by ``svds``.
* Uncertainty vertices are FROZEN (constant ``Delta``) plants; a time-varying ``Delta(t)`` makes the map
  non-Toeplitz and is covered only by the LMI of Theorem 1 and by simulation.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from foilc_hil.design.models import DiscreteModel, Uncertainty
from foilc_hil.errors import ConfigError, ConvergenceCertificateError, InputError

__all__ = [
    "DENSE_LIMIT",
    "Certification",
    "LiftedErrorMap",
    "certify",
    "dense_error_map",
    "dense_input_map",
    "law_filter_matrix",
    "lifted_error_map",
    "lifted_input_map",
    "map_certificate",
]

#: Up to this many rows, norms and spectra are computed densely (exact, LAPACK).
DENSE_LIMIT = 600
#: ARPACK restarts allowed for one norm; beyond that the dense fallback (or no certificate).
ARPACK_RESTARTS = 60
#: Largest map a non-converged ARPACK norm falls back to a dense SVD for.
DENSE_FALLBACK_LIMIT = 2500
#: Power iterations for the lower bound used when the spectral radius already rules a certificate out.
POWER_ITERATIONS = 40
#: Columns of the fractional operator allowed to deviate from Toeplitz form (Caputo corrections).
CORRECTION_COLUMNS = 4
#: Admissible certificate: the worst-case 2-norm must be at most this (strictly below one).
CONTRACTION_LIMIT = 1.0 - 1e-9


# --- lifted block-Toeplitz operators via FFT ------------------------------------------------------------------


class _BlockToeplitz:
    """Block lower-triangular Toeplitz operator ``y[i] = sum_{j<=i} blocks[i-j] x[j]`` on ``(L, cols)`` arrays."""

    def __init__(self, blocks: np.ndarray) -> None:
        from scipy.fft import next_fast_len, rfft

        self.blocks = blocks  # (L, rows, cols)
        self.length = blocks.shape[0]
        self.nfft = next_fast_len(2 * self.length, real=True)
        self._spectrum = rfft(blocks, n=self.nfft, axis=0)  # (F, rows, cols)

    def matvec(self, x: np.ndarray) -> np.ndarray:
        from scipy.fft import irfft, rfft

        spectrum = rfft(x, n=self.nfft, axis=0)  # (F, cols)
        out = np.einsum("frc,fc->fr", self._spectrum, spectrum)
        return np.asarray(irfft(out, n=self.nfft, axis=0)[: self.length])

    def rmatvec(self, y: np.ndarray) -> np.ndarray:
        from scipy.fft import irfft, rfft

        spectrum = rfft(y[::-1], n=self.nfft, axis=0)
        out = np.einsum("frc,fr->fc", self._spectrum, spectrum)
        return np.asarray(irfft(out, n=self.nfft, axis=0)[: self.length][::-1])


@dataclass(frozen=True)
class _ScalarFilter:
    """A scalar lifted filter ``F`` (acting on every channel) as Toeplitz weights plus a few dense columns.

    ``F = Toeplitz(weights) + sum_j corrections[:, j] e_j^T`` for ``j < corrections.shape[1]``. With
    ``window = w > 0`` that operator acts on samples ``w:`` only and the first ``w`` samples pass unchanged
    (``F = diag(I_w, F_window)``: the law's "controllable" fractional memory).
    """

    weights: np.ndarray  # (N - window,)
    corrections: np.ndarray  # (N - window, K)
    window: int = 0

    def sub(self, lead: int) -> _ScalarFilter:
        """``F[lead:, lead:]`` in the same form."""
        n = self.weights.shape[0]
        k = self.corrections.shape[1]
        kept = max(0, k - lead)
        corrections = self.corrections[lead:, lead : lead + kept] if kept else np.zeros((n - lead, 0))
        return _ScalarFilter(self.weights[: n - lead], corrections)

    def dense(self) -> np.ndarray:
        from scipy.linalg import block_diag, toeplitz

        n = self.weights.shape[0]
        matrix = toeplitz(self.weights, np.zeros(n))
        k = self.corrections.shape[1]
        matrix[:, :k] += self.corrections
        if self.window:
            return np.asarray(block_diag(np.eye(self.window), matrix))
        return np.asarray(matrix)

    def matvec(self, x: np.ndarray) -> np.ndarray:
        from scipy.signal import fftconvolve

        if self.window:
            out = np.array(x, dtype=float, copy=True)
            out[self.window :] = self._unwindowed().matvec(x[self.window :])
            return out
        n = self.weights.shape[0]
        out = np.asarray(fftconvolve(self.weights[:, None], x, axes=0)[:n])
        k = self.corrections.shape[1]
        if k:
            out = out + self.corrections @ x[:k]
        return out

    def _unwindowed(self) -> _ScalarFilter:
        return _ScalarFilter(self.weights, self.corrections)

    def rmatvec(self, y: np.ndarray) -> np.ndarray:
        from scipy.signal import fftconvolve

        if self.window:
            out = np.array(y, dtype=float, copy=True)
            out[self.window :] = self._unwindowed().rmatvec(y[self.window :])
            return out
        n = self.weights.shape[0]
        out = np.asarray(fftconvolve(self.weights[:, None], y[::-1], axes=0)[:n][::-1])
        k = self.corrections.shape[1]
        if k:
            out[:k] += self.corrections.T @ y
        return out


def _check_memory(fractional_memory: str) -> str:
    if fractional_memory not in ("controllable", "trial"):
        raise ConfigError(
            f"must be 'controllable' or 'trial', got {fractional_memory!r}", key="law.fractional_memory"
        )
    return fractional_memory


def _zero_history_filter(kp: float, r: float, h: float, n: int) -> _ScalarFilter:
    """``FractionalPD(kp, r, h, history="zero")`` on ``n`` samples: pure lower-triangular Toeplitz."""
    from foilc_hil.design.fractional import FractionalPD, gl_weights

    FractionalPD(kp, r, h, history="zero")  # validates kp, r, h
    weights = kp * h**-r * gl_weights(r, n)
    weights[0] += 1.0
    return _ScalarFilter(weights, np.zeros((n, 0)))


def _law_filter(kp: float, r: float, h: float, n: int, lead: int, fractional_memory: str) -> _ScalarFilter:
    """The ``N x N`` operator ``E = F e`` (per channel) that :mod:`foilc_hil.laws.learning` applies, as a filter.

    ``"controllable"``: ``diag(I_lead, Toeplitz)`` (zero-history GL on ``e[lead:]``); ``"trial"``: the Caputo
    ``FractionalPD`` on the whole trial (Toeplitz plus correction columns, or dense columns if that fails).
    """
    if _check_memory(fractional_memory) == "controllable":
        return _windowed(kp, r, h, n, lead)
    filt, fpd = _fractional_filter(kp, r, h, n)
    if filt is None:
        filt = _ScalarFilter(np.zeros(n), np.asarray(fpd.matrix(n), dtype=float))
    return filt


def _windowed(kp: float, r: float, h: float, n: int, lead: int) -> _ScalarFilter:
    inner = _zero_history_filter(kp, r, h, n - lead)
    return _ScalarFilter(inner.weights, inner.corrections, window=lead)


def law_filter_matrix(
    kp: float, r: float, sample_time: float, n_samples: int, lead: int = 0, fractional_memory: str = "controllable"
) -> np.ndarray:
    """The dense ``(N, N)`` matrix ``F`` of ``E = F e`` as :class:`foilc_hil.laws.learning.Foilc` computes it per
    channel.

    ``fractional_memory="controllable"``: ``diag(I_lead, I + kp h^-r T)`` with ``T`` the GL Toeplitz matrix on
    ``N - lead`` samples; ``"trial"``: ``FractionalPD(kp, r, h).matrix(N)`` (Caputo over the whole trial).
    """
    if not (isinstance(n_samples, int) and n_samples > lead >= 0):
        raise InputError(f"n_samples: must be an integer above lead={lead}, got {n_samples!r}")
    return _law_filter(kp, r, sample_time, n_samples, lead, fractional_memory).dense()


def _fractional_filter(kp: float, r: float, h: float, n: int) -> tuple[_ScalarFilter | None, Any]:
    """Decompose ``FractionalPD(kp, r, h)`` on ``n`` samples; ``None`` when the decomposition fails the probe."""
    from foilc_hil.design.fractional import FractionalPD

    fpd = FractionalPD(kp, r, h)
    k = min(CORRECTION_COLUMNS, n)
    extended = np.zeros(n + k)
    extended[k] = 1.0
    weights = np.asarray(fpd.apply(extended), dtype=float)[k:]
    corrections = np.zeros((n, k))
    for j in range(k):
        unit = np.zeros(n)
        unit[j] = 1.0
        column = np.asarray(fpd.apply(unit), dtype=float)
        toeplitz_column = np.concatenate([np.zeros(j), weights[: n - j]])
        corrections[:, j] = column - toeplitz_column
    candidate = _ScalarFilter(weights, corrections)
    probe = np.random.default_rng(12345).standard_normal(n)
    expected = np.asarray(fpd.apply(probe), dtype=float)
    got = candidate.matvec(probe[:, None])[:, 0]
    scale = max(1.0, float(np.max(np.abs(expected))))
    if n <= 3 or float(np.max(np.abs(got - expected))) > 1e-9 * scale:
        return None, fpd
    return candidate, fpd


# --- the error map T (no Q-filter) ----------------------------------------------------------------------------


def _markov_blocks(A_cl: np.ndarray, B_in: np.ndarray, C_out: np.ndarray, start: int, count: int) -> np.ndarray:
    """``C_out A_cl^(start + j) B_in`` for ``j = 0..count-1``, shape ``(count, p, m)``."""
    blocks = np.empty((count, C_out.shape[0], B_in.shape[1]))
    state = np.linalg.matrix_power(A_cl, start) @ B_in
    for j in range(count):
        blocks[j] = C_out @ state
        state = A_cl @ state
        if j % 64 == 63 and not np.all(np.isfinite(state)):
            blocks[j + 1 :] = np.nan
            break
    return blocks


@dataclass(frozen=True)
class LiftedErrorMap:
    """``T = I - H F'`` on ``e[lead:]`` (module notes), with its pieces for fast products."""

    H: _BlockToeplitz
    F: _ScalarFilter | None  # None: the dense path
    dense_matrix: np.ndarray | None
    n_outputs: int
    length: int  # L = N - lead

    @property
    def size(self) -> int:
        """Rows of ``T``."""
        return self.length * self.n_outputs

    def matvec(self, x: np.ndarray) -> np.ndarray:
        """``T x`` for a flat vector ``x`` of :attr:`size` entries (sample-major)."""
        if self.dense_matrix is not None:
            return np.asarray(self.dense_matrix @ x)
        assert self.F is not None
        X = x.reshape(self.length, self.n_outputs)
        return (X - self.H.matvec(self.F.matvec(X))).ravel()

    def rmatvec(self, y: np.ndarray) -> np.ndarray:
        """``T^T y``."""
        if self.dense_matrix is not None:
            return np.asarray(self.dense_matrix.T @ y)
        assert self.F is not None
        Y = y.reshape(self.length, self.n_outputs)
        return (Y - self.F.rmatvec(self.H.rmatvec(Y))).ravel()

    def to_dense(self) -> np.ndarray:
        """``T`` as a dense matrix (for small trials and tests)."""
        if self.dense_matrix is not None:
            return self.dense_matrix
        assert self.F is not None
        return np.eye(self.size) - _dense_block_toeplitz(self.H.blocks) @ np.kron(
            self.F.dense(), np.eye(self.n_outputs)
        )

    def diagonal_block(self) -> np.ndarray:
        """The repeated diagonal block ``I - h_0 w_0`` of the Toeplitz part."""
        assert self.F is not None
        return np.eye(self.n_outputs) - self.H.blocks[0] * self.F.weights[0]

    def spectral_radius(self) -> float:
        """Exact spectral radius (module notes)."""
        if self.dense_matrix is not None:
            return _radius(self.dense_matrix)
        assert self.F is not None
        p = self.n_outputs
        k = self.F.corrections.shape[1]
        radius = _radius(self.diagonal_block())
        if k:
            # T = [[X11, 0], [X21, X22]] with X11 the first k samples: its leading block.
            columns = np.column_stack([self.matvec(_unit(self.size, j)) for j in range(k * p)])
            radius = max(radius, _radius(columns[: k * p, :]))
        return radius

    def _taus(self) -> np.ndarray:
        """The Toeplitz blocks ``tau_j = delta_j I - sum_l h_l w_(j-l)`` of ``T`` (without correction columns)."""
        from scipy.signal import fftconvolve

        assert self.F is not None
        length = self.length
        taus = -np.asarray(fftconvolve(self.H.blocks, self.F.weights[:length, None, None], axes=0)[:length])
        taus[0] += np.eye(self.n_outputs)
        return taus

    def norm_upper_bound(self) -> float:
        """A rigorous upper bound: ``sum_j ||tau_j||_2`` (Toeplitz part) + Frobenius norm of the correction columns."""
        if self.F is None:
            assert self.dense_matrix is not None
            return float(np.linalg.norm(self.dense_matrix, "fro"))
        taus = self._taus()
        toeplitz_bound = float(np.sum(np.linalg.norm(taus, ord=2, axis=(1, 2))))
        k = self.F.corrections.shape[1]
        if not k:
            return toeplitz_bound
        correction = np.zeros((self.size, 0))
        for j in range(k):
            block = np.zeros((self.length, self.n_outputs, self.n_outputs))
            block[:, np.arange(self.n_outputs), np.arange(self.n_outputs)] = self.F.corrections[:, j : j + 1]
            for q in range(self.n_outputs):
                correction = np.column_stack([correction, self.H.matvec(block[:, :, q]).ravel()])
        return toeplitz_bound + float(np.linalg.norm(correction, "fro"))

    def symbol_norm(self, grid: int = 4096) -> float:
        """sup over a frequency grid of the largest singular value of the Toeplitz part's symbol."""
        if self.F is None:
            return math.nan
        from scipy.fft import fft

        length = self.length
        taus = self._taus()
        n_fft = max(grid, 2 * length)
        symbol = fft(taus, n=n_fft, axis=0)
        if self.n_outputs == 1:
            return float(np.max(np.abs(symbol)))
        return float(np.max(np.linalg.svd(symbol, compute_uv=False)))


def _unit(size: int, index: int) -> np.ndarray:
    vector = np.zeros(size)
    vector[index] = 1.0
    return vector


def _radius(matrix: np.ndarray) -> float:
    if matrix.size == 0:
        return 0.0
    values = np.linalg.eigvals(matrix)
    return float(np.max(np.abs(values))) if np.all(np.isfinite(values)) else math.inf


def lifted_error_map(
    A: np.ndarray,
    B: np.ndarray,
    C_measured: np.ndarray,
    p1: np.ndarray,
    p2: np.ndarray,
    *,
    kp: float,
    r: float,
    sample_time: float,
    n_samples: int,
    lead: int = 0,
    fractional_memory: str = "controllable",
) -> LiftedErrorMap:
    """The trial-to-trial error map ``T`` of the law as it runs (module notes).

    Parameters
    ----------
    A, B, C_measured
        The (delay-augmented) plant and its measured output.
    p1, p2
        The gain blocks (``m x n``, ``m x p``).
    kp, r, sample_time
        The fractional PD function ``FractionalPD(kp, r, sample_time)``.
    n_samples
        ``N``, samples per trial.
    lead
        The input delay ``d`` in samples (the law uses ``E[i + d]``).
    fractional_memory
        The law's ``law.fractional_memory``: ``"controllable"`` (``F'`` is the zero-history Toeplitz operator
        on the ``N - lead`` controllable samples) or ``"trial"`` (``F' = F[lead:, lead:]`` of the Caputo
        operator over the whole trial).
    """
    _check_memory(fractional_memory)
    n_out = C_measured.shape[0]
    if not (isinstance(n_samples, int) and n_samples > lead + 1):
        raise InputError(f"n_samples: must be an integer above {lead + 1}, got {n_samples!r}")
    length = n_samples - lead
    A_cl = A + B @ p1
    blocks = _markov_blocks(A_cl, B @ p2, C_measured, lead, length)
    H = _BlockToeplitz(blocks)
    finite = bool(np.all(np.isfinite(blocks)))  # an overflowing plant takes the dense path (caller reports it)
    if fractional_memory == "controllable":
        window = _zero_history_filter(kp, r, sample_time, length)
        if finite:
            return LiftedErrorMap(H, window, None, n_out, length)
        F_dense = window.dense()
    else:
        filt, fpd = _fractional_filter(kp, r, sample_time, n_samples)
        if filt is not None and finite:
            return LiftedErrorMap(H, filt.sub(lead), None, n_out, length)
        F_dense = np.asarray(fpd.matrix(n_samples), dtype=float)[lead:, lead:]
    # Dense path: exact, O(N^2) memory.
    H_dense = _dense_block_toeplitz(blocks)
    T = np.eye(length * n_out) - H_dense @ np.kron(F_dense, np.eye(n_out))
    return LiftedErrorMap(H, None, T, n_out, length)


def _dense_block_toeplitz(blocks: np.ndarray) -> np.ndarray:
    """Dense block lower-triangular Toeplitz matrix with ``blocks[i - j]`` at block ``(i, j)``."""
    length, rows, cols = blocks.shape
    lag = np.arange(length)[:, None] - np.arange(length)[None, :]
    padded = np.concatenate([blocks, np.zeros((1, rows, cols))])
    tiles = padded[np.where(lag >= 0, lag, length)]  # (L, L, rows, cols); index L is the zero block
    return np.asarray(tiles.transpose(0, 2, 1, 3).reshape(length * rows, length * cols))


# --- dense reference maps (tests, small trials) ---------------------------------------------------------------


def _lifted_plant(A: np.ndarray, B: np.ndarray, C: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Dense ``Gz`` (``u[0..N-1] -> z[0..N-1]``, ``z[i] = z(i Ts)``) and ``Gy`` (``-> y((i+1) Ts)``)."""
    ns, m = B.shape
    p = C.shape[0]
    Gz = np.zeros((n * ns, n * m))
    Gy = np.zeros((n * p, n * m))
    power = B.copy()
    for k in range(n):  # z[i] gets A^(i-1-j) B u[j]; y[i] gets C A^(i-j) B u[j]
        for j in range(n - k):
            Gy[(j + k) * p : (j + k + 1) * p, j * m : (j + 1) * m] = C @ power
            if j + k + 1 < n:
                Gz[(j + k + 1) * ns : (j + k + 2) * ns, j * m : (j + 1) * m] = power
        power = A @ power
    return Gz, Gy


def _advance(n: int, lead: int, channels: int) -> np.ndarray:
    """``S``: ``(S v)[i] = v[i + lead]``, zero past the end."""
    return np.kron(np.eye(n, k=lead), np.eye(channels))


def dense_error_map(
    A: np.ndarray,
    B: np.ndarray,
    C_measured: np.ndarray,
    p1: np.ndarray,
    p2: np.ndarray,
    F: np.ndarray,
    lead: int = 0,
) -> np.ndarray:
    """``T_full = I - Gy (I - P1 Gz)^-1 P2 S F`` on the whole error ``e[0..N-1]`` (dense; a second method).

    Its first ``lead`` samples form the identity (they never change); ``T_full[lead:, lead:]`` is the map of
    :func:`lifted_error_map`.
    """
    n = F.shape[0]
    m = B.shape[1]
    p = C_measured.shape[0]
    Gz, Gy = _lifted_plant(A, B, C_measured, n)
    P1 = np.kron(np.eye(n), p1)
    P2 = np.kron(np.eye(n), p2)
    R = np.linalg.solve(np.eye(n * m) - P1 @ Gz, np.eye(n * m))
    return np.eye(n * p) - Gy @ R @ P2 @ _advance(n, lead, p) @ np.kron(F, np.eye(p))


def dense_input_map(
    A: np.ndarray,
    B: np.ndarray,
    C_measured: np.ndarray,
    p1: np.ndarray,
    p2: np.ndarray,
    F: np.ndarray,
    Q: np.ndarray,
    lead: int = 0,
) -> np.ndarray:
    """``M = R (Q - P2 S F Gy - P1 Gz)`` on the input ``u[0..N-1]`` (dense; with a Q-filter)."""
    n = F.shape[0]
    m = B.shape[1]
    p = C_measured.shape[0]
    Gz, Gy = _lifted_plant(A, B, C_measured, n)
    P1 = np.kron(np.eye(n), p1)
    P2 = np.kron(np.eye(n), p2)
    Qm = np.kron(Q, np.eye(m))
    R = np.linalg.solve(np.eye(n * m) - P1 @ Gz, np.eye(n * m))
    learning = P2 @ _advance(n, lead, p) @ np.kron(F, np.eye(p)) @ Gy
    return R @ (Qm - learning - P1 @ Gz)


# --- the input map M (with a Q-filter), as an operator ---------------------------------------------------------


@dataclass(frozen=True)
class LiftedInputMap:
    """``M`` of the module notes via fast products; ``u`` flat, sample-major, ``m`` channels."""

    Gz: _BlockToeplitz  # u -> z (strictly causal: block 0 is zero)
    Gy: _BlockToeplitz  # u -> y
    R: _BlockToeplitz  # (I - P1 Gz)^-1 = I + P1 Gz_cl
    F: _ScalarFilter
    Q: np.ndarray
    p1: np.ndarray
    p2: np.ndarray
    lead: int
    n_samples: int
    n_inputs: int
    n_outputs: int

    @property
    def size(self) -> int:
        return self.n_samples * self.n_inputs

    def matvec(self, x: np.ndarray) -> np.ndarray:
        U = x.reshape(self.n_samples, self.n_inputs)
        E = self.F.matvec(self.Gy.matvec(U))
        advanced = np.zeros_like(E)
        advanced[: self.n_samples - self.lead] = E[self.lead :]
        out = self.Q @ U - advanced @ self.p2.T - self.Gz.matvec(U) @ self.p1.T
        return self.R.matvec(out).ravel()

    def rmatvec(self, y: np.ndarray) -> np.ndarray:
        Y = self.R.rmatvec(y.reshape(self.n_samples, self.n_inputs))
        back = np.zeros((self.n_samples, self.n_outputs))
        back[self.lead :] = (Y @ self.p2)[: self.n_samples - self.lead]
        learning = self.Gy.rmatvec(self.F.rmatvec(back))
        return (self.Q.T @ Y - learning - self.Gz.rmatvec(Y @ self.p1)).ravel()


def lifted_input_map(
    A: np.ndarray,
    B: np.ndarray,
    C_measured: np.ndarray,
    p1: np.ndarray,
    p2: np.ndarray,
    *,
    kp: float,
    r: float,
    sample_time: float,
    Q: np.ndarray,
    lead: int = 0,
    fractional_memory: str = "controllable",
) -> LiftedInputMap:
    """The input map ``M`` (with the ``N x N`` Q-filter matrix ``Q``) as fast ``matvec``/``rmatvec`` products.

    ``fractional_memory`` as in :func:`lifted_error_map` (the operator is :func:`law_filter_matrix`'s).
    """
    n_samples = Q.shape[0]
    filt = _law_filter(kp, r, sample_time, n_samples, lead, fractional_memory)
    return _input_map(A, B, C_measured, p1, p2, filt, Q, lead)


def _input_map(
    A: np.ndarray,
    B: np.ndarray,
    C_measured: np.ndarray,
    p1: np.ndarray,
    p2: np.ndarray,
    F: _ScalarFilter,
    Q: np.ndarray,
    lead: int,
) -> LiftedInputMap:
    n = Q.shape[0]
    ns, m = B.shape
    p = C_measured.shape[0]
    z_blocks = np.zeros((n, ns, m))
    z_blocks[1:] = _markov_blocks(A, B, np.eye(ns), 0, n - 1)
    y_blocks = _markov_blocks(A, B, C_measured, 0, n)
    A_cl = A + B @ p1
    r_blocks = np.zeros((n, m, m))
    r_blocks[0] = np.eye(m)
    r_blocks[1:] = _markov_blocks(A_cl, B, p1, 0, n - 1)
    return LiftedInputMap(
        _BlockToeplitz(z_blocks), _BlockToeplitz(y_blocks), _BlockToeplitz(r_blocks), F, Q, p1, p2, lead, n, m, p
    )


# --- certificates ---------------------------------------------------------------------------------------------


def _power_norm(
    size: int,
    matvec: Callable[[np.ndarray], np.ndarray],
    rmatvec: Callable[[np.ndarray], np.ndarray],
    iterations: int = POWER_ITERATIONS,
) -> float:
    """A LOWER bound on the largest singular value: ``||T v||`` for ``v`` from power iteration on ``T^T T``."""
    v = np.random.default_rng(0).standard_normal(size)
    v /= np.linalg.norm(v)
    estimate = 0.0
    for _ in range(iterations):
        w = matvec(v)
        estimate = max(estimate, float(np.linalg.norm(w)))
        if not math.isfinite(estimate):
            return math.inf
        v = rmatvec(w)
        norm = float(np.linalg.norm(v))
        if norm == 0.0:
            break
        v /= norm
    return estimate


def _operator_norm(
    size: int,
    matvec: Callable[[np.ndarray], np.ndarray],
    rmatvec: Callable[[np.ndarray], np.ndarray],
    dense: Callable[[], np.ndarray],
    upper_bound: Callable[[], float] | None = None,
) -> tuple[float, str]:
    """Largest singular value: dense SVD for small sizes, ARPACK ``svds`` otherwise.

    ARPACK is capped (``ARPACK_RESTARTS``); when it does not converge -- clustered top singular values, e.g. a
    Toeplitz map whose symbol is flat near its maximum -- a dense SVD is used up to ``DENSE_FALLBACK_LIMIT``
    rows, and beyond that a rigorous ``upper_bound`` when it is below one, else ``inf`` with the method saying why,
    so a certificate is never granted on an unconverged estimate.
    """
    if size <= DENSE_LIMIT:
        matrix = dense()
        if not np.all(np.isfinite(matrix)):
            return math.inf, "dense"
        return float(np.linalg.norm(matrix, 2)), "dense"
    from scipy.sparse.linalg import ArpackNoConvergence, LinearOperator, svds

    operator = LinearOperator((size, size), matvec=matvec, rmatvec=rmatvec, dtype=float)
    try:
        values = svds(
            operator, k=1, which="LM", tol=1e-8, return_singular_vectors=False, random_state=0, maxiter=ARPACK_RESTARTS
        )
    except ArpackNoConvergence:
        lower = _power_norm(size, matvec, rmatvec)
        if lower >= 1.0:  # enough for the verdict: no monotonic certificate
            return lower, "lower bound (power iteration; ARPACK did not converge)"
        if size <= DENSE_FALLBACK_LIMIT:
            matrix = dense()
            if not np.all(np.isfinite(matrix)):
                return math.inf, "dense (ARPACK did not converge)"
            return float(np.linalg.norm(matrix, 2)), "dense (ARPACK did not converge)"
        if upper_bound is not None:
            bound = upper_bound()
            if bound < 1.0:
                return bound, "upper bound (triangle inequality; ARPACK did not converge)"
        return math.inf, "not computed: ARPACK did not converge"
    return float(np.max(values)), "svds"


def map_certificate(
    A: np.ndarray,
    B: np.ndarray,
    C_measured: np.ndarray,
    p1: np.ndarray,
    p2: np.ndarray,
    *,
    kp: float,
    r: float,
    sample_time: float,
    n_samples: int,
    lead: int = 0,
    q_filter: np.ndarray | None = None,
    fractional_memory: str = "controllable",
) -> dict[str, Any]:
    """Spectral radius and induced 2-norm of the lifted trial-to-trial map for one plant (module notes).

    When the spectral radius is not below one the 2-norm is not computed: ``norm_2`` then holds the radius,
    a lower bound (``||T|| >= rho(T)``), and ``norm_2_method`` says so. ``fractional_memory``: the law's
    ``law.fractional_memory`` (see :func:`lifted_error_map`).
    """
    if q_filter is None:
        T = lifted_error_map(
            A,
            B,
            C_measured,
            p1,
            p2,
            kp=kp,
            r=r,
            sample_time=sample_time,
            n_samples=n_samples,
            lead=lead,
            fractional_memory=fractional_memory,
        )
        if not np.all(np.isfinite(T.H.blocks)):
            return {"map": "error", "spectral_radius": math.inf, "norm_2": math.inf, "norm_2_method": "overflow"}
        radius = T.spectral_radius()
        result: dict[str, Any] = {"map": "error", "spectral_radius": radius}
        if radius >= 1.0:
            bound = max(radius, _power_norm(T.size, T.matvec, T.rmatvec))
            result.update({"norm_2": bound, "norm_2_method": "lower bound (spectral radius >= 1; power iteration)"})
        else:
            norm, method = _operator_norm(T.size, T.matvec, T.rmatvec, T.to_dense, T.norm_upper_bound)
            result.update({"norm_2": norm, "norm_2_method": method})
        if T.F is not None:
            result["norm_2_symbol"] = T.symbol_norm()
        return result
    Q = np.asarray(q_filter, dtype=float)
    if Q.shape != (n_samples, n_samples):
        raise InputError(f"q_filter: must be {n_samples}x{n_samples} (one trial), got {Q.shape}")
    filt = _law_filter(kp, r, sample_time, n_samples, lead, fractional_memory)
    M = _input_map(A, B, C_measured, p1, p2, filt, Q, lead)

    def dense() -> np.ndarray:
        return dense_input_map(A, B, C_measured, p1, p2, filt.dense(), Q, lead)

    if M.size <= DENSE_LIMIT:
        radius, radius_method = _radius(dense()), "dense"
    else:
        from scipy.sparse.linalg import ArpackNoConvergence, LinearOperator, eigs

        operator = LinearOperator((M.size, M.size), matvec=M.matvec, dtype=float)
        try:
            values = eigs(operator, k=1, which="LM", tol=1e-8, return_eigenvectors=False, maxiter=50 * M.size)
            radius, radius_method = float(np.max(np.abs(values))), "eigs"
        except ArpackNoConvergence:
            radius, radius_method = math.nan, "eigs did not converge"
    result = {"map": "input (Q-filter)", "spectral_radius_method": radius_method}
    if math.isfinite(radius) and radius >= 1.0:
        result.update(
            {"spectral_radius": radius, "norm_2": radius, "norm_2_method": "lower bound: the spectral radius"}
        )
        return result
    norm, method = _operator_norm(M.size, M.matvec, M.rmatvec, dense)
    if not math.isfinite(radius):  # fall back on the bound rho <= ||M||
        radius, result["spectral_radius_method"] = norm, "upper bound: the induced 2-norm (eigs did not converge)"
    result.update({"spectral_radius": radius, "norm_2": norm, "norm_2_method": method})
    return result


@dataclass(frozen=True)
class Certification:
    """What :func:`certify` hands back: the gain that runs, its scale and the certificates."""

    P: np.ndarray
    gain_scale: float
    certificates: dict[str, Any] = field(default_factory=dict)


def _plants(model: DiscreteModel, uncertainty: Uncertainty) -> list[tuple[str, np.ndarray, np.ndarray]]:
    from foilc_hil.design.lmi import uncertainty_vertices

    plants = [("nominal", model.A, model.B)]
    for index, (dA, dB) in enumerate(uncertainty_vertices(uncertainty), start=1):
        plants.append((f"vertex {index}", model.A + dA, model.B + dB))
    return plants


def _worst(entries: list[dict[str, Any]], key: str) -> float:
    values = [float(entry[key]) for entry in entries]
    return max(values) if all(math.isfinite(v) for v in values) else math.inf


def certify(
    model: DiscreteModel,
    uncertainty: Uncertainty,
    P: np.ndarray,
    *,
    kp: float,
    r: float,
    n_samples: int,
    on_divergent_filter: str = "rescale",
    q_filter: np.ndarray | None = None,
    require_monotonic: bool = True,
    growth_horizon: int = 10,
    fractional_memory: str = "controllable",
) -> Certification:
    """Certify the law with gain ``P`` as it runs, nominal and at the uncertainty vertices; fix or refuse.

    The law is admissible when the spectral radius is below one at every plant (asymptotic convergence) and, if
    ``require_monotonic``, the induced 2-norm too (monotonic convergence of the error in l2). Otherwise, by
    ``on_divergent_filter``:

    ``"rescale"``
        scale ``p2`` by ``s`` in ``(0, 1]``. The worst-case 2-norm of ``I - s K`` is convex in ``s`` and equals
        one at ``s = 0``, so the scales with a monotonic certificate form an interval ``(0, s_max)``; we take the
        ``s`` that minimises the worst-case 2-norm (the fastest certified monotone contraction, bounded Brent
        search on ``log s``; the largest admissible ``s`` is reported too, by bisection). When no ``s`` gives a
        2-norm below one -- typical for ``r > 1``, where the fractional term's phase exceeds 90 degrees over a
        band of low frequencies, and whenever the Caputo corrections for ``e(0)``, ``e'(0)`` dominate -- and
        monotonicity is not required, we take the ``s`` minimising the worst-case spectral radius instead and
        report ``monotonic: false`` with the growth bound ``||T||_2^k`` over ``growth_horizon`` trials.
        ``P`` is returned with ``p2`` scaled.
    ``"refuse"``
        raise :class:`ConvergenceCertificateError`.
    ``"augment"``
        not available: designing on a model augmented with the filter's dynamics is not implemented; raises
        :class:`ConvergenceCertificateError` saying so (use ``rescale``).

    ``fractional_memory`` is the law's ``law.fractional_memory``; the certificate is of that operator and is
    recorded as ``certificates["fractional_memory"]`` (the law refuses a design certified with another one).

    Raises
    ------
    foilc_hil.errors.ConvergenceCertificateError
        When the law is not certified and cannot be fixed (exit 3).
    """
    _check_memory(fractional_memory)
    if on_divergent_filter not in ("rescale", "augment", "refuse"):
        raise ConfigError(
            f"must be 'rescale', 'augment' or 'refuse', got {on_divergent_filter!r}",
            key="synthesis.on_divergent_filter",
        )
    n = model.n_states
    P = np.asarray(P, dtype=float)
    p1, p2 = P[:, :n], P[:, n:]
    plants = _plants(model, uncertainty)
    lead = model.input_delay
    C_meas = model.measured_output
    h = model.sample_time

    def evaluate(scale: float, kp_value: float, with_q: bool = True) -> list[dict[str, Any]]:
        entries = []
        for name, A_v, B_v in plants:
            entry = map_certificate(
                A_v,
                B_v,
                C_meas,
                p1,
                scale * p2,
                kp=kp_value,
                r=r,
                sample_time=h,
                n_samples=n_samples,
                lead=lead,
                q_filter=q_filter if with_q else None,
                fractional_memory=fractional_memory,
            )
            entries.append({"plant": name, **entry})
        return entries

    def admissible(entries: list[dict[str, Any]]) -> bool:
        radius_ok = _worst(entries, "spectral_radius") < 1.0
        norm_ok = _worst(entries, "norm_2") <= CONTRACTION_LIMIT
        return radius_ok and (norm_ok or not require_monotonic)

    designed = evaluate(1.0, kp)
    naive = evaluate(1.0, 0.0, with_q=False)
    certificates: dict[str, Any] = {
        "spectral_radius": _worst(designed, "spectral_radius"),
        "norm_2": _worst(designed, "norm_2"),
        "monotonic_required": require_monotonic,
        "n_samples": n_samples,
        "lead": lead,
        "fractional_memory": fractional_memory,
        "filter_first_weight": 1.0 + kp * h**-r,
        "naive_without_filter": {
            "spectral_radius": _worst(naive, "spectral_radius"),
            "norm_2": _worst(naive, "norm_2"),
        },
        "designed": {
            "spectral_radius": _worst(designed, "spectral_radius"),
            "norm_2": _worst(designed, "norm_2"),
        },
        "vertices": len(plants) - 1,
        "q_filter": q_filter is not None,
    }

    def verdict(entries: list[dict[str, Any]]) -> dict[str, Any]:
        radius, norm = _worst(entries, "spectral_radius"), _worst(entries, "norm_2")
        return {
            "spectral_radius": radius,
            "norm_2": norm,
            "asymptotic": radius < 1.0,
            "monotonic": radius < 1.0 and norm <= CONTRACTION_LIMIT,
            "plants": entries,
        }

    if admissible(designed):
        certificates.update({"action": "none", "gain_scale": 1.0, **verdict(designed)})
        return Certification(P, 1.0, certificates)
    summary = (
        f"spectral radius {certificates['spectral_radius']:.4g}, induced 2-norm {certificates['norm_2']:.4g} "
        f"(filter first weight 1 + kp h^-r = {certificates['filter_first_weight']:.4g})"
    )
    if on_divergent_filter == "refuse":
        raise ConvergenceCertificateError(
            f"the law as it runs is not certified to converge: {summary}; synthesis.on_divergent_filter=refuse"
        )
    if on_divergent_filter == "augment":
        raise ConvergenceCertificateError(
            f"the law as it runs is not certified to converge: {summary}; 'augment' is not implemented, "
            "use synthesis.on_divergent_filter=rescale"
        )
    from scipy.optimize import minimize_scalar

    cache: dict[float, list[dict[str, Any]]] = {}

    def entries_at(scale: float) -> list[dict[str, Any]]:
        if scale not in cache:
            cache[scale] = evaluate(scale, kp)
        return cache[scale]

    def objective(key: str) -> Callable[[float], float]:
        def worst(log_scale: float) -> float:
            value = _worst(entries_at(math.exp(log_scale)), key)
            return value if math.isfinite(value) else 1e300

        return worst

    # The optimum sits near 1 / (filter gain * loop gain); search a window wide enough around it.
    low = math.log(min(1.0, 1e-3 / max(1.0, certificates["filter_first_weight"])))
    # 1. Monotonic: the worst-case 2-norm is convex in s and 1 at s = 0; take its minimiser.
    search = minimize_scalar(objective("norm_2"), bounds=(low, 0.0), method="bounded", options={"xatol": 1e-2})
    best_scale = math.exp(float(search.x))
    best = entries_at(best_scale)
    criterion = "monotonic"
    if not verdict(best)["monotonic"]:
        if require_monotonic:
            raise ConvergenceCertificateError(
                f"the law as it runs is not certified to converge monotonically: {summary}; no rescaling of p2 "
                f"in (0, 1] gives an induced 2-norm below 1 (best {_worst(best, 'norm_2'):.6g} at scale "
                f"{best_scale:.4g})"
            )
        # 2. Asymptotic only (monotonic not required, and not reachable): minimise the worst spectral radius.
        search = minimize_scalar(
            objective("spectral_radius"), bounds=(low, 0.0), method="bounded", options={"xatol": 1e-2}
        )
        best_scale = math.exp(float(search.x))
        best = entries_at(best_scale)
        criterion = "asymptotic"
        if not admissible(best):
            raise ConvergenceCertificateError(
                f"the law as it runs is not certified to converge: {summary}; no rescaling of p2 in (0, 1] helps "
                f"(best worst-case spectral radius {_worst(best, 'spectral_radius'):.6g} at scale {best_scale:.4g})"
            )
    # Largest admissible scale (same criterion), by bisection between the chosen scale and 1 (not admissible).
    lo, hi = best_scale, 1.0
    for _ in range(40):
        if hi - lo <= 1e-2 * hi:
            break
        mid = math.sqrt(lo * hi)
        if admissible(entries_at(mid)):
            lo = mid
        else:
            hi = mid
    scaled = P.copy()
    scaled[:, n:] = best_scale * p2
    if criterion == "asymptotic":
        # ||T^k|| <= ||T||^k: a rigorous bound on how much the error's l2 norm can grow over the run.
        certificates["growth_bound"] = {"trials": growth_horizon, "bound": _worst(best, "norm_2") ** growth_horizon}
    certificates.update(
        {
            "action": "rescale",
            "rescale_criterion": criterion,
            "gain_scale": best_scale,
            "largest_admissible_scale": lo,
            **verdict(best),
        }
    )
    return Certification(scaled, best_scale, certificates)

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
* Induced 2-norm of ``T`` (monotonic convergence in l2), first: a RIGOROUS UPPER BOUND from the truncated
  Toeplitz symbol (:meth:`LiftedErrorMap.symbol_upper_bound`: the sup of the symbol on a fine grid, widened by its
  Lipschitz constant, plus the correction columns' Frobenius norm). When that bound is below 1 it is the
  certificate (``norm_2_method = "upper bound (truncated Toeplitz symbol)"``; ``norm_2`` is then the bound, at most
  a few 1e-5 above the exact finite-trial norm on the shipped configs) and nothing iterative runs. Otherwise a
  power iteration's ``||T v||`` (a unit ``v``: a rigorous LOWER bound) at or above 1 settles the verdict, not
  monotonic (``"lower bound (power iteration; the symbol bound is not below 1)"``). Only between the two, for
  the exact value: ARPACK (``scipy.sparse.linalg.svds``) with
  FFT matrix-vector products, to a relative tolerance of 1e-8 -- an iterative estimate of the exact finite-trial
  norm, not a bound. For trials short enough (``L p <= DENSE_LIMIT``) it is a dense SVD instead; if ARPACK does
  not converge, a dense SVD up to ``DENSE_FALLBACK_LIMIT`` rows, else no certificate. When the spectral radius
  is already ``>= 1`` the norm is not needed for the verdict: ``norm_2`` is then a lower bound (the larger of
  the radius and a short power iteration).
* The rescale search of :func:`certify` evaluates tens of scales of ``p2`` at every plant; for single-output
  Toeplitz maps the blocks are affine in the scale, so :class:`_ScaledErrorMap` computes each plant's symbol once
  and a scale costs one pass over the grid -- the same bounds, not an approximation of them.
* ``norm_2_symbol``: the sup over a frequency grid of the Toeplitz symbol of ``T`` (the long-trial limit of the
  2-norm of the Toeplitz part), for information.
* With a Q-filter: up to :data:`DENSE_LIMIT` rows the dense map (exact); beyond, the structured certificate of
  :mod:`foilc_hil.design.qmap` in bounded time (a symbol bound plus an exact test of the finite-length
  correction; the exact radius of a causal filter's map; each plant's ``proof`` says what is proved and how;
  ``docs/certificates.md``). The rescale search runs on that module's cheap estimates and certifies the scale it
  picks on the whole trial.
* Uncertainty vertices are FROZEN (constant ``Delta``) plants; a time-varying ``Delta(t)`` makes the map
  non-Toeplitz and is covered only by the LMI of Theorem 1 and by simulation.

Module order: after :mod:`foilc_hil.design.record` (whose typed :class:`~foilc_hil.design.record.Certificates`
this module fills in), :mod:`foilc_hil.design.lifted` and :mod:`foilc_hil.design.qmap`, before
:mod:`foilc_hil.design.lmi` (which certifies the gain it solves for).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from foilc_hil.config import DivergentFilterPolicy, FractionalMemory, LawKind
from foilc_hil.design.convolution import fft_convolve
from foilc_hil.design.lifted import (
    SYMBOL_GRID_CAP,
    SYMBOL_GRID_CAP_MIMO,
    SYMBOL_SLACK,
    BlockToeplitz,
    LawStructure,
    LoopPlant,
    ScalarFilter,
    dense_block_toeplitz,
    fractional_filter,
    grid_bound,
    law_filter_matrix,
    markov_blocks,
    moments,
    symbol_grid,
    vector_norm,
    zero_history_filter,
)
from foilc_hil.design.models import DiscreteModel, Uncertainty, uncertainty_vertices
from foilc_hil.design.ptype import frequency_bound
from foilc_hil.design.qmap import (
    INPUT_MAP,
    EdgeProxy,
    StructuredInputMap,
    input_map_certificate,
    structured_input_map,
    triangular_radius,
    unstructured_certificate,
)
from foilc_hil.design.record import (
    BoundClaim,
    Bounds,
    CertificateAction,
    CertificateMethod,
    Certificates,
    Design,
    GrowthBound,
    MonotoneVerdict,
    PlantCertificate,
    Proof,
    PTypeGain,
)
from foilc_hil.errors import ConvergenceCertificateError
from foilc_hil.progress import as_step

__all__ = [
    "DENSE_LIMIT",
    "Certification",
    "FftOperand",
    "LawStructure",
    "LiftedErrorMap",
    "LoopPlant",
    "PTypeScales",
    "ScaledVerdict",
    "block_toeplitz_product",
    "bounded_matrix_certificate",
    "certify",
    "certify_as_given",
    "certify_p_type",
    "dense_block_toeplitz",
    "dense_error_map",
    "dense_input_map",
    "gram_norm_bound",
    "law_filter_matrix",
    "lifted_error_map",
    "map_certificate",
    "markov_blocks",
    "matrix_certificate",
    "matrix_norm_bound",
    "power_norm",
]

#: Up to this many rows, norms and spectra are computed densely (exact, LAPACK).
DENSE_LIMIT = 600
#: Up to this many rows the input map's spectral radius is computed densely: these maps are far from normal, and
#: ARPACK's ``eigs`` needs thousands of restarts on them (minutes at 700 rows on a loaded machine), LAPACK a second.
RADIUS_DENSE_LIMIT = 1000
#: ARPACK restarts allowed for one norm; beyond that the dense fallback (or no certificate).
ARPACK_RESTARTS = 60
#: Largest map a non-converged ARPACK norm falls back to a dense SVD for.
DENSE_FALLBACK_LIMIT = 2500
#: Power iterations for the lower bound used when the spectral radius already rules a certificate out.
POWER_ITERATIONS = 40
#: Admissible certificate: the worst-case 2-norm must be at most this (strictly below one).
CONTRACTION_LIMIT = 1.0 - 1e-9
#: The Cholesky test of :func:`matrix_norm_bound` tries ``rho^2 = (1 + gap) lambda`` (``lambda``: an estimate of
#: ``lambda_max(T^T T)``, :func:`_norm_estimate`) for each gap in turn until it succeeds.
CHOLESKY_GAPS = (1e-8, 1e-6, 1e-4, 1e-2, 1e-1, 1.0, 10.0)
#: Bisection steps between the last gap that failed and the one that passed, when they are more than 1e-4 apart.
CHOLESKY_BISECTIONS = 14
#: Unit roundoff of float64.
UNIT_ROUNDOFF = 2.0**-53
#: Transforms behind one FFT product column (forward of each factor, inverse) for its rounding bound.
FFT_TRANSFORMS = 3
#: Per-level constant of the FFT's relative rounding bound (Higham, Accuracy and Stability, sec. 24.1: at most
#: ``log2(n) eta / (1 - log2(n) eta)`` with ``eta = mu + gamma_4 (sqrt 2 + mu)``, about ``6 u`` per level for a
#: twiddle error ``mu`` of a few ``u``); taken with a factor 2 to spare.
FFT_LEVEL_CONSTANT = 12.0


# --- lifted block-Toeplitz operators via FFT ------------------------------------------------------------------


@dataclass(frozen=True)
class LiftedErrorMap:
    """``T = I - H F'`` on ``e[lead:]`` (module notes), with its pieces for fast products."""

    H: BlockToeplitz
    F: ScalarFilter | None  # None: the dense path
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
        return np.eye(self.size) - dense_block_toeplitz(self.H.blocks) @ np.kron(self.F.dense(), np.eye(self.n_outputs))

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
        assert self.F is not None
        length = self.length
        taus = -np.asarray(fft_convolve(self.H.blocks, self.F.weights[:length, None, None])[:length])
        taus[0] += np.eye(self.n_outputs)
        return taus

    def norm_upper_bound(self) -> float:
        """A rigorous upper bound: ``sum_j ||tau_j||_2`` (Toeplitz part) + Frobenius norm of the correction columns."""
        if self.F is None:
            assert self.dense_matrix is not None
            return float(np.linalg.norm(self.dense_matrix, "fro"))
        taus = self._taus()
        return float(np.sum(np.linalg.norm(taus, ord=2, axis=(1, 2)))) + self._correction_norm()

    def symbol_upper_bound(self) -> float:
        """A rigorous, tight upper bound on ``||T||_2`` from the truncated symbol (the fast certificate).

        The Toeplitz part of ``T`` is a finite section (a compression) of the Laurent operator of the truncated
        symbol ``a(theta) = sum_{j < L} tau_j e^{i j theta}``, whose norm is ``sup_theta ||a(theta)||_2``; so that sup
        bounds it, for every trial length. The sup is taken on an ``M``-point grid and widened rigorously: for one
        output by :func:`grid_bound` (the smallest of a Lipschitz, a curvature and the triangle bound; the
        curvature widening shrinks like ``1 / M^2``, so the grid stays small), for several by
        ``(pi / M) sum_j j ||tau_j||_2`` (``||a'|| <= sum_j j ||tau_j||``, every ``theta`` within ``pi / M`` of a
        grid point); the correction columns of the "trial" memory add their Frobenius norm.
        """
        if self.F is None:
            return self.norm_upper_bound()
        from scipy.fft import fft

        taus = self._taus()
        magnitudes = np.linalg.norm(taus, ord=2, axis=(1, 2))
        sums = moments(magnitudes)
        if self.n_outputs == 1:
            grid = symbol_grid(self.length, sums, SYMBOL_GRID_CAP)
            peak = float(np.max(np.abs(fft(taus[:, 0, 0], n=grid))))
            return grid_bound(peak, grid, sums) + self._correction_norm()
        lipschitz = sums[1]
        wanted = max(4096, 2 * self.length, math.ceil(lipschitz * math.pi / SYMBOL_SLACK))
        grid = min(SYMBOL_GRID_CAP_MIMO, 1 << math.ceil(math.log2(wanted)))
        peak = float(np.max(np.linalg.svd(fft(taus, n=grid, axis=0), compute_uv=False)))
        # both are rigorous; the triangle inequality wins when every tau_j has the same phase at one frequency
        return min(peak + lipschitz * math.pi / grid, sums[0]) + self._correction_norm()

    def _correction_norm(self) -> float:
        """Frobenius norm of ``T``'s correction columns (the Caputo terms of the "trial" memory); 0 without."""
        assert self.F is not None
        k = self.F.corrections.shape[1]
        if not k:
            return 0.0
        correction = np.zeros((self.size, 0))
        for j in range(k):
            block = np.zeros((self.length, self.n_outputs, self.n_outputs))
            block[:, np.arange(self.n_outputs), np.arange(self.n_outputs)] = self.F.corrections[:, j : j + 1]
            for q in range(self.n_outputs):
                correction = np.column_stack([correction, self.H.matvec(block[:, :, q]).ravel()])
        return float(np.linalg.norm(correction, "fro"))

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


def lifted_error_map(loop: LoopPlant, law: LawStructure) -> LiftedErrorMap:
    """The trial-to-trial error map ``T`` of the law as it runs (module notes), without a Q-filter.

    ``law.fractional_memory`` picks ``F'``: ``"controllable"`` -- the zero-history Toeplitz operator on the
    ``N - lead`` controllable samples; ``"trial"`` -- ``F' = F[lead:, lead:]`` of the Caputo operator over the whole
    trial. ``law.q_filter`` is not used here (see :func:`lifted_input_map`).
    """
    n_out = loop.C_measured.shape[0]
    kp, r, sample_time, n_samples, lead = law.kp, law.r, law.sample_time, law.n_samples, law.lead
    length = n_samples - lead
    A_cl = loop.A + loop.B @ loop.p1
    blocks = markov_blocks(A_cl, loop.B @ loop.p2, loop.C_measured, lead, length)
    H = BlockToeplitz(blocks)
    finite = bool(np.all(np.isfinite(blocks)))  # an overflowing plant takes the dense path (caller reports it)
    if law.fractional_memory is FractionalMemory.CONTROLLABLE:
        window = zero_history_filter(kp, r, sample_time, length)
        if finite:
            return LiftedErrorMap(H, window, None, n_out, length)
        F_dense = window.dense()
    else:
        filt, fpd = fractional_filter(kp, r, sample_time, n_samples)
        if filt is not None and finite:
            return LiftedErrorMap(H, filt.sub(lead), None, n_out, length)
        F_dense = np.asarray(fpd.matrix(n_samples), dtype=float)[lead:, lead:]
    # Dense path: exact, O(N^2) memory.
    H_dense = dense_block_toeplitz(blocks)
    T = np.eye(length * n_out) - H_dense @ np.kron(F_dense, np.eye(n_out))
    return LiftedErrorMap(H, None, T, n_out, length)


def _gamma(k: int) -> float:
    """``gamma_k = k u / (1 - k u)``: the classical bound on the relative rounding error of ``k`` operations."""
    return k * UNIT_ROUNDOFF / (1.0 - k * UNIT_ROUNDOFF)


@dataclass(frozen=True)
class FftOperand:
    """A right-hand side ``X`` of :func:`block_toeplitz_product`, transformed once for many left factors: the
    per-draw NOILC maps of a robustness chunk all multiply the same gain, and its FFT was a third of each product.

    Attributes
    ----------
    spectrum
        ``rfft`` of ``X``'s ``K`` columns as ``(K, cols, F)``: each column's blocks, ``nfft`` points along them (the
        transform runs along the last, contiguous axis: along the first, strided one, pocketfft took twice as long
        at 2000 x 2000).
    length, cols
        The block rows of ``X`` and the columns of each block (the blocks' input channels).
    nfft
        The FFT length: ``next_fast_len(2 length)``, room for the full linear convolution.
    norm
        ``||X||_F``, for the rounding bound.
    """

    spectrum: np.ndarray
    length: int
    cols: int
    nfft: int
    norm: float

    @classmethod
    def of(cls, X: np.ndarray, length: int) -> FftOperand:
        """``X`` (``length * cols`` rows) transformed."""
        from scipy.fft import next_fast_len, rfft

        cols = X.shape[0] // length
        nfft = next_fast_len(2 * length, real=True)
        columns = np.ascontiguousarray(X.reshape(length, cols, X.shape[1]).transpose(2, 1, 0))  # (K, cols, length)
        spectrum = rfft(columns, n=nfft, axis=-1)
        return cls(spectrum, length, cols, nfft, float(np.linalg.norm(X)))


def block_toeplitz_product(blocks: np.ndarray, X: np.ndarray | FftOperand) -> tuple[np.ndarray, float]:
    """``dense_block_toeplitz(blocks) @ X`` by FFT, and a rigorous bound on the Frobenius norm of its rounding error.

    ``O(L^2 log L)`` for an ``(L m) x K`` right-hand side instead of the ``O(L^2 K)`` of a dense product (the per-draw
    NOILC map: ``K = L`` columns); ``X`` may come transformed already (:class:`FftOperand`). The bound: every column
    is a convolution done with :data:`FFT_TRANSFORMS` FFTs of ``M`` points, each accurate to ``FFT_LEVEL_CONSTANT
    log2(M) u`` relative in 2-norm, and ``||h * x||_2 <= sum_j ||h_j||_F ||x||_2``; so ``||error||_F <=
    (FFT_TRANSFORMS FFT_LEVEL_CONSTANT log2 M + m + 2) u sum_j ||h_j||_F ||X||_F`` (``m + 2``: the per-frequency
    products and sums).
    """
    from scipy.fft import irfft, rfft

    length, rows, cols = blocks.shape
    operand = X if isinstance(X, FftOperand) else FftOperand.of(X, length)
    if (operand.length, operand.cols) != (length, cols):
        raise ValueError(f"X has {operand.length} blocks of {operand.cols} columns; the blocks are {length} x {cols}")
    nfft = operand.nfft
    spectrum = rfft(blocks.transpose(1, 2, 0), n=nfft, axis=-1)  # (rows, cols, F)
    if rows == cols == 1:  # single channel: a broadcast product, no einsum dispatch over a (K, 1, F) array
        mixed = operand.spectrum * spectrum[0]
    else:
        mixed = np.einsum("rcf,kcf->krf", spectrum, operand.spectrum)
    columns = irfft(mixed, n=nfft, axis=-1, overwrite_x=True)[..., :length]  # (K, rows, length)
    # the product's columns are the rows of this array: an F-ordered view for rows == 1 (no copy)
    product = np.asarray(columns.transpose(2, 1, 0)).reshape(length * rows, -1)
    relative = (FFT_TRANSFORMS * FFT_LEVEL_CONSTANT * math.log2(nfft) + cols + 2) * UNIT_ROUNDOFF
    h_norm = float(np.sum(np.linalg.norm(blocks.reshape(length, -1), axis=1)))
    return product, relative * h_norm * operand.norm


# --- dense reference maps (tests, small trials) ---------------------------------------------------------------


def _lifted_plant(A: np.ndarray, B: np.ndarray, C: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Dense ``Gz`` (``u[0..N-1] -> z[0..N-1]``, ``z[i] = z(i Ts)``) and ``Gy`` (``-> y((i+1) Ts)``)."""
    ns, m = B.shape
    p = C.shape[0]
    powers = np.empty((n + 1, ns, m))  # A^k B; powers[n] is a zero block (the entries above the diagonals)
    powers[n] = 0.0
    power = B.copy()
    for k in range(n):
        powers[k] = power
        power = A @ power
    markov = C @ powers  # C A^k B, k = 0..n (the last zero)
    # z[i] gets A^(i-1-j) B u[j]; y[i] gets C A^(i-j) B u[j]: block (i, j) by its lag, the zero block where none.
    # (Indexed once, not assigned block by block in Python: 0.8 s a call at N = 700.)
    lag = np.subtract.outer(np.arange(n), np.arange(n))
    Gy = markov[np.where(lag >= 0, lag, n)].transpose(0, 2, 1, 3).reshape(n * p, n * m)
    Gz = powers[np.where(lag >= 1, lag - 1, n)].transpose(0, 2, 1, 3).reshape(n * ns, n * m)
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


# --- certificates ---------------------------------------------------------------------------------------------


def power_norm(
    size: int,
    matvec: Callable[[np.ndarray], np.ndarray],
    rmatvec: Callable[[np.ndarray], np.ndarray],
    iterations: int = POWER_ITERATIONS,
    enough: float = math.inf,
) -> float:
    """A LOWER bound on the largest singular value: ``||T v||`` for ``v`` from power iteration on ``T^T T``;
    it stops early once the bound reaches ``enough`` (all a verdict may need to know)."""
    v = np.random.default_rng(0).standard_normal(size)
    v /= vector_norm(v)
    estimate = 0.0
    for _ in range(iterations):
        w = matvec(v)
        estimate = max(estimate, vector_norm(w))
        if not math.isfinite(estimate):
            return math.inf
        if estimate >= enough:
            break
        v = rmatvec(w)
        norm = vector_norm(v)
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
        lower = power_norm(size, matvec, rmatvec)
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


def _error_map_certificate(loop: LoopPlant, law: LawStructure) -> PlantCertificate:
    """:func:`map_certificate` without a Q-filter: the exact error map ``T``."""
    T = lifted_error_map(loop, law)
    if not np.all(np.isfinite(T.H.blocks)):
        return PlantCertificate("", "error", math.inf, math.inf, "overflow")
    radius = T.spectral_radius()
    bound = T.symbol_upper_bound() if radius < 1.0 and T.size > DENSE_LIMIT and T.F is not None else math.inf
    if radius >= 1.0:
        norm = max(radius, power_norm(T.size, T.matvec, T.rmatvec))
        method = "lower bound (spectral radius >= 1; power iteration)"
    elif bound < 1.0:  # conclusive: monotonic, and no iterative or dense SVD is needed
        norm, method = bound, "upper bound (truncated Toeplitz symbol)"
    else:
        # a cheap lower bound first: above one it settles the verdict (not monotonic) without ARPACK, which the
        # rescale search would otherwise run at every scale past the admissible interval (seconds each at N = 6000)
        lower = power_norm(T.size, T.matvec, T.rmatvec, enough=1.0) if T.size > DENSE_LIMIT else 0.0
        if lower >= 1.0:
            norm, method = lower, "lower bound (power iteration; the symbol bound is not below 1)"
        else:
            norm, method = _operator_norm(T.size, T.matvec, T.rmatvec, T.to_dense, T.norm_upper_bound)
    symbol = T.symbol_norm() if T.F is not None else None
    return PlantCertificate("", "error", radius, norm, method, norm_2_symbol=symbol)


def _matrix_radius(matrix: np.ndarray) -> tuple[float, str]:
    """Spectral radius of a dense map: LAPACK up to :data:`RADIUS_DENSE_LIMIT` rows, beyond that not computed
    (``nan``: the caller bounds it by the 2-norm; ARPACK's ``eigs`` is unbounded in time on these far-from-normal
    maps)."""
    if matrix.shape[0] <= RADIUS_DENSE_LIMIT:
        return _radius(matrix), "dense"
    return math.nan, "not computed"


def _dense_input_certificate(loop: LoopPlant, law: LawStructure) -> PlantCertificate:
    """The Q-filtered input map of a short trial, densely: exact 2-norm and spectral radius."""
    assert law.q_filter is not None
    F = law.filter().dense()
    M = dense_input_map(loop.A, loop.B, loop.C_measured, loop.p1, loop.p2, F, law.q_filter.matrix(), law.lead)
    if not np.all(np.isfinite(M)):
        return PlantCertificate("", INPUT_MAP, math.inf, math.inf, "overflow", "overflow")
    norm, radius = float(np.linalg.norm(M, 2)), _radius(M)
    verdict = MonotoneVerdict.MONOTONE if norm <= CONTRACTION_LIMIT else MonotoneVerdict.NOT_MONOTONE
    proof = Proof(BoundClaim.EXACT, BoundClaim.EXACT, verdict, CertificateMethod.DENSE)
    return PlantCertificate("", INPUT_MAP, radius, norm, "dense", "dense", proof=proof)


def _input_map_certificate(
    loop: LoopPlant, law: LawStructure, scaled: StructuredInputMap | None = None, scale: float = 1.0
) -> PlantCertificate:
    """:func:`map_certificate` with a Q-filter: the input map ``M``, densely for short trials, else in the
    structured form of :mod:`foilc_hil.design.qmap` (``scaled``: that form of the unscaled loop, ``scale`` the
    scale of ``p2`` to certify), else -- a map without that structure -- inconclusive."""
    assert law.q_filter is not None
    if law.n_samples * loop.B.shape[1] <= DENSE_LIMIT:
        return _dense_input_certificate(loop.scaled(scale), law)
    structured = scaled if scaled is not None else structured_input_map(loop, law)
    if structured is None:
        return unstructured_certificate(loop.scaled(scale), law)
    return input_map_certificate(structured, scale, exact=law.exact)


def map_certificate(loop: LoopPlant, law: LawStructure) -> PlantCertificate:
    """Spectral radius and induced 2-norm of the lifted trial-to-trial map for one plant (module notes).

    Without ``law.q_filter`` the error map ``T``, with it the input map ``M``. When the spectral radius is not
    below one the 2-norm is not computed: ``norm_2`` then holds a lower bound (``||T|| >= rho(T)``) and
    ``norm_2_method`` says so. The result's ``plant`` name is empty (the caller names it).
    """
    if law.q_filter is None:
        return _error_map_certificate(loop, law)
    return _input_map_certificate(loop, law)


def matrix_certificate(matrix: np.ndarray, kind: str) -> PlantCertificate:
    """Spectral radius and induced 2-norm of a trial-to-trial map given as a dense matrix.

    For laws whose map has no Toeplitz structure (norm-optimal ILC). Up to :data:`DENSE_LIMIT` rows: a dense SVD
    and eigenvalues (exact). Beyond: ``||T||_2 = sqrt(lambda_max(T^T T))`` from the largest eigenvalue of the Gram
    matrix (LAPACK ``eigh`` on that one eigenvalue: exact to rounding, and unlike ARPACK unaffected by the
    clustered top singular values these maps have); when it is below one it bounds the spectral radius
    (``rho <= ||T||``, so the verdict needs no eigenvalues) and the method says so, else LAPACK's eigenvalues up
    to :data:`RADIUS_DENSE_LIMIT` rows and beyond that "inconclusive at bound" the 2-norm.
    """
    from scipy.linalg import eigh

    T = np.asarray(matrix, dtype=float)
    if not np.all(np.isfinite(T)):
        return PlantCertificate("", kind, math.inf, math.inf, "overflow")
    size = T.shape[0]
    if size <= DENSE_LIMIT:
        return PlantCertificate("", kind, _radius(T), float(np.linalg.norm(T, 2)), "dense", "dense")
    top = eigh(T.T @ T, eigvals_only=True, subset_by_index=[size - 1, size - 1])
    norm = math.sqrt(max(float(top[0]), 0.0))
    method = "dense (largest eigenvalue of T^T T)"
    if norm < 1.0:
        return PlantCertificate("", kind, norm, norm, method, "upper bound: the induced 2-norm")
    radius, radius_method = _matrix_radius(T)
    if math.isnan(radius):  # rho <= ||T||: an upper bound, not below one here
        radius, radius_method = norm, f"inconclusive at bound {norm:.6g} (the induced 2-norm)"
    return PlantCertificate("", kind, radius, norm, method, radius_method)


#: ``norm_2_method`` of a certificate from :func:`matrix_norm_bound`.
CHOLESKY_METHOD = "upper bound (Cholesky of rho^2 I - T^T T)"


def _norm_estimate(gram: np.ndarray, column: np.ndarray | None) -> tuple[float, np.ndarray | None]:
    """An estimate of ``||T||_2^2`` to try the Cholesky test at (neither bound nor certificate: the test decides),
    and a start vector for :func:`_power_lower` (``None``: a random one).

    Up to :data:`DENSE_LIMIT` columns (or without ``column``) the largest eigenvalue of the Gram matrix (LAPACK).
    Beyond, the squared sup of the symbol of ``T``'s middle ``column`` (its two-sided impulse response there, by
    FFT): the trial maps certified here are Toeplitz-like away from the trial's ends, and their top singular values
    cluster within about 1e-6 of that sup (Krylov methods stall on such clusters: ARPACK needed seconds and did not
    converge on NOILC's maps). The top singular vectors of such a map (left and right) are close to a sinusoid at
    the sup's frequency, the start vector:
    from it one power step reached within 3e-4 of the top eigenvalue on paper_sim's NOILC draws, where ten steps
    from a random vector stayed 2.5 % below.
    """
    from scipy.linalg import eigh

    size = gram.shape[0]
    if size <= DENSE_LIMIT or column is None:
        return float(eigh(gram, eigvals_only=True, subset_by_index=[size - 1, size - 1])[0]), None
    return _column_estimate(column)


def _column_estimate(column: np.ndarray) -> tuple[float, np.ndarray]:
    """The squared sup of the symbol of a Toeplitz-like map's middle ``column`` (its two-sided impulse response
    there, by FFT) and a sinusoid at the sup's frequency (:func:`_norm_estimate`)."""
    from scipy.fft import next_fast_len

    size = column.shape[0]
    middle = size // 2
    response = np.zeros(next_fast_len(4 * size))
    response[: size - middle] = column[middle:]  # lags 0, 1, ...
    response[response.shape[0] - middle :] = column[:middle]  # lags -middle .. -1, wrapped
    magnitude = np.abs(np.fft.fft(response))
    peak = int(np.argmax(magnitude))
    return float(magnitude[peak]) ** 2, np.cos(2.0 * math.pi * peak / response.shape[0] * np.arange(size))


def _power_lower(gram: np.ndarray, start: np.ndarray | None = None) -> float:
    """A lower bound on ``lambda_max`` of a Gram matrix: the best Rayleigh quotient of a few power steps (two from
    ``start``, ten from a random vector)."""
    steps = 10 if start is None else 2
    vector = np.asarray(np.random.default_rng(0).standard_normal((gram.shape[0],)) if start is None else start)
    best = 0.0
    for _ in range(steps):
        norm = float(np.linalg.norm(vector))
        if not norm > 0:
            break
        vector = vector / norm
        image = np.asarray(gram @ vector)
        best = max(best, float(np.dot(vector, image)))
        vector = image
    return best


def _cholesky_succeeds(gram: np.ndarray, rho2: float) -> bool:
    """Rump's test (Verification of positive definiteness, BIT 46, 2006): a floating-point Cholesky of
    ``fl(A - c I)`` with ``A = fl(rho2 I - gram)`` runs to completion only if ``A`` is positive definite, for
    ``c >= gamma_(n+1) / (1 - gamma_(n+1)) tr(A) + 4 n (2 (n + 1) + max A_ii) eta`` (``eta``: the smallest
    subnormal). We take ``c`` with ``4 gamma_(2n+2)`` and ``16 n (2 (n + 2) + ...)`` to spare."""
    from scipy.linalg import LinAlgError, cholesky

    size = gram.shape[0]
    shifted = -gram
    diagonal = np.arange(size)
    shifted[diagonal, diagonal] += rho2  # A = fl(rho2 I - gram), as the theorem's floating-point matrix
    trace = float(np.sum(shifted[diagonal, diagonal]))
    if not trace > 0:
        return False
    eta = math.ulp(0.0)
    shift = 4.0 * _gamma(2 * size + 2) * trace + 16.0 * size * (2 * (size + 2) + rho2) * eta
    shifted[diagonal, diagonal] -= shift
    try:
        cholesky(shifted, lower=False, overwrite_a=True, check_finite=False)
    except LinAlgError:
        return False
    return True


def matrix_norm_bound(matrix: np.ndarray, error: float = 0.0) -> float | None:
    """A RIGOROUS upper bound on ``||T||_2`` for ``T = matrix + E``, ``||E||_2 <= error``; ``None`` when the test
    fails at every gap of :data:`CHOLESKY_GAPS`.

    ``||T||_2 < rho`` if and only if ``rho^2 I - T^T T`` is positive definite, which a Cholesky factorisation decides
    (``n^3 / 3`` flops, no eigenvalue or singular value decomposition). ``rho^2``, an estimate of ``lambda_max`` of the
    Gram matrix (:func:`_norm_estimate`), is widened by the gap; the rounding is accounted for:
    the computed Gram matrix is within ``gamma_n ||T||_F^2`` of ``T^T T`` (2-norm), forming ``A = rho^2 I - gram``
    rounds its diagonal by at most ``u (rho^2 + max gram_ii)``, and :func:`_cholesky_succeeds` proves ``A``
    positive definite. So ``||matrix||_2^2 < rho^2 + u (rho^2 + max gram_ii) + gamma_n ||matrix||_F^2``, and
    ``||T||_2`` is at most its square root plus ``error``. The bound is as tight as the estimate: at or below the
    exact ``lambda_max`` (the LAPACK value of small maps), the first gap that succeeds; above it (a symbol estimate
    of a large map, measured about 1.5e-7 relative above on paper_sim's NOILC draws), by that much. A poor estimate
    (a map far from Toeplitz) passes only at a wide gap, or far above a power-iteration lower bound: bisection
    (:data:`CHOLESKY_BISECTIONS` Cholesky tests) narrows it.
    """
    T = np.asarray(matrix, dtype=float)
    if not np.all(np.isfinite(T)):
        return None
    gram = T.T @ T  # numpy computes a product with its own transpose by a symmetric rank-k update (syrk)
    column = T[:, T.shape[1] // 2] if T.shape[0] == T.shape[1] else None
    frobenius2 = float(np.einsum("ij,ij->", T, T)) * (1.0 + _gamma(T.shape[0] * T.shape[1]))
    bound = gram_norm_bound(gram, _gamma(T.shape[0]) * frobenius2, column)
    return None if bound is None else bound + error


def gram_norm_bound(gram: np.ndarray, gram_error: float, column: np.ndarray | None = None) -> float | None:
    """A RIGOROUS upper bound on ``sqrt(lambda_max(S))`` for a symmetric ``S`` within ``gram_error`` (2-norm) of the
    computed ``gram`` (its upper triangle is read): :func:`matrix_norm_bound`'s Cholesky tests from the estimate of
    :func:`_norm_estimate` (``column``: the middle column of the square map ``T``, if any); ``None`` when every gap
    of :data:`CHOLESKY_GAPS` fails. ``S`` is ``T^T T`` or ``T T^T`` (the same largest eigenvalue, ``||T||_2^2``).
    """
    estimate, start = _norm_estimate(gram, column)
    estimate = max(estimate, 0.0)
    diagonal_max = float(np.max(np.diag(gram))) if gram.size else 0.0
    failed, passed = 0.0, math.nan
    for gap in CHOLESKY_GAPS:
        if _cholesky_succeeds(gram, estimate * (1.0 + gap) + gram_error):
            passed = estimate * (1.0 + gap) + gram_error
            break
        failed = estimate * (1.0 + gap) + gram_error
    if math.isnan(passed):
        return None
    # A poor estimate (a map far from Toeplitz) passed only at a wide gap, or far above a lower bound (a few power
    # steps: slow on the clustered spectra of Toeplitz-like maps, hence the 5 % before it counts): bisect. The
    # estimate's sinusoid starts the power steps; where it falls short (a map unlike a Toeplitz one), random ones.
    lower = _power_lower(gram, start)
    if start is not None and passed > lower * (1.0 + 0.05):
        lower = max(lower, _power_lower(gram))
    wide = passed > failed * (1.0 + 1e-4) if failed > 0.0 else passed > lower * (1.0 + 0.05)
    failed = max(failed, lower)
    for _ in range(CHOLESKY_BISECTIONS if wide else 0):
        middle = 0.5 * (failed + passed)
        if _cholesky_succeeds(gram, middle):
            passed = middle
        else:
            failed = middle
    bound2 = (passed + UNIT_ROUNDOFF * (passed + diagonal_max) + gram_error) * (1.0 + 4.0 * UNIT_ROUNDOFF)
    return math.nextafter(math.sqrt(bound2) * (1.0 + 2.0 * UNIT_ROUNDOFF), math.inf)


def bounded_matrix_certificate(matrix: np.ndarray, kind: str, error: float = 0.0) -> PlantCertificate:
    """:func:`matrix_certificate` by the Cholesky bound (:func:`matrix_norm_bound`) where that bound is a certificate.

    When the bound is at most :data:`CONTRACTION_LIMIT` it is the certificate: ``norm_2`` is the bound (rigorous,
    slightly above the exact norm: :func:`matrix_norm_bound`) and so is ``spectral_radius`` (``rho <= ||T||``).
    Otherwise the exact dense path of :func:`matrix_certificate` decides. ``error`` bounds (2-norm) how far
    ``matrix`` may be from the exact map (its rounding when it was formed, e.g. :func:`block_toeplitz_product`'s).
    """
    bound = matrix_norm_bound(matrix, error)
    if bound is not None and bound <= CONTRACTION_LIMIT:
        return PlantCertificate("", kind, bound, bound, CHOLESKY_METHOD, "upper bound: the induced 2-norm")
    return matrix_certificate(matrix, kind)


@dataclass(frozen=True)
class _ScaledErrorMap:
    """The error map ``T(s) = I - s H F'`` of one single-output plant for every scale ``s`` of ``p2`` at once.

    The rescale search of :func:`certify` evaluates tens of scales at every plant. ``H`` is linear in ``p2``, so
    the Toeplitz blocks are ``tau_j(s) = delta_j - s c_j`` with ``c = h * w`` (``h`` the unscaled Markov
    parameters, ``w`` the filter's weights) computed once, and so is their spectrum on the symbol grid: a scale
    then costs one pass over that grid. The numbers are those of :meth:`LiftedErrorMap.spectral_radius` and
    :meth:`LiftedErrorMap.symbol_upper_bound` (the same rigorous :func:`grid_bound`, with ``S_1``, ``S_2`` of
    ``T(s)`` equal to ``s`` times those of ``c``), for pure Toeplitz maps (no correction
    columns) longer than :data:`DENSE_LIMIT`; anything else, and any scale whose bound is not below one, takes
    :func:`map_certificate`.
    """

    c: np.ndarray  # (L,)
    # the rfft of c on the symbol grid (|symbol| is even in theta: half the grid suffices) as its real part and
    # squared modulus: |1 - s C|^2 = 1 - 2 s Re C + s^2 |C|^2, one fused pass per scale
    real: np.ndarray
    modulus2: np.ndarray
    grid: int
    c_moments: tuple[float, float]  # sum_j j |c_j|, sum_j j^2 |c_j|: S_1 and S_2 of T(s) are s times these
    info_spectrum: np.ndarray  # fft of c on LiftedErrorMap.symbol_norm's grid

    @staticmethod
    def of(loop: LoopPlant, law: LawStructure) -> _ScaledErrorMap | None:
        """The precomputed map, or ``None`` where :func:`map_certificate` must run (see the class notes)."""
        from scipy.fft import fft, rfft

        if law.q_filter is not None or loop.C_measured.shape[0] != 1 or loop.p2.shape != (1, 1):
            return None
        T = lifted_error_map(loop, law)
        if T.F is None or T.F.corrections.shape[1] or T.size <= DENSE_LIMIT or not np.all(np.isfinite(T.H.blocks)):
            return None
        taus = T._taus()[:, 0, 0]
        c = -taus  # tau_j = delta_j - c_j
        c[0] += 1.0
        _, s1, s2 = moments(np.abs(c))
        grid = symbol_grid(T.length, moments(np.abs(taus)), SYMBOL_GRID_CAP)  # s = 1: the largest moments
        info = fft(c, n=max(4096, 2 * T.length))
        spectrum = rfft(c, n=grid)
        return _ScaledErrorMap(
            c, np.ascontiguousarray(spectrum.real), np.abs(spectrum) ** 2, grid, (s1, s2), np.asarray(info)
        )

    def certificate(self, scale: float, loop: LoopPlant, law: LawStructure) -> PlantCertificate | None:
        """The certificate at ``scale`` when it is conclusive -- the symbol bound below one, or else a power
        iteration's lower bound at or above one -- else ``None`` (``loop``, ``law``: the unscaled map's)."""
        radius = abs(1.0 - scale * float(self.c[0]))
        if radius >= 1.0:
            return None
        peak = math.sqrt(max(0.0, float(np.max(scale * scale * self.modulus2 - 2.0 * scale * self.real)) + 1.0))
        taus = -scale * self.c
        taus[0] += 1.0
        sums = (float(np.sum(np.abs(taus))), scale * self.c_moments[0], scale * self.c_moments[1])
        bound = grid_bound(peak, self.grid, sums)
        symbol = float(np.max(np.abs(1.0 - scale * self.info_spectrum)))
        if bound < 1.0:
            return PlantCertificate(
                "", "error", radius, bound, "upper bound (truncated Toeplitz symbol)", norm_2_symbol=symbol
            )
        T = lifted_error_map(loop.scaled(scale), law)
        lower = power_norm(T.size, T.matvec, T.rmatvec, enough=1.0)
        if lower < 1.0:  # inconclusive: the exact norm decides (map_certificate)
            return None
        method = "lower bound (power iteration; the symbol bound is not below 1)"
        return PlantCertificate("", "error", radius, lower, method, norm_2_symbol=symbol)


@dataclass(frozen=True)
class Certification:
    """What :func:`certify` hands back: the gain that runs, its scale and the certificates."""

    P: np.ndarray
    gain_scale: float
    certificates: Certificates


def _plants(model: DiscreteModel, uncertainty: Uncertainty) -> list[tuple[str, np.ndarray, np.ndarray]]:
    plants = [("nominal", model.A, model.B)]
    for index, (dA, dB) in enumerate(uncertainty_vertices(uncertainty), start=1):
        plants.append((f"vertex {index}", model.A + dA, model.B + dB))
    return plants


@dataclass(frozen=True)
class ScaledVerdict:
    """The certificates of one gain scale ``s`` at every plant (nominal first, then the vertices): what the rescale
    rule of every law reads (here for the 2D laws; :mod:`foilc_hil.design.admission` for p-type, noilc, gradient)."""

    scale: float
    plants: tuple[PlantCertificate, ...]

    def _worst(self, key: str) -> float:
        values = [float(getattr(entry, key)) for entry in self.plants]
        return max(values) if values and all(math.isfinite(v) for v in values) else math.inf

    @property
    def spectral_radius(self) -> float:
        """The worst-case spectral radius (``inf`` when one is not finite)."""
        return self._worst("spectral_radius")

    @property
    def norm_2(self) -> float:
        """The worst-case induced 2-norm."""
        return self._worst("norm_2")

    @property
    def asymptotic(self) -> bool:
        """Certified to converge."""
        return self.spectral_radius < 1.0

    @property
    def monotonic(self) -> bool:
        """Certified to converge monotonically in l2."""
        return self.asymptotic and self.norm_2 <= CONTRACTION_LIMIT

    def admissible(self, require_monotonic: bool) -> bool:
        """What the rule asks of it."""
        return self.monotonic if require_monotonic else self.asymptotic

    def bounds(self) -> Bounds:
        return Bounds(self.spectral_radius, self.norm_2)


class _Evaluator:
    """The lifted maps of one gain, nominal and at the uncertainty vertices, per scale of ``p2`` (cached)."""

    def __init__(self, model: DiscreteModel, uncertainty: Uncertainty, P: np.ndarray, law: LawStructure) -> None:
        n = model.n_states
        self.law = law
        self.loops = [
            (name, LoopPlant(A_v, B_v, model.measured_output, P[:, :n], P[:, n:]))
            for name, A_v, B_v in _plants(model, uncertainty)
        ]
        self._cache: dict[float, ScaledVerdict] = {}
        self._scaled: dict[tuple[int, float, float, str], _ScaledErrorMap | None] = {}
        self._structured: dict[tuple[int, float, float, str], StructuredInputMap | None] = {}
        self._proxies: dict[tuple[int, float, float, str], EdgeProxy | None] = {}

    def at(self, scale: float, law: LawStructure | None = None) -> ScaledVerdict:
        """The verdict with ``p2`` scaled by ``scale`` (for ``law``, default the law as it runs)."""
        if law is not None:
            return self._evaluate(scale, law)
        if scale not in self._cache:
            self._cache[scale] = self._evaluate(scale, self.law)
        return self._cache[scale]

    def _evaluate(self, scale: float, law: LawStructure) -> ScaledVerdict:
        return ScaledVerdict(scale, tuple(self._certificate(index, scale, law) for index in range(len(self.loops))))

    def _certificate(self, index: int, scale: float, law: LawStructure) -> PlantCertificate:
        """One plant's certificate: the precomputed scaled map where it is conclusive, else :func:`map_certificate`."""
        name, loop = self.loops[index]
        key = (index, law.kp, law.r, str(law.fractional_memory))
        if law.q_filter is not None:
            if law.n_samples * loop.B.shape[1] <= DENSE_LIMIT:
                return _input_map_certificate(loop, law, scale=scale).named(name)
            if key not in self._structured:
                self._structured[key] = structured_input_map(loop, law)
            return _input_map_certificate(loop, law, self._structured[key], scale).named(name)
        if key not in self._scaled:
            self._scaled[key] = _ScaledErrorMap.of(loop, law)
        scaled = self._scaled[key]
        fast = None if scaled is None else scaled.certificate(scale, loop, law)
        return (fast or map_certificate(loop.scaled(scale), law)).named(name)

    def _proxy(self, index: int) -> EdgeProxy | None:
        """The rescale search's estimate of plant ``index``'s Q-filtered map (``None``: no structured form, or a
        trial short enough to certify densely at every scale)."""
        loop = self.loops[index][1]
        law = self.law
        if law.q_filter is None or law.n_samples * loop.B.shape[1] <= DENSE_LIMIT:
            return None
        key = (index, law.kp, law.r, str(law.fractional_memory))
        if key not in self._structured:
            self._structured[key] = structured_input_map(loop, law)
        if key not in self._proxies:
            structured = self._structured[key]
            self._proxies[key] = None if structured is None else EdgeProxy(structured)
        return self._proxies[key]

    def estimate(self, scale: float, key: str) -> float:
        """The worst-case ``key`` at ``scale`` for the search: the certificates themselves where they are cheap
        (no Q-filter, short trials), else the Q-filtered maps' :class:`~foilc_hil.design.qmap.EdgeProxy` (the
        spectral radius of a causal filter's map exactly, from its diagonal)."""
        proxies = [self._proxy(index) for index in range(len(self.loops))]
        if any(proxy is None for proxy in proxies):
            return float(getattr(self.at(scale), key))
        values = []
        for index, proxy in enumerate(proxies):
            assert proxy is not None
            structured = self._structured[(index, self.law.kp, self.law.r, str(self.law.fractional_memory))]
            if key == "spectral_radius" and structured is not None and structured.triangular:
                values.append(triangular_radius(structured, scale))
            else:
                values.append(proxy.estimate(scale))
        return max(values) if all(math.isfinite(v) for v in values) else math.inf

    def admissible(self, scale: float, require_monotonic: bool) -> bool:
        """Whether ``scale`` looks admissible to the search's estimates (:meth:`estimate`)."""
        if self.estimate(scale, "spectral_radius") >= 1.0:
            return False
        return not require_monotonic or self.estimate(scale, "norm_2") <= CONTRACTION_LIMIT

    def objective(self, key: str) -> Callable[[float], float]:
        """The worst-case ``key`` estimate as a function of ``log(scale)`` (``1e300`` where it is not finite)."""

        def worst(log_scale: float) -> float:
            value = self.estimate(math.exp(log_scale), key)
            return value if math.isfinite(value) else 1e300

        return worst


def _record(
    evaluator: _Evaluator, chosen: ScaledVerdict, require_monotonic: bool, action: CertificateAction
) -> Certificates:
    """The typed certificates of the ``chosen`` verdict (the designed and naive ones for comparison)."""
    law = evaluator.law
    return Certificates(
        spectral_radius=chosen.spectral_radius,
        norm_2=chosen.norm_2,
        monotonic_required=require_monotonic,
        n_samples=law.n_samples,
        lead=law.lead,
        fractional_memory=law.fractional_memory,
        filter_first_weight=law.filter_first_weight,
        naive_without_filter=evaluator.at(1.0, law.without_filters()).bounds(),
        designed=evaluator.at(1.0).bounds(),
        vertices=len(evaluator.loops) - 1,
        q_filter=law.q_filter is not None,
        action=action,
        gain_scale=chosen.scale,
        asymptotic=chosen.asymptotic,
        monotonic=chosen.monotonic,
        plants=chosen.plants,
    )


def certify_as_given(
    model: DiscreteModel, uncertainty: Uncertainty, P: np.ndarray, law: LawStructure, *, require_monotonic: bool
) -> Certificates:
    """The certificates of gain ``P`` exactly as given, nominal and at the uncertainty vertices (no fix)."""
    evaluator = _Evaluator(model, uncertainty, np.asarray(P, dtype=float), law)
    return _record(evaluator, evaluator.at(1.0), require_monotonic, CertificateAction.NONE)


def _summary(designed: ScaledVerdict, law: LawStructure) -> str:
    return (
        f"spectral radius {designed.spectral_radius:.4g}, induced 2-norm {designed.norm_2:.4g} "
        f"(filter first weight 1 + kp h^-r = {law.filter_first_weight:.4g})"
    )


def _refuse(policy: DivergentFilterPolicy, summary: str) -> None:
    """Raise for the policies that do not rescale (``refuse``, and ``augment``, which is not implemented)."""
    if policy is DivergentFilterPolicy.REFUSE:
        raise ConvergenceCertificateError(
            f"the law as it runs is not certified to converge: {summary}; synthesis.on_divergent_filter=refuse"
        )
    if policy is DivergentFilterPolicy.AUGMENT:
        raise ConvergenceCertificateError(
            f"the law as it runs is not certified to converge: {summary}; 'augment' is not implemented, "
            "use synthesis.on_divergent_filter=rescale"
        )


def _best_scale(evaluator: _Evaluator, summary: str, require_monotonic: bool) -> tuple[ScaledVerdict, str]:
    """The scale of ``p2`` minimising the worst-case 2-norm (monotonic), else the worst spectral radius."""
    from scipy.optimize import minimize_scalar

    # The optimum sits near 1 / (filter gain * loop gain); search a window wide enough around it.
    low = math.log(min(1.0, 1e-3 / max(1.0, evaluator.law.filter_first_weight)))
    # 1. Monotonic: the worst-case 2-norm is convex in s and 1 at s = 0; take its minimiser.
    search = minimize_scalar(
        evaluator.objective("norm_2"), bounds=(low, 0.0), method="bounded", options={"xatol": 1e-2}
    )
    best = evaluator.at(math.exp(float(search.x)))
    if best.monotonic:
        return best, "monotonic"
    if require_monotonic:
        raise ConvergenceCertificateError(
            f"the law as it runs is not certified to converge monotonically: {summary}; no rescaling of p2 "
            f"in (0, 1] gives an induced 2-norm below 1 (best {best.norm_2:.6g} at scale {best.scale:.4g})"
        )
    # 2. Asymptotic only (monotonic not required, and not reachable): minimise the worst spectral radius.
    search = minimize_scalar(
        evaluator.objective("spectral_radius"), bounds=(low, 0.0), method="bounded", options={"xatol": 1e-2}
    )
    best = evaluator.at(math.exp(float(search.x)))
    if not best.asymptotic:
        raise ConvergenceCertificateError(
            f"the law as it runs is not certified to converge: {summary}; no rescaling of p2 in (0, 1] helps "
            f"(best worst-case spectral radius {best.spectral_radius:.6g} at scale {best.scale:.4g})"
        )
    return best, "asymptotic"


def _largest_admissible(evaluator: _Evaluator, best: ScaledVerdict, require_monotonic: bool) -> float:
    """Largest admissible scale (same criterion), by bisection on the search's estimates between the chosen scale
    and 1 (not admissible), the result certified as every chosen scale is (else the chosen scale itself)."""
    lo, hi = best.scale, 1.0
    for _ in range(40):
        if hi - lo <= 1e-2 * hi:
            break
        mid = math.sqrt(lo * hi)
        if evaluator.admissible(mid, require_monotonic):
            lo = mid
        else:
            hi = mid
    return lo if lo == best.scale or evaluator.at(lo).admissible(require_monotonic) else best.scale


@as_step("certificates of the law as it runs")
def certify(
    model: DiscreteModel,
    uncertainty: Uncertainty,
    P: np.ndarray,
    law: LawStructure,
    *,
    policy: DivergentFilterPolicy = DivergentFilterPolicy.RESCALE,
    require_monotonic: bool = True,
    growth_horizon: int = 10,
) -> Certification:
    """Certify the law with gain ``P`` as it runs (``law``), nominal and at the uncertainty vertices; fix or refuse.

    The law is admissible when the spectral radius is below one at every plant (asymptotic convergence) and, if
    ``require_monotonic``, the induced 2-norm too (monotonic convergence of the error in l2). Otherwise, by
    ``policy`` (``synthesis.on_divergent_filter``):

    ``rescale``
        scale ``p2`` by ``s`` in ``(0, 1]``. The worst-case 2-norm of ``I - s K`` is convex in ``s`` and equals
        one at ``s = 0``, so the scales with a monotonic certificate form an interval ``(0, s_max)``; we take the
        ``s`` that minimises the worst-case 2-norm (the fastest certified monotone contraction, bounded Brent
        search on ``log s``; the largest admissible ``s`` is reported too, by bisection). When no ``s`` gives a
        2-norm below one -- typical for ``r > 1``, where the fractional term's phase exceeds 90 degrees over a
        band of low frequencies, and whenever the Caputo corrections for ``e(0)``, ``e'(0)`` dominate -- and
        monotonicity is not required, we take the ``s`` minimising the worst-case spectral radius instead and
        report ``monotonic: false`` with the growth bound ``||T||_2^k`` over ``growth_horizon`` trials.
        ``P`` is returned with ``p2`` scaled.
    ``refuse``
        raise :class:`ConvergenceCertificateError`.
    ``augment``
        not available: designing on a model augmented with the filter's dynamics is not implemented; raises
        :class:`ConvergenceCertificateError` saying so (use ``rescale``).

    The certificate is of ``law.fractional_memory``'s operator and records it (the law refuses a design
    certified with another one).

    Raises
    ------
    foilc_hil.errors.ConvergenceCertificateError
        When the law is not certified and cannot be fixed (exit 3).
    """
    policy = DivergentFilterPolicy.parse(policy)
    P = np.asarray(P, dtype=float)
    evaluator = _Evaluator(model, uncertainty, P, law)
    designed = evaluator.at(1.0)
    if designed.admissible(require_monotonic):
        return Certification(P, 1.0, _record(evaluator, designed, require_monotonic, CertificateAction.NONE))
    summary = _summary(designed, law)
    _refuse(policy, summary)
    best, criterion = _best_scale(evaluator, summary, require_monotonic)
    scaled = P.copy()
    scaled[:, model.n_states :] = best.scale * P[:, model.n_states :]
    # ||T^k|| <= ||T||^k: a rigorous bound on how much the error's l2 norm can grow over the run.
    growth = GrowthBound(growth_horizon, best.norm_2**growth_horizon) if criterion == "asymptotic" else None
    record = _record(evaluator, best, require_monotonic, CertificateAction.RESCALE)
    certificates = replace(
        record,
        growth_bound=growth,
        rescale_criterion=criterion,
        largest_admissible_scale=_largest_admissible(evaluator, best, require_monotonic),
    )
    return Certification(scaled, best.scale, certificates)


class PTypeScales:
    """The P-type design ``P = (0 s Gamma)`` at every scale ``s`` of its gain, from one set of lifted maps: what the
    rule of :mod:`foilc_hil.design.admission` searches over (the pipeline's P-type design).

    ``design(s)`` is certified as it runs (``law``: ``kp = 0``), its certificates adding the gain and its
    frequency-domain bound (:class:`PTypeGain`); ``estimate(s)`` gives the rescale search's worst-case spectral
    radius and 2-norm (cheap; the certificates themselves where they are cheap anyway).
    """

    def __init__(
        self,
        model: DiscreteModel,
        uncertainty: Uncertainty,
        gain: np.ndarray,
        law: LawStructure,
        *,
        require_monotonic: bool,
    ) -> None:
        self.model, self.uncertainty, self.law = model, uncertainty, law
        self.gain = np.asarray(gain, dtype=float)
        self.require_monotonic = require_monotonic
        P = np.hstack([np.zeros((model.n_inputs, model.n_states)), self.gain])
        self._evaluator = _Evaluator(model, uncertainty, P, law)

    def design(self, scale: float) -> Design:
        """The design with ``Gamma`` scaled by ``scale`` and its certificates (``designed``: at scale 1; the naive
        comparison: the scaled gain with the filters off)."""
        gamma = scale * self.gain
        evaluator = self._evaluator
        record = _record(evaluator, evaluator.at(scale), self.require_monotonic, CertificateAction.NONE)
        certificates = replace(
            record,
            naive_without_filter=evaluator.at(scale, self.law.without_filters()).bounds(),
            gain_scale=1.0,
            p_type=PTypeGain(gamma, frequency_bound(self.model, gamma)),
        )
        P = np.hstack([np.zeros((self.model.n_inputs, self.model.n_states)), gamma])
        return Design(
            law=LawKind.P_TYPE,
            model=self.model,
            uncertainty=self.uncertainty,
            P=P,
            kp=self.law.kp,
            r=self.law.r,
            certificates=certificates,
        )

    def estimate(self, scale: float) -> Bounds:
        """The worst-case spectral radius and 2-norm at ``scale`` as the rescale search sees them."""
        return Bounds(self._evaluator.estimate(scale, "spectral_radius"), self._evaluator.estimate(scale, "norm_2"))


@as_step("certificates of the P-type law")
def certify_p_type(
    model: DiscreteModel, uncertainty: Uncertainty, gain: np.ndarray, law: LawStructure, *, require_monotonic: bool
) -> Design:
    """The P-type design ``P = (0 Gamma)`` on ``model``, with its certificates as it runs (``law``: ``kp = 0``).

    The gain is the law's (``law.p_type_gain`` or its default, :mod:`foilc_hil.design.ptype`), run as given:
    the certificates report it, nothing rescales it (``synthesis.on_divergent_filter`` is about the fractional
    filter, which P-type does not have). They add the gain and its frequency-domain bound (:class:`PTypeGain`).
    """
    return PTypeScales(model, uncertainty, gain, law, require_monotonic=require_monotonic).design(1.0)

"""The lifted trial-to-trial map of the 2D laws (FOILC, IOILC, P-type) as operators: the error map ``T`` in its
Toeplitz form with fast products, the dense reference maps, and the FFT product of a block Toeplitz matrix.

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

with ``Gz``, ``Gy`` the lifted input-to-state and input-to-output maps and ``S`` the ``d``-sample advance
(:func:`dense_input_map`; for long trials the structured form of :mod:`foilc_hil.design.qmap`).

Module order: after :mod:`foilc_hil.design.lifted` and :mod:`foilc_hil.design.map_norms`, before
:mod:`foilc_hil.design.certificates` (which certifies these maps).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from foilc_hil.config import FractionalMemory
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
    markov_blocks,
    moments,
    symbol_grid,
    zero_history_filter,
)
from foilc_hil.design.map_norms import UNIT_ROUNDOFF, radius_of

__all__ = [
    "FftOperand",
    "LiftedErrorMap",
    "block_toeplitz_product",
    "dense_error_map",
    "dense_input_map",
    "lifted_error_map",
]


#: Transforms behind one FFT product column (forward of each factor, inverse) for its rounding bound.
FFT_TRANSFORMS = 3


#: Per-level constant of the FFT's relative rounding bound (Higham, Accuracy and Stability, sec. 24.1: at most
#: ``log2(n) eta / (1 - log2(n) eta)`` with ``eta = mu + gamma_4 (sqrt 2 + mu)``, about ``6 u`` per level for a
#: twiddle error ``mu`` of a few ``u``); taken with a factor 2 to spare.
FFT_LEVEL_CONSTANT = 12.0


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
            return radius_of(self.dense_matrix)
        assert self.F is not None
        p = self.n_outputs
        k = self.F.corrections.shape[1]
        radius = radius_of(self.diagonal_block())
        if k:
            # T = [[X11, 0], [X21, X22]] with X11 the first k samples: its leading block.
            columns = np.column_stack([self.matvec(_unit(self.size, j)) for j in range(k * p)])
            radius = max(radius, radius_of(columns[: k * p, :]))
        return radius

    def taus(self) -> np.ndarray:
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
        taus = self.taus()
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

        taus = self.taus()
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
        taus = self.taus()
        n_fft = max(grid, 2 * length)
        symbol = fft(taus, n=n_fft, axis=0)
        if self.n_outputs == 1:
            return float(np.max(np.abs(symbol)))
        return float(np.max(np.linalg.svd(symbol, compute_uv=False)))


def _unit(size: int, index: int) -> np.ndarray:
    vector = np.zeros(size)
    vector[index] = 1.0
    return vector


def lifted_error_map(loop: LoopPlant, law: LawStructure) -> LiftedErrorMap:
    """The trial-to-trial error map ``T`` of the law as it runs (module notes), without a Q-filter.

    ``law.fractional_memory`` picks ``F'``: ``"controllable"`` -- the zero-history Toeplitz operator on the
    ``N - lead`` controllable samples; ``"trial"`` -- ``F' = F[lead:, lead:]`` of the Caputo operator over the whole
    trial. ``law.q_filter`` is not used here (the input map: :func:`dense_input_map`, :mod:`foilc_hil.design.qmap`).
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


def _dense_loop(
    A: np.ndarray, B: np.ndarray, C_measured: np.ndarray, p1: np.ndarray, p2: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``Gz, Gy, P1, P2, R = (I - P1 Gz)^-1`` of the dense maps: the lifted plant and the 2D law's in-trial loop."""
    m = B.shape[1]
    Gz, Gy = _lifted_plant(A, B, C_measured, n)
    P1 = np.kron(np.eye(n), p1)
    P2 = np.kron(np.eye(n), p2)
    R = np.linalg.solve(np.eye(n * m) - P1 @ Gz, np.eye(n * m))
    return Gz, Gy, P1, P2, R


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
    n, p = F.shape[0], C_measured.shape[0]
    _, Gy, _, P2, R = _dense_loop(A, B, C_measured, p1, p2, n)
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
    n, m, p = F.shape[0], B.shape[1], C_measured.shape[0]
    Gz, Gy, P1, P2, R = _dense_loop(A, B, C_measured, p1, p2, n)
    Qm = np.kron(Q, np.eye(m))
    learning = P2 @ _advance(n, lead, p) @ np.kron(F, np.eye(p)) @ Gy
    return R @ (Qm - learning - P1 @ Gz)

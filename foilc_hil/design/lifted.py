"""The lifted operators of one trial that every certificate of the 2D laws is built from.

The law's structure (:class:`LawStructure`: fractional PD, trial length, input delay, fractional memory,
Q-filter), one plant with the gain applied (:class:`LoopPlant`), the plant's Markov blocks
(:func:`markov_blocks`), block lower-triangular Toeplitz products by FFT (:class:`BlockToeplitz`), the law's
fractional operator as Toeplitz weights plus correction columns (:class:`ScalarFilter`, :func:`law_filter`), and
the rigorous sup of a truncated symbol on a grid (:func:`grid_bound`). Split out of
:mod:`foilc_hil.design.certificates` (which re-exports the public names) so that :mod:`foilc_hil.design.qmap`
can build the Q-filtered input map from the same pieces.

Module order: after :mod:`foilc_hil.design.fractional` and :mod:`foilc_hil.design.qfilter`, before
:mod:`foilc_hil.design.qmap` and :mod:`foilc_hil.design.certificates`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from foilc_hil.config import FractionalMemory
from foilc_hil.design.convolution import fft_convolve
from foilc_hil.design.fractional import FractionalPD, gl_weights
from foilc_hil.design.qfilter import TrialQFilter
from foilc_hil.errors import ConfigError, InputError

__all__ = [
    "CORRECTION_COLUMNS",
    "SYMBOL_GRID_CAP",
    "SYMBOL_GRID_CAP_MIMO",
    "SYMBOL_SLACK",
    "BlockToeplitz",
    "LawStructure",
    "LoopPlant",
    "ScalarFilter",
    "dense_block_toeplitz",
    "fractional_filter",
    "grid_bound",
    "law_filter",
    "law_filter_matrix",
    "markov_blocks",
    "moments",
    "symbol_grid",
    "vector_norm",
    "zero_history_filter",
]

#: the symbol bound's grid is refined until its Lipschitz widening is at most this ...
SYMBOL_SLACK = 1e-5
#: ... or the grid has this many points (single output; several outputs need an SVD per point)
SYMBOL_GRID_CAP = 1 << 22
SYMBOL_GRID_CAP_MIMO = 1 << 15
#: Columns of the fractional operator allowed to deviate from Toeplitz form (Caputo corrections).
CORRECTION_COLUMNS = 4


class BlockToeplitz:
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
class ScalarFilter:
    """A scalar lifted filter ``F`` (acting on every channel) as Toeplitz weights plus a few dense columns.

    ``F = Toeplitz(weights) + sum_j corrections[:, j] e_j^T`` for ``j < corrections.shape[1]``. With
    ``window = w > 0`` that operator acts on samples ``w:`` only and the first ``w`` samples pass unchanged
    (``F = diag(I_w, F_window)``: the law's "controllable" fractional memory).
    """

    weights: np.ndarray  # (N - window,)
    corrections: np.ndarray  # (N - window, K)
    window: int = 0

    def sub(self, lead: int) -> ScalarFilter:
        """``F[lead:, lead:]`` in the same form."""
        n = self.weights.shape[0]
        k = self.corrections.shape[1]
        kept = max(0, k - lead)
        corrections = self.corrections[lead:, lead : lead + kept] if kept else np.zeros((n - lead, 0))
        return ScalarFilter(self.weights[: n - lead], corrections)

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
        if self.window:
            out = np.array(x, dtype=float, copy=True)
            out[self.window :] = self._unwindowed().matvec(x[self.window :])
            return out
        n = self.weights.shape[0]
        out = np.asarray(fft_convolve(self.weights[:, None], x)[:n])
        k = self.corrections.shape[1]
        if k:
            out = out + self.corrections @ x[:k]
        return out

    def _unwindowed(self) -> ScalarFilter:
        return ScalarFilter(self.weights, self.corrections)

    def rmatvec(self, y: np.ndarray) -> np.ndarray:
        if self.window:
            out = np.array(y, dtype=float, copy=True)
            out[self.window :] = self._unwindowed().rmatvec(y[self.window :])
            return out
        n = self.weights.shape[0]
        out = np.asarray(fft_convolve(self.weights[:, None], y[::-1])[:n][::-1])
        k = self.corrections.shape[1]
        if k:
            out[:k] += self.corrections.T @ y
        return out


@dataclass(frozen=True)
class LawStructure:
    """How the learning law runs, everything its lifted trial map depends on besides the plant and the gain.

    Attributes
    ----------
    kp, r, sample_time
        The fractional PD function ``FractionalPD(kp, r, sample_time)`` (``kp = 0``: ``E = e``).
    n_samples
        ``N``, samples per trial.
    lead
        The input delay ``d`` in samples (the law uses ``E[i + d]``).
    fractional_memory
        The law's ``law.fractional_memory`` (:class:`~foilc_hil.config.FractionalMemory`).
    q_filter
        The Q-filter the law applies to the feedforward between trials (:class:`~foilc_hil.design.qfilter.
        TrialQFilter`: zero-phase or causal, on ``N`` samples), or ``None``.
    exact
        ``synthesis.exact_certificates``: compute exact values where a fast bound is inconclusive (slow on long
        trials) instead of reporting "inconclusive at bound X" (:mod:`foilc_hil.design.qmap`).
    """

    kp: float
    r: float
    sample_time: float
    n_samples: int
    lead: int = 0
    fractional_memory: FractionalMemory = FractionalMemory.CONTROLLABLE
    q_filter: TrialQFilter | None = None
    exact: bool = False

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "fractional_memory", FractionalMemory(self.fractional_memory))
        except ValueError:
            raise ConfigError(
                f"must be 'controllable' or 'trial', got {self.fractional_memory!r}", key="law.fractional_memory"
            ) from None
        if not (isinstance(self.n_samples, int) and self.n_samples > self.lead + 1):
            raise InputError(f"n_samples: must be an integer above {self.lead + 1}, got {self.n_samples!r}")
        if self.q_filter is not None and not (
            isinstance(self.q_filter, TrialQFilter) and self.q_filter.n_samples == self.n_samples
        ):
            raise InputError(f"q_filter: must be a TrialQFilter on {self.n_samples} samples, got {self.q_filter!r}")

    @property
    def filter_first_weight(self) -> float:
        """``1 + kp h^-r``: the weight of the newest error sample in ``E`` (module notes)."""
        return 1.0 + self.kp * self.sample_time**-self.r

    def without_filters(self) -> LawStructure:
        """The same law with the fractional filter and the Q-filter off (``E = e``): the naive comparison."""
        return LawStructure(
            0.0, self.r, self.sample_time, self.n_samples, self.lead, self.fractional_memory, exact=self.exact
        )

    def filter(self) -> ScalarFilter:
        """The ``N x N`` operator ``E = F e`` (per channel) the law applies, as a filter (see :func:`law_filter`)."""
        return law_filter(self.kp, self.r, self.sample_time, self.n_samples, self.lead, self.fractional_memory)


@dataclass(frozen=True)
class LoopPlant:
    """One plant of the learning loop with the gain ``P = (p1 p2)`` applied to it.

    ``A``, ``B`` the (delay-augmented) plant, ``C_measured`` its measured output, ``p1`` (``m x n``) and ``p2``
    (``m x p``) the gain blocks.
    """

    A: np.ndarray
    B: np.ndarray
    C_measured: np.ndarray
    p1: np.ndarray
    p2: np.ndarray

    def scaled(self, scale: float) -> LoopPlant:
        """The loop with ``p2`` scaled by ``scale``."""
        return LoopPlant(self.A, self.B, self.C_measured, self.p1, scale * self.p2)


def zero_history_filter(kp: float, r: float, h: float, n: int) -> ScalarFilter:
    """``FractionalPD(kp, r, h, history="zero")`` on ``n`` samples: pure lower-triangular Toeplitz."""
    FractionalPD(kp, r, h, history="zero")  # validates kp, r, h
    weights = kp * h**-r * gl_weights(r, n)
    weights[0] += 1.0
    return ScalarFilter(weights, np.zeros((n, 0)))


def law_filter(kp: float, r: float, h: float, n: int, lead: int, fractional_memory: str) -> ScalarFilter:
    """The ``N x N`` operator ``E = F e`` (per channel) that :mod:`foilc_hil.laws.learning` applies, as a filter.

    ``"controllable"``: ``diag(I_lead, Toeplitz)`` (zero-history GL on ``e[lead:]``); ``"trial"``: the Caputo
    ``FractionalPD`` on the whole trial (Toeplitz plus correction columns, or dense columns if that fails).
    """
    if FractionalMemory(fractional_memory) is FractionalMemory.CONTROLLABLE:
        return _windowed(kp, r, h, n, lead)
    filt, fpd = fractional_filter(kp, r, h, n)
    if filt is None:
        filt = ScalarFilter(np.zeros(n), np.asarray(fpd.matrix(n), dtype=float))
    return filt


def _windowed(kp: float, r: float, h: float, n: int, lead: int) -> ScalarFilter:
    inner = zero_history_filter(kp, r, h, n - lead)
    return ScalarFilter(inner.weights, inner.corrections, window=lead)


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
    return law_filter(kp, r, sample_time, n_samples, lead, fractional_memory).dense()


def fractional_filter(kp: float, r: float, h: float, n: int) -> tuple[ScalarFilter | None, FractionalPD]:
    """Decompose ``FractionalPD(kp, r, h)`` on ``n`` samples; ``None`` when the decomposition fails the probe."""
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
    candidate = ScalarFilter(weights, corrections)
    probe = np.random.default_rng(12345).standard_normal(n)
    expected = np.asarray(fpd.apply(probe), dtype=float)
    got = candidate.matvec(probe[:, None])[:, 0]
    scale = max(1.0, float(np.max(np.abs(expected))))
    if n <= 3 or float(np.max(np.abs(got - expected))) > 1e-9 * scale:
        return None, fpd
    return candidate, fpd


# --- the error map T (no Q-filter) ----------------------------------------------------------------------------


#: :func:`markov_blocks` steps this many powers at once (one stacked product per stride instead of one per power).
MARKOV_STRIDE = 64


def markov_blocks(A_cl: np.ndarray, B_in: np.ndarray, C_out: np.ndarray, start: int, count: int) -> np.ndarray:
    """``C_out A_cl^(start + j) B_in`` for ``j = 0..count-1``, shape ``(count, p, m)``; ``nan`` past an overflow.

    The first :data:`MARKOV_STRIDE` powers one by one, then every further stride at once by ``A_cl^stride`` (a
    stacked product): a Python step per power was a large share of a robustness draw's IOILC certificate. The
    blocks are the model the certificates take as given, as before.

    """
    blocks = np.empty((count, C_out.shape[0], B_in.shape[1]))
    if count == 0:
        return blocks
    stride = min(MARKOV_STRIDE, count)
    states = np.empty((stride, *B_in.shape))
    states[0] = np.linalg.matrix_power(A_cl, start) @ B_in
    for j in range(1, stride):
        states[j] = A_cl @ states[j - 1]
    jump = np.linalg.matrix_power(A_cl, stride)
    for first in range(0, count, stride):
        if not np.all(np.isfinite(states)):
            blocks[first:] = np.nan
            break
        taken = min(stride, count - first)
        blocks[first : first + taken] = C_out @ states[:taken]
        states = jump @ states
    return blocks


def symbol_grid(length: int, moments: tuple[float, float, float], cap: int) -> int:
    """Points of the symbol grid: a power of two, at least ``max(4096, 2 L)``, fine enough that the curvature
    widening of :func:`grid_bound` is at most :data:`SYMBOL_SLACK` (``moments``: ``S_k = sum_j j^k ||tau_j||``)."""
    s0, s1, s2 = moments
    curvature = 2.0 * (s0 * s2 + s1 * s1)
    wanted = max(4096, 2 * length, math.ceil(2.0 * math.pi * math.sqrt(curvature / (8.0 * SYMBOL_SLACK))))
    return min(cap, 1 << math.ceil(math.log2(wanted)))


def grid_bound(peak: float, grid: int, moments: tuple[float, float, float]) -> float:
    """A rigorous bound on ``sup_theta |a(theta)|`` from its maximum ``peak`` on a uniform ``grid``-point grid.

    With ``S_k = sum_j j^k |tau_j|``: every ``theta`` lies within ``pi / M`` of a grid point and ``|a'| <= S_1``
    (Lipschitz); ``g = |a|^2`` has ``|g''| <= 2 (S_0 S_2 + S_1^2)``, so between two grid points ``g`` exceeds the
    larger end by at most ``(2 pi / M)^2 / 8`` times that (curvature); and ``|a| <= S_0`` (triangle inequality).
    The smallest of the three.
    """
    s0, s1, s2 = moments
    step = 2.0 * math.pi / grid
    lipschitz = peak + s1 * step / 2.0
    curvature = math.sqrt(peak * peak + step * step / 8.0 * 2.0 * (s0 * s2 + s1 * s1))
    return min(lipschitz, curvature, s0)


def moments(magnitudes: np.ndarray) -> tuple[float, float, float]:
    """``S_k = sum_j j^k magnitudes[j]`` for ``k = 0, 1, 2``."""
    j = np.arange(magnitudes.shape[0], dtype=float)
    return float(np.sum(magnitudes)), float(np.sum(j * magnitudes)), float(np.sum(j * j * magnitudes))


def vector_norm(x: np.ndarray) -> float:
    """The 2-norm of a whole array as a sum of squares (an ``einsum`` loop): ``numpy.linalg.norm`` calls BLAS,
    whose threads made the certificates' power iterations several times slower on a loaded two-core host (3.3 s of
    a 6 s FOILC design at N = 20000)."""
    flat = np.asarray(x).reshape(-1)
    return math.sqrt(float(np.einsum("i,i->", flat, flat)))


def dense_block_toeplitz(blocks: np.ndarray) -> np.ndarray:
    """Dense block lower-triangular Toeplitz matrix with ``blocks[i - j]`` at block ``(i, j)``."""
    length, rows, cols = blocks.shape
    lag = np.arange(length)[:, None] - np.arange(length)[None, :]
    padded = np.concatenate([blocks, np.zeros((1, rows, cols))])
    tiles = padded[np.where(lag >= 0, lag, length)]  # (L, L, rows, cols); index L is the zero block
    return np.asarray(tiles.transpose(0, 2, 1, 3).reshape(length * rows, length * cols))

"""The Q-filtered input map of the 2D laws (FOILC, IOILC, P-type) as a Toeplitz section plus a low-rank correction,
and its certificate in bounded time.

The map
-------
With a Q-filter the law stores ``Q u_k`` for the next trial, and the trial-to-trial map acts on the input
(:mod:`foilc_hil.design.certificates` notes)::

    M(s) = R (Q - s P2 S F Gy - P1 Gz),   R = (I - P1 Gz)^-1,

``s`` the scale of ``p2`` (the rescale search's variable). Every factor but ``Q`` (zero-phase: the backward pass)
and ``S`` (the ``d``-sample advance) is causal and Toeplitz, and products of causal finite sections are finite
sections again, so ``M`` differs from the finite section ``T = T_N(a)`` of its two-sided symbol
``a = r (q - s p2 c - p1 gz)`` (``q`` the filter's: ``|h|^2`` zero-phase, ``h`` causal; ``c = f * z^d g`` the
fractional weights times the plant's Markov parameters advanced by ``d``) only by a correction ``E = M - T`` of low
rank whose range or co-range is known in advance (Widom's formula ``T_N(xy) = T_N(x) T_N(y) + P_N H(x) H(y~) P_N +
W_N H(x~) H(y) W_N`` applied to each product):

* ``R`` (causal, ``ns`` states) times the anticausal part of ``q`` (and of ``c`` when the plant's first ``d`` Markov
  parameters do not vanish): range in the span of ``i -> p1 A_cl^i`` (the start of the trial);
* the zero-phase backward pass from zero state at the end: ``Q = T_N(|h|^2) - (rank n_q)``, co-range in the span of
  ``j -> A_h^(N-1-j) B_h`` (the end of the trial);
* ``E[j] = 0`` for ``j >= N`` in the learning term: range in the last ``d`` samples;
* the Caputo correction columns of the "trial" memory (and the first ``d`` error samples no input moves): co-range
  in the first ``max(d, K)`` samples.

With ``U``, ``V`` orthonormal bases of the known ranges and co-ranges, ``(I - P_U) E (I - P_V) = 0``, so
``E = U (E^T U)^T + (I - P_U) (E V) V^T`` exactly, from ``k = dim U + dim V`` products with ``M`` and ``T`` (the
structure is checked on random probes every time; a map that fails the check is not certified this way).

What is computed
----------------
* ``tau >= ||T||_2``: the sup of the truncated symbol on a grid, widened rigorously
  (:func:`foilc_hil.design.lifted.grid_bound`): the "symbol" part.
* ``||M||_2 < gamma`` for a ``gamma > tau`` is decided EXACTLY ("structured exact"): ``gamma^2 I - M^T M = D - W C
  W^T`` with ``D = gamma^2 I - T^T T`` positive definite (``gamma > tau``) and ``W C W^T = M^T M - T^T T`` of rank
  ``2 k`` (``W = [V_E, T^T U_E]`` for ``E = U_E V_E^T``), so it is positive definite if and only if
  ``G^-1 - C`` is, ``G = W^T D^-1 W`` (``2 k x 2 k``). ``D^-1 W`` comes from preconditioned conjugate gradients
  (the circulant with the symbol's values as preconditioner: about a dozen FFT products) and ``G`` is bounded
  above in the Loewner order by the residual: ``G <= sym(W^T Z + Z^T R) + ||R||^2 / (gamma^2 - tau^2) I`` for
  any ``Z`` with residual ``R = W - D Z``; a bound above ``G`` keeps the test one-sided (it can only fail where
  the exact test passes). The first ``gamma`` tried is ``max(tau, lower)`` widened by ``1e-6`` (``lower``: the
  rigorous lower bound below); when it fails, Newton steps on the test's smallest eigenvalue (increasing in
  ``gamma``, with derivative ``2 gamma ||x||^2`` for its direction ``x``) find the edge singular value within a few
  tests (at most :data:`FAST_TESTS`; the answer is then the smallest ``gamma`` that passed).
* Lower bounds (rigorous: ``||M x|| / ||x||``): half-sine windowed sinusoids at the symbol's peak (the interior), and
  each test's direction of its smallest margin refined by a few power steps (the edge singular vector when the
  test ran near it): ``x^T (gamma^2 I - M^T M) x = y^T (G^-1 - C) y`` for ``x = D^-1 W G^-1 y``.
* Spectral radius. A CAUSAL Q-filter keeps ``M`` lower triangular (block: ``m x m``) whenever the plant's first
  ``d`` Markov parameters vanish (the delay-augmented design models): its spectrum is that of its diagonal blocks,
  EXACT. A zero-phase filter makes ``M`` non-triangular: ``rho(M) <= ||M||_2`` (an upper bound, said so); the
  exact value is computed densely only when asked (``LawStructure.exact``) and the trial is short enough.

The rescale search does not run tests: :class:`EdgeProxy` estimates the 2-norm at every scale from the symbol's bound
of the whole trial and the dense map of a short one (its edges); the scale it picks is certified. A map without the
structure (an in-trial loop ``A + B p1`` that is unstable) gets a power iteration's lower bound
(:func:`unstructured_certificate`).

Rounding: the test is exact in exact arithmetic; the residual term of ``G`` is rigorous, the FFT products that
form ``E`` and ``D Z`` carry relative errors of a few ``1e-15`` (Higham's FFT bound), covered by
:data:`ROUNDING_MARGIN` added to every upper bound (a margin, not a proof: as in
:mod:`foilc_hil.design.trial_operator`). Everything runs in ``O(k N log N)`` per test: nothing ``N x N``.

The pieces live beside it: the Toeplitz sections, signal algebra and symbol bound in
:mod:`foilc_hil.design.toeplitz_section`, the structured test and its edge search in
:mod:`foilc_hil.design.norm_test`.

Module order: after :mod:`foilc_hil.design.lifted`, :mod:`foilc_hil.design.certificate_record`,
:mod:`foilc_hil.design.toeplitz_section` and :mod:`foilc_hil.design.norm_test`, before
:mod:`foilc_hil.design.certificates` (which calls :func:`input_map_certificate`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from foilc_hil.config import FractionalMemory, QFilterPhase
from foilc_hil.design.certificate_record import (
    BoundClaim,
    CertificateMethod,
    MonotoneVerdict,
    PlantCertificate,
    Proof,
)
from foilc_hil.design.convolution import fft_convolve
from foilc_hil.design.lifted import (
    LawStructure,
    LoopPlant,
    ScalarFilter,
    markov_blocks,
    vector_norm,
    zero_history_filter,
)
from foilc_hil.design.map_norms import CONTRACTION_LIMIT
from foilc_hil.design.norm_test import EXACT_TOLERANCE, FAST_TOLERANCE, EdgeSearch, NormTest
from foilc_hil.design.qfilter import TrialQFilter
from foilc_hil.design.toeplitz_section import (
    CausalToeplitz,
    SectionSymbol,
    ToeplitzSection,
    flat,
    inner,
    project_out,
    wrapped,
)
from foilc_hil.progress import step

__all__ = [
    "INPUT_MAP",
    "ROUNDING_MARGIN",
    "EdgeProxy",
    "StructuredInputMap",
    "StructuredNorm",
    "input_map_certificate",
    "structured_input_map",
    "triangular_radius",
    "unstructured_certificate",
]

#: Relative margin added to every structured upper bound for the FFT products' rounding (module notes).
ROUNDING_MARGIN = 1e-11
#: Relative widening of the first ``gamma`` tried above the symbol's bound (above an edge's lower bound: half of
#: :data:`FAST_TOLERANCE`).
FIRST_WIDENING = 1e-6
#: Structured tests allowed per certificate in the default (bounded-time) mode.
FAST_TESTS = 6
#: A bracket at most this wide (relative) is reported as the exact value. Where the symbol's bound is the upper
#: end (no test runs below it), the width is that of a finite Toeplitz section below its symbol's sup: about
#: ``c (pi / N)^2`` (8e-6 at N = 1500, 5e-7 at N = 6000 on paper_sim's P-type with a zero-phase filter).
EXACT_CLAIM_TOLERANCE = 1e-6
#: Power steps from a structured test's direction behind its lower bound.
RATIO_STEPS = 2
#: Power steps for the short trial's top singular vector (the edges' lower bound).
SHORT_POWER_STEPS = 40
#: Largest trial (rows) whose exact spectral radius is computed densely when asked (``LawStructure.exact``).
EXACT_RADIUS_DENSE_LIMIT = 6000
#: Relative size of ``(I - P_U) E (I - P_V) x`` on random probes above which the structure counts as absent.
STRUCTURE_TOLERANCE = 1e-9


# --- the input map as the law runs it (exact products: the reference every structure is checked against) --------


@dataclass(frozen=True)
class InputOperator:
    """``M(s) = M0 - s M1`` applied as the law runs it, on ``(K, m, N)`` signals: ``M0 = R (Q - P1 Gz)``,
    ``M1 = R P2 S F Gy`` (module notes; ``Q`` by :meth:`~foilc_hil.design.qfilter.QFilter.apply`)."""

    R: CausalToeplitz  # m x m: I, p1 A_cl^(k-1) B
    P1Gz: CausalToeplitz  # m x m: 0, p1 A^(k-1) B
    Gy: CausalToeplitz  # p x m: C A^k B
    F: ScalarFilter
    q: TrialQFilter
    p2: np.ndarray
    lead: int

    def _filter(self, x: np.ndarray, adjoint: bool) -> np.ndarray:
        """``Q x`` (or ``Q^T x``: the zero-phase ``Q`` is symmetric, the causal one is reversed in time)."""
        if adjoint and self.q.phase is QFilterPhase.CAUSAL:
            return self._filter(x[..., ::-1], adjoint=False)[..., ::-1]
        return np.moveaxis(self.q.apply(np.moveaxis(x, -1, 0)), 0, -1)

    def _fractional(self, x: np.ndarray, adjoint: bool) -> np.ndarray:
        """``F`` (or ``F^T``) on every channel of every column."""
        k, channels, n = x.shape
        flat = x.reshape(k * channels, n).T
        out = self.F.rmatvec(flat) if adjoint else self.F.matvec(flat)
        return np.ascontiguousarray(out.T).reshape(k, channels, n)

    def apply(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(M0 x, M1 x)``."""
        if x.shape[0] == 0:
            return x.copy(), x.copy()
        d, n = self.lead, x.shape[-1]
        error = self._fractional(self.Gy.apply(x), adjoint=False)
        advanced = np.zeros_like(error)
        advanced[..., : n - d] = error[..., d:]
        learning = np.einsum("ap,kpt->kat", self.p2, advanced)
        return self.R.apply(self._filter(x, adjoint=False) - self.P1Gz.apply(x)), self.R.apply(learning)

    def adjoint(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(M0^T y, M1^T y)``."""
        if y.shape[0] == 0:
            return y.copy(), y.copy()
        d, n = self.lead, y.shape[-1]
        back = self.R.adjoint(y)
        delayed = np.zeros((*back.shape[:-2], self.p2.shape[1], n))
        delayed[..., d:] = np.einsum("ap,kat->kpt", self.p2, back)[..., : n - d]
        learning = self.Gy.adjoint(self._fractional(delayed, adjoint=True))
        return self._filter(back, adjoint=True) - self.P1Gz.adjoint(back), learning


# --- the Toeplitz part and the known corner spaces -------------------------------------------------------------------


def _two_sided_conv(causal: np.ndarray, two_sided: np.ndarray) -> np.ndarray:
    """``(causal * two_sided)_k`` for ``|k| < N`` (both ``(2N - 1, m, m)``, ``two_sided`` at ``k + N - 1``)."""
    from scipy.fft import irfft, next_fast_len, rfft

    length = causal.shape[0]
    nfft = int(next_fast_len(2 * length - 1, real=True))
    left = rfft(causal, n=nfft, axis=0)
    right = rfft(two_sided, n=nfft, axis=0)
    return np.asarray(irfft(np.einsum("fab,fbc->fac", left, right), n=nfft, axis=0)[:length])


def _filter_coefficients(q: TrialQFilter) -> np.ndarray:
    """``q_k``, ``|k| < N``, at ``k + N - 1``: ``h`` (causal) or ``sum_j h_j h_(j+|k|)`` (zero phase: from the
    controllability Gramian ``W`` of one pass, ``q_0 = D^2 + C W C^T``, ``q_k = C A^(k-1) (B D + A W C^T)``)."""
    from scipy.linalg import solve_discrete_lyapunov

    n = q.n_samples
    system = q.filter.realization()
    A, B, C, D = system.A, system.B, system.C, system.D
    out = np.zeros(2 * n - 1)
    if q.phase is QFilterPhase.CAUSAL:
        out[n - 1] = D[0, 0]
        out[n:] = markov_blocks(A, B, C, 0, n - 1)[:, 0, 0]
        return out
    gramian = solve_discrete_lyapunov(A, B @ B.T)
    out[n - 1] = D[0, 0] ** 2 + float((C @ gramian @ C.T)[0, 0])
    out[n:] = markov_blocks(A, B * D[0, 0] + A @ gramian @ C.T, C, 0, n - 1)[:, 0, 0]
    out[: n - 1] = out[n:][::-1]
    return out


def _learning_weights(law: LawStructure) -> tuple[np.ndarray, int] | None:
    """The fractional operator's Toeplitz weights on ``N`` samples and its correction columns' count, or ``None``
    when it has no such form (a Caputo operator that failed the decomposition probe)."""
    n = law.n_samples
    if law.fractional_memory is FractionalMemory.CONTROLLABLE:
        # the window's weights on N - d samples are the first N - d of these; rows past N - d are the
        # correction's (they are zeroed by the advance), so any continuation serves
        return zero_history_filter(law.kp, law.r, law.sample_time, n).weights, 0
    filt = law.filter()
    columns = filt.corrections.shape[1]
    return (filt.weights, columns) if columns < n // 4 else None


def _toeplitz_parts(loop: LoopPlant, law: LawStructure, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The coefficients of ``T_N(a0)`` and ``T_N(a1)`` with ``a(s) = a0 - s a1`` (module notes), ``(2N-1, m, m)``."""
    assert law.q_filter is not None
    n, d = law.n_samples, law.lead
    m = loop.B.shape[1]
    A_cl = loop.A + loop.B @ loop.p1
    r = np.zeros((2 * n - 1, m, m))
    r[0] = np.eye(m)
    r[1:] = markov_blocks(A_cl, loop.B, loop.p1, 0, 2 * n - 2)
    x0 = np.zeros((2 * n - 1, m, m))
    x0[:] = np.eye(m) * _filter_coefficients(law.q_filter)[:, None, None]
    x0[n:] -= markov_blocks(loop.A, loop.B, loop.p1, 0, n - 1)
    ahead = markov_blocks(loop.A, loop.B, loop.C_measured, 0, n + d)  # g_(k+d), k = -d .. N-1
    c = fft_convolve(weights[:, None, None], ahead)[: n + d]
    x1 = np.zeros((2 * n - 1, m, m))
    x1[n - 1 - d :] = np.einsum("ap,kpb->kab", loop.p2, c)
    return _two_sided_conv(r, x0), _two_sided_conv(r, x1)


def _orthonormal(columns: np.ndarray) -> np.ndarray:
    """An orthonormal basis of the span of ``columns`` (``(K, m, N)``), numerically dependent ones dropped."""
    from scipy.linalg import qr

    k, m, n = columns.shape
    if k == 0:
        return columns
    flat = columns.reshape(k, m * n).T
    basis, triangle, _ = qr(flat, mode="economic", pivoting=True)
    diagonal = np.abs(np.diag(triangle))
    kept = int(np.sum(diagonal > 1e-13 * diagonal[0])) if diagonal.size and diagonal[0] > 0 else 0
    return np.ascontiguousarray(basis[:, :kept].T).reshape(kept, m, n)


def _units(samples: range, m: int, n: int) -> np.ndarray:
    """Unit signals at the given samples, every channel: ``(len(samples) m, m, N)``."""
    out = np.zeros((len(samples) * m, m, n))
    for index, (t, a) in enumerate((t, a) for t in samples for a in range(m)):
        out[index, a, t] = 1.0
    return out


def _corner_spaces(
    loop: LoopPlant, law: LawStructure, anticausal: bool, corrections: int
) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal ``U`` (known ranges of ``E``) and ``V`` (known co-ranges), module notes."""
    assert law.q_filter is not None
    n, d = law.n_samples, law.lead
    ns, m = loop.B.shape
    ranges = [_units(range(n - d, n), m, n)]
    if anticausal:
        A_cl = loop.A + loop.B @ loop.p1
        ranges.append(markov_blocks(A_cl, np.eye(ns), loop.p1, 0, n).transpose(2, 1, 0))  # i -> p1 A_cl^i
    coranges = [_units(range(max(d, corrections)), m, n)]
    if law.q_filter.phase is QFilterPhase.ZERO:
        system = law.q_filter.filter.realization()
        order = system.A.shape[0]
        tail = markov_blocks(system.A, system.B, np.eye(order), 0, n)[::-1, :, 0]  # j -> A^(N-1-j) B
        per_channel = np.zeros((order * m, m, n))
        for a in range(m):
            per_channel[a * order : (a + 1) * order, a, :] = tail.T
        coranges.append(per_channel)
    return _orthonormal(np.concatenate(ranges)), _orthonormal(np.concatenate(coranges))


# --- one plant's map for every scale of p2 ---------------------------------------------------------------------------


@dataclass(frozen=True)
class StructuredNorm:
    """The 2-norm of ``M`` bracketed: ``lower <= ||M||_2 <= upper`` (rigorous; ``upper`` ``inf`` when no test
    passed), ``tau`` the symbol's bound, ``tests`` the structured tests run, and whether the upper bound is the
    symbol's (the first test, at ``tau`` widened, passed with ``tau`` above the lower bound) or the edge's."""

    upper: float
    lower: float
    tau: float
    tests: int
    by_symbol: bool


@dataclass(frozen=True)
class StructuredInputMap:
    """``M(s) = T_N(a0 - s a1) + E(s)`` of one plant (module notes), precomputed for every scale ``s``.

    ``U``/``V``: orthonormal bases of ``E``'s known ranges and co-ranges; ``EtU``, ``EV``: ``E_j^T U`` and
    ``(I - P_U) E_j V`` for ``E(s) = E0 - s E1``, so ``E(s) = [U, EV0 - s EV1] [EtU0 - s EtU1, V]^T``.
    """

    operator: InputOperator
    a0: np.ndarray
    a1: np.ndarray
    symbol: SectionSymbol
    circulant: tuple[np.ndarray, np.ndarray]
    U: np.ndarray
    V: np.ndarray
    EtU: tuple[np.ndarray, np.ndarray]
    EV: tuple[np.ndarray, np.ndarray]
    structure_residual: float
    triangular: bool
    short: tuple[np.ndarray, np.ndarray]  # M0, M1 of the same law on PROXY_SAMPLES samples, dense (its edges)

    @property
    def n_samples(self) -> int:
        """``N``."""
        return (self.a0.shape[0] + 1) // 2

    def toeplitz(self, scale: float) -> ToeplitzSection:
        """``T_N(a0 - s a1)``."""
        return ToeplitzSection.of(self.a0 - scale * self.a1)

    def factors(self, scale: float) -> tuple[np.ndarray, np.ndarray]:
        """``U_E``, ``V_E`` with ``E(s) = U_E V_E^T`` (``(k, m, N)`` each)."""
        Ue = np.concatenate([self.U, self.EV[0] - scale * self.EV[1]])
        Ve = np.concatenate([self.EtU[0] - scale * self.EtU[1], self.V])
        return Ue, Ve

    def apply(self, scale: float, x: np.ndarray) -> np.ndarray:
        """``M(s) x`` as the law runs it."""
        first, second = self.operator.apply(x)
        return first - scale * second

    def adjoint(self, scale: float, y: np.ndarray) -> np.ndarray:
        """``M(s)^T y``."""
        first, second = self.operator.adjoint(y)
        return first - scale * second

    def _ratio(self, scale: float, x: np.ndarray) -> float:
        """A lower bound on the 2-norm from ``x``: the best ``||M(s) v|| / ||v||`` over ``v = x`` and
        :data:`RATIO_STEPS` power steps of ``M^T M`` from it, widened down for rounding (0 for ``x = 0``)."""
        best = 0.0
        for _ in range(RATIO_STEPS + 1):
            size = vector_norm(x)
            if not (size > 0.0 and math.isfinite(size)):
                break
            x = x / size
            image = self.apply(scale, x)
            value = vector_norm(image)
            if not math.isfinite(value):
                break
            best = max(best, value)
            x = self.adjoint(scale, image)
        return best * (1.0 - ROUNDING_MARGIN)

    def lower_bound(self, scale: float, frequency: float) -> float:
        """A rigorous lower bound on ``||M(s)||_2``: ``sigma_max(M X)`` for ``X`` the orthonormalised half-sine
        windowed sinusoids (cosine and sine, every channel) at the symbol's peak ``frequency`` (the interior's top
        singular vectors; the edges' come from the structured tests' directions)."""
        m, n = self.U.shape[1], self.n_samples
        # the half-sine envelope: a finite section's top singular vector near a smooth peak of its symbol (the
        # discrete Laplacian's first eigenvector), within about 1e-7 of the top singular value at N = 1500
        window = np.sin(np.pi * (np.arange(n) + 1.0) / (n + 1.0))
        waves = np.zeros((2 * m, m, n))
        for a in range(m):
            waves[2 * a, a] = window * np.cos(frequency * np.arange(n))
            waves[2 * a + 1, a] = window * np.sin(frequency * np.arange(n))
        image = self.apply(scale, _orthonormal(waves))
        gram = np.einsum("kat,lat->kl", image, image)  # 2m x 2m: its top eigenvalue is sigma_max^2
        top = math.sqrt(max(0.0, float(np.linalg.eigvalsh(gram)[-1]))) if np.all(np.isfinite(gram)) else math.inf
        return top * (1.0 - ROUNDING_MARGIN) if math.isfinite(top) else math.inf

    def edge_lower_bound(self, scale: float) -> float:
        """A rigorous lower bound from the short trial's map: its top right singular vector (by
        :data:`SHORT_POWER_STEPS` power steps), its first half placed at the start of the whole trial and its second
        half at the end (the edges it holds do not depend on the trial's length), then :meth:`_ratio` on the whole
        map. The products are ``einsum`` loops, not BLAS: on a loaded two-core host a threaded BLAS made the
        256 x 256 SVD this replaced take 0.24 s."""
        short = self.short[0] - scale * self.short[1]
        if not np.all(np.isfinite(short)):
            return 0.0
        m, n = self.U.shape[1], self.n_samples
        length = short.shape[1] // m
        vector = np.ones(short.shape[1])
        for _ in range(SHORT_POWER_STEPS):
            vector = np.einsum("ij,i->j", short, np.einsum("ij,j->i", short, vector))
            size = float(np.sqrt(np.einsum("i,i->", vector, vector)))
            if not (size > 0 and math.isfinite(size)):
                return 0.0
            vector /= size
        top = vector.reshape(m, length)
        x = np.zeros((1, m, n))
        half = length // 2
        x[0, :, :half] = top[:, :half]
        x[0, :, n - (length - half) :] = top[:, half:]
        return self._ratio(scale, x)

    def norm(self, scale: float, *, exact: bool = False, tests: int = FAST_TESTS) -> StructuredNorm:
        """``||M(s)||_2`` bracketed (module notes): the first test at ``max(tau, lower)`` widened by
        :data:`FIRST_WIDENING`, then a secant on the test's margin; ``exact`` narrows the bracket to
        :data:`EXACT_TOLERANCE` (more tests, with progress)."""
        tau, frequency = self.symbol.bound(scale)
        lower = max(self.lower_bound(scale, frequency), self.edge_lower_bound(scale))
        if not (math.isfinite(tau) and math.isfinite(lower)):
            return StructuredNorm(math.inf, lower, tau, 0, False)
        Ue, Ve = self.factors(scale)
        if Ue.shape[0] == 0:  # no correction: M is the Toeplitz section itself
            return StructuredNorm(tau * (1.0 + ROUNDING_MARGIN), min(lower, tau), tau, 0, True)
        circulant = self.circulant[0] - scale * self.circulant[1]
        test = NormTest.of(self.toeplitz(scale), Ue, Ve, tau, circulant)
        # above the symbol the lower bound is an edge's, from a short trial's vector: within about 1e-5 of it, so
        # the first test goes half the bracket's tolerance above it (one test where the edge sets the norm)
        widening = EXACT_TOLERANCE / 2 if exact else (FIRST_WIDENING if tau >= lower else FAST_TOLERANCE / 2)
        first = max(tau * (1.0 + FIRST_WIDENING), lower * (1.0 + widening))
        search = EdgeSearch(test, lambda x: self._ratio(scale, x), lower, exact, tests if not exact else 60)
        upper, lower = search.run(first)
        residual = self.structure_residual * max(upper, 1.0) if math.isfinite(upper) else 0.0
        upper = upper * (1.0 + ROUNDING_MARGIN) + residual
        return StructuredNorm(upper, lower, tau, search.count, search.count == 1 and tau >= lower)


def _structure_residual(
    operator: InputOperator, T: tuple[ToeplitzSection, ToeplitzSection], U: np.ndarray, V: np.ndarray
) -> float:
    """``max ||(I - P_U) E_j (I - P_V) x|| / (||M_j x'|| + ||T_j x'||)`` over two random probes ``x`` and both
    parts ``j`` (``x' = (I - P_V) x``): zero in exact arithmetic when the module notes' structure holds."""
    m, n = U.shape[1], U.shape[2]
    probes = project_out(V, np.random.default_rng(20260).standard_normal((2, m, n)))
    images = operator.apply(probes)
    worst = 0.0
    for part in (0, 1):
        toeplitz = T[part].apply(probes)
        scale = vector_norm(images[part]) + vector_norm(toeplitz)
        left = project_out(U, images[part] - toeplitz)
        worst = max(worst, vector_norm(left) / max(scale, 1e-300))
    return worst if math.isfinite(worst) else math.inf


def structured_input_map(loop: LoopPlant, law: LawStructure) -> StructuredInputMap | None:
    """The input map of ``loop`` under ``law`` (with its Q-filter) in the structured form of the module notes, for
    every scale of ``p2``; ``None`` when the map does not have that form (a fractional operator without a
    Toeplitz decomposition, an overflowing plant, or a structure probe above :data:`STRUCTURE_TOLERANCE`)."""
    from scipy.fft import fft

    assert law.q_filter is not None
    n, d = law.n_samples, law.lead
    learning = _learning_weights(law)
    if learning is None:
        return None
    weights, corrections = learning
    a0, a1 = _toeplitz_parts(loop, law, weights)
    if not (np.all(np.isfinite(a0)) and np.all(np.isfinite(a1))):
        return None
    ahead = markov_blocks(loop.A, loop.B, loop.C_measured, 0, max(d, 1))[:d]
    anticausal = law.q_filter.phase is QFilterPhase.ZERO or bool(np.any(ahead))
    if not anticausal:  # T and M are causal: the anticausal coefficients are rounding noise, exactly zero
        a0[: n - 1] = 0.0
        a1[: n - 1] = 0.0
    U, V = _corner_spaces(loop, law, anticausal, corrections)
    operator = _operator(loop, law)
    T = (ToeplitzSection.of(a0), ToeplitzSection.of(a1))
    residual = _structure_residual(operator, T, U, V)
    if not residual <= STRUCTURE_TOLERANCE:
        return None
    mt_u, m_v = operator.adjoint(U), operator.apply(V)
    EtU = (mt_u[0] - T[0].adjoint(U), mt_u[1] - T[1].adjoint(U))
    EV = (project_out(U, m_v[0] - T[0].apply(V)), project_out(U, m_v[1] - T[1].apply(V)))
    circulant = (fft(wrapped(a0, n), axis=0), fft(wrapped(a1, n), axis=0))
    symbol = SectionSymbol.of(a0, a1)
    return StructuredInputMap(
        operator, a0, a1, symbol, circulant, U, V, EtU, EV, residual, not anticausal, _short(loop, law)
    )


def _short(loop: LoopPlant, law: LawStructure) -> tuple[np.ndarray, np.ndarray]:
    """``M0`` and ``M1`` of the same law on a trial of :data:`PROXY_SAMPLES` samples (or ``N``, if shorter), dense."""
    assert law.q_filter is not None
    short = min(law.n_samples, PROXY_SAMPLES)
    short_law = LawStructure(
        law.kp, law.r, law.sample_time, short, law.lead, law.fractional_memory, law.q_filter.filter.on(short)
    )
    m = loop.B.shape[1]
    first, second = _operator(loop, short_law).apply(np.eye(m * short).reshape(m * short, m, short))
    return flat(first), flat(second)


def _operator(loop: LoopPlant, law: LawStructure) -> InputOperator:
    """The exact input map's factors (:class:`InputOperator`)."""
    assert law.q_filter is not None
    n, d = law.n_samples, law.lead
    m = loop.B.shape[1]
    A_cl = loop.A + loop.B @ loop.p1
    r = np.zeros((n, m, m))
    r[0] = np.eye(m)
    r[1:] = markov_blocks(A_cl, loop.B, loop.p1, 0, n - 1)
    z = np.zeros((n, m, m))
    z[1:] = markov_blocks(loop.A, loop.B, loop.p1, 0, n - 1)
    y = markov_blocks(loop.A, loop.B, loop.C_measured, 0, n)
    return InputOperator(
        CausalToeplitz.of(r), CausalToeplitz.of(z), CausalToeplitz.of(y), law.filter(), law.q_filter, loop.p2, d
    )


# --- the certificate -------------------------------------------------------------------------------------------------

#: ``PlantCertificate.map`` of every Q-filtered certificate.
INPUT_MAP = "input (Q-filter)"


def _verdict(norm: StructuredNorm) -> MonotoneVerdict:
    """Monotone, not monotone, or neither, from the bracket (module notes)."""
    if norm.upper <= CONTRACTION_LIMIT:
        return MonotoneVerdict.MONOTONE
    if norm.lower > CONTRACTION_LIMIT:
        return MonotoneVerdict.NOT_MONOTONE
    return MonotoneVerdict.INCONCLUSIVE


def _norm_text(norm: StructuredNorm, verdict: MonotoneVerdict, claim: BoundClaim) -> str:
    """``norm_2_method``: the method, what the number is, and the bracket behind it."""
    method = CertificateMethod.SYMBOL if norm.by_symbol or not norm.tests else CertificateMethod.STRUCTURED
    bracket = f"{norm.lower:.9g} <= ||M|| <= {norm.upper:.9g}; symbol bound {norm.tau:.9g}; {norm.tests} test(s)"
    if verdict is MonotoneVerdict.INCONCLUSIVE:
        return f"inconclusive at bound {norm.upper:.6g} ({method}; {bracket})"
    return f"{claim} ({method}; {bracket})"


def triangular_radius(smap: StructuredInputMap, scale: float) -> float:
    """The exact spectral radius of a lower block-triangular ``M``: the largest over its diagonal blocks."""
    Ue, Ve = smap.factors(scale)
    n = smap.n_samples
    blocks = np.einsum("kat,kbt->tab", Ue, Ve) + (smap.a0[n - 1] - scale * smap.a1[n - 1])
    values = np.linalg.eigvals(blocks)
    return float(np.max(np.abs(values))) if np.all(np.isfinite(values)) else math.inf


def _dense_radius(smap: StructuredInputMap, scale: float) -> float:
    """The exact spectral radius of ``M`` from its dense matrix (the exact mode's, short trials only)."""
    m, n = smap.U.shape[1], smap.n_samples
    with step("dense spectral radius of the input map", total=2) as advance:
        identity = np.eye(m * n).reshape(m * n, m, n)
        dense = flat(smap.apply(scale, identity))
        advance(1)
        values = np.linalg.eigvals(dense)
        advance(2)
    return float(np.max(np.abs(values))) if np.all(np.isfinite(values)) else math.inf


def _triangle_bound(smap: StructuredInputMap, scale: float, tau: float) -> float:
    """``tau + ||E(s)||_2``: rigorous and cheap (``E = U_E V_E^T`` through two small QR factors), and loose."""
    Ue, Ve = smap.factors(scale)
    # ||U V^T||^2 = lambda_max(U^T U V^T V): both Gram matrices are k x k
    product = inner(Ue, Ue) @ inner(Ve, Ve)
    top = float(np.max(np.abs(np.linalg.eigvals(product)))) if product.size else 0.0
    return (tau + math.sqrt(top)) * (1.0 + ROUNDING_MARGIN)


def _quick_norm(smap: StructuredInputMap, scale: float, exact: bool) -> StructuredNorm | None:
    """The 2-norm without a structured test when a lower bound above the contraction limit settles the verdict
    (not monotone) and the exact mode is off; ``None`` otherwise."""
    if exact:
        return None
    tau, frequency = smap.symbol.bound(scale)
    lower = smap.lower_bound(scale, frequency)
    if not lower > CONTRACTION_LIMIT:
        lower = max(lower, smap.edge_lower_bound(scale))
    if not lower > CONTRACTION_LIMIT:
        return None
    return StructuredNorm(max(_triangle_bound(smap, scale, tau), lower), lower, tau, 0, False)


def input_map_certificate(smap: StructuredInputMap, scale: float, *, exact: bool = False) -> PlantCertificate:
    """The certificate of ``M(s)`` (module notes): the 2-norm bracketed by the structured test (a lower bound above
    the contraction limit settles "not monotone" without one; the upper bound is then ``tau + ||E||``), the
    spectral radius exact for a causal filter and bounded by the 2-norm otherwise (exact and dense when ``exact``
    and the trial is short enough)."""
    m = smap.U.shape[1]
    norm = _quick_norm(smap, scale, exact) or smap.norm(scale, exact=exact)
    if smap.triangular:
        radius, radius_claim = triangular_radius(smap, scale), BoundClaim.EXACT
        radius_text = "exact (lower block-triangular map: its diagonal blocks)"
    elif exact and smap.n_samples * m <= EXACT_RADIUS_DENSE_LIMIT:
        radius, radius_claim, radius_text = _dense_radius(smap, scale), BoundClaim.EXACT, "dense (exact)"
    else:
        radius, radius_claim, radius_text = norm.upper, BoundClaim.UPPER, "upper bound: the induced 2-norm"
        if not radius < 1.0:
            radius_text = f"inconclusive at bound {radius:.6g} (the induced 2-norm)"
    verdict = _verdict(norm)
    exact_norm = norm.upper <= norm.lower * (1.0 + EXACT_CLAIM_TOLERANCE)
    if verdict is MonotoneVerdict.NOT_MONOTONE:
        value, claim = norm.lower, BoundClaim.LOWER
    else:
        value, claim = norm.upper, BoundClaim.EXACT if exact_norm else BoundClaim.UPPER
    method = CertificateMethod.SYMBOL if norm.by_symbol or not norm.tests else CertificateMethod.STRUCTURED
    proof = Proof(claim, radius_claim, verdict, method)
    text = _norm_text(norm, verdict, claim)
    return PlantCertificate("", INPUT_MAP, radius, value, text, radius_text, norm_2_symbol=norm.tau, proof=proof)


# --- the rescale search's estimate -----------------------------------------------------------------------------------

#: Samples of the short trial whose map stands in for the full one's edges in the rescale search.
PROXY_SAMPLES = 256
#: Power steps per estimate of the short map's norm (warm-started from the previous scale's vector).
PROXY_STEPS = 12


class EdgeProxy:
    """An estimate of ``||M(s)||_2`` for the rescale search, cheap at every scale: the larger of the symbol's bound
    ``tau(s)`` of the full trial (its interior) and the norm of the same law's map on a short trial of
    :data:`PROXY_SAMPLES` samples (its edges, which do not depend on the trial's length), by power iteration on
    its dense matrix warm-started from the last scale's vector. Not a certificate: the scale it picks is
    certified on the full trial (:func:`input_map_certificate`)."""

    def __init__(self, smap: StructuredInputMap) -> None:
        self.symbol = smap.symbol
        self.dense = smap.short
        self.vector: np.ndarray = np.random.default_rng(7).standard_normal((smap.short[0].shape[1],))

    def estimate(self, scale: float) -> float:
        """``max(tau(s), ||M_short(s) v||)`` after :data:`PROXY_STEPS` power steps (``inf`` if not finite)."""
        matrix = self.dense[0] - scale * self.dense[1]
        value = 0.0
        for _ in range(PROXY_STEPS):
            size = vector_norm(self.vector)
            if not (size > 0 and math.isfinite(size)):
                return math.inf
            image = np.einsum("ij,j->i", matrix, self.vector / size)  # not BLAS (edge_lower_bound's notes)
            value = float(np.sqrt(np.einsum("i,i->", image, image)))
            self.vector = np.einsum("ij,i->j", matrix, image)
        return max(self.symbol.bound(scale)[0], value)


#: Power steps behind the lower bound of a map without the structured form.
UNSTRUCTURED_STEPS = 8


def unstructured_certificate(loop: LoopPlant, law: LawStructure) -> PlantCertificate:
    """The certificate of a Q-filtered map without the structured form (e.g. an in-trial feedback ``p1`` that
    makes ``A + B p1`` unstable: the map then grows like its powers): a power iteration's lower bound on the exact
    operator settles "not monotone" when it is above the contraction limit; otherwise "inconclusive at bound inf"."""
    assert law.q_filter is not None
    operator = _operator(loop, law)
    x = np.random.default_rng(0).standard_normal((1, loop.B.shape[1], law.n_samples))
    lower = 0.0
    for _ in range(UNSTRUCTURED_STEPS):
        size = vector_norm(x)
        if not (size > 0 and math.isfinite(size)):
            break
        first, second = operator.apply(x / size)
        image = first - second
        value = vector_norm(image)
        if not math.isfinite(value):
            lower = math.inf
            break
        lower = max(lower, value * (1.0 - ROUNDING_MARGIN))
        first, second = operator.adjoint(image)
        x = first - second
    if lower > CONTRACTION_LIMIT:
        text = f"lower bound (power iteration on the exact map; it has no structured form): {lower:.6g}"
        proof = Proof(BoundClaim.LOWER, BoundClaim.UPPER, MonotoneVerdict.NOT_MONOTONE, CertificateMethod.SYMBOL)
        return PlantCertificate("", INPUT_MAP, math.inf, lower, text, "not computed (no structured form)", proof=proof)
    text = "inconclusive at bound inf (the input map has no Toeplitz-plus-low-rank form to certify)"
    return PlantCertificate("", INPUT_MAP, math.inf, math.inf, text, text)

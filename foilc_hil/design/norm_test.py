"""The structured exact test ``||T + U_E V_E^T||_2 < gamma`` of a Toeplitz section plus a low-rank correction, and
the search for the smallest ``gamma`` it passes at: the "structured exact" certificate of
:mod:`foilc_hil.design.qmap` (whose module notes derive it).

:class:`NormTest` decides one ``gamma`` EXACTLY: ``gamma^2 I - M^T M = D - W C W^T`` with ``D = gamma^2 I - T^T T``
positive definite above the symbol's bound ``tau``, so it is positive definite if and only if ``G^-1 - C`` is,
``G = W^T D^-1 W`` (``2 k x 2 k``), ``D^-1 W`` from preconditioned conjugate gradients and ``G`` bounded above in
the Loewner order by the residual (a one-sided test: it can only fail where the exact test passes).
:class:`EdgeSearch` runs such tests, each warm-started from the last, with Newton steps on the test's smallest
eigenvalue (increasing in ``gamma``) and the lower bound each test's direction gives, until the bracket is narrow
enough or the budget of tests is spent.

Module order: after :mod:`foilc_hil.design.map_norms` and :mod:`foilc_hil.design.toeplitz_section`, before
:mod:`foilc_hil.design.qmap`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from foilc_hil.design.lifted import vector_norm
from foilc_hil.design.map_norms import UNIT_ROUNDOFF
from foilc_hil.design.toeplitz_section import ToeplitzSection, inner, orthonormalize
from foilc_hil.progress import step

__all__ = ["CG_STEPS", "EXACT_TOLERANCE", "FAST_TOLERANCE", "EdgeSearch", "NormTest", "NormTestOutcome"]


#: Relative width of the bracket at which the default mode stops.
FAST_TOLERANCE = 1e-4


#: Relative width of the bracket at which the exact mode's search stops.
EXACT_TOLERANCE = 1e-9


#: Conjugate-gradient steps allowed per structured test.
CG_STEPS = 150


@dataclass(frozen=True)
class NormTestOutcome:
    """One structured test: passed (``||M|| < gamma``), the smallest eigenvalue of ``G^-1 - C`` for the bound of
    ``G`` (increasing in ``gamma``; negative where the test fails), whether the failure is beyond the bound's slack
    (then ``||M|| >= gamma``: a lower bound), the solution to warm-start the next test from, and the direction
    ``x = Z G^-1 y`` of that smallest eigenvalue's ``y`` (``x^T (gamma^2 I - M^T M) x = y^T (G^-1 - C) y``: the
    edge singular vector's approximation, whose ``||M x|| / ||x||`` is a lower bound)."""

    gamma: float
    passed: bool
    margin: float
    refuted: bool
    solution: np.ndarray
    direction: np.ndarray


@dataclass(frozen=True)
class NormTest:
    """The structured test of one map at one scale (:mod:`foilc_hil.design.qmap` notes): ``T``, the rank-``2k``
    correction ``W C W^T = M^T M - T^T T`` with ``W`` orthonormal, ``tau >= ||T||`` and the circulant
    preconditioner's symbol values."""

    T: ToeplitzSection
    W: np.ndarray  # (kw, m, N), orthonormal
    C: np.ndarray  # (kw, kw)
    tau: float
    circulant: np.ndarray  # (N, m, m): the symbol at the N-th roots of unity

    @classmethod
    def of(cls, T: ToeplitzSection, Ue: np.ndarray, Ve: np.ndarray, tau: float, circulant: np.ndarray) -> NormTest:
        """The test of the map ``T + U_E V_E^T`` (``W`` orthonormalised: ``C`` carries its triangle)."""
        k = Ue.shape[0]
        W = np.concatenate([Ve, T.adjoint(Ue)])
        C = np.block([[inner(Ue, Ue), np.eye(k)], [np.eye(k), np.zeros((k, k))]])
        basis, triangle = orthonormalize(W)
        return cls(T, np.ascontiguousarray(basis), triangle @ C @ triangle.T, tau, circulant)

    def _operator(self, gamma: float, x: np.ndarray) -> np.ndarray:
        """``D x = gamma^2 x - T^T T x``."""
        return gamma * gamma * x - self.T.adjoint(self.T.apply(x))

    def _preconditioner(self, gamma: float) -> Callable[[np.ndarray], np.ndarray]:
        """``(gamma^2 I - C^T C)^-1`` for the circulant ``C`` with the symbol's values (floored: it only steers), on
        real signals: the half spectrum (``rfft``; real coefficients make the rest its conjugate)."""
        from scipy.fft import irfft, rfft

        n = self.circulant.shape[0]
        half = self.circulant[: n // 2 + 1]
        m = half.shape[1]
        blocks = gamma * gamma * np.eye(m) - np.einsum("fba,fbc->fac", half.conj(), half)
        floor = 1e-12 * gamma * gamma
        if m == 1:
            inverse = 1.0 / np.maximum(blocks[:, 0, 0].real, floor)

            def apply_scalar(x: np.ndarray) -> np.ndarray:
                return np.asarray(irfft(rfft(x, axis=-1) * inverse, n=n, axis=-1))

            return apply_scalar
        inverse_blocks = np.linalg.inv(blocks + floor * np.eye(m))

        def apply_blocks(x: np.ndarray) -> np.ndarray:
            mixed = np.einsum("fab,kbf->kaf", inverse_blocks, rfft(x, axis=-1))
            return np.asarray(irfft(mixed, n=n, axis=-1))

        return apply_blocks

    def run(self, gamma: float, start: np.ndarray | None = None) -> NormTestOutcome:
        """Decide ``||M|| < gamma`` (``gamma > tau``) by conjugate gradients on ``D Z = W`` and the Loewner
        bound of ``G`` (:mod:`foilc_hil.design.qmap` notes)."""
        gap = gamma * gamma - self.tau * self.tau
        precondition = self._preconditioner(gamma)
        Z = np.zeros_like(self.W) if start is None else start.copy()
        residual = self.W - self._operator(gamma, Z)
        direction = precondition(residual)
        rz = np.einsum("kat,kat->k", residual, direction)
        for _ in range(CG_STEPS):
            if float(np.einsum("kat,kat->", residual, residual)) <= 1e-9 * gap * gap:
                break
            image = self._operator(gamma, direction)
            alpha = rz / np.maximum(np.einsum("kat,kat->k", direction, image), 1e-300)
            Z += alpha[:, None, None] * direction
            residual -= alpha[:, None, None] * image
            preconditioned = precondition(residual)
            rz_next = np.einsum("kat,kat->k", residual, preconditioned)
            direction = preconditioned + (rz_next / np.maximum(rz, 1e-300))[:, None, None] * direction
            rz = rz_next
        residual = self.W - self._operator(gamma, Z)  # recomputed: the recurrence's residual drifts
        passed, margin, refuted, combination = self._decide(gamma, Z, residual, gap)
        direction = np.einsum("k,kat->at", combination, Z)[None]
        return NormTestOutcome(gamma, passed, margin, refuted, Z, direction)

    def _decide(
        self, gamma: float, Z: np.ndarray, residual: np.ndarray, gap: float
    ) -> tuple[bool, float, bool, np.ndarray]:
        """``G^-1 - C > 0`` with ``G`` replaced by its bound ``G_hat`` from above (qmap notes); refuted when the
        smallest eigenvalue is below ``-2 slack ||G_hat^-1||^2`` (``G^-1 - G_hat^-1`` is at most about
        ``slack ||G_hat^-1||^2``: then ``G^-1 - C`` is not positive definite either)."""
        from scipy.linalg import LinAlgError, cho_factor, cho_solve

        size = self.W.shape[1] * self.W.shape[2]
        z_norm = vector_norm(Z)
        fft_error = (3 * 12.0 * math.log2(self.T.nfft) + 4) * UNIT_ROUNDOFF * (gamma**2 + self.T.l1() ** 2) * z_norm
        rho = vector_norm(residual) + fft_error
        product = inner(self.W, Z) + inner(Z, residual)
        slack = rho * rho / gap + 4.0 * size * UNIT_ROUNDOFF * z_norm * (math.sqrt(self.W.shape[0]) + rho)
        bound = 0.5 * (product + product.T) + slack * np.eye(product.shape[0])
        try:
            factor = cho_factor(bound)
        except LinAlgError:
            return False, -math.inf, False, np.zeros(bound.shape[0])
        inverse = cho_solve(factor, np.eye(bound.shape[0]))
        X = inverse - self.C
        eigenvalues, vectors = np.linalg.eigh(0.5 * (X + X.T))
        tolerance = 1e-12 * (float(np.max(np.abs(eigenvalues))) + float(np.max(np.abs(self.C), initial=0.0)))
        margin = float(eigenvalues[0])
        inverse_norm = float(np.linalg.norm(inverse, 2))
        refuted = margin < -2.0 * slack * inverse_norm * inverse_norm - tolerance
        return margin > tolerance, margin, refuted, inverse @ vectors[:, 0]


class EdgeSearch:
    """The smallest ``gamma`` the structured test passes at. After each test the direction of its smallest margin
    gives a lower bound (``||M x|| / ||x||``, by ``ratio``: at the edge singular value when the test ran near it);
    the next ``gamma`` is that lower bound widened, or a secant step up on the margin (which grows like
    ``2 gamma (gamma - ||M||)``), until the bracket is :data:`EXACT_TOLERANCE` (exact) or ``1e-5`` (fast) wide or
    ``budget`` tests have run."""

    def __init__(
        self, test: NormTest, ratio: Callable[[np.ndarray], float], lower: float, exact: bool, budget: int
    ) -> None:
        self.test = test
        self.ratio = ratio
        self.lower = lower
        self.tolerance = EXACT_TOLERANCE if exact else FAST_TOLERANCE
        self.budget = budget
        self.count = 0
        self._solution: np.ndarray | None = None

    def _run(self, gamma: float, advance: Callable[[int], None]) -> NormTestOutcome:
        """One structured test at ``gamma``, warm-started; the lower bound from its direction."""
        outcome = self.test.run(gamma, self._solution)
        self._solution = outcome.solution
        self.count += 1
        advance(self.count)
        self.lower = max(self.lower, gamma if outcome.refuted else 0.0, self.ratio(outcome.direction))
        return outcome

    def _next(self, outcome: NormTestOutcome, low: float, high: float) -> float | None:
        """The next ``gamma``, strictly between the largest failed one (or ``tau``) and the smallest passed one: a
        Newton step on the test's margin (its derivative in ``gamma`` is ``2 gamma ||x||^2`` for the direction ``x``
        of the smallest eigenvalue), overshooting a little up from a failure, else just above the lower bound, else
        the bracket's middle; ``None`` when the bracket has no room left."""
        floor = max(low, self.test.tau * (1.0 + 1e-12))
        slope = 2.0 * outcome.gamma * float(np.sum(outcome.direction**2))
        newton = outcome.gamma - outcome.margin / slope if slope > 0 and math.isfinite(outcome.margin) else math.nan
        candidates = [self.lower * (1.0 + self.tolerance / 2.0)]
        if math.isfinite(newton):
            width = abs(newton - outcome.gamma)
            candidates.insert(0, newton + (0.05 * width if not outcome.passed else 0.0) + self.tolerance * newton / 4)
        for guess in candidates:
            if floor < guess < high:
                return guess
        middle = 0.5 * (floor + high) if math.isfinite(high) else floor * (1.0 + 1e-3)
        return middle if floor < middle < high else None

    def run(self, first: float) -> tuple[float, float]:
        """``(upper, lower)``: the smallest passing ``gamma`` (``inf`` if none) and the best lower bound. The
        bracket counts as closed at ``max(lower, tau)`` (no test runs at or below the symbol's bound)."""
        with step("structured 2-norm test", total=self.budget) as advance:
            gamma: float | None = first
            high, low = math.inf, 0.0
            while gamma is not None and self.count < self.budget:
                outcome = self._run(gamma, advance)
                if outcome.passed:
                    high = gamma
                else:
                    low = gamma
                if high <= max(self.lower, self.test.tau) * (1.0 + self.tolerance):
                    break
                gamma = self._next(outcome, low, high)
            return high, self.lower

"""Linear maps on one trial given by state-space recursions: the structure NOILC and gradient ILC use at scale.

Every map these laws apply or certify -- the lifted plant ``G`` (causal), its adjoint ``G^T`` (anticausal), the
norm-optimal update (a backward costate pass, then a forward pass with the Riccati feedback), the trial-to-trial
map ``I - G_v L`` at a plant ``G_v`` -- is a product of causal and anticausal linear time-varying systems over
the ``L`` samples of a trial. Such a map ``T`` (``p`` outputs, ``m`` inputs per sample) is held as

    y_i = Cf_i x_i + Cb_i z_(i+1) + D_i w_i,
    x_0 = 0,  x_(i+1) = Af_i x_i + Bf_i w_i        (forward state: the past inputs),
    z_L = 0,  z_i = Ab_i z_(i+1) + Bb_i w_i        (backward state: the future inputs),

so its entries are ``T_ij = Cf_i Af_(i-1) ... Af_(j+1) Bf_j`` below the diagonal, ``D_i`` on it and
``Cb_i Ab_(i+1) ... Ab_(j-1) Bb_j`` above (a quasiseparable matrix). Nothing ``L x L`` is formed: applying ``T``
costs ``O(L)`` (:meth:`TrialOperator.apply`); so do its transpose, sums and products
(:meth:`TrialOperator.product`, whose cross terms are one forward and one backward recursion), and a test of
``||T||_2 < rho``: the Cholesky-type LDL^T of the dilation ``[[rho I, T], [T^T, rho I]]`` in the order of the
samples, through the generators (:func:`foilc_hil.design.lifted_kernel.dilation_positive`), ``O(L (r + 2p)^3)``
for ``r`` states in all. Bisection on ``rho`` gives the induced 2-norm from above and from below
(:meth:`TrialOperator.norm_bound`).

Rounding
--------
The LDL^T test decides positive definiteness exactly in exact arithmetic. In floating point its computed pivots
are those of a nearby matrix; the eigenvalues of the dilation are ``rho +- sigma_i(T)``, so a perturbation of the
dilation by ``E`` moves the decided ``rho`` by at most ``||E||_2``. :data:`ROUNDING_MARGIN` times ``rho`` is added
to every upper bound for that: it is not a proof (no bound of the recursion's backward error is derived here),
but it is three orders above the differences between the test's flip point and a dense SVD measured on random
plants (150 plants of 1 to 3 states, 1 or 2 channels, 0 to 2 delay samples, ``L`` up to 300: at most 1.4e-13
relative for NOILC's trial maps, 1.3e-15 for the lifted plant; ``tests/design/test_trial_operator.py`` checks the
bracket).

Module order: imports no other design module (only :mod:`foilc_hil.design.lifted_kernel`, function-locally); after
:mod:`foilc_hil.design.certificates`, before :mod:`foilc_hil.design.noilc`, which builds its maps from it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from foilc_hil.errors import InputError

__all__ = ["ROUNDING_MARGIN", "NormBound", "TrialOperator"]

#: Relative margin added to every upper bound of :meth:`TrialOperator.norm_bound` for the test's rounding (notes).
ROUNDING_MARGIN = 1e-10
#: Relative width of the bisection bracket at which :meth:`TrialOperator.norm_bound` stops by default.
NORM_TOLERANCE = 1e-6
#: Lanczos steps behind the lower bound that starts the bracket.
LANCZOS_STEPS = 12
#: The first upper bracket is the lower bound widened by this (relative), then four times more per failed test:
#: twelve Lanczos steps land 1e-3 to 2e-3 below the norm of the lifted laws' maps at N = 6000 (their top singular
#: values cluster), so one test usually brackets it.
START_WIDTH = 4e-3
#: Widenings of the bracket allowed before the norm counts as unbounded (an overflowing plant).
BRACKET_DOUBLINGS = 40
#: Dilation tests one norm may take in all (the bisection from a bracket of width one reaches 1e-13 in about 45).
BISECTION_LIMIT = 80


@dataclass(frozen=True)
class NormBound:
    """The induced 2-norm of a trial operator, bracketed: ``lower <= ||T||_2 <= upper``.

    ``upper`` is the smallest ``rho`` whose dilation test passed, plus :data:`ROUNDING_MARGIN` (``inf`` when none
    did: the operator overflows); ``lower`` the largest ``||T v||`` of a power iteration (a unit ``v``: rigorous) or
    the largest ``rho`` whose test failed (a lower bound in exact arithmetic), whichever is larger; ``estimate`` the
    geometric middle of the final bracket, without the margin. ``tests`` counts the dilation tests run.
    """

    upper: float
    lower: float
    estimate: float
    tests: int


def _norm(signal: np.ndarray) -> float:
    """The 2-norm of a whole signal (a sum of squares: BLAS's threads cost more than the sum on a busy host)."""
    return math.sqrt(float(np.einsum("ij,ij->", signal, signal)))


def _stack(*blocks: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.concatenate(blocks, axis=1), dtype=float)


def _side(*blocks: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.concatenate(blocks, axis=2), dtype=float)


def _block_diagonal(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    length, a, b = first.shape[0], first.shape[1], second.shape[1]
    out = np.zeros((length, a + b, a + b))
    out[:, :a, :a] = first
    out[:, a:, a:] = second
    return out


def _transposed(X: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.swapaxes(X, 1, 2))


@dataclass(frozen=True, eq=False)
class TrialOperator:
    """A linear map on one trial of ``L`` samples by a forward and a backward recursion (module notes).

    Attributes
    ----------
    Af, Bf, Cf
        ``(L, nf, nf)``, ``(L, nf, m)``, ``(L, p, nf)``: the forward (causal, strictly lower) part.
    Ab, Bb, Cb
        ``(L, nb, nb)``, ``(L, nb, m)``, ``(L, p, nb)``: the backward (anticausal, strictly upper) part.
    D
        ``(L, p, m)``: the diagonal blocks.
    """

    Af: np.ndarray
    Bf: np.ndarray
    Cf: np.ndarray
    Ab: np.ndarray
    Bb: np.ndarray
    Cb: np.ndarray
    D: np.ndarray

    # eq=False: compared (and hashed, as a cache key) by identity; its arrays are never compared elementwise

    @property
    def length(self) -> int:
        """``L``, samples."""
        return int(self.D.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        """``(p, m)``: outputs and inputs per sample."""
        return int(self.D.shape[1]), int(self.D.shape[2])

    @property
    def order(self) -> int:
        """States in all, forward and backward (``r`` of the cost notes)."""
        return int(self.Af.shape[1] + self.Ab.shape[1])

    @classmethod
    def identity(cls, length: int, channels: int) -> TrialOperator:
        """``I`` on ``channels`` channels."""
        none = np.zeros((length, 0, 0))
        return cls(
            none,
            np.zeros((length, 0, channels)),
            np.zeros((length, channels, 0)),
            none,
            np.zeros((length, 0, channels)),
            np.zeros((length, channels, 0)),
            np.ascontiguousarray(np.broadcast_to(np.eye(channels), (length, channels, channels))),
        )

    @classmethod
    def causal(cls, A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, length: int) -> TrialOperator:
        """The time-invariant causal system ``xi_(i+1) = A xi_i + B w_i``, ``y_i = C xi_i + D w_i``, ``xi_0 = 0``:
        the lower-triangular block Toeplitz matrix with blocks ``D, C B, C A B, ...``."""
        m, p = B.shape[1], C.shape[0]

        def each(X: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(np.broadcast_to(np.asarray(X, dtype=float), (length, *X.shape)))

        return cls(
            each(A),
            each(B),
            each(C),
            np.zeros((length, 0, 0)),
            np.zeros((length, 0, m)),
            np.zeros((length, p, 0)),
            each(D),
        )

    def transpose(self) -> TrialOperator:
        """``T^T``: the forward part becomes the backward one and back (``Ab' = Af^T``, ``Bb' = Cf^T``, ...)."""
        return TrialOperator(
            _transposed(self.Ab),
            _transposed(self.Cb),
            _transposed(self.Bb),
            _transposed(self.Af),
            _transposed(self.Cf),
            _transposed(self.Bf),
            _transposed(self.D),
        )

    def scaled(self, factor: float) -> TrialOperator:
        """``factor T``."""
        return TrialOperator(
            self.Af, self.Bf, factor * self.Cf, self.Ab, self.Bb, factor * self.Cb, factor * self.D
        )

    def plus(self, other: TrialOperator) -> TrialOperator:
        """``T + other`` (states side by side)."""
        if other.length != self.length or other.shape != self.shape:
            raise InputError(f"operators of {self.length} x {self.shape} and {other.length} x {other.shape}")
        return TrialOperator(
            _block_diagonal(self.Af, other.Af),
            _stack(self.Bf, other.Bf),
            _side(self.Cf, other.Cf),
            _block_diagonal(self.Ab, other.Ab),
            _stack(self.Bb, other.Bb),
            _side(self.Cb, other.Cb),
            self.D + other.D,
        )

    def product(self, first: TrialOperator) -> TrialOperator:
        """``self @ first`` (``first`` acts first), with the states of both.

        Below the diagonal, ``(T2 T1)_ij`` sums ``T2_ik T1_kj`` over every ``k``: the cascade of the two forward
        parts (``j < k < i``), plus ``k`` before ``j`` (``T2``'s forward state fed by ``T1``'s backward one:
        ``Y_(j+1) = Af2_j Y_j Ab1_j + Bf2_j Cb1_j``) and ``k`` after ``i`` (``T2``'s backward state fed by ``T1``'s
        forward one: ``Z_(i-1) = Bb2_i Cf1_i + Ab2_i Z_i Af1_i``), which enter the input and the output maps of the
        cascade. Above the diagonal the same for ``T1^T T2^T``, transposed (its cross terms are ``Y^T``, ``Z^T``).
        """
        from foilc_hil.design.lifted_kernel import backward_cross, forward_cross

        second = self
        if first.length != second.length or first.shape[0] != second.shape[1]:
            raise InputError(f"cannot compose {second.length} x {second.shape} after {first.length} x {first.shape}")
        Y = forward_cross(second.Af, second.Bf, first.Ab, first.Cb)
        Z = backward_cross(second.Ab, second.Bb, first.Af, first.Cf)
        Af, Bf, Cf = _lower_product(second, first, Y, Z)
        At, Bt, Ct = _lower_product(first.transpose(), second.transpose(), _transposed(Y), _transposed(Z))
        D = second.D @ first.D + second.Cf @ Y @ first.Bb + second.Cb @ Z @ first.Bf
        return TrialOperator(Af, Bf, Cf, _transposed(At), _transposed(Ct), _transposed(Bt), np.ascontiguousarray(D))

    def apply(self, signal: np.ndarray) -> np.ndarray:
        """``T w`` for ``w`` of shape ``(L, m)`` (one signal) or ``(L, m, K)`` (``K`` signals); the same shape back
        with ``p`` channels."""
        from foilc_hil.design.lifted_kernel import apply_operator

        W = np.asarray(signal, dtype=float)
        single = W.ndim == 2
        W3 = np.ascontiguousarray(W[:, :, None] if single else W)
        if W3.shape[:2] != (self.length, self.shape[1]):
            raise InputError(f"signal: must be ({self.length}, {self.shape[1]}[, K]), got {W.shape}")
        out = apply_operator(self.Af, self.Bf, self.Cf, self.Ab, self.Bb, self.Cb, self.D, W3)
        return np.asarray(out[:, :, 0] if single else out)

    def dense(self) -> np.ndarray:
        """``T`` as a dense ``(L p) x (L m)`` matrix (sample-major): for small trials and tests."""
        length, (p, m) = self.length, self.shape
        unit = np.eye(length * m).reshape(length, m, length * m)
        return np.asarray(self.apply(unit).reshape(length * p, length * m))

    def below(self, rho: float) -> bool:
        """Whether the dilation test proves ``||T||_2 < rho`` (module notes); ``T`` must be square."""
        from foilc_hil.design.lifted_kernel import dilation_positive

        if self.shape[0] != self.shape[1]:
            raise InputError(f"the norm test needs a square operator, got {self.shape}")
        return bool(
            rho > 0
            and math.isfinite(rho)
            and dilation_positive(self.Af, self.Bf, self.Cf, self.Ab, self.Bb, self.Cb, self.D, float(rho))
        )

    def lanczos_lower(self, steps: int = LANCZOS_STEPS) -> float:
        """A rigorous lower bound of ``||T||_2``: ``||T y|| / ||y||`` for the top Ritz vector ``y`` of ``T^T T`` after
        ``steps`` Lanczos steps (full reorthogonalisation). The top singular values of these Toeplitz-like maps
        cluster, and it converges slowly into the cluster: measured on NOILC's maps at N = 6000, 7e-3 below the norm
        after 6 steps, 2e-3 after 12, 1e-4 after 48 (a power iteration stays percent below)."""
        from scipy.linalg import eigh_tridiagonal

        length, m = self.length, self.shape[1]
        steps = max(1, min(steps, length * m))
        basis = np.zeros((steps, length, m))
        v = np.random.default_rng(0).standard_normal((length, m))
        transposed = self.transpose()
        alphas: list[float] = []
        betas: list[float] = []
        for j in range(steps):
            basis[j] = v / _norm(v)
            w = transposed.apply(self.apply(basis[j]))
            if not np.all(np.isfinite(w)):
                return math.inf
            alphas.append(float(np.einsum("ij,ij->", basis[j], w)))
            for _ in range(2):  # full reorthogonalisation, twice ("twice is enough")
                w = w - np.einsum("k,kij->ij", np.einsum("kij,ij->k", basis[: j + 1], w), basis[: j + 1])
            beta = _norm(w)
            if j + 1 == steps or not beta > 1e-12 * max(abs(alphas[0]), 1e-300):
                break
            betas.append(beta)
            v = w
        count = len(alphas)
        _, vectors = eigh_tridiagonal(np.array(alphas), np.array(betas[: count - 1]))
        ritz = np.einsum("k,kij->ij", vectors[:, -1], basis[:count])
        return _norm(self.apply(ritz)) / _norm(ritz) if _norm(ritz) > 0 else 0.0

    def norm_bound(self, tolerance: float = NORM_TOLERANCE, *, decide_at: float | None = None) -> NormBound:
        """``||T||_2`` bracketed by the dilation test: from a Lanczos lower bound, an upper bracket widened until a
        test passes, then bisection to ``upper / lower - 1 <= tolerance``. ``decide_at``: bisect on while the
        bracket (its upper end with the rounding margin) still straddles this value, so the verdict at it is
        settled; at most :data:`BISECTION_LIMIT` tests in all."""
        lower = self.lanczos_lower()
        tests = 0
        if not math.isfinite(lower):
            return NormBound(math.inf, math.inf, math.inf, tests)
        floor = max(lower, 1e-300)
        width = START_WIDTH
        upper = math.inf
        for _ in range(BRACKET_DOUBLINGS):
            tests += 1
            candidate = floor * (1.0 + width)
            if self.below(candidate):
                upper = candidate
                break
            floor, width = candidate, 4.0 * width
        while math.isfinite(upper) and tests < BISECTION_LIMIT:
            straddles = decide_at is not None and floor < decide_at < upper * (1.0 + ROUNDING_MARGIN)
            if upper <= floor * (1.0 + tolerance) and not straddles:
                break
            tests += 1
            middle = math.sqrt(floor * upper)
            if self.below(middle):
                upper = middle
            else:
                floor = middle
        if not math.isfinite(upper):
            return NormBound(math.inf, lower, math.inf, tests)
        floor = max(lower, floor)
        return NormBound(upper * (1.0 + ROUNDING_MARGIN), floor, math.sqrt(floor * upper), tests)


def _lower_product(
    second: TrialOperator, first: TrialOperator, Y: np.ndarray, Z: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The forward generators of ``second @ first`` (:meth:`TrialOperator.product`): the cascade state
    ``[x1; x2]`` with ``Af = [[Af1, 0], [Bf2 Cf1, Af2]]``, ``Bf = [Bf1; Bf2 D1 + Af2 Y Bb1]`` and
    ``Cf = [D2 Cf1 + Cb2 Z Af1, Cf2]``."""
    nf1 = first.Af.shape[1]
    Af = _block_diagonal(first.Af, second.Af)
    Af[:, nf1:, :nf1] = second.Bf @ first.Cf
    Bf = _stack(first.Bf, second.Bf @ first.D + second.Af @ Y @ first.Bb)
    Cf = _side(second.D @ first.Cf + second.Cb @ Z @ first.Af, second.Cf)
    return np.ascontiguousarray(Af), Bf, Cf

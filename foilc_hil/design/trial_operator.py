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
but it is four orders above the differences to a dense SVD measured on random plants (``tests/test_gradient.py``:
below 1e-13 relative at ``L <= 600``).

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
ROUNDING_MARGIN = 1e-11
#: Relative width of the bisection bracket at which :meth:`TrialOperator.norm_bound` stops by default.
NORM_TOLERANCE = 1e-10
#: Power iterations behind the lower bound that starts the bisection.
POWER_STEPS = 6
#: Doublings of the bracket's width allowed before the norm counts as unbounded (an overflowing plant).
BRACKET_DOUBLINGS = 80


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

    def power_lower(self, steps: int = POWER_STEPS) -> float:
        """A rigorous lower bound of ``||T||_2``: the largest ``||T v||`` over a power iteration's unit vectors."""
        length, m = self.length, self.shape[1]
        v = np.random.default_rng(0).standard_normal((length, m))
        transposed = self.transpose()
        best = 0.0
        for _ in range(steps):
            v /= _norm(v)
            w = self.apply(v)
            best = max(best, _norm(w))
            if not math.isfinite(best):
                return math.inf
            v = transposed.apply(w)
            if not _norm(v) > 0:
                break
        return best

    def norm_bound(self, tolerance: float = NORM_TOLERANCE, *, stop_below: float = 0.0) -> NormBound:
        """``||T||_2`` bracketed by bisection on the dilation test, to ``upper / lower - 1 <= tolerance``.

        ``stop_below``: the bisection stops as soon as an upper bound is at most this (a verdict needs no more).
        """
        lower = self.power_lower()
        tests = 0
        if not math.isfinite(lower):
            return NormBound(math.inf, math.inf, math.inf, tests)
        floor = max(lower, 1e-300)
        width = 1e-3
        upper = math.inf
        for _ in range(BRACKET_DOUBLINGS):
            tests += 1
            candidate = floor * (1.0 + width)
            if self.below(candidate):
                upper = candidate
                break
            floor, width = candidate, 2.0 * width
        while math.isfinite(upper) and upper > floor * (1.0 + tolerance) and upper > stop_below:
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

"""The compiled recursions of :mod:`foilc_hil.design.trial_operator`: numba, loaded on first use.

A trial operator (a forward and a backward state-space recursion over one trial, see that module) is applied, composed
and certified by loops over the trial's samples with small matrices at each step: in Python each step would cost
microseconds of interpreter per small product, in these kernels nanoseconds. Kept apart so that importing the design
modules never loads numba (about 0.6 s of a process's start): :mod:`foilc_hil.design.trial_operator` imports this
module inside the functions that need it. Importing it compiles the kernels, or loads them from numba's cache.

Compilation as for the other kernels: ``cache=True``, no ``fastmath`` (IEEE-exact, reproducible: the learning law
applies NOILC's and gradient ILC's update through :func:`apply_operator`, and ``replay --verify`` re-runs it bit for
bit). The small products are plain loops in a fixed order (no BLAS), so their rounding does not depend on the
machine's BLAS build.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["apply_operator", "backward_cross", "dilation_positive", "forward_cross", "noilc_riccati"]


@njit(cache=True)
def _product(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """``out = a @ b`` (2-D), plain loops."""
    for i in range(a.shape[0]):
        for j in range(b.shape[1]):
            total = 0.0
            for k in range(a.shape[1]):
                total += a[i, k] * b[k, j]
            out[i, j] = total


@njit(cache=True)
def _accumulate(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """``out += a @ b`` (2-D), plain loops."""
    for i in range(a.shape[0]):
        for j in range(b.shape[1]):
            total = 0.0
            for k in range(a.shape[1]):
                total += a[i, k] * b[k, j]
            out[i, j] += total


@njit(cache=True, inline="always")
def _advance(i: int, c: int, A: np.ndarray, B: np.ndarray, W: np.ndarray, state: np.ndarray,
             scratch: np.ndarray) -> None:
    """Column ``c`` of ``state <- A_i state + B_i w_i`` in place (through ``scratch``): one step of either sweep of
    :func:`apply_operator`, the generators indexed, not sliced (no views in the inner loop). Inlined in numba's IR
    (``inline="always"``): called as a function, the apply was 1.6-1.8x slower at N = 6000; inlined it is as fast as
    the loops written out twice, and bit-identical to them."""
    n, m = A.shape[1], B.shape[2]
    for row in range(n):
        total = 0.0
        for k in range(n):
            total += A[i, row, k] * state[k, c]
        for k in range(m):
            total += B[i, row, k] * W[i, k, c]
        scratch[row, c] = total
    for row in range(n):
        state[row, c] = scratch[row, c]


@njit(cache=True)
def apply_operator(
    Af: np.ndarray,
    Bf: np.ndarray,
    Cf: np.ndarray,
    Ab: np.ndarray,
    Bb: np.ndarray,
    Cb: np.ndarray,
    D: np.ndarray,
    W: np.ndarray,
) -> np.ndarray:
    """``Y = T W`` for ``W`` of shape ``(L, m, K)`` (``K`` signals at once): one backward pass, then one forward pass.

    ``y_i = Cf_i x_i + Cb_i z_(i+1) + D_i w_i`` with ``x_0 = 0``, ``x_(i+1) = Af_i x_i + Bf_i w_i`` and ``z_L = 0``,
    ``z_i = Ab_i z_(i+1) + Bb_i w_i`` (:class:`foilc_hil.design.trial_operator.TrialOperator`). Written out index by
    index (no views of the generators: this is the inner loop of every norm estimate).
    """
    length, m, columns = W.shape
    p, nf, nb = D.shape[1], Af.shape[1], Ab.shape[1]
    out = np.zeros((length, p, columns))
    state = np.zeros((nb, columns))
    scratch = np.zeros((nb, columns))
    for i in range(length - 1, -1, -1):
        for c in range(columns):
            for row in range(p):  # state is z_(i+1) here
                total = 0.0
                for k in range(nb):
                    total += Cb[i, row, k] * state[k, c]
                out[i, row, c] = total
            _advance(i, c, Ab, Bb, W, state, scratch)
    state = np.zeros((nf, columns))
    scratch = np.zeros((nf, columns))
    for i in range(length):
        for c in range(columns):
            for row in range(p):
                total = out[i, row, c]
                for k in range(nf):
                    total += Cf[i, row, k] * state[k, c]
                for k in range(m):
                    total += D[i, row, k] * W[i, k, c]
                out[i, row, c] = total
            _advance(i, c, Af, Bf, W, state, scratch)
    return out


@njit(cache=True)
def forward_cross(Af2: np.ndarray, Bf2: np.ndarray, Ab1: np.ndarray, Cb1: np.ndarray) -> np.ndarray:
    """``Y_0 = 0``, ``Y_(j+1) = Af2_j Y_j Ab1_j + Bf2_j Cb1_j``: the forward state of a product's second factor
    driven by the backward state of its first (:meth:`~foilc_hil.design.trial_operator.TrialOperator.product`)."""
    length = Af2.shape[0]
    Y = np.zeros((length, Af2.shape[1], Ab1.shape[1]))
    left = np.zeros((Af2.shape[1], Ab1.shape[1]))
    for j in range(length - 1):
        _product(Af2[j], Y[j], left)
        _product(left, Ab1[j], Y[j + 1])
        _accumulate(Bf2[j], Cb1[j], Y[j + 1])
    return Y


@njit(cache=True)
def backward_cross(Ab2: np.ndarray, Bb2: np.ndarray, Af1: np.ndarray, Cf1: np.ndarray) -> np.ndarray:
    """``Z_(L-1) = 0``, ``Z_(i-1) = Bb2_i Cf1_i + Ab2_i Z_i Af1_i``: the backward state of a product's second
    factor driven by the forward state of its first."""
    length = Ab2.shape[0]
    Z = np.zeros((length, Ab2.shape[1], Af1.shape[1]))
    left = np.zeros((Ab2.shape[1], Af1.shape[1]))
    for i in range(length - 1, 0, -1):
        _product(Ab2[i], Z[i], left)
        _product(left, Af1[i], Z[i - 1])
        _accumulate(Bb2[i], Cf1[i], Z[i - 1])
    return Z


@njit(cache=True)
def _cholesky(M: np.ndarray, out: np.ndarray) -> bool:
    """``M = out out^T`` with ``out`` lower triangular; ``False`` unless every pivot is positive (a NaN fails)."""
    size = M.shape[0]
    for j in range(size):
        total = M[j, j]
        for k in range(j):
            total -= out[j, k] * out[j, k]
        if not total > 0.0:
            return False
        pivot = np.sqrt(total)
        out[j, j] = pivot
        for i in range(j + 1, size):
            value = M[i, j]
            for k in range(j):
                value -= out[i, k] * out[j, k]
            out[i, j] = value / pivot
        for i in range(j):
            out[i, j] = 0.0
    return True


@njit(cache=True)
def _pivot(i: int, F: np.ndarray, Cf: np.ndarray, Bb: np.ndarray, D: np.ndarray, rho: float, FP: np.ndarray,
           pivot: np.ndarray) -> None:
    """Sample ``i``'s ``FP = F P_i^T`` and pivot ``Delta_i = d_i - P_i F P_i^T`` (:func:`dilation_positive`)."""
    p, nf, nb = D.shape[1], Cf.shape[2], Bb.shape[1]
    for row in range(nf + nb):  # FP = F P^T = [F[:, :nf] Cf^T, F[:, nf:] Bb]
        for col in range(p):
            total = 0.0
            for k in range(nf):
                total += F[row, k] * Cf[i, col, k]
            FP[row, col] = total
            total = 0.0
            for k in range(nb):
                total += F[row, nf + k] * Bb[i, k, col]
            FP[row, p + col] = total
    for row in range(p):  # - P F P^T
        for col in range(2 * p):
            total = 0.0
            for k in range(nf):
                total += Cf[i, row, k] * FP[k, col]
            pivot[row, col] = -total
            total = 0.0
            for k in range(nb):
                total += Bb[i, k, row] * FP[nf + k, col]
            pivot[p + row, col] = -total
    for row in range(p):  # + d, once every entry of P F P^T is in
        pivot[row, row] += rho
        pivot[p + row, p + row] += rho
        for col in range(p):
            pivot[row, p + col] += D[i, row, col]
            pivot[p + col, row] += D[i, row, col]


@njit(cache=True)
def _next_state(i: int, Af: np.ndarray, Bf: np.ndarray, Ab: np.ndarray, Cb: np.ndarray, F: np.ndarray,
                FP: np.ndarray, factor: np.ndarray, G: np.ndarray, H: np.ndarray, aF: np.ndarray) -> None:
    """``F <- a_i F a_i^T + G Delta_i^-1 G^T`` with ``G = Q_i - a_i F P_i^T`` (``factor``: ``Delta_i``'s Cholesky
    factor), in place (:func:`dilation_positive`)."""
    nf, nb, s = Af.shape[1], Ab.shape[1], factor.shape[0]
    p, r = s // 2, nf + nb
    for col in range(s):  # G = Q - a F P^T
        for row in range(nf):
            total = 0.0
            for k in range(nf):
                total += Af[i, row, k] * FP[k, col]
            G[row, col] = (Bf[i, row, col - p] if col >= p else 0.0) - total
        for row in range(nb):
            total = 0.0
            for k in range(nb):
                total += Ab[i, k, row] * FP[nf + k, col]
            G[nf + row, col] = (Cb[i, col, row] if col < p else 0.0) - total
    for col in range(r):  # H = factor^-1 G^T (forward substitution), so G Delta^-1 G^T = H^T H
        for row in range(s):
            value = G[col, row]
            for k in range(row):
                value -= factor[row, k] * H[k, col]
            H[row, col] = value / factor[row, row]
    for col in range(r):  # aF = a F
        for row in range(nf):
            total = 0.0
            for k in range(nf):
                total += Af[i, row, k] * F[k, col]
            aF[row, col] = total
        for row in range(nb):
            total = 0.0
            for k in range(nb):
                total += Ab[i, k, row] * F[nf + k, col]
            aF[nf + row, col] = total
    for row in range(r):  # F = aF a^T + H^T H
        for col in range(nf):
            total = 0.0
            for k in range(nf):
                total += aF[row, k] * Af[i, col, k]
            for k in range(s):
                total += H[k, row] * H[k, col]
            F[row, col] = total
        for col in range(nb):
            total = 0.0
            for k in range(nb):
                total += aF[row, nf + k] * Ab[i, k, col]
            for k in range(s):
                total += H[k, row] * H[k, nf + col]
            F[row, nf + col] = total


@njit(cache=True)
def dilation_positive(
    Af: np.ndarray,
    Bf: np.ndarray,
    Cf: np.ndarray,
    Ab: np.ndarray,
    Bb: np.ndarray,
    Cb: np.ndarray,
    D: np.ndarray,
    rho: float,
) -> bool:
    """Whether ``K = [[rho I, T], [T^T, rho I]]`` is positive definite (``||T||_2 < rho``), by its block LDL^T in
    the order of the samples (each sample's ``2p x 2p`` block), computed through ``T``'s generators.

    ``K`` (sample-interleaved) is a symmetric quasiseparable matrix: below the diagonal its block ``(i, j)`` is
    ``P_i a_(i-1) ... a_(j+1) Q_j`` with ``P_i = [[Cf_i, 0], [0, Bb_i^T]]``, ``a_k = diag(Af_k, Ab_k^T)``,
    ``Q_j = [[0, Bf_j], [Cb_j^T, 0]]``, and its diagonal block ``[[rho I, D_i], [D_i^T, rho I]]``. Its LDL^T
    (Eidelman and Gohberg's recursion) is ``Delta_j = d_j - P_j F_j P_j^T``, ``G_j = Q_j - a_j F_j P_j^T``,
    ``F_(j+1) = a_j F_j a_j^T + G_j Delta_j^-1 G_j^T`` (``F_0 = 0``): ``K`` is positive definite exactly when every
    pivot ``Delta_j`` is, which a Cholesky factorisation of each decides. The products are written out block by
    block (the zero blocks of ``P``, ``a``, ``Q`` skipped): ``O(L r^2 (r + p))`` for ``r`` states in all. A
    non-finite number fails the test.
    """
    length, p = D.shape[0], D.shape[1]
    r, s = Af.shape[1] + Ab.shape[1], 2 * p
    F = np.zeros((r, r))
    FP = np.zeros((r, s))
    pivot = np.zeros((s, s))
    factor = np.zeros((s, s))
    G = np.zeros((r, s))
    H = np.zeros((s, r))
    aF = np.zeros((r, r))
    for i in range(length):
        _pivot(i, F, Cf, Bb, D, rho, FP, pivot)
        if not _cholesky(pivot, factor):
            return False
        _next_state(i, Af, Bf, Ab, Cb, F, FP, factor, G, H, aF)
    return True


@njit(cache=True)
def noilc_riccati(
    A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, q: float, r: float, length: int
) -> tuple[np.ndarray, np.ndarray]:
    """The backward Riccati recursion of norm-optimal ILC over ``length`` samples: ``K_i`` (``m x n``) and
    ``W_i^-1`` (``m x m``) for the plant ``xi_(i+1) = A xi_i + B u_i``, ``y_i = C xi_i + D u_i`` and the cost
    ``sum_i q ||e_i - y_i||^2 + r ||u_i||^2`` (:func:`foilc_hil.design.noilc.noilc_operator`).

    ``P_L = 0``; ``W_i = q D^T D + r I + B^T P_(i+1) B``, ``K_i = W_i^-1 (q D^T C + B^T P_(i+1) A)``, and
    ``P_i = (A - B K_i)^T P_(i+1) (A - B K_i) + q (C - D K_i)^T (C - D K_i) + r K_i^T K_i`` (the symmetric,
    positive semidefinite form of the update).
    """
    n, m = A.shape[0], B.shape[1]
    gains = np.zeros((length, m, n))
    inverses = np.zeros((length, m, m))
    P = np.zeros((n, n))
    Bt, Dt = np.ascontiguousarray(B.T), np.ascontiguousarray(D.T)
    DtD, DtC = Dt @ D, Dt @ C
    for i in range(length - 1, -1, -1):
        PB = P @ B
        W = q * DtD + Bt @ PB
        for k in range(m):
            W[k, k] += r
        W = 0.5 * (W + np.ascontiguousarray(W.T))
        inverse = np.linalg.inv(W)
        K = inverse @ (q * DtC + np.ascontiguousarray(PB.T) @ A)
        closed = A - B @ K
        output = C - D @ K
        P = np.ascontiguousarray(closed.T) @ P @ closed + q * (np.ascontiguousarray(output.T) @ output)
        P = P + r * (np.ascontiguousarray(K.T) @ K)
        P = 0.5 * (P + np.ascontiguousarray(P.T))
        gains[i] = K
        inverses[i] = inverse
    return gains, inverses


# At import, compiled or loaded from numba's cache (C-contiguous float64, as the callers pass): not inside a trial.
_ONE = np.ones((1, 1, 1))
apply_operator(_ONE, _ONE, _ONE, _ONE, _ONE, _ONE, _ONE, _ONE)
forward_cross(_ONE, _ONE, _ONE, _ONE)
backward_cross(_ONE, _ONE, _ONE, _ONE)
dilation_positive(_ONE, _ONE, _ONE, _ONE, _ONE, _ONE, _ONE, 2.0)
noilc_riccati(np.ones((1, 1)), np.ones((1, 1)), np.ones((1, 1)), np.ones((1, 1)), 1.0, 1.0, 2)

"""The Arimoto P-type gain ``Gamma`` of ``u_k(t) = u_{k-1}(t) + Gamma e_{k-1}[t + d]``, and its frequency bound.

A P-type design is a :class:`~foilc_hil.design.record.Design` with ``P = (0 Gamma)``; this module only chooses
``Gamma`` (:func:`p_type_gain`). Its certificates are those of every law
(:func:`foilc_hil.design.certificates.certify_p_type`), plus :func:`frequency_bound`.

Module order: after :mod:`foilc_hil.design.models`, before :mod:`foilc_hil.design.record`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from foilc_hil.design.models import DiscreteModel
from foilc_hil.errors import ConfigError

__all__ = ["frequency_bound", "p_type_default_gain", "p_type_gain"]

#: Points of the ``[0, pi]`` frequency grid the symbol bound is taken over.
FREQUENCY_GRID = 2048
#: The default gain's frequency bound must be below this at every plant (strictly below one, with room for the
#: grid: the certificate of the lifted map, not this bound, is what certifies).
MONOTONIC_BOUND = 1.0 - 1e-6


def _first_markov(A: np.ndarray, B: np.ndarray, C: np.ndarray, input_delay: int) -> np.ndarray:
    """``C A^d B``: the first non-zero Markov parameter of a model whose ``d`` delay states are augmented."""
    return np.asarray(C @ np.linalg.matrix_power(A, input_delay) @ B, dtype=float)


def _shifted_response(A: np.ndarray, B: np.ndarray, C: np.ndarray, input_delay: int) -> np.ndarray:
    """``z^(1+d) C (zI - A)^-1 B`` at ``z = exp(j w)`` on the grid: the plant seen by a law that learns from
    ``e[t + d]``."""
    n = A.shape[0]
    z = np.exp(1j * np.linspace(0.0, math.pi, FREQUENCY_GRID))
    # every grid point's resolvent in one stacked solve (LAPACK's gesv per point, as a loop of solves would)
    resolvent = np.linalg.solve(z[:, None, None] * np.eye(n) - A, np.broadcast_to(B, (z.size, *B.shape)))
    shift = z ** (1 + input_delay)
    return np.asarray(shift[:, None, None] * (C @ resolvent), dtype=complex)


def _symbol_bound(response: np.ndarray, gamma: np.ndarray) -> float:
    """``sup_w sigma_max(I - G(w) Gamma)`` over the grid: an upper bound of the lifted ``||I - G Gamma||_2``."""
    p = response.shape[1]
    residual = np.eye(p) - response @ gamma
    if p == 1 and residual.shape[2] == 1:
        return float(np.max(np.abs(residual[:, 0, 0])))
    return float(np.max(np.linalg.norm(residual, 2, axis=(1, 2))))


def frequency_bound(model: DiscreteModel, gamma: np.ndarray) -> float:
    """``sup_w ||I - G(e^jw) Gamma||`` on the grid: bounds the induced 2-norm of the nominal P-type error map for
    every trial length (the symbol bound of a Toeplitz operator)."""
    response = _shifted_response(model.A, model.B, model.measured_output, model.input_delay)
    return _symbol_bound(response, np.asarray(gamma, dtype=float))


def _bound_minimiser(response: np.ndarray, base: np.ndarray) -> float:
    """The ``alpha`` minimising the nominal symbol bound of ``I - G alpha base`` (the fallback default)."""
    from scipy.optimize import minimize_scalar

    # The bound is convex in alpha (a supremum of norms of affine maps), equal to 1 at alpha = 0 and growing
    # without limit: bracket its minimum by doubling, then minimise on the bracket.
    upper = 1.0
    for _ in range(60):
        if _symbol_bound(response, upper * base) > 1.0:
            break
        upper *= 2.0
    found = minimize_scalar(
        lambda alpha: _symbol_bound(response, alpha * base),
        bounds=(0.0, upper),
        method="bounded",
        options={"xatol": 1e-6 * upper},
    )
    return float(found.x)


def _dc_inverse(response: np.ndarray) -> np.ndarray | None:
    """``pinv(G(1))`` when the DC gain is finite and of full rank, else ``None``."""
    dc = response[0]
    if not np.all(np.isfinite(dc)) or np.linalg.matrix_rank(dc) < min(dc.shape):
        return None
    return np.asarray(np.linalg.pinv(dc.real), dtype=float)  # G(1) is real: z = 1


def p_type_default_gain(
    A: np.ndarray,
    B: np.ndarray,
    C: np.ndarray,
    input_delay: int = 0,
    *,
    vertices: Sequence[tuple[np.ndarray, np.ndarray]] = (),
) -> np.ndarray:
    """Default Arimoto gain: DC-deadbeat, shrunk only as far as a certified monotonic contraction needs.

    The P-type error map is ``e_k = (I - G Gamma) e_{k-1}`` with ``G`` the lifted (lower-triangular block
    Toeplitz) plant; its induced 2-norm, for every trial length, is at most :func:`frequency_bound`
    ``sup_w ||I - G(e^jw) Gamma||``. On a slow plant sampled fast every gain leaves that bound close to 1 (the
    high frequencies, where ``|G|`` is small, barely move), so the 2-norm alone is a poor criterion: the gain
    minimising the nominal bound (``alpha pinv(C A^d B)``, the earlier default) buys a bound a hair lower by
    slowing the low frequencies -- where a set-point's energy is -- to a crawl, and is not robust (a larger ``B``
    pushes it above 1).

    The default is therefore ``Gamma = alpha pinv(G(1))``: the DC-deadbeat gain (the low frequencies converge in
    one trial), with ``alpha = 1`` when the frequency bound is below 1 at the nominal plant and at every
    uncertainty vertex ``(dA, dB)`` of ``vertices`` (a certified monotonic contraction everywhere), else the
    largest ``alpha`` in ``(0, 1)`` for which it is (bisection). Without such an ``alpha`` (or a finite,
    full-rank DC gain: an integrating plant), the earlier default: the ``alpha pinv(C A^d B)`` that minimises the
    nominal bound.

    ``A``, ``B`` are the (delay-augmented) model, ``C`` its MEASURED output map, ``input_delay`` its ``d``.

    Raises
    ------
    foilc_hil.errors.ConfigError
        If ``C A^d B`` is zero (the law cannot learn through this model).
    """
    markov = _first_markov(A, B, C, input_delay)
    if not np.any(markov):
        raise ConfigError("C A^d B is zero: P-type learning needs a non-zero first Markov parameter", key="plant")
    response = _shifted_response(A, B, C, input_delay)
    with np.errstate(all="ignore"):
        dc_inverse = _dc_inverse(response)
    if dc_inverse is not None:
        responses = [response] + [_shifted_response(A + dA, B + dB, C, input_delay) for dA, dB in vertices]

        def worst(alpha: float) -> float:
            return max(_symbol_bound(each, alpha * dc_inverse) for each in responses)

        if worst(1.0) < MONOTONIC_BOUND:
            return dc_inverse
        low, high = 0.0, 1.0
        for _ in range(40):  # the bound is convex in alpha and 1 at alpha = 0: bisect for the edge of "< 1"
            middle = 0.5 * (low + high)
            low, high = (middle, high) if worst(middle) < MONOTONIC_BOUND else (low, middle)
        if low > 0.0:
            return np.asarray(low * dc_inverse, dtype=float)
    base = np.linalg.pinv(markov)
    return np.asarray(_bound_minimiser(response, base) * base, dtype=float)


def p_type_gain(
    gain: float | np.ndarray | None,
    A: np.ndarray,
    B: np.ndarray,
    C: np.ndarray,
    input_delay: int = 0,
    *,
    vertices: Sequence[tuple[np.ndarray, np.ndarray]] = (),
) -> np.ndarray:
    """``Gamma`` (``m x p``) for the model ``(A, B)`` with measured output ``C`` and ``input_delay`` augmented delay
    states: a scalar ``g`` gives ``g I``, a matrix is taken as is, ``None`` the default of
    :func:`p_type_default_gain` (``law.p_type_gain``; ``vertices`` are the uncertainty vertices it certifies at)."""
    if gain is None:
        return p_type_default_gain(
            np.asarray(A, dtype=float), np.asarray(B, dtype=float), C, input_delay, vertices=vertices
        )
    if np.ndim(gain) == 0:
        return float(gain) * np.eye(np.shape(B)[1], np.shape(C)[0])
    return np.asarray(gain, dtype=float)

"""The Arimoto P-type gain ``Gamma`` of ``u_k(t) = u_{k-1}(t) + Gamma e_{k-1}[t + d]``, and its frequency bound.

A P-type design is a :class:`~foilc_hil.design.record.Design` with ``P = (0 Gamma)``; this module only chooses
``Gamma`` (:func:`p_type_gain`). Its certificates are those of every law
(:func:`foilc_hil.design.certificates.certify_p_type`), plus :func:`frequency_bound`.

Module order: after :mod:`foilc_hil.design.models`, before :mod:`foilc_hil.design.record`.
"""

from __future__ import annotations

import math

import numpy as np

from foilc_hil.design.models import DiscreteModel
from foilc_hil.errors import ConfigError

__all__ = ["frequency_bound", "p_type_default_gain", "p_type_gain"]

#: Points of the ``[0, pi]`` frequency grid the symbol bound is taken over.
FREQUENCY_GRID = 2048


def _first_markov(A: np.ndarray, B: np.ndarray, C: np.ndarray, input_delay: int) -> np.ndarray:
    """``C A^d B``: the first non-zero Markov parameter of a model whose ``d`` delay states are augmented."""
    return np.asarray(C @ np.linalg.matrix_power(A, input_delay) @ B, dtype=float)


def _shifted_response(A: np.ndarray, B: np.ndarray, C: np.ndarray, input_delay: int) -> np.ndarray:
    """``z^(1+d) C (zI - A)^-1 B`` at ``z = exp(j w)`` on the grid: the plant seen by a law that learns from
    ``e[t + d]``."""
    n = A.shape[0]
    w = np.linspace(0.0, math.pi, FREQUENCY_GRID)
    out = np.empty((w.size, C.shape[0], B.shape[1]), dtype=complex)
    for i, wi in enumerate(w):
        z = np.exp(1j * wi)
        out[i] = z ** (1 + input_delay) * (C @ np.linalg.solve(z * np.eye(n) - A, B))
    return out


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


def p_type_default_gain(A: np.ndarray, B: np.ndarray, C: np.ndarray, input_delay: int = 0) -> np.ndarray:
    """Default Arimoto gain ``Gamma = alpha * pinv(C A^d B)`` chosen for monotonic convergence.

    The P-type error map is ``e_k = (I - G Gamma) e_{k-1}`` with ``G`` the lifted (lower-triangular block
    Toeplitz) plant. Its induced 2-norm, for every trial length, is at most :func:`frequency_bound`. ``alpha``
    minimises that bound; when the minimum is below 1 the law converges monotonically in the 2-norm on the
    nominal model. The plain ``1 / (C B)`` (``alpha = 1``) would make the spectral radius zero but, on a slow
    plant sampled fast, the 2-norm large: a classic transient blow-up before convergence.

    ``A``, ``B`` are the (delay-augmented) model, ``C`` its MEASURED output map, ``input_delay`` its ``d``.

    Raises
    ------
    foilc_hil.errors.ConfigError
        If ``C A^d B`` is zero (the law cannot learn through this model).
    """
    from scipy.optimize import minimize_scalar

    markov = _first_markov(A, B, C, input_delay)
    if not np.any(markov):
        raise ConfigError("C A^d B is zero: P-type learning needs a non-zero first Markov parameter", key="plant")
    base = np.linalg.pinv(markov)
    response = _shifted_response(A, B, C, input_delay)
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
    return np.asarray(float(found.x) * base, dtype=float)


def p_type_gain(
    gain: float | np.ndarray | None, A: np.ndarray, B: np.ndarray, C: np.ndarray, input_delay: int = 0
) -> np.ndarray:
    """``Gamma`` (``m x p``) for the model ``(A, B)`` with measured output ``C`` and ``input_delay`` augmented delay
    states: a scalar ``g`` gives ``g I``, a matrix is taken as is, ``None`` the default of
    :func:`p_type_default_gain` (``law.p_type_gain``)."""
    if gain is None:
        return p_type_default_gain(np.asarray(A, dtype=float), np.asarray(B, dtype=float), C, input_delay)
    if np.ndim(gain) == 0:
        return float(gain) * np.eye(np.shape(B)[1], np.shape(C)[0])
    return np.asarray(gain, dtype=float)

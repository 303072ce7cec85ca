"""Grünwald–Letnikov / Caputo fractional derivative of a whole trial, and the fractional PD function.

The learning law (paper eq. (15), (21)) filters the tracking error of a finished trial with
``E = e + kp * D^r e``, where ``D^r`` is the Caputo derivative of order ``0 < r < 2``. A trial is a finite
sampled signal, so the derivative is computed for every sample at once.

Discretisation
--------------
The Grünwald–Letnikov (GL) sum with step ``h``,

    ``D^r g(t_n) ~= h^-r * sum_{j=0..n} w_j g(t_{n-j})``,  ``w_j = (-1)^j binom(r, j)``,

approximates the Riemann–Liouville derivative of ``g`` with error ``O(h)`` for smooth ``g`` at a fixed
``t > 0`` only: the first samples (``t_n = n h`` with small ``n``) carry an error of order ``n^-1``, not ``h``
(5-56 % relative on the first samples at any step, for ``t^alpha``-type signals), because the expansion behind
``O(h)`` needs ``t_n`` to stay fixed as ``h -> 0``. The Caputo
derivative equals the Riemann–Liouville derivative of ``f`` minus its Taylor polynomial at 0 (errata item 7):

* ``0 < r <= 1``: ``g = f - f(0)``;
* ``1 < r < 2``:  ``g = f - f(0) - f'(0) t``.

``f'(0)`` is taken from the caller (``df0``) or estimated from the samples with the second-order one-sided
difference ``(-3 f_0 + 4 f_1 - f_2) / (2 h)`` (error ``O(h^2)``; with two samples the first-order
``(f_1 - f_0) / h``; with one sample 0). Because that estimate is linear in the samples, the whole map
``f -> D^r f`` is linear and :meth:`FractionalPD.matrix` returns it exactly as a matrix.

Memory (``history``)
--------------------
:class:`FractionalPD` offers two lower terminals for that memory:

* ``history="caputo"`` (default): the Caputo derivative above, memory from the first sample of the array, with
  the correction for ``f(0)`` (and ``f'(0)``) -- the paper's literal operator over a whole trial.
* ``history="zero"``: the GL sum of ``f`` itself, i.e. the signal is taken to be zero (with zero slope) before
  the first sample: a Riemann–Liouville operator with zero history (no Caputo correction of ``f(0)``). It is
  the law's "controllable" memory (``law.fractional_memory: controllable``), not a Caputo operator.
  The operator is then a pure lower-triangular Toeplitz matrix ``I + kp h^-r T`` with diagonal
  ``1 + kp h^-r`` (invertible). For a signal that really starts from rest (``f(0) = 0``, and ``f'(0) = 0`` for
  ``r > 1``), Grünwald–Letnikov, Riemann–Liouville and Caputo agree, so both modes give the same derivative.
  The learning law uses this mode on the controllable part of the error (:mod:`foilc_hil.laws.learning`).

The sum is a *linear* (not circular) convolution of the weights with ``g``. Short signals use a direct
convolution; long ones sum the first :data:`NEAR_FIELD` weights directly and the rest by a zero-padded FFT
(:func:`foilc_hil.design.convolution.fft_convolve`: ``scipy.signal.fftconvolve``'s operations, bit for bit,
without importing ``scipy.signal``), so the FFT's rounding never dominates the small early samples (at N = 200,000,
r = 0.7, f = t^1.5: within 6.8e-11 of the direct sum at every sample, in a fraction of its time). For r > 1 the sum

itself cancels (alternating weights against a growing signal) and both methods lose digits alike. The direct sum of
a 2-D signal (the learning law's) is a compiled loop that adds the products in the order of scipy's 2-D direct
``signal.convolve``, so it equals scipy's bit for bit (``replay --verify`` of logs written with scipy needs it) at a
fifteenth of its time (numba, in :mod:`foilc_hil.design.gl_kernel`, loaded on the first 2-D call); a 1-D signal uses
scipy's 1-D direct convolution, which is ``numpy.convolve``. The third-party ``differint`` package's GL uses an
unpadded (circular) FFT and is only right at the last sample, so it is not used.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from foilc_hil.design.convolution import fft_convolve
from foilc_hil.errors import ConfigError, InputError

__all__ = [
    "FFT_THRESHOLD",
    "NEAR_FIELD",
    "FractionalPD",
    "History",
    "caputo_derivative",
    "estimate_initial_slope",
    "gl_derivative",
    "gl_weights",
]

#: Signals at least this long use the zero-padded FFT convolution; shorter ones the direct sum.
FFT_THRESHOLD = 512
#: With the FFT, the first this many weights are still summed directly (see :func:`_linear_convolution`).
NEAR_FIELD = 256

ConvolutionMethod = Literal["auto", "direct", "fft"]
#: Lower terminal of the fractional memory (module notes).
History = Literal["caputo", "zero"]


def _check_order(r: float) -> float:
    if not (isinstance(r, (int, float)) and math.isfinite(r) and 0.0 < r < 2.0):
        raise ConfigError(f"must satisfy 0 < r < 2, got {r!r}", key="r")
    return float(r)


def _check_step(h: float) -> float:
    if not (isinstance(h, (int, float)) and math.isfinite(h) and h > 0.0):
        raise ConfigError(f"must be a finite step > 0, got {h!r}", key="h")
    return float(h)


def _check_signal(f: np.ndarray | list[float], name: str) -> np.ndarray:
    array = np.asarray(f, dtype=float)
    if array.ndim not in (1, 2):
        raise InputError(f"{name}: must have shape (N,) or (N, p), got {array.shape}")
    if array.shape[0] == 0:
        raise InputError(f"{name}: must have at least one sample")
    if not np.all(np.isfinite(array)):
        raise InputError(f"{name}: must be finite (found NaN or inf)")
    return array


def gl_weights(r: float, n: int) -> np.ndarray:
    """The first ``n`` Grünwald–Letnikov weights ``w_j = (-1)^j binom(r, j)``.

    Parameters
    ----------
    r
        Derivative order; any real number is accepted here (the recurrence is exact for all ``r``).
    n
        Number of weights, ``n >= 0``.

    Returns
    -------
    numpy.ndarray
        Shape ``(n,)``, from the stable recurrence ``w_0 = 1``, ``w_j = w_{j-1} (1 - (r + 1) / j)``.
    """
    if n < 0:
        raise InputError(f"n: must be >= 0, got {n}")
    if not math.isfinite(r):
        raise ConfigError(f"must be finite, got {r!r}", key="r")
    if n == 0:
        return np.zeros(0)
    factors = np.ones(n)
    j = np.arange(1, n, dtype=float)
    factors[1:] = 1.0 - (r + 1.0) / j
    return np.cumprod(factors)


def _slope_coefficients(n: int, h: float) -> np.ndarray:
    """Row vector ``c`` with ``c @ f`` the one-sided estimate of ``f'(0)`` used by :func:`caputo_derivative`."""
    c = np.zeros(n)
    if n >= 3:
        c[:3] = np.array([-3.0, 4.0, -1.0]) / (2.0 * h)
    elif n == 2:
        c[:2] = np.array([-1.0, 1.0]) / h
    return c


def estimate_initial_slope(f: np.ndarray, h: float) -> np.ndarray | float:
    """``f'(0)`` from samples: ``(-3 f_0 + 4 f_1 - f_2) / (2 h)`` (``O(h^2)``); fewer samples: see module doc."""
    array = _check_signal(f, "f")
    coefficients = _slope_coefficients(array.shape[0], _check_step(h))
    slope = coefficients @ array
    return float(slope) if array.ndim == 1 else np.asarray(slope)


def _direct(weights: np.ndarray, g: np.ndarray) -> np.ndarray:
    """First ``len(g)`` samples of the direct linear convolution along axis 0 (1-D: scipy's, which is
    ``numpy.convolve``; 2-D: the same sums as scipy's 2-D direct method, compiled --
    :func:`foilc_hil.design.gl_kernel.direct_columns`)."""
    if g.ndim == 1:
        # scipy.signal.convolve(method="direct") of two 1-D float arrays returns numpy.convolve's result: the same
        # call, without importing scipy.signal (about 1 s of a process's start)
        return np.asarray(np.convolve(weights, g, mode="full")[: g.shape[0]])
    # Only the learning law filters 2-D signals; numba (about 0.6 s to import and start) is loaded on this first
    # use, not by every importer of this module (the design uses 1-D signals only)
    from foilc_hil.design.gl_kernel import direct_columns

    return direct_columns(np.ascontiguousarray(weights, dtype=float), np.ascontiguousarray(g, dtype=float))


def _linear_convolution(weights: np.ndarray, g: np.ndarray, method: ConvolutionMethod) -> np.ndarray:
    """First ``len(g)`` samples of the linear convolution of ``weights`` with ``g`` along axis 0."""
    n = g.shape[0]
    use_fft = method == "fft" or (method == "auto" and n >= FFT_THRESHOLD)
    if not use_fft:
        return _direct(weights, g)
    # Near field direct, far field by FFT. An FFT's rounding error is absolute, on the scale of the whole product
    # (~eps * |w| * |g|); on the first samples, where the derivative is small, that is a large relative error
    # (3.7e-6 at N = 200,000). The first NEAR_FIELD weights carry almost all of each sample's value and are summed
    # exactly as the direct method does; the far weights decay like j^(-1-r), so their FFT rounding is small
    # against every sample, and the first NEAR_FIELD samples get no FFT contribution at all.
    near = min(n, NEAR_FIELD)
    out = _direct(weights[:near], g)
    if n > near:
        # fft_convolve (scipy.signal.fftconvolve's operations) pads both operands to the full linear length: no
        # wrap-around.
        kernel = weights if g.ndim == 1 else weights[:, None]
        far = fft_convolve(kernel[near:], g[: n - near])[: n - near]
        out[near:] += far
    return out


def gl_derivative(
    f: np.ndarray | list[float], r: float, h: float, *, method: ConvolutionMethod = "auto"
) -> np.ndarray:
    """Grünwald–Letnikov derivative of order ``r`` with zero history: ``h^-r sum_{j<=n} w_j f(t_{n-j})``.

    The signal is taken to be zero before its first sample (the GL sum of the samples themselves, no Caputo
    correction). Shapes, errors and ``method`` as in :func:`caputo_derivative`.
    """
    r = _check_order(r)
    h = _check_step(h)
    samples = _check_signal(f, "f")
    if method not in ("auto", "direct", "fft"):
        raise InputError(f"method: must be 'auto', 'direct' or 'fft', got {method!r}")
    return _linear_convolution(gl_weights(r, samples.shape[0]), samples, method) * h**-r


def caputo_derivative(
    f: np.ndarray | list[float],
    r: float,
    h: float,
    *,
    df0: float | np.ndarray | None = None,
    method: ConvolutionMethod = "auto",
) -> np.ndarray:
    """Caputo derivative of order ``r`` of a sampled signal, at every sample (GL discretisation, ``O(h)``).

    Parameters
    ----------
    f
        Samples ``f(t_k)``, ``t_k = k h``, shape ``(N,)`` or ``(N, p)`` (``p`` channels along axis 1).
    r
        Order, ``0 < r < 2``.
    h
        Sample step, ``h > 0``.
    df0
        ``f'(0)`` (scalar, or shape ``(p,)``), used only for ``1 < r < 2``. ``None``: estimated from the samples
        by the second-order one-sided difference ``(-3 f_0 + 4 f_1 - f_2) / (2 h)``.
    method
        ``"direct"`` or ``"fft"`` convolution, or ``"auto"`` (FFT from :data:`FFT_THRESHOLD` samples on).

    Returns
    -------
    numpy.ndarray
        Same shape as ``f``. The value at ``t_0`` is 0 (the GL sum of ``g(0) = 0``).

    Raises
    ------
    foilc_hil.errors.ConfigError
        ``r`` outside ``(0, 2)`` or ``h <= 0`` (the message names the parameter).
    foilc_hil.errors.InputError
        ``f`` or ``df0`` not finite or of the wrong shape.
    """
    r = _check_order(r)
    h = _check_step(h)
    samples = _check_signal(f, "f")
    if method not in ("auto", "direct", "fft"):
        raise InputError(f"method: must be 'auto', 'direct' or 'fft', got {method!r}")
    n = samples.shape[0]
    g = samples - samples[0]
    if r > 1.0:
        if df0 is None:
            slope = _slope_coefficients(n, h) @ samples
        else:
            slope = np.asarray(df0, dtype=float)
            if not np.all(np.isfinite(slope)):
                raise InputError("df0: must be finite")
            expected = () if samples.ndim == 1 else (samples.shape[1],)
            if slope.shape not in (expected, ()):
                raise InputError(f"df0: must have shape {expected or 'scalar'}, got {slope.shape}")
        t = h * np.arange(n, dtype=float)
        g = g - (np.multiply.outer(t, slope) if samples.ndim == 2 else t * slope)
    weights = gl_weights(r, n)
    return _linear_convolution(weights, g, method) * h**-r


class FractionalPD:
    """The fractional PD function ``E = e + kp * D^r e`` (Caputo, GL-discretised) over a whole trial.

    Parameters
    ----------
    kp
        Gain of the fractional term, ``kp >= 0``; ``kp = 0`` is the identity (integer-order ILC, IOILC).
    r
        Order, ``0 < r < 2``.
    h
        Sample step (seconds), ``h > 0``.
    history
        ``"caputo"`` (default): Caputo derivative with memory from the first sample (corrections for ``e(0)``
        and, for ``r > 1``, ``e'(0)``). ``"zero"``: Grünwald–Letnikov with zero history before the first
        sample -- a pure lower-triangular Toeplitz operator (module notes).

    Notes
    -----
    ``f'(0)`` for ``1 < r < 2`` is always estimated from the samples here, so :meth:`apply` is linear in ``e``
    and equal to ``matrix(n) @ e`` in both modes.
    """

    def __init__(self, kp: float, r: float, h: float, history: History = "caputo") -> None:
        if not (isinstance(kp, (int, float)) and math.isfinite(kp) and kp >= 0.0):
            raise ConfigError(f"must be a finite gain >= 0, got {kp!r}", key="kp")
        if history not in ("caputo", "zero"):
            raise ConfigError(f"must be 'caputo' or 'zero', got {history!r}", key="history")
        self.kp = float(kp)
        self.r = _check_order(r)
        self.h = _check_step(h)
        self.history: History = history

    def __repr__(self) -> str:
        return f"FractionalPD(kp={self.kp!r}, r={self.r!r}, h={self.h!r}, history={self.history!r})"

    @property
    def first_weight(self) -> float:
        """``1 + kp * h^-r``: the GL sum's instantaneous gain on the newest sample (errata item 4).

        With ``history="caputo"`` the corrections subtract ``f(0)`` (and ``f'(0) t``), so the lifted matrix's
        diagonal differs from this at the first samples; from ``t_3`` on the diagonal entry is exactly this value.
        With ``history="zero"`` every diagonal entry is this value.
        """
        return 1.0 + self.kp * self.h**-self.r

    def apply(self, e: np.ndarray | list[float], *, method: ConvolutionMethod = "auto") -> np.ndarray:
        """``E = e + kp * D^r e`` for a whole trial ``e`` of shape ``(N,)`` or ``(N, p)``."""
        samples = _check_signal(e, "e")
        if self.kp == 0.0:
            return samples.copy()
        if self.history == "zero":
            return samples + self.kp * gl_derivative(samples, self.r, self.h, method=method)
        return samples + self.kp * caputo_derivative(samples, self.r, self.h, method=method)

    def matrix(self, n: int) -> np.ndarray:
        """The lifted ``(n, n)`` matrix ``M`` with ``M @ e == apply(e)`` for every ``e`` of length ``n``.

        ``history="caputo"``: ``M = I + kp h^-r T (I - 1 e_0^T - t c^T)``: ``T`` the lower-triangular Toeplitz
        matrix of GL weights, ``1 e_0^T`` removes ``e(0)``, and for ``1 < r < 2`` ``t c^T`` removes ``e'(0) t``
        with ``c`` the one-sided difference row. The correction columns make ``M`` lower triangular only up to
        its first three columns. ``history="zero"``: ``M = I + kp h^-r T``, lower-triangular Toeplitz.
        """
        from scipy.linalg import toeplitz

        if n < 1:
            raise InputError(f"n: must be >= 1, got {n}")
        identity = np.eye(n)
        if self.kp == 0.0:
            return identity
        weights = gl_weights(self.r, n)
        lower = toeplitz(weights, np.zeros(n))
        if self.history == "zero":
            return np.asarray(identity + self.kp * self.h**-self.r * lower)
        remove = identity.copy()
        remove[:, 0] -= 1.0
        if self.r > 1.0:
            t = self.h * np.arange(n, dtype=float)
            remove -= np.outer(t, _slope_coefficients(n, self.h))
        return np.asarray(identity + self.kp * self.h**-self.r * (lower @ remove))

"""Grünwald–Letnikov / Caputo derivative and the fractional PD function, against analytic truths.

Truths used (Caputo derivative, order r, m = ceil(r)):
* ``D^r t^p = Gamma(p+1) / Gamma(p+1-r) t^(p-r)`` for ``p >= m`` (terms with ``p < m`` give 0);
* series: ``exp``, ``sin``, ``cos`` are power series, so term by term
  ``D^r exp(t) = sum_{k>=m} t^(k-r) / Gamma(k+1-r)`` and likewise for ``sin``/``cos``.

GL error: for ``g = f - (Taylor polynomial of degree m-1)`` whose lowest power is ``q``, the error at sample
``t_n > 0`` is ``O(h * t_n^min(0, q-1-r))`` -- uniformly ``O(h)`` when ``q >= r + 1``. The tests check EVERY
sample against that weighted bound and check the order by halving ``h``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import gamma, rgamma

from foilc_hil.design.fractional import (
    FFT_THRESHOLD,
    NEAR_FIELD,
    FractionalPD,
    caputo_derivative,
    estimate_initial_slope,
    gl_derivative,
    gl_weights,
)
from foilc_hil.errors import ConfigError, InputError

Truth = Callable[[np.ndarray, float], np.ndarray]


def _exp_truth(t: np.ndarray, r: float) -> np.ndarray:
    m = math.ceil(r)
    return np.asarray(sum(t ** (k - r) * rgamma(k + 1 - r) for k in range(m, 60)))


def _sin_truth(t: np.ndarray, r: float) -> np.ndarray:
    m = math.ceil(r)
    terms = [(-1) ** j * t ** (2 * j + 1 - r) * rgamma(2 * j + 2 - r) for j in range(40) if 2 * j + 1 >= m]
    return np.asarray(sum(terms))


def _cos_truth(t: np.ndarray, r: float) -> np.ndarray:
    m = math.ceil(r)
    terms = [(-1) ** j * t ** (2 * j - r) * rgamma(2 * j + 1 - r) for j in range(40) if 2 * j >= m]
    return np.asarray(sum(terms))


def _weighted_error(f: Callable[[np.ndarray], np.ndarray], truth: Truth, r: float, q: int, n: int) -> float:
    """max over samples n >= 1 of |GL - truth| / t^min(0, q-1-r), divided by h; sample 0 checked apart."""
    span = 2.0
    h = span / (n - 1)
    t = np.arange(n) * h
    derivative = caputo_derivative(f(t), r, h)
    assert derivative[0] == 0.0
    weight = t[1:] ** min(0.0, q - 1 - r)
    return float(np.max(np.abs(derivative[1:] - truth(t[1:], r)) / weight) / h)


@pytest.mark.parametrize("r", [0.2, 0.5, 0.99, 1.0, 1.01, 1.5, 1.95])
@pytest.mark.parametrize(
    ("name", "f", "truth", "q_low", "q_high"),
    [
        ("exp", np.exp, _exp_truth, 1, 2),  # exp - 1 ~ t; exp - 1 - t ~ t^2/2
        ("sin", np.sin, _sin_truth, 1, 3),  # sin ~ t; sin - t ~ -t^3/6
        ("cos", np.cos, _cos_truth, 2, 2),  # cos - 1 ~ -t^2/2; cos'(0) = 0
    ],
)
def test_series_truths_every_sample_first_order(
    name: str, f: Callable[[np.ndarray], np.ndarray], truth: Truth, q_low: int, q_high: int, r: float
) -> None:
    q = q_low if r <= 1 else q_high
    coarse = _weighted_error(f, truth, r, q, 101)
    fine = _weighted_error(f, truth, r, q, 201)
    # error/h is a bounded constant (O(h) at every sample, weighted) and does not grow when h halves
    assert coarse < 20.0, name
    assert 0.8 < fine / coarse < 1.25, (name, coarse, fine)


@pytest.mark.parametrize(("r", "p"), [(0.3, 1.5), (0.5, 2.0), (0.9, 2.0), (1.2, 2.5), (1.5, 3.0), (1.9, 3.0)])
def test_power_law_uniform_first_order_convergence(r: float, p: float) -> None:
    errors = []
    for n in (101, 201, 401):
        h = 2.0 / (n - 1)
        t = np.arange(n) * h
        truth = gamma(p + 1) / gamma(p + 1 - r) * t ** (p - r)
        errors.append(np.max(np.abs(caputo_derivative(t**p, r, h) - truth)))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(np.abs(orders - 1.0) < 0.1), orders
    assert errors[-1] < 0.05


@settings(max_examples=25, deadline=None)
@given(
    r=st.floats(0.05, 1.95),
    extra=st.floats(1.0, 3.0),
    n=st.integers(40, 300),
)
def test_power_law_property(r: float, extra: float, n: int) -> None:
    """p >= r + 1: GL error at every sample is O(h); halving h roughly halves it."""
    p = r + extra
    errors = []
    for count in (n, 2 * n - 1):
        h = 1.5 / (count - 1)
        t = np.arange(count) * h
        truth = gamma(p + 1) / gamma(p + 1 - r) * t ** (p - r)
        errors.append(float(np.max(np.abs(caputo_derivative(t**p, r, h) - truth))))
    assert errors[0] < 5.0 * (1.5 / (n - 1)) * gamma(p + 1) / gamma(p - r) * 1.5 ** (p - r)
    assert 1.5 < errors[0] / errors[1] < 2.6, errors


def test_r_above_one_uses_initial_value_and_slope() -> None:
    """f = 2 + 3 t + t^3: Caputo (1 < r < 2) sees only t^3; a plain GL (Riemann-Liouville) does not."""
    r = 1.4
    n = 401
    h = 2.0 / (n - 1)
    t = np.arange(n) * h
    f = 2.0 + 3.0 * t + t**3
    truth = 6.0 / gamma(4.0 - r) * t ** (3.0 - r)
    estimated = caputo_derivative(f, r, h)
    given_slope = caputo_derivative(f, r, h, df0=3.0)
    assert np.max(np.abs(estimated - truth)) < 0.05
    # the 3-point slope of t^3 is off by exactly -2 h^2; its GL image h^-r * (w_0 t_1) = h^(1-r) peaks at t_1
    slope_error_image = 2.0 * h**2 * h ** (1.0 - r)
    assert np.max(np.abs(estimated - given_slope)) == pytest.approx(slope_error_image, rel=1e-6)
    assert np.max(np.abs(given_slope - truth)) < 0.05
    plain_gl = np.convolve(gl_weights(r, n), f)[:n] * h**-r
    assert np.max(np.abs(plain_gl - truth)) > 10.0  # the uncorrected sum is far off near t = 0


def test_initial_slope_estimate_second_order() -> None:
    errors = []
    for h in (0.01, 0.005):
        t = np.arange(5) * h
        errors.append(abs(float(estimate_initial_slope(np.sin(t + 0.3), h)) - math.cos(0.3)))
    assert abs(math.log2(errors[0] / errors[1]) - 2.0) < 0.2


def test_fft_and_direct_agree_past_threshold() -> None:
    rng = np.random.default_rng(1)
    for r in (0.4, 1.0, 1.7):
        n = FFT_THRESHOLD + 300
        signal = np.cumsum(rng.standard_normal((n, 3)), axis=0)
        direct = caputo_derivative(signal, r, 0.01, method="direct")
        fft = caputo_derivative(signal, r, 0.01, method="fft")
        assert np.max(np.abs(direct - fft)) <= 1e-10 * np.max(np.abs(direct))
        assert np.array_equal(caputo_derivative(signal, r, 0.01), fft)  # auto picks FFT when long


def test_fft_is_linear_not_circular() -> None:
    """A circular FFT wraps the tail into the head; the linear one must match the direct sum at sample 1."""
    n = 2048
    h = 1e-3
    t = np.arange(n) * h
    f = t**2
    fft = caputo_derivative(f, 0.5, h, method="fft")
    direct = caputo_derivative(f, 0.5, h, method="direct")
    assert abs(fft[1] - direct[1]) < 1e-12 * max(1.0, abs(direct[-1]))
    circular = np.fft.irfft(np.fft.rfft(gl_weights(0.5, n)) * np.fft.rfft(f - f[0]), n) * h**-0.5
    assert abs(circular[1] - direct[1]) > 1e-3  # the trap we avoid really is one


def test_vector_signal_is_columnwise() -> None:
    h = 0.01
    t = np.arange(300) * h
    columns = np.column_stack([np.sin(t), np.exp(t), t**3])
    for r in (0.6, 1.3):
        stacked = caputo_derivative(columns, r, h)
        for k in range(3):
            assert np.allclose(stacked[:, k], caputo_derivative(columns[:, k], r, h), rtol=1e-12, atol=1e-12)
        slopes = np.array([1.0, 1.0, 0.0])
        with_slopes = caputo_derivative(columns, r, h, df0=slopes)
        assert with_slopes.shape == columns.shape


def test_gl_weights_are_signed_binomials() -> None:
    from scipy.special import binom

    for r in (0.3, 1.0, 1.7):
        j = np.arange(12)
        assert np.allclose(gl_weights(r, 12), (-1.0) ** j * binom(r, j), rtol=1e-12, atol=1e-15)
    assert np.allclose(gl_weights(1.0, 4), [1.0, -1.0, 0.0, 0.0])


@settings(max_examples=30, deadline=None)
@given(
    kp=st.floats(0.0, 5.0),
    r=st.floats(0.05, 1.95),
    n=st.integers(1, 80),
    seed=st.integers(0, 2**16),
    history=st.sampled_from(["caputo", "zero"]),
)
def test_matrix_equals_apply(kp: float, r: float, n: int, seed: int, history: str) -> None:
    pd = FractionalPD(kp, r, 0.01, history=history)  # type: ignore[arg-type]
    e = np.random.default_rng(seed).standard_normal(n)
    matrix = pd.matrix(n)
    expected = pd.apply(e)
    assert np.allclose(matrix @ e, expected, rtol=1e-10, atol=1e-10 * (1 + np.max(np.abs(expected))))


def test_matrix_diagonal_and_identity() -> None:
    pd = FractionalPD(2.0, 0.7, 0.01)
    m = pd.matrix(20)
    assert np.allclose(np.diag(m)[3:], pd.first_weight)
    assert pd.first_weight == pytest.approx(1.0 + 2.0 * 0.01**-0.7)
    assert np.array_equal(FractionalPD(0.0, 1.2, 0.01).matrix(7), np.eye(7))
    e = np.arange(5.0)
    assert np.array_equal(FractionalPD(0.0, 1.2, 0.01).apply(e), e)


def test_apply_matches_derivative_definition() -> None:
    h = 0.005
    t = np.arange(400) * h
    pd = FractionalPD(0.8, 0.6, h)
    e = np.sin(3 * t) + 0.2
    assert np.allclose(pd.apply(e), e + 0.8 * caputo_derivative(e, 0.6, h), rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("r", [0.0, 2.0, -0.5, 2.5, float("nan")])
def test_bad_order_names_r(r: float) -> None:
    with pytest.raises(ConfigError, match="r: must satisfy 0 < r < 2"):
        caputo_derivative([0.0, 1.0], r, 0.1)
    with pytest.raises(ConfigError, match="r:"):
        FractionalPD(1.0, r, 0.1)


def test_bad_inputs_are_named() -> None:
    with pytest.raises(ConfigError, match="h:"):
        caputo_derivative([0.0, 1.0], 0.5, 0.0)
    with pytest.raises(ConfigError, match="kp:"):
        FractionalPD(-1.0, 0.5, 0.1)
    with pytest.raises(InputError, match="f: must be finite"):
        caputo_derivative([0.0, float("nan")], 0.5, 0.1)
    with pytest.raises(InputError, match="e: must be finite"):
        FractionalPD(1.0, 0.5, 0.1).apply([float("inf"), 1.0])
    with pytest.raises(InputError, match="df0"):
        caputo_derivative([0.0, 1.0, 2.0], 1.5, 0.1, df0=float("nan"))
    with pytest.raises(InputError, match="shape"):
        caputo_derivative(np.zeros((2, 2, 2)), 0.5, 0.1)
    assert issubclass(ConfigError, ValueError)


# --- zero history (the law's operator on the controllable samples) ------------------------------------------------


@pytest.mark.parametrize("r", [0.3, 0.8, 1.0, 1.4, 1.9])
def test_zero_history_is_the_plain_gl_convolution(r: float) -> None:
    """Second method: the GL sum written out with scipy's binomials, no shared code with the module."""
    from scipy.special import binom

    h, n = 0.02, 60
    f = np.random.default_rng(3).standard_normal(n) + 1.0  # f(0) != 0: no Caputo correction may be applied
    expected = np.array([sum((-1) ** j * binom(r, j) * f[i - j] for j in range(i + 1)) for i in range(n)]) * h**-r
    np.testing.assert_allclose(gl_derivative(f, r, h), expected, rtol=1e-10, atol=1e-10 * np.max(np.abs(expected)))
    pd = FractionalPD(0.7, r, h, history="zero")
    np.testing.assert_allclose(pd.apply(f), f + 0.7 * expected, rtol=1e-10, atol=1e-10 * np.max(np.abs(expected)))
    # Caputo differs on this signal (it subtracts f(0)): the modes are really different operators.
    assert np.max(np.abs(FractionalPD(0.7, r, h).apply(f) - pd.apply(f))) > 1e-3


@pytest.mark.parametrize("r", [0.4, 1.0, 1.3, 1.8])
def test_zero_history_equals_caputo_for_a_signal_starting_from_rest(r: float) -> None:
    """f(0) = 0 and f'(0) = 0: GL = Riemann-Liouville = Caputo, at every sample."""
    h, n = 0.01, 300
    t = np.arange(n) * h
    f = t**2 * np.sin(3 * t) + 0.5 * t**3  # f(0) = 0, f'(0) = 0
    caputo = caputo_derivative(f, r, h, df0=0.0)
    zero = gl_derivative(f, r, h)
    np.testing.assert_allclose(zero, caputo, rtol=1e-12, atol=1e-12 * np.max(np.abs(caputo)))
    if r <= 1.0:  # no slope correction: FractionalPD's Caputo mode agrees as well
        np.testing.assert_allclose(
            FractionalPD(0.5, r, h, history="zero").apply(f), FractionalPD(0.5, r, h).apply(f), rtol=1e-12, atol=1e-12
        )
    assert np.max(np.abs(zero)) > 0.1  # not a vacuous comparison of zeros


@pytest.mark.parametrize(("r", "p"), [(0.3, 1.5), (0.7, 2.0), (1.2, 2.5), (1.6, 3.0)])
def test_zero_history_power_law_first_order(r: float, p: float) -> None:
    """t^p with p >= r + 1 (and p >= 2 for r > 1) starts from rest: D^r t^p = Gamma(p+1)/Gamma(p+1-r) t^(p-r)."""
    errors = []
    for n in (101, 201, 401):
        h = 2.0 / (n - 1)
        t = np.arange(n) * h
        truth = gamma(p + 1) / gamma(p + 1 - r) * t ** (p - r)
        errors.append(np.max(np.abs(gl_derivative(t**p, r, h) - truth)))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(np.abs(orders - 1.0) < 0.1), orders
    assert errors[-1] < 0.05


def test_zero_history_matrix_is_lower_triangular_toeplitz_with_the_first_weight() -> None:
    pd = FractionalPD(2.0, 1.3, 0.01, history="zero")
    m = pd.matrix(25)
    np.testing.assert_allclose(np.diag(m), pd.first_weight, rtol=1e-14)
    assert np.all(np.triu(m, 1) == 0)
    for k in range(1, 25):  # constant along every subdiagonal
        np.testing.assert_allclose(np.diag(m, -k), np.diag(m, -k)[0], rtol=1e-13)
    with pytest.raises(ConfigError, match="history"):
        FractionalPD(1.0, 0.5, 0.1, history="riemann")  # type: ignore[arg-type]


@pytest.mark.parametrize(("r", "p"), [(0.3, 0.5), (0.7, 1.5), (0.9, 3.0)])
def test_long_fft_keeps_every_sample_to_1e9_of_the_direct_sum(r: float, p: float) -> None:
    """The FFT path on a long trial: every sample within 1e-9 (relative) of the direct linear convolution, and the
    first NEAR_FIELD samples are direct sums, equal to rounding (the FFT's absolute rounding never reaches them)."""
    n, h = 20_000, 1e-3
    f = (np.arange(n) * h) ** p
    fast = gl_derivative(f, r, h, method="fft")
    exact = gl_derivative(f, r, h, method="direct")
    nonzero = exact != 0.0
    relative = np.abs(fast[nonzero] - exact[nonzero]) / np.abs(exact[nonzero])
    assert relative.max() <= 1e-9
    np.testing.assert_allclose(fast[:NEAR_FIELD], exact[:NEAR_FIELD], rtol=1e-12, atol=0.0)


def _rising_factorial_sequence(c: float, n: int) -> np.ndarray:
    """``Gamma(k + c) / (Gamma(c) k!)`` for ``k = 0..n-1``: the coefficients of ``(1 - z)^-c``, by their ratio
    recurrence (relative rounding about ``k`` eps, 1e-12 at the lengths used here)."""
    k = np.arange(1, n, dtype=float)
    return np.concatenate([[1.0], np.cumprod((k - 1.0 + c) / k)])


@pytest.mark.parametrize(("r", "b"), [(0.3, 1.0), (0.5, 2.0), (0.7, 2.5), (0.9, 0.6), (1.3, 2.5), (1.6, 1.0)])
def test_fft_path_matches_the_discrete_analytic_derivative_at_every_sample(r: float, b: float) -> None:
    """The GL sum is the convolution with the coefficients of ``(1 - z)^r``, so for ``f_k`` the coefficients of
    ``(1 - z)^-b`` (a discrete ``t^(b-1) / Gamma(b)``) it is exactly the coefficients of ``(1 - z)^(r-b)`` times
    ``h^-r``: an analytic truth for every sample, independent of how the sum is computed. The long-trial path
    (near field direct, far field by FFT) stays within 1e-9 of it at every sample."""
    n, h = 3 * FFT_THRESHOLD + 17, 1e-3
    f = _rising_factorial_sequence(b, n)
    truth = _rising_factorial_sequence(b - r, n) * h**-r
    got = gl_derivative(f, r, h)  # auto: the FFT path at this length
    relative = np.abs(got - truth) / np.abs(truth)
    assert relative.max() <= 1e-9, f"worst sample {relative.argmax()}: {relative.max():.2e}"


@pytest.mark.parametrize(
    ("n", "p", "r"), [(1, 1, 0.7), (5, 2, 1.3), (NEAR_FIELD + 3, 1, 0.7), (FFT_THRESHOLD + 40, 3, 1.6)]
)
def test_compiled_direct_sum_rounds_as_scipys_2d_direct_convolution(n: int, p: int, r: float) -> None:
    """The 2-D near field (and short direct path) is a compiled loop; logs written with scipy's 2-D direct
    ``signal.convolve`` must still replay bit for bit, so every sample equals scipy's to the last bit (float64 bytes,
    ``-0.0`` included), with and without the FFT far field."""
    from scipy import signal as scipy_signal

    rng = np.random.default_rng(n + p)
    g = rng.standard_normal((n, p)) * 10.0 ** rng.integers(-8, 8, size=(n, p))
    g[::7] = -0.0
    weights = gl_weights(r, n)
    kernel = weights[:, None]
    near = min(n, NEAR_FIELD)
    scipy_direct = scipy_signal.convolve(kernel, g, mode="full", method="direct")[:n] * 1e-3**-r
    direct = gl_derivative(g, r, 1e-3, method="direct")
    assert direct.tobytes() == scipy_direct.tobytes()
    # the old long path: scipy's 2-D direct near field plus the same FFT far field
    old = scipy_signal.convolve(kernel[:near], g, mode="full", method="direct")[:n]
    if n > near:
        old[near:] += scipy_signal.fftconvolve(kernel[near:], g[: n - near], mode="full", axes=0)[: n - near]
    assert gl_derivative(g, r, 1e-3, method="fft").tobytes() == (old * 1e-3**-r).tobytes()

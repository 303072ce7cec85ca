"""The Q-filter: zero-phase and causal, its matrix, its realization and the one constructor law and design share."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from foilc_hil.config import LawConfig, QFilterConfig, QFilterPhase, load_config
from foilc_hil.design.qfilter import FilterRealization, QFilter
from foilc_hil.errors import ConfigError

TS = 0.001
NYQUIST = np.pi / TS


def _toeplitz_of(impulse: np.ndarray) -> np.ndarray:
    """The lower-triangular Toeplitz matrix of a causal impulse response."""
    from scipy.linalg import toeplitz

    return np.asarray(toeplitz(impulse, np.zeros_like(impulse)))


def _impulse(system: FilterRealization, n: int) -> np.ndarray:
    """``h_0 = D``, ``h_k = C A^(k-1) B``, by stepping the state (not by the filter's own code)."""
    state = np.zeros(system.A.shape[0])
    out = np.zeros(n)
    for t in range(n):
        u = 1.0 if t == 0 else 0.0
        out[t] = float(system.C[0] @ state + system.D[0, 0] * u)
        state = system.A @ state + system.B[:, 0] * u
    return out


@pytest.mark.parametrize("order", [1, 2, 4])
@pytest.mark.parametrize("fraction", [0.02, 0.2, 0.45])
def test_the_realization_is_one_pass_of_the_filter(order: int, fraction: float) -> None:
    """The state-space form the structured certificates use has the impulse response of scipy's own Butterworth
    (``lfilter`` on the transfer function: a second method), and ``apply`` is ``H`` (causal) or ``H^T H`` (zero)."""
    n = 120
    causal = QFilter(fraction * NYQUIST, order, TS, QFilterPhase.CAUSAL)
    zero = QFilter(fraction * NYQUIST, order, TS)
    system = causal.realization()
    impulse = _impulse(system, n)
    b, a = signal.butter(order, fraction, btype="low")
    unit = np.zeros(n)
    unit[0] = 1.0
    np.testing.assert_allclose(impulse, signal.lfilter(b, a, unit), atol=1e-9)
    H = _toeplitz_of(impulse)
    np.testing.assert_allclose(causal.matrix(n), H, atol=1e-12)
    np.testing.assert_allclose(zero.matrix(n), H.T @ H, atol=1e-12)
    u = np.random.default_rng(order).standard_normal((n, 2))
    np.testing.assert_allclose(causal.apply(u), H @ u, atol=1e-12)
    np.testing.assert_allclose(zero.apply(u), H.T @ H @ u, atol=1e-12)


@pytest.mark.parametrize("phase", list(QFilterPhase))
def test_neither_phase_amplifies(phase: QFilterPhase) -> None:
    for order, fraction in [(1, 0.05), (2, 0.2), (4, 0.02), (8, 0.45)]:
        Q = QFilter(fraction * NYQUIST, order, TS, phase).matrix(300)
        assert np.linalg.norm(Q, 2) <= 1.0 + 1e-12


def test_the_law_and_the_design_build_the_same_filter() -> None:
    """``QFilter.of`` is the one constructor: the law's filter and the certificates' are the same operator."""
    from foilc_hil.config import LawKind
    from foilc_hil.design.pipeline import law_structure

    section = {"cutoff": 0.2 * NYQUIST, "order": 2, "phase": "causal"}
    config = load_config(
        None,
        {"plant.a": -1.0, "plant.b": 1.0, "sample_time": TS, "law.q_filter": section, "law.p_type_gain": 0.5},
    )
    structure = law_structure(config, LawKind.P_TYPE, 50, input_delay=1)
    assert structure.q_filter is not None
    law_filter = QFilter.of(LawConfig(q_filter=QFilterConfig(**section)).q_filter, TS)  # type: ignore[arg-type]
    np.testing.assert_array_equal(structure.q_filter.matrix(), law_filter.matrix(50))
    np.testing.assert_array_equal(np.asarray(structure.q_filter), law_filter.matrix(50))  # the array protocol
    assert structure.q_filter.phase is QFilterPhase.CAUSAL


def test_a_bad_phase_names_its_key() -> None:
    with pytest.raises(ConfigError, match=r"law\.q_filter\.phase"):
        QFilter(100.0, 2, TS, "backward")
    with pytest.raises(ConfigError, match="phase"):
        load_config(None, {"law.q_filter": {"cutoff": 100.0, "phase": "backward"}})

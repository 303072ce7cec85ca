"""Discretisation (ZOH, Euler), input-delay augmentation and the discrete uncertainty."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import signal

from foilc_hil.design.certificates import certify_as_given
from foilc_hil.design.lifted import LawStructure
from foilc_hil.design.models import (
    DiscreteModel,
    Uncertainty,
    augment_input_delay,
    discretize,
    uncertainty_from_config,
)
from foilc_hil.design.record import Design
from foilc_hil.errors import ConfigError, InputError
from plant_emulator.config import UncertaintyConfig
from plant_emulator.linear import ContinuousModel


def _scalar(a: float, b: float) -> ContinuousModel:
    return ContinuousModel(np.array([[a]]), np.array([[b]]), np.array([[1.0]]))


@pytest.mark.parametrize("ts", [0.01, 0.001, 0.5])
def test_zoh_scalar_matches_the_analytic_formula(ts: float) -> None:
    a, b = -1.23, 1.68
    model = discretize(_scalar(a, b), ts, "zoh")
    assert model.A[0, 0] == pytest.approx(np.exp(a * ts), rel=1e-13)
    assert model.B[0, 0] == pytest.approx(b / a * (np.exp(a * ts) - 1.0), rel=1e-12)


def test_zoh_mimo_matches_scipy_cont2discrete() -> None:
    rng = np.random.default_rng(3)
    a = rng.standard_normal((3, 3))
    b = rng.standard_normal((3, 2))
    c = rng.standard_normal((2, 3))
    model = discretize(ContinuousModel(a, b, c), 0.05, "zoh")
    Ad, Bd, Cd, _, _ = signal.cont2discrete((a, b, c, np.zeros((2, 2))), 0.05, method="zoh")
    np.testing.assert_allclose(model.A, Ad, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(model.B, Bd, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(model.C, Cd)


def test_euler_is_identity_plus_a_ts_and_differs_from_zoh() -> None:
    euler = discretize(_scalar(-1.23, 1.68), 0.1, "euler")
    zoh = discretize(_scalar(-1.23, 1.68), 0.1, "zoh")
    assert euler.A[0, 0] == pytest.approx(1.0 - 0.123)
    assert euler.B[0, 0] == pytest.approx(0.168)
    assert abs(euler.A[0, 0] - zoh.A[0, 0]) > 1e-3
    # Errata 1: the paper's A = a - I is Euler with Ts = 1.
    assert discretize(_scalar(-1.23, 1.68), 1.0, "euler").A[0, 0] == pytest.approx(-1.23 + 1.0)


def test_bad_inputs_name_the_culprit() -> None:
    with pytest.raises(InputError, match="sample_time"):
        discretize(_scalar(-1.0, 1.0), 0.0)
    with pytest.raises(InputError, match="method"):
        discretize(_scalar(-1.0, 1.0), 0.1, "tustin")  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"^B: must have 2 rows"):
        DiscreteModel(np.eye(2), np.ones((3, 1)), np.ones((1, 2)), 0.1)
    with pytest.raises(InputError, match=r"^C: must have 2 columns"):
        DiscreteModel(np.eye(2), np.ones((2, 1)), np.ones((1, 3)), 0.1)
    with pytest.raises(InputError, match=r"^A: must be finite"):
        DiscreteModel(np.array([[np.nan]]), np.ones((1, 1)), np.ones((1, 1)), 0.1)


def _simulate(A: np.ndarray, B: np.ndarray, C: np.ndarray, u: np.ndarray, delay: int = 0) -> np.ndarray:
    """y(t) = C x(t), x(t+1) = A x(t) + B u(t - delay), x(0) = 0."""
    x = np.zeros(A.shape[0])
    out = []
    for t in range(u.shape[0]):
        out.append(C @ x)
        applied = u[t - delay] if t - delay >= 0 else np.zeros(B.shape[1])
        x = A @ x + B @ applied
    return np.array(out)


@pytest.mark.parametrize("delay", [1, 2, 3])
def test_delay_augmentation_reproduces_the_delayed_plant(delay: int) -> None:
    rng = np.random.default_rng(delay)
    base = DiscreteModel(
        rng.standard_normal((2, 2)) * 0.5, rng.standard_normal((2, 2)), rng.standard_normal((1, 2)), 0.1
    )
    augmented, _ = augment_input_delay(base, delay)
    u = rng.standard_normal((40, 2))
    y_plant = _simulate(base.A, base.B, base.C, u, delay)
    y_measured = _simulate(augmented.A, augmented.B, augmented.measured_output, u)
    np.testing.assert_allclose(y_measured, y_plant, atol=1e-12)
    # The design output is the d-step-ahead output: C z(t) = y(t + d).
    y_ahead = _simulate(augmented.A, augmented.B, augmented.C, u)
    np.testing.assert_allclose(y_ahead[: 40 - delay], y_plant[delay:], atol=1e-12)
    assert augmented.input_delay == delay
    assert augmented.n_states == 2 + 2 * delay


def test_delay_augmentation_pads_uncertainty_into_separate_channels() -> None:
    base = DiscreteModel(np.array([[0.9]]), np.array([[0.1]]), np.array([[1.0]]), 0.01)
    unc = Uncertainty(np.array([[0.05]]), np.array([[1.0]]), np.array([[0.02]]), np.array([[1.0]]))
    augmented, padded = augment_input_delay(base, 1, unc)
    channels = padded.channels()
    assert [kind for kind, _, _ in channels] == ["state", "state"]
    # dA acts on x; the delayed dB acts on the delay slot u(t-1).
    np.testing.assert_allclose(channels[0][1] @ channels[0][2], [[0.05, 0.0], [0.0, 0.0]])
    np.testing.assert_allclose(channels[1][1] @ channels[1][2], [[0.0, 0.02], [0.0, 0.0]])
    assert augmented.B.tolist() == [[0.0], [1.0]]


def test_no_delay_returns_the_model_unchanged() -> None:
    base = DiscreteModel(np.array([[0.9]]), np.array([[0.1]]), np.array([[1.0]]), 0.01)
    model, unc = augment_input_delay(base, 0)
    assert model is base
    assert unc.is_zero


def test_uncertainty_from_config_defaults_and_errors() -> None:
    none = uncertainty_from_config(UncertaintyConfig(), 2, 1)
    assert none.is_zero and none.G1.shape == (2, 1) and none.H2.shape == (1, 1)
    given = uncertainty_from_config(UncertaintyConfig(G1=[[0.1], [0.0]], H1=[[1.0, 0.0]]), 2, 1)
    assert not given.is_zero
    with pytest.raises(ConfigError, match=r"plant\.uncertainty\.H1"):
        uncertainty_from_config(UncertaintyConfig(G1=[[0.1], [0.0]]), 2, 1)
    with pytest.raises(ConfigError, match=r"plant\.uncertainty\.G2: must have 2 rows"):
        uncertainty_from_config(UncertaintyConfig(G2=[[0.1]], H2=[[1.0]]), 2, 1)
    with pytest.raises(ConfigError, match=r"plant\.uncertainty\.H2: must have 1 columns"):
        uncertainty_from_config(UncertaintyConfig(G2=[[0.1], [0.0]], H2=[[1.0, 1.0]]), 2, 1)


def _design(**overrides: object) -> Design:
    A, B, C = np.array([[0.9, 0.1], [0.0, 0.0]]), np.array([[0.0], [1.0]]), np.array([[0.9, 0.1]])
    model = DiscreteModel(A, B, C, 0.01, input_delay=1, C_measured=np.array([[1.0, 0.0]]))
    uncertainty = Uncertainty(np.zeros((2, 1)), np.zeros((1, 2)), np.zeros((2, 1)), np.zeros((1, 1)))
    P = np.array([[-1.0, 0.5, 2.0]])
    law = LawStructure(kp=0.1, r=0.9, sample_time=0.01, n_samples=20, lead=1)
    fields: dict[str, object] = {
        "law": "foilc",
        "model": model,
        "uncertainty": uncertainty,
        "P": P,
        "Qb": np.eye(2),
        "Qt": [[1.0]],
        "gamma": 1.5,
        "tau": 0.8,
        "theta": 0.7,
        "kp": 0.1,
        "r": 0.9,
        "gain_scale": 0.25,
        "certificates": certify_as_given(model, uncertainty, P, law, require_monotonic=True),
    }
    fields.update(overrides)
    return Design(**fields)  # type: ignore[arg-type]


def test_design_json_round_trip_is_exact() -> None:
    design = _design()
    document = json.loads(json.dumps(design.to_json()))
    again = Design.from_json(document)
    assert again.to_json() == design.to_json()
    np.testing.assert_array_equal(again.p1, [[-1.0, 0.5]])
    np.testing.assert_array_equal(again.p2, [[2.0]])
    assert again.error_lead == 1
    np.testing.assert_array_equal(again.measured_output, [[1.0, 0.0]])


def test_design_validation_names_the_field() -> None:
    with pytest.raises(InputError, match=r"design\.P: must be 1x3"):
        _design(P=[[1.0, 2.0]])
    with pytest.raises(InputError, match=r"design\.law"):
        _design(law="pid")
    with pytest.raises(InputError, match=r"design\.C_measured: is required"):
        Design.from_json({k: v for k, v in _design().to_json().items() if k != "C_measured"})
    with pytest.raises(InputError, match=r"design: Qb, Qt, gamma, tau, theta are given together"):
        _design(gamma=None)
    with pytest.raises(InputError, match=r"design\.gamma: is required"):
        Design.from_json({k: v for k, v in _design().to_json().items() if k != "gamma"})

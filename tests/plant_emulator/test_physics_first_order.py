"""The first-order plant (paper eq. 48) against independent truths: analytic solutions, scipy's lsim, and a
fine-step Runge-Kutta solution of the time-varying equation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal
from scipy.integrate import solve_ivp

from foilc_hil.errors import ConfigError, InputError
from plant_emulator.config import DisturbanceConfig, PlantConfig, VariationConfig
from plant_emulator.physics import Plant, build_plant
from plant_emulator.physics.disturbance import Disturbance
from plant_emulator.physics.first_order import FirstOrderPlant
from plant_emulator.physics.variation import VariationSignal

A, B = -1.23, 1.68


def _scalar(**fields: object) -> PlantConfig:
    return PlantConfig.model_validate({"a": A, "b": B, "c": 1.0, **fields})


def test_first_order_plant_satisfies_the_protocol() -> None:
    plant = build_plant(_scalar())
    assert isinstance(plant, Plant)
    assert (plant.n_inputs, plant.n_outputs) == (1, 1)


def test_scalar_step_response_matches_the_analytic_solution_at_every_sample() -> None:
    x0, u, dt = 0.5, 2.0, 0.01
    plant = build_plant(_scalar(x0=[x0]))
    plant.reset(1)
    assert plant.output()[0] == pytest.approx(x0, abs=1e-15)
    for k in range(1, 301):
        y = plant.step(np.array([u]), dt)[0]
        t = k * dt
        expected = x0 * math.exp(A * t) + B / A * (math.exp(A * t) - 1.0) * u
        assert y == pytest.approx(expected, rel=1e-12, abs=1e-13), f"sample {k}"
        assert plant.time == pytest.approx(t, rel=1e-12)


def test_mimo_response_matches_scipy_lsim_with_zero_order_hold() -> None:
    a = np.array([[-1.0, 0.5, 0.0], [0.0, -2.0, 1.0], [0.2, 0.0, -0.7]])
    b = np.array([[1.0, 0.0], [0.0, 2.0], [0.5, -1.0]])
    c = np.array([[1.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    x0 = [0.1, -0.2, 0.3]
    dt, steps = 0.02, 150
    inputs = np.random.default_rng(7).uniform(-1, 1, size=(steps, 2))
    plant = build_plant(PlantConfig(a=a.tolist(), b=b.tolist(), c=c.tolist(), x0=x0))
    outputs = np.array([plant.step(u, dt) for u in inputs])
    times = dt * np.arange(steps + 1)
    held = np.vstack([inputs, inputs[-1]])
    _, expected, _ = signal.lsim((a, b, c, np.zeros((2, 2))), held, times, X0=x0, interp=False)
    np.testing.assert_allclose(outputs, expected[1:], rtol=1e-9, atol=1e-11)


def _time_varying_error(dt: float) -> float:
    """Max state error of the piecewise-constant-Delta integration against a fine RK45 solution."""
    variation = {
        "a": {"kind": "sine", "amplitude": 0.6, "frequency": 3.0},
        "b": {"kind": "sine", "amplitude": 0.4, "frequency": 2.0},
    }
    disturbance = {"kind": "sine", "amplitude": 0.3, "frequency": 5.0, "start_time": 0.2}
    plant = build_plant(_scalar(variation=variation, disturbance=disturbance, x0=[0.2]))
    duration = 2.0
    steps = round(duration / dt)
    x = np.array([0.2])
    worst = 0.0
    for k in range(steps):
        t0 = k * dt
        u = math.sin(1.3 * t0) + 0.5  # held over the step

        def rhs(t: float, state: np.ndarray, u: float = u) -> np.ndarray:
            d = 0.3 * math.sin(5.0 * (t - 0.2)) if t >= 0.2 else 0.0
            return (A + 0.6 * math.sin(3.0 * t)) * state + (B + 0.4 * math.sin(2.0 * t)) * u + d

        x = solve_ivp(rhs, (t0, t0 + dt), x, rtol=1e-11, atol=1e-13, method="DOP853").y[:, -1]
        worst = max(worst, abs(plant.step(np.array([u]), dt)[0] - x[0]))
    return worst


def test_time_varying_integration_error_is_small_and_second_order_in_the_step() -> None:
    coarse = _time_varying_error(0.02)
    fine = _time_varying_error(0.01)
    # Midpoint sampling of Delta(t) and d(t): a local error O(dt^3), a global error O(dt^2).
    assert coarse < 2e-4, coarse
    assert fine < coarse / 3.0, (coarse, fine)


def test_disturbance_acts_from_its_start_trial_and_matches_the_analytic_response() -> None:
    d, dt = 0.7, 0.01
    plant = build_plant(_scalar(disturbance={"kind": "constant", "amplitude": d, "start_trial": 3}))
    undisturbed = build_plant(_scalar())
    plant.reset(2)
    first = [plant.step(np.zeros(1), dt)[0] for _ in range(50)]
    assert max(abs(v) for v in first) == 0.0
    plant.reset(3)
    undisturbed.reset(3)
    for k in range(1, 51):
        y = plant.step(np.array([1.0]), dt)[0]
        t = k * dt
        expected = (B * 1.0 + d) / A * (math.exp(A * t) - 1.0)
        assert y == pytest.approx(expected, rel=1e-12)
        assert undisturbed.step(np.array([1.0]), dt)[0] != pytest.approx(y, rel=1e-3)


@pytest.mark.parametrize(
    ("kind", "times", "expected"),
    [
        ("constant", [0.0, 0.5, 2.0], [2.0, 2.0, 2.0]),
        ("step", [0.0, 0.99, 1.0, 3.0], [0.0, 0.0, 2.0, 2.0]),
        ("sine", [0.5, 1.0, 1.0 + math.pi / 8], [0.0, 0.0, 2.0]),
        ("square", [0.5, 1.1, 1.0 + 3 * math.pi / 8], [0.0, 2.0, -2.0]),
    ],
)
def test_disturbance_shapes(kind: str, times: list[float], expected: list[float]) -> None:
    disturbance = Disturbance(DisturbanceConfig(kind=kind, amplitude=2.0, frequency=4.0, start_time=1.0))
    disturbance.reset(1)
    assert [disturbance.value(t) for t in times] == pytest.approx(expected, abs=1e-12)


def test_saturation_clips_the_input_and_says_so() -> None:
    clipped = build_plant(_scalar(saturation={"u_min": -1.0, "u_max": 1.0}))
    reference = build_plant(_scalar())
    for _ in range(20):
        assert clipped.step(np.array([5.0]), 0.01)[0] == reference.step(np.array([1.0]), 0.01)[0]
    assert clipped.saturated  # type: ignore[attr-defined]
    clipped.step(np.array([0.5]), 0.01)
    assert not clipped.saturated  # type: ignore[attr-defined]


def test_transport_delay_shifts_the_response() -> None:
    delay, dt = 0.015, 0.01
    plant = build_plant(_scalar(delay=delay))
    for k in range(1, 40):
        y = plant.step(np.array([1.0]), dt)[0]
        t = k * dt
        expected = B / A * (math.exp(A * (t - delay)) - 1.0) if t > delay else 0.0
        assert y == pytest.approx(expected, rel=1e-11, abs=1e-14), f"sample {k}"


def test_output_noise_is_seeded_per_trial() -> None:
    config = _scalar(output_noise=0.1)
    first = build_plant(config, seed=5)
    again = build_plant(config, seed=5)
    other = build_plant(config, seed=6)

    def run(plant: Plant, trial: int) -> np.ndarray:
        plant.reset(trial)
        return np.array([plant.step(np.zeros(1), 0.01)[0] for _ in range(400)])

    noise = run(first, 2)
    assert np.array_equal(noise, run(again, 2))
    assert not np.array_equal(noise, run(other, 2))
    assert not np.array_equal(noise, run(first, 3))
    assert np.array_equal(noise, run(first, 2))  # a reset replays the trial
    assert 0.08 < float(np.std(noise)) < 0.12


def test_the_pre_drawn_noise_vector_is_the_noise_the_plant_adds() -> None:
    """``noise.trial_vector`` (what a compiled trial kernel takes) equals ``y - c x`` measured step by step."""
    plant = build_plant(_scalar(output_noise=0.2, c=2.0), seed=9)
    assert isinstance(plant, FirstOrderPlant)
    plant.reset(3)
    added = [plant.output()[0] - 2.0 * plant.state()[0]]
    for k in range(50):
        y = plant.step(np.array([math.sin(0.1 * k)]), 0.01)[0]
        added.append(y - 2.0 * plant.state()[0])
    assert np.allclose(added, plant.noise.trial_vector(3, 51)[:, 0], rtol=0, atol=1e-12)
    assert not np.array_equal(plant.noise.trial_vector(3, 51), plant.noise.trial_vector(4, 51))
    quiet = build_plant(_scalar(), seed=9)
    assert isinstance(quiet, FirstOrderPlant)
    assert not quiet.noise.active and not np.any(quiet.noise.trial_vector(1, 5))


def test_random_walk_variation_is_bounded_reproducible_and_moves() -> None:
    config = VariationConfig(kind="random_walk", amplitude=0.3, frequency=2.0)
    walk, again = VariationSignal(config, seed=1, stream=1), VariationSignal(config, seed=1, stream=1)
    walk.reset(4)
    again.reset(4)
    values = np.array([walk.over_step(0.01 * k, 0.01) for k in range(5000)])
    assert np.array_equal(values, [again.over_step(0.01 * k, 0.01) for k in range(5000)])
    assert np.max(np.abs(values)) <= 0.3
    assert np.std(values) > 0.05


def test_random_walk_variation_changes_the_response_within_its_bound() -> None:
    variation = {"a": {"kind": "random_walk", "amplitude": 0.5, "frequency": 1.0}}
    plant = build_plant(_scalar(variation=variation), seed=3)
    nominal = build_plant(_scalar())
    ys = np.array([plant.step(np.ones(1), 0.01)[0] for _ in range(300)])
    ref = np.array([nominal.step(np.ones(1), 0.01)[0] for _ in range(300)])
    assert np.max(np.abs(ys - ref)) > 1e-4
    # |Da| <= 0.5 keeps the pole within [-1.73, -0.73]: the response stays between those two plants.
    t = 0.01 * np.arange(1, 301)
    slow, fast = B / 0.73 * (1 - np.exp(-0.73 * t)), B / 1.73 * (1 - np.exp(-1.73 * t))
    assert np.all(ys <= slow + 1e-12) and np.all(ys >= fast - 1e-12)


def test_bad_inputs_and_configs_name_what_is_wrong() -> None:
    with pytest.raises(ConfigError, match=r"plant\.x0: must have 1 entries"):
        build_plant(_scalar(x0=[1.0, 2.0]))
    plant = build_plant(_scalar())
    with pytest.raises(InputError, match="u must have 1 entries"):
        plant.step(np.zeros(2), 0.01)
    with pytest.raises(InputError, match="dt must be positive"):
        plant.step(np.zeros(1), 0.0)
    with pytest.raises(ConfigError, match="trial numbers start at 1"):
        plant.reset(0)


def test_mimo_time_varying_integration_matches_a_fine_reference() -> None:
    a = np.array([[-1.0, 0.4], [-0.3, -2.0]])
    b = np.array([[1.0, 0.0], [0.5, 2.0]])
    variation = {
        "a": {"kind": "sine", "amplitude": 0.5, "frequency": 4.0},
        "b": {"kind": "sine", "amplitude": 0.3, "frequency": 2.0},
    }
    disturbance = {"kind": "sine", "amplitude": 0.2, "frequency": 3.0}
    plant = build_plant(
        PlantConfig.model_validate(
            {"a": a.tolist(), "b": b.tolist(), "variation": variation, "disturbance": disturbance}
        )
    )
    pattern = (b != 0).astype(float)
    dt, x, worst = 0.01, np.zeros(2), 0.0
    for k in range(150):
        t0 = k * dt
        u = np.array([math.cos(2.0 * t0), 1.0])

        def rhs(t: float, state: np.ndarray, u: np.ndarray = u) -> np.ndarray:
            a_t = a + 0.5 * math.sin(4.0 * t) * np.eye(2)
            b_t = b + 0.3 * math.sin(2.0 * t) * pattern
            return a_t @ state + b_t @ u + 0.2 * math.sin(3.0 * t)

        x = solve_ivp(rhs, (t0, t0 + dt), x, rtol=1e-11, atol=1e-13, method="DOP853").y[:, -1]
        worst = max(worst, float(np.max(np.abs(plant.step(u, dt) - x))))
    assert worst < 5e-5, worst


@pytest.mark.parametrize("fields", [
    {},
    {"c": -2.0},  # at rest, c x is -0.0: measured +0.0, as c @ x sums it
    {
        "output_noise": 0.05,
        "saturation": {"u_min": -0.5, "u_max": 0.8},
        "variation": {"a": {"kind": "random_walk", "amplitude": 0.5, "frequency": 1.0},
                      "b": {"kind": "random_walk", "amplitude": 0.2, "frequency": 3.0}},
        "disturbance": {"kind": "constant", "amplitude": 0.3, "start_trial": 2},
    },
])
def test_the_papers_plant_steps_in_floats_as_the_general_path_does_bit_for_bit(fields: dict[str, object]) -> None:
    """The scalar plant's float step (``step_scalar``, the virtual drive's call, and ``step``) against the array
    path every other plant takes, forced on a twin: the same outputs, state, saturation flag and draws."""
    by_floats, general = FirstOrderPlant(_scalar(**fields), seed=7), FirstOrderPlant(_scalar(**fields), seed=7)
    general._floats = False
    rng = np.random.default_rng(1)
    for trial in (1, 2):
        by_floats.reset(trial)
        general.reset(trial)
        for k in range(300):
            u = 0.0 if k < 5 else float(rng.uniform(-2.0, 2.0))
            dt = 0.013 if k % 7 == 0 else 0.01
            expected = general.step(np.array([u]), dt)[0]
            got = by_floats.step_scalar(u, dt) if k % 2 else by_floats.step(np.array([u]), dt)[0]
            assert np.float64(got).tobytes() == expected.tobytes(), (trial, k)
            assert by_floats.saturated == general.saturated
        assert by_floats.state().tobytes() == general.state().tobytes()
        assert by_floats.output().tobytes() == general.output().tobytes()
        assert by_floats.time == general.time
    with pytest.raises(InputError, match="finite"):
        by_floats.step_scalar(math.nan, 0.01)

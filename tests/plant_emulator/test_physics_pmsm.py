"""The PMSM axis against independent truths: energy balance, analytic steady states and step responses,
resolver quantisation bounds, seeded reproducibility, limits."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from scipy import signal

from foilc_hil.errors import ConfigError
from plant_emulator.config import PlantConfig
from plant_emulator.physics import Plant, build_plant
from plant_emulator.physics.pmsm import RAD_PER_S_PER_RPM, PmsmPlant

FRICTIONLESS: dict[str, Any] = {"viscous": 0.0, "coulomb": 0.0, "cogging_amplitude": 0.0}


def _pmsm(pmsm: dict[str, Any] | None = None, seed: int | None = None, **plant: Any) -> PmsmPlant:
    built = build_plant(PlantConfig.model_validate({"model": "pmsm", "pmsm": pmsm or {}, **plant}), seed=seed)
    assert isinstance(built, PmsmPlant)
    return built


def test_pmsm_satisfies_the_protocol() -> None:
    plant = _pmsm()
    assert isinstance(plant, Plant)
    assert (plant.n_inputs, plant.n_outputs) == (1, 1)
    assert plant.state().shape == (4,)


def _work_and_kinetic_energy(dt: float, duration: float) -> tuple[float, float, float]:
    plant = _pmsm({**FRICTIONLESS, "input_kind": "torque"})
    inertia = plant.drawn_parameters()["inertia"]
    omega, torque = [plant.state()[1]], [plant.torque]
    for k in range(round(duration / dt)):
        plant.step(np.array([0.3 * math.sin(2 * math.pi * k * dt) + 0.1]), dt)
        omega.append(plant.state()[1])
        torque.append(plant.torque)
    power = np.array(torque) * np.array(omega)
    work = float(np.sum(0.5 * (power[1:] + power[:-1])) * dt)
    kinetic = 0.5 * inertia * (omega[-1] ** 2 - omega[0] ** 2)
    return work, kinetic, float(np.sum(np.abs(power)) * dt)


def test_pmsm_conserves_energy_with_friction_off() -> None:
    # Sampled at the internal step, the trapezoid of Te*w is the integrator's own quadrature: exact.
    work, kinetic, scale = _work_and_kinetic_energy(5e-5, 0.5)
    assert kinetic > 1.0
    assert abs(work - kinetic) <= 1e-9 * scale
    # Sampled at 1 kHz the test's quadrature misses the current-loop ripple; the balance still holds to 0.3 %.
    work, kinetic, scale = _work_and_kinetic_energy(1e-3, 1.5)
    assert abs(work - kinetic) <= 3e-3 * scale


def test_pmsm_keeps_its_speed_with_zero_torque_and_no_friction() -> None:
    plant = _pmsm({**FRICTIONLESS, "input_kind": "torque"}, x0=[300.0])
    readings = np.array([plant.step(np.zeros(1), 1e-3)[0] for _ in range(1000)])
    assert plant.state()[1] / RAD_PER_S_PER_RPM == pytest.approx(300.0, abs=1e-3)
    count = 2 * math.pi / 2**16 / 1e-3 / RAD_PER_S_PER_RPM
    assert np.max(np.abs(readings - 300.0)) <= count


def test_viscous_steady_state_and_transient_match_the_analytic_solution() -> None:
    viscous, torque, dt = 1e-2, 0.5, 1e-3
    plant = _pmsm({"viscous": viscous, "coulomb": 0.0, "cogging_amplitude": 0.0, "input_kind": "torque"})
    inertia = plant.drawn_parameters()["inertia"]
    lag = 1.0 / plant._config.current_bandwidth  # the closed current loop delays the torque by about 1/wc
    for k in range(1, 601):
        plant.step(np.array([torque]), dt)
        t = k * dt
        if t > 0.01:
            expected = torque / viscous * (1 - math.exp(-(t - lag) * viscous / inertia))
            assert plant.state()[1] == pytest.approx(expected, rel=2e-3), f"t = {t}"
    assert plant.state()[1] == pytest.approx(torque / viscous, rel=1e-4)


def test_velocity_loop_step_response_matches_the_analytic_closed_loop() -> None:
    plant = _pmsm({"coulomb": 0.0, "cogging_amplitude": 0.0})
    c = plant._config
    times = 1e-3 * np.arange(1, 1501)
    speeds = np.array([plant.step(np.array([400.0]), 1e-3)[0] for _ in times])
    closed_loop = ([c.velocity_ki], [c.inertia, c.velocity_kp + c.viscous, c.velocity_ki])
    _, unit = signal.step(closed_loop, T=times)
    # Current loop, velocity-estimate filter and quantisation make up the rest: under 1 % of the step.
    assert np.max(np.abs(speeds - 400.0 * unit)) < 4.0
    a, b = plant.nominal_first_order()
    assert b == pytest.approx(-a)
    assert np.max(np.abs(speeds - 400.0 * (1 - np.exp(a * times)))) < 0.06 * 400.0


def test_velocity_loop_reaches_the_command_despite_friction_and_cogging() -> None:
    plant = _pmsm()
    speeds = np.array([plant.step(np.array([500.0]), 1e-3)[0] for _ in range(2500)])
    assert float(np.mean(speeds[-500:])) == pytest.approx(500.0, abs=0.2)


def test_resolver_velocity_error_is_bounded_by_one_count_per_sample() -> None:
    plant = _pmsm({"resolver_bits": 12})
    dt = 1e-3
    count_speed = 2 * math.pi / 2**12 / dt  # rad/s of one count per sample
    errors = []
    for k in range(800):
        theta0 = plant.state()[0]
        measured = plant.step(np.array([300.0 + 200.0 * math.sin(0.01 * k)]), dt)[0] * RAD_PER_S_PER_RPM
        true_mean = (plant.state()[0] - theta0) / dt
        errors.append(measured - true_mean)
        assert measured / count_speed == pytest.approx(round(measured / count_speed), abs=1e-6)
    assert np.max(np.abs(errors)) < count_speed
    assert np.max(np.abs(errors)) > 0.3 * count_speed  # quantisation is really there


def test_seeds_reproduce_bit_for_bit_and_differ_between_seeds() -> None:
    pmsm = {"spread": {"inertia": 0.1, "viscous": 0.2, "torque_constant": 0.05}}

    def run(seed: int, trial: int = 1) -> tuple[np.ndarray, dict[str, float]]:
        plant = _pmsm(pmsm, seed=seed, output_noise=0.5)
        plant.reset(trial)
        return np.array([plant.step(np.array([400.0]), 1e-3)[0] for _ in range(200)]), plant.drawn_parameters()

    first, drawn = run(11)
    again, drawn_again = run(11)
    other, drawn_other = run(12)
    assert np.array_equal(first, again) and drawn == drawn_again
    assert not np.array_equal(first, other) and drawn != drawn_other
    assert not np.array_equal(first, run(11, trial=2)[0])  # noise is per trial
    nominal = PlantConfig(model="pmsm").pmsm
    assert abs(drawn["inertia"] / nominal.inertia - 1) <= 0.1
    assert abs(drawn["viscous"] / nominal.viscous - 1) <= 0.2
    assert abs(drawn["torque_constant"] / nominal.torque_constant - 1) <= 0.05
    assert drawn["coulomb"] == nominal.coulomb  # no spread given


def test_inertia_drift_varies_the_response_between_trials() -> None:
    plant = _pmsm({"drift": {"amplitude": 0.3, "frequency": 2.0, "phase_per_trial": 1.0}})

    def trial(k: int) -> np.ndarray:
        plant.reset(k)
        return np.array([plant.step(np.array([400.0]), 1e-3)[0] for _ in range(300)])

    first = trial(1)
    assert np.array_equal(first, trial(1))
    assert np.max(np.abs(first - trial(2))) > 1.0


def test_torque_limit_flag_and_clamp() -> None:
    plant = _pmsm({"input_kind": "torque"})
    plant.step(np.array([10.0]), 5e-3)
    assert plant.torque_limited
    assert plant.torque_command == plant._config.torque_limit
    assert plant.torque == pytest.approx(plant._config.torque_limit, rel=0.01)
    plant.step(np.array([1.0]), 1e-3)
    assert not plant.torque_limited


def test_over_speed_flag() -> None:
    plant = _pmsm({**FRICTIONLESS, "input_kind": "torque"})
    flags = []
    while plant.time < 0.2:
        plant.step(np.array([3.0]), 1e-3)
        flags.append((plant.state()[1] / RAD_PER_S_PER_RPM, plant.over_speed))
    assert any(flag for _, flag in flags)
    assert all(flag == (speed > 3600.0) for speed, flag in flags if abs(speed - 3600.0) > 50.0)


def test_velocity_command_is_clamped_to_rated_speed_and_saturation_applies_first() -> None:
    plant = _pmsm({"velocity_kp": 0.2, "velocity_ki": 4.0})
    for _ in range(150):
        plant.step(np.array([5000.0]), 1e-2)
    assert plant.output()[0] == pytest.approx(3000.0, abs=3.0)
    saturated = _pmsm(saturation={"u_max": 450.0})
    for _ in range(250):
        saturated.step(np.array([600.0]), 1e-2)
    assert saturated.saturated
    assert saturated.output()[0] == pytest.approx(450.0, abs=2.0)


def test_switching_input_kind_at_run_time_is_bumpless() -> None:
    plant = _pmsm()
    for _ in range(1500):
        plant.step(np.array([400.0]), 1e-3)
    holding = plant.torque_command
    plant.set_input_kind("torque")
    assert plant.input_kind == "torque"
    speeds = [plant.step(np.array([holding]), 1e-3)[0] for _ in range(100)]
    assert max(abs(s - 400.0) for s in speeds) < 5.0
    plant.set_input_kind("velocity")
    speeds = [plant.step(np.array([400.0]), 1e-3)[0] for _ in range(300)]
    assert max(abs(s - 400.0) for s in speeds) < 5.0
    with pytest.raises(ConfigError, match="input_kind"):
        plant.set_input_kind("position")  # type: ignore[arg-type]


def test_load_disturbance_acts_from_its_start_trial() -> None:
    viscous, torque, load = 1e-2, 0.5, 0.2
    plant = _pmsm(
        {"viscous": viscous, "coulomb": 0.0, "cogging_amplitude": 0.0, "input_kind": "torque"},
        disturbance={"kind": "constant", "amplitude": load, "start_trial": 2},
    )
    for trial, expected in ((1, torque / viscous), (2, (torque + load) / viscous)):
        plant.reset(trial)
        for _ in range(60):
            plant.step(np.array([torque]), 1e-2)
        assert plant.state()[1] == pytest.approx(expected, rel=1e-3)


def test_pmsm_rejects_first_order_variation_and_bad_x0() -> None:
    with pytest.raises(ConfigError, match=r"plant\.variation"):
        _pmsm(variation={"a": {"kind": "sine", "amplitude": 0.1}})
    with pytest.raises(ConfigError, match=r"plant\.x0"):
        _pmsm(x0=[1.0, 2.0])


def test_nominal_first_order_in_torque_mode() -> None:
    plant = _pmsm({"input_kind": "torque"})
    c = plant._config
    a, b = plant.nominal_first_order()
    assert a == pytest.approx(-c.viscous / c.inertia)
    assert b == pytest.approx(60.0 / (2 * math.pi) / c.inertia)


def test_closed_current_loop_is_a_first_order_lag_of_the_configured_bandwidth() -> None:
    plant = _pmsm({**FRICTIONLESS, "input_kind": "torque"})
    bandwidth = plant._config.current_bandwidth
    for k in range(1, 41):
        plant.step(np.array([1.0]), 1e-4)
        expected = 1.0 - math.exp(-bandwidth * k * 1e-4)
        assert plant.torque == pytest.approx(expected, abs=0.03), f"t = {k * 1e-4}"


def test_default_pmsm_design_model_is_its_nominal_first_order() -> None:
    from plant_emulator.linear import continuous_model

    config = PlantConfig(model="pmsm")
    model = continuous_model(config)
    a, b = _pmsm().nominal_first_order()
    assert (model.a[0, 0], model.b[0, 0], model.c[0, 0]) == (a, b, 1.0)
    c = config.pmsm
    assert -1.0 / a == pytest.approx((c.velocity_kp + c.viscous) / c.velocity_ki)
    given = continuous_model(PlantConfig(model="pmsm", a=-2.0, b=3.0))
    assert (given.a[0, 0], given.b[0, 0]) == (-2.0, 3.0)


LOADED_AXIS: dict[str, Any] = {**FRICTIONLESS, "input_kind": "torque", "inertia": 6.0e-4}
BRAKE_DT = 2.5e-3


def _held_for(plant: PmsmPlant, steps: int) -> list[float]:
    """The true speed (rad/s) after each of ``steps`` unpowered steps (zero torque command)."""
    speeds = []
    for _ in range(steps):
        plant.step(np.zeros(1), BRAKE_DT)
        speeds.append(float(plant.state()[1]))
    return speeds


def test_closed_brake_holds_a_load_within_its_torque_and_releases_it_when_opened() -> None:
    plant = _pmsm({**LOADED_AXIS, "brake_torque": 0.5}, disturbance={"kind": "constant", "amplitude": 0.2})
    plant.set_brake(True)
    assert _held_for(plant, 400) == [0.0] * 400  # one second: not a count of motion
    assert plant.state()[0] == 0.0 and not plant.over_speed
    plant.set_brake(False)
    speeds = _held_for(plant, 40)  # released: the load accelerates the axis at d / J
    assert speeds[-1] == pytest.approx(0.2 / 6.0e-4 * 40 * BRAKE_DT, rel=1e-2)


def test_a_load_beyond_the_brake_slips_at_the_torque_difference() -> None:
    plant = _pmsm({**LOADED_AXIS, "brake_torque": 0.1}, disturbance={"kind": "constant", "amplitude": -0.3})
    plant.set_brake(True)
    speeds = _held_for(plant, 40)
    assert speeds[-1] == pytest.approx(-(0.3 - 0.1) / 6.0e-4 * 40 * BRAKE_DT, rel=1e-2)


def test_closed_brake_stops_a_moving_axis_at_its_deceleration_and_does_not_reverse_it() -> None:
    brake, speed = 0.5, 1000.0 * RAD_PER_S_PER_RPM
    plant = _pmsm({**LOADED_AXIS, "brake_torque": brake}, x0=[1000.0])
    plant.set_brake(True)
    speeds = np.array(_held_for(plant, 100))
    stop_time = 6.0e-4 * speed / brake  # J w0 / Tb = 0.126 s
    moving = int(np.count_nonzero(speeds))
    assert abs(moving * BRAKE_DT - stop_time) <= BRAKE_DT
    assert np.all(np.diff(speeds) <= 0) and np.all(speeds >= 0.0)  # braked down to rest, never back up
    mid = round(0.5 * stop_time / BRAKE_DT)
    assert speeds[mid - 1] == pytest.approx(speed - brake / 6.0e-4 * mid * BRAKE_DT, rel=1e-3)


def test_without_a_brake_set_brake_changes_nothing() -> None:
    free, braked = (_pmsm(LOADED_AXIS, disturbance={"kind": "constant", "amplitude": 0.2}) for _ in range(2))
    braked.set_brake(True)  # brake_torque 0: no brake to close
    assert _held_for(free, 20) == _held_for(braked, 20)
    assert free.state()[1] > 0.0  # the unbraked axis falls under its load


def test_the_scalar_step_is_the_array_step_bit_for_bit() -> None:
    """``step_scalar`` (the virtual drive's per-cycle call) and ``step`` run the same step: from the same seed and
    commands, the same outputs and state; a non-finite input is refused as ``step`` refuses it."""
    from foilc_hil.errors import InputError

    by_array, by_float = _pmsm(seed=4, output_noise=0.3), _pmsm(seed=4, output_noise=0.3)
    for u in 250.0 * np.sin(np.linspace(0.0, 3.0, 200)):
        y = by_array.step(np.array([u]), 1e-3)
        assert np.float64(by_float.step_scalar(float(u), 1e-3)).tobytes() == y[0].tobytes()
    assert by_array.state().tobytes() == by_float.state().tobytes()
    with pytest.raises(InputError, match="finite"):
        by_float.step_scalar(math.nan, 1e-3)


def test_the_drive_steps_a_wrapped_plant_through_the_wrappers_step() -> None:
    """The virtual drive takes ``step_scalar`` from the plant's class: a wrapper that delegates attributes
    (the input-gain drift of fault injection) is stepped through its own ``step``, so its gain applies."""
    from plant_emulator.device import VirtualDrive
    from plant_emulator.faults import InputGainDrift

    calls: list[float] = []

    class Recording(InputGainDrift):
        def step(self, u: np.ndarray, dt: float) -> np.ndarray:
            calls.append(float(np.asarray(u)[0]))
            return super().step(u, dt)

    drive = VirtualDrive(_pmsm(seed=1), node_id=5, cycle_period=1e-3)
    assert getattr(drive.physics.plant, "step_scalar", None) is not None  # the instance delegates it
    drive.physics.plant = Recording(drive.physics.plant, 3.0)
    drive.physics.tick(1e-3)
    assert len(calls) == 1

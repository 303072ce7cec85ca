"""The compiled physics kernels against independent truths: scipy's ``solve_ivp`` of the same ODE, closed forms.

The kernels are the only implementation of the plants' arithmetic (``plant_emulator.physics.kernels``), so these
tests check the equations themselves, not agreement between two copies.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from plant_emulator.config import PlantConfig
from plant_emulator.physics import build_plant
from plant_emulator.physics.kernels import DisturbanceCode, disturbance_value, scalar_zoh_step
from plant_emulator.physics.pmsm import RAD_PER_S_PER_RPM, PmsmPlant


def test_scalar_zoh_step_is_the_exact_solution_of_the_linear_ode() -> None:
    a, bu, d, x0, h = -1.23, 0.84, 0.1, 0.3, 0.01
    truth = solve_ivp(lambda _t, x: a * x + bu + d, (0.0, h), [x0], rtol=1e-12, atol=1e-14).y[0, -1]
    assert scalar_zoh_step(x0, a, bu, d, h) == pytest.approx(truth, rel=1e-10)
    # a = 0 is the pure integrator (the closed form's removable singularity), and a tiny a h loses no digits
    assert scalar_zoh_step(x0, 0.0, bu, d, h) == pytest.approx(x0 + (bu + d) * h, rel=1e-15)
    tiny = 1e-12
    assert scalar_zoh_step(0.0, tiny, 1.0, 0.0, 1.0) == pytest.approx(math.expm1(tiny) / tiny, rel=1e-15)


def test_first_order_step_response_reaches_the_analytic_steady_state() -> None:
    plant = build_plant(PlantConfig.model_validate({"a": -2.0, "b": 3.0, "c": 1.0}))
    for _ in range(20000):  # 40 s, 80 time constants: e^-80 is below double precision
        y = plant.step(np.array([0.5]), 2e-3)[0]
    assert y == pytest.approx(3.0 / 2.0 * 0.5, rel=1e-13)


@pytest.mark.parametrize(
    ("code", "t", "expected"),
    [
        (DisturbanceCode.NONE, 3.0, 0.0),
        (DisturbanceCode.CONSTANT, 0.5, 2.0),
        (DisturbanceCode.STEP, 0.5, 0.0),
        (DisturbanceCode.STEP, 1.5, 2.0),
        (DisturbanceCode.SINE, 1.0 + math.pi / 8, 2.0),
        (DisturbanceCode.SQUARE, 1.0 + 3 * math.pi / 8, -2.0),
    ],
)
def test_disturbance_kernel_shapes(code: DisturbanceCode, t: float, expected: float) -> None:
    assert disturbance_value(int(code), 2.0, 4.0, 0.0, 1.0, t) == pytest.approx(expected, abs=1e-12)


def test_the_square_disturbance_is_the_sign_of_its_sine_at_and_near_every_switch() -> None:
    """The square wave decides its sign from the half period without calling sin away from the switches; it must
    be ``amplitude`` exactly where ``sin(frequency (t - start)) >= 0``: checked at random times, at the doubles
    around each switch of 200 periods, and for arguments beyond the shortcut's range."""
    amplitude, frequency, start = 0.15, 3.14159, 1.0
    rng = np.random.default_rng(4)
    times = [start + t for t in rng.uniform(0.0, 400.0, 20000)]
    for k in range(400):  # the doubles around t where frequency (t - start) = k pi
        switch = start + k * math.pi / frequency
        times += [switch, *np.nextafter(switch, [-math.inf, math.inf]), switch - 1e-9, switch + 1e-9]
    times += [start + 1e9, start + 1e300, start - 0.5]  # beyond 1e6 periods, sin's own reduction; before start
    for t in times:
        expected = 0.0 if t < start else amplitude if math.sin(frequency * (t - start)) >= 0 else -amplitude
        assert disturbance_value(int(DisturbanceCode.SQUARE), amplitude, frequency, 0.0, start, t) == expected, t


def test_pmsm_with_nonlinear_friction_and_cogging_matches_solve_ivp() -> None:
    """Torque mode, nominal motor, Coulomb friction, cogging and viscous friction on: the kernel against solve_ivp
    of ``J w' = Kt iq - B w - Tc tanh(w / ws) - Tcog sin(N theta)``, ``theta' = w`` with the closed current loop
    as its continuous-time design target ``iq' = wc (iq* - iq)`` (pole-zero cancellation: exact in continuous
    time; the discrete 20 kHz PI differs by O(h))."""
    pmsm = {"input_kind": "torque", "viscous": 2e-3, "coulomb": 0.05, "cogging_amplitude": 0.03}
    plant = build_plant(PlantConfig.model_validate({"model": "pmsm", "pmsm": pmsm}))
    assert isinstance(plant, PmsmPlant)
    c = plant._config
    torque, dt, n = 0.4, 1e-3, 400
    omega_scale = c.coulomb_velocity_scale * RAD_PER_S_PER_RPM

    def rhs(_t: float, z: np.ndarray) -> list[float]:
        theta, omega, iq = z
        losses = c.viscous * omega + c.coulomb * math.tanh(omega / omega_scale)
        losses += c.cogging_amplitude * math.sin(c.cogging_periods * theta)
        current_rate = c.current_bandwidth * (torque / c.torque_constant - iq)
        return [omega, (c.torque_constant * iq - losses) / c.inertia, current_rate]

    times = dt * np.arange(1, n + 1)
    truth = solve_ivp(rhs, (0.0, times[-1]), [0.0, 0.0, 0.0], t_eval=times, rtol=1e-10, atol=1e-12, method="DOP853")
    states = np.array([(plant.step(np.array([torque]), dt), plant.state())[1] for _ in times])
    speed_error = np.max(np.abs(states[:, 1] - truth.y[1]))
    assert speed_error < 5e-4 * np.max(np.abs(truth.y[1]))
    assert np.max(np.abs(states[:, 0] - truth.y[0])) < 5e-4 * np.max(np.abs(truth.y[0]))


def test_pmsm_is_deterministic_bit_for_bit_across_instances() -> None:
    config = PlantConfig.model_validate(
        {"model": "pmsm", "output_noise": 0.5, "pmsm": {"spread": {"inertia": 0.2}, "drift": {"amplitude": 0.05}}}
    )
    first, second = build_plant(config, seed=3), build_plant(config, seed=3)
    commands = 300.0 * np.sin(np.linspace(0.0, 6.0, 500))
    run_a = [first.step(np.array([u]), 1e-3)[0] for u in commands]
    run_b = [second.step(np.array([u]), 1e-3)[0] for u in commands]
    assert run_a == run_b
    assert np.array_equal(first.state(), second.state())


def test_the_plants_direct_kernel_call_is_the_dispatched_kernel_bit_for_bit() -> None:
    """``PmsmPlant.step`` calls ``pmsm_step``'s machine code without numba's dispatcher: the same function, so a
    step through it and one through the dispatcher from the same state give the same state and output."""
    from plant_emulator.physics.kernels import PMSM_STATE_SIZE, pmsm_step, pmsm_step_compiled

    plant = build_plant(PlantConfig.model_validate({"model": "pmsm", "seed": 5}))
    assert isinstance(plant, PmsmPlant)
    for _ in range(30):
        plant.step(np.array([350.0]), 1e-3)
    params = plant._params
    direct, dispatched = plant._state.copy(), plant._state.copy()
    assert direct.shape == (PMSM_STATE_SIZE,)
    args = (420.0, 1e-3, 20, True, 1, 0.3, 349.0)
    y_direct = pmsm_step_compiled(direct, params, *args)
    y_dispatched = pmsm_step(dispatched, params, *args)
    assert not np.array_equal(direct, plant._state)  # the step moved the axis
    assert direct.tobytes() == dispatched.tobytes()
    assert np.float64(y_direct).tobytes() == np.float64(y_dispatched).tobytes()


@pytest.mark.parametrize("u", [np.array([2.5]), [2.5], 2.5, np.array([2], dtype=np.int32), np.array([[2.5]])])
def test_a_single_input_is_read_as_check_input_reads_it(u: object) -> None:
    from plant_emulator.physics.base import check_input, check_scalar_input

    assert check_scalar_input(u) == float(check_input(u, 1)[0])  # type: ignore[arg-type]


@pytest.mark.parametrize("u", [np.array([math.nan]), np.array([math.inf]), np.array([1.0, 2.0]), [], "x"])
def test_a_bad_single_input_is_refused_as_check_input_refuses_it(u: object) -> None:
    from foilc_hil.errors import InputError
    from plant_emulator.physics.base import check_scalar_input

    with pytest.raises((InputError, ValueError)):
        check_scalar_input(u)  # type: ignore[arg-type]


@pytest.mark.slow
@pytest.mark.parametrize(
    ("voltages", "v_max"),
    [
        ((3.0, 4.0), 5.0 * (1.0 - 1e-12)),  # just past the limit: inside the squared pre-check's band
        ((3.0, 4.0), 5.0 * (1.0 + 1e-12)),  # just inside it
        ((3.0, 4.0), 5.0),  # on it: hypot(3, 4) == 5 is not past the limit
        ((3.0, 4.0), 10.0),  # far inside (the pre-check alone decides)
        ((30.0, -40.0), 5.0),  # far past
    ],
)
def test_the_voltage_limit_is_hypots_decision_near_and_far_from_it(
    voltages: tuple[float, float], v_max: float
) -> None:
    """The current loop skips ``hypot`` far inside the voltage limit (a squared-magnitude pre-check); whether the
    vector is scaled back must still be exactly ``hypot(vd, vq) > v_max``. At rest with zero currents and no torque
    command the PI's output is its integrators, so they set ``(vd, vq)``."""
    from plant_emulator.physics.kernels import PMSM_PARAM_SIZE, PmsmParam, _current_loop, _motor

    params = np.ones(PMSM_PARAM_SIZE)
    params[PmsmParam.V_MAX] = v_max
    vd, vq, int_d, int_q = _current_loop(_motor(params), 0.0, 0.0, (0.0, 0.0), voltages, 5e-5)
    magnitude = math.hypot(*voltages)
    if magnitude > v_max:
        assert (vd, vq) == (voltages[0] * (v_max / magnitude), voltages[1] * (v_max / magnitude))
    else:
        assert (vd, vq) == voltages
    assert (int_d, int_q) == voltages  # zero errors: the integrators hold, limited or not


@pytest.mark.slow
def test_the_drift_phasor_follows_the_phase_of_each_internal_step() -> None:
    """The inertia drift's sine is turned by ``drift_frequency h`` per internal step instead of recomputed; over a
    caller step's internal steps it stays within a few ulps of ``sin`` of each step's midpoint phase."""
    from plant_emulator.physics.kernels import PMSM_PARAM_SIZE, PmsmParam, _derive, _drift_phasor, _drift_turn, _motor

    params = np.ones(PMSM_PARAM_SIZE)
    frequency, per_trial, offset, h, t0, trial = 2.0, 0.7, 1.9, 5e-5, 4.321, 3
    params[PmsmParam.DRIFT_AMPLITUDE] = 0.05
    params[PmsmParam.DRIFT_FREQUENCY] = frequency
    params[PmsmParam.DRIFT_PHASE_PER_TRIAL] = per_trial
    params[PmsmParam.DRIFT_PHASE] = offset
    _derive(params, h)
    motor = _motor(params)
    phasor = _drift_phasor(motor, t0, h, trial)
    for k in range(40):  # twice a 1 ms caller step's 20 internal steps
        phase = frequency * (t0 + k * h + 0.5 * h) + offset + per_trial * (trial - 1)
        assert phasor[0] == pytest.approx(math.sin(phase), abs=1e-14)
        assert phasor[1] == pytest.approx(math.cos(phase), abs=1e-14)
        phasor = _drift_turn(motor, phasor)


def test_the_derived_slots_follow_the_internal_step() -> None:
    """``pmsm_advance`` keeps the slots derived from ``h`` in the parameter vector; a call with another ``h``
    derives them again, so a vector used at one step length and then another advances as a fresh one."""
    from plant_emulator.physics.kernels import PmsmParam, pmsm_advance

    config = {"model": "pmsm", "seed": 5, "pmsm": {"drift": {"amplitude": 0.05}}}
    plant = build_plant(PlantConfig.model_validate(config))
    assert isinstance(plant, PmsmPlant)
    used, fresh = plant._params.copy(), plant._params.copy()
    assert used[PmsmParam.DERIVED_STEP] != 1e-4
    pmsm_advance(plant._state.copy(), used, 300.0, 5e-5, 20, True, 1)
    assert used[PmsmParam.DERIVED_STEP] == 5e-5
    after_used, after_fresh = plant._state.copy(), plant._state.copy()
    pmsm_advance(after_used, used, 300.0, 1e-4, 10, True, 1)
    pmsm_advance(after_fresh, fresh, 300.0, 1e-4, 10, True, 1)
    assert used[PmsmParam.DERIVED_STEP] == 1e-4
    resistance = used[PmsmParam.RESISTANCE]
    assert used[PmsmParam.DECAY_D] == math.exp(-resistance * 1e-4 / used[PmsmParam.INDUCTANCE_D])
    assert after_used.tobytes() == after_fresh.tobytes()
    assert used.tobytes() == fresh.tobytes()

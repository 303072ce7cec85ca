"""A PMSM servo axis with its drive's current and velocity loops (``plant.model: pmsm``).

Model (all internal quantities SI; the interface speaks rpm and N m):

- **Electrical, dq frame.** ``Ld id' = vd - Rs id + we Lq iq``, ``Lq iq' = vq - Rs iq - we (Ld id + psi_f)``,
  ``we = p w``, torque ``Te = 1.5 p (psi_f iq + (Ld - Lq) id iq)`` with ``psi_f = Kt / (1.5 p)``.
- **Current loop.** The drive runs a discrete PI per axis every internal step (default 50 us, i.e. a 20 kHz
  current loop) with decoupling feed-forward and the voltage vector limited to ``Vdc / sqrt(3)`` (integrators
  frozen while limited). The PI is tuned by pole-zero cancellation on the *nominal* ``R``, ``L``
  (``kp = L wc``, ``ki = R wc``), so with nominal parameters the closed current loop is a first-order lag of
  bandwidth ``current_bandwidth``; drawn parameters (``spread``) detune it as on a real drive. The reference is
  ``id* = 0``, ``iq* = T* / Kt_nominal``. Over one internal step the voltages and cross-coupling terms are held
  and each axis is integrated exactly (exponential of ``-R h / L``), which is stable for any step.
- **Mechanics.** ``J(t) w' = Te + d(t) - B w - Tc tanh(w / w_s) - Tcog sin(N theta)``, ``theta' = w``, integrated
  by Heun's method with ``Te`` held over an internal step (with ``B = Tc = Tcog = d = 0`` this conserves
  ``0.5 J w^2 - integral Te w dt`` exactly). ``d(t)`` is ``plant.disturbance`` as a load torque in N m.
- **Sensing.** A resolver with ``2**resolver_bits`` counts per revolution; the reported velocity is the
  difference of the quantised angle over the caller's step ``dt`` (as in the paper's experiment), optionally
  low-passed (``velocity_filter``) and with ``plant.output_noise`` (rpm) added. The drive's own velocity loop
  differentiates the quantised angle every internal step and low-passes it (``velocity_loop_filter``).
- **Velocity loop (CSV).** ``T* = kp (beta w* - w_est) + ki integral(w* - w_est)``, clamped to
  ``torque_limit``, with conditional-integration anti-windup. ``beta = velocity_setpoint_weight``; the default
  ``beta = 0`` (I-P form) gives the overshoot-free closed loop ``ki / (J s^2 + (kp + B) s + ki)``. With the
  defaults (J = 5e-4, B = 1e-4, kp = 0.05, ki = 0.25) its poles are at about -5.3 and -95 rad/s: a dominant
  time constant of about 0.19 s plus a 10.5 ms lag, i.e. roughly first order with mean delay
  ``(kp (1 - beta) + B) / ki`` = 0.2 s -- see :meth:`PmsmPlant.nominal_first_order`.
- **Torque mode (CST).** ``T* = u`` clamped to ``torque_limit``.
- **Holding brake** (``brake_torque`` > 0). The drive closes it (:meth:`PmsmPlant.set_brake`) while its power stage
  is off: a dry friction of up to ``brake_torque`` that holds the axis at rest against a load within it and brakes
  a moving axis to rest. Without a brake an unpowered axis under ``d(t)`` accelerates, as a real one would.

Limits: velocity commands are clamped to ``+-rated_speed``; ``torque_limited`` is set when the torque command
was clipped during the last step, ``over_speed`` when ``|w|`` exceeded ``speed_limit`` during it, so the
virtual drive can raise EMCY. ``plant.saturation`` clips the raw input first, in the input's unit.

The sub-steps and the reported velocity run in the compiled kernel :func:`~plant_emulator.physics.kernels.pmsm_step`
(one call per caller step, or a whole trial in a compiled loop: :meth:`PmsmPlant.trial_program`); this class holds
the configuration, the seeded draws and noise, and the ``Plant`` protocol.

The state is ``[theta (rad, unwrapped mechanical angle), w (rad/s), id (A), iq (A)]``; the output is the
measured velocity in rpm. ``plant.a``/``b``/``c``/``delay``/``uncertainty`` are the *design* model of a PMSM
plant and are not used by the physics.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from drivers.errors import ConfigError
from plant_emulator.config import DisturbanceConfig, PlantConfig, PmsmConfig
from plant_emulator.physics.base import check_scalar_input, check_step, check_trial, trial_rng
from plant_emulator.physics.disturbance import Disturbance
from plant_emulator.physics.kernels import PMSM_PARAM_SIZE, PMSM_STATE_SIZE, PmsmParam, PmsmState, pmsm_step_compiled
from plant_emulator.physics.noise import plant_noise
from plant_emulator.physics.trial import PlantKind, PmsmTrialParam, PmsmTrialState, TrialProgram

__all__ = ["RAD_PER_S_PER_RPM", "InputKind", "PmsmPlant", "nominal_first_order"]

RAD_PER_S_PER_RPM = 2.0 * math.pi / 60.0
InputKind = Literal["velocity", "torque"]

_NOISE_STREAM = 3
_DRAW_STREAM = 10
_RUN_TRIAL = 0  # parameter draws belong to the run, not to a trial
_SUBSTEP_CACHE = 64  # step lengths remembered (bounded: a caller passing measured periods must not grow it)


class PmsmPlant:
    """A PMSM axis behind a CiA 402 drive; implements ``Plant`` with one input and one output (velocity, rpm).

    Parameters
    ----------
    plant
        The ``plant:`` section with ``model: pmsm``; the motor is ``plant.pmsm``.
    seed
        Seed of the parameter draws (per run) and of the output noise (per trial; ``plant.noise_seed`` if set).
    """

    n_inputs = 1
    n_outputs = 1

    def __init__(self, plant: PlantConfig, *, seed: int) -> None:
        config = plant.pmsm
        if plant.variation.a.kind != "none" or plant.variation.b.kind != "none":
            raise ConfigError(
                "applies to the first_order model; a pmsm drifts by 'plant.pmsm.drift'", key="plant.variation"
            )
        if plant.x0 is not None and len(plant.x0) != 1:
            raise ConfigError(f"a pmsm takes one entry (initial speed, rpm), got {len(plant.x0)}", key="plant.x0")
        self._config = config
        self._initial_speed = 0.0 if plant.x0 is None else plant.x0[0] * RAD_PER_S_PER_RPM
        self._u_min = -math.inf if plant.saturation.u_min is None else plant.saturation.u_min
        self._u_max = math.inf if plant.saturation.u_max is None else plant.saturation.u_max
        self.noise = plant_noise(plant, seed, _NOISE_STREAM, 1)
        """The sensor noise on the reported velocity (rpm), on top of the resolver's quantisation."""
        self._disturbance = Disturbance(plant.disturbance)
        self._input_kind: InputKind = config.input_kind
        self._velocity_mode = config.input_kind == "velocity"
        self._drawn = _draw_parameters(config, seed)
        self._count_angle = 2.0 * math.pi / float(2**config.resolver_bits)
        self._params = _kernel_parameters(config, self._drawn, self._count_angle)
        _set_disturbance_shape(self._params, plant.disturbance)
        self._state = np.zeros(PMSM_STATE_SIZE)
        self._per_step: dict[float, tuple[int, float]] = {}
        self._trial = 1
        self.reset(1)

    # --- Plant protocol ---------------------------------------------------------------------------------------

    def reset(self, trial: int) -> None:
        """Start ``trial`` at rest (or at ``plant.x0`` rpm) at angle 0 with every controller state cleared."""
        self._trial = check_trial(trial)
        state = self._state
        state.fill(0.0)
        state[PmsmState.OMEGA] = self._initial_speed
        state[PmsmState.OMEGA_ESTIMATE] = self._initial_speed
        self._reported_rpm = self._initial_speed / RAD_PER_S_PER_RPM
        self._disturbance.reset(self._trial)
        self._params[PmsmParam.DISTURBANCE_CODE] = float(self._disturbance.code)
        self.noise.reset(self._trial)
        self.saturated = False
        """Whether the last input was clipped by ``plant.saturation``."""
        self._y = self._reported_rpm + self._noise()

    @property
    def torque_limited(self) -> bool:
        """Whether the torque command was clipped to ``torque_limit`` during the last step."""
        return bool(self._state[PmsmState.TORQUE_LIMITED])

    @property
    def over_speed(self) -> bool:
        """Whether ``|w|`` exceeded ``speed_limit`` during the last step."""
        return bool(self._state[PmsmState.OVER_SPEED])

    def step(self, u: np.ndarray, dt: float) -> np.ndarray:
        """Hold ``u`` (rpm in velocity mode, N m in torque mode) over ``dt`` seconds; return the measured rpm."""
        return np.array([self._advance(check_scalar_input(u), dt)])

    def step_scalar(self, u: float, dt: float) -> float:
        """:meth:`step` with the input and the output as floats: the virtual drive's call once a cycle, which then
        builds no array for the input and none for the output (:class:`~plant_emulator.physics.base.ScalarPlant`)."""
        return self._advance(check_scalar_input(u), dt)

    def _advance(self, command: float, dt: float) -> float:
        """The step of a checked input (:meth:`step`, :meth:`step_scalar`): the measured rpm."""
        applied = min(max(command, self._u_min), self._u_max)
        self.saturated = applied != command
        steps, smoothing = self._per_step_of(dt)
        self._reported_rpm = pmsm_step_compiled(
            self._state, self._params, applied, dt, steps, self._velocity_mode, self._trial, smoothing,
            self._reported_rpm,
        )
        self._y = self._reported_rpm + self._noise()
        return self._y

    def output(self) -> np.ndarray:
        """The measured velocity in rpm (quantisation, filter and noise included)."""
        return np.array([self._y])

    def state(self) -> np.ndarray:
        """``[theta (rad), w (rad/s), id (A), iq (A)]``."""
        return self._state[[PmsmState.THETA, PmsmState.OMEGA, PmsmState.ID, PmsmState.IQ]].copy()

    @property
    def time(self) -> float:
        """Seconds since :meth:`reset`."""
        return float(self._state[PmsmState.TIME])

    # --- drive-facing extras ----------------------------------------------------------------------------------

    @property
    def input_kind(self) -> InputKind:
        """``"velocity"`` (CSV, the input is a speed command in rpm) or ``"torque"`` (CST, N m)."""
        return self._input_kind

    def set_input_kind(self, kind: InputKind) -> None:
        """Switch between velocity (CSV) and torque (CST) input, bumplessly: the velocity integrator starts from
        the torque being applied."""
        if kind not in ("velocity", "torque"):
            raise ConfigError(f"must be 'velocity' or 'torque', got {kind!r}", key="plant.pmsm.input_kind")
        if kind == "velocity" and self._input_kind == "torque":
            state = self._state
            state[PmsmState.INT_VELOCITY] = (
                state[PmsmState.TORQUE_COMMAND] + self._config.velocity_kp * state[PmsmState.OMEGA_ESTIMATE]
            )
        self._input_kind = kind
        self._velocity_mode = kind == "velocity"

    def set_brake(self, closed: bool) -> None:
        """Close or open the holding brake (``plant.pmsm.brake_torque``; without one this changes nothing)."""
        self._params[PmsmParam.HOLDING_TORQUE] = self._config.brake_torque if closed else 0.0

    @property
    def torque(self) -> float:
        """The electromagnetic torque ``Te`` (N m) at the end of the last step."""
        return float(self._state[PmsmState.TORQUE])

    @property
    def torque_command(self) -> float:
        """The torque the drive commanded (N m) in the last internal step, after the torque limit."""
        return float(self._state[PmsmState.TORQUE_COMMAND])

    @property
    def position_counts(self) -> int:
        """The resolver position, multi-turn, in counts (``counts_per_revolution`` per revolution)."""
        return int(self._state[PmsmState.COUNT])

    @property
    def counts_per_revolution(self) -> int:
        """Resolver counts per mechanical revolution."""
        return int(2**self._config.resolver_bits)

    @property
    def rated_torque(self) -> float:
        """Rated torque (N m): the unit of 0x6071/0x6077 is a per mille of it."""
        return self._config.rated_torque

    def drawn_parameters(self) -> dict[str, float]:
        """The parameter values this run uses (after the seeded ``spread`` draws), for logs."""
        return dict(self._drawn)

    def nominal_first_order(self) -> tuple[float, float]:
        """``(a, b)`` of the first-order approximation of the nominal axis for the current input kind; see
        :func:`nominal_first_order`."""
        return nominal_first_order(self._config, self._input_kind)

    # --- a whole trial in a compiled loop ----------------------------------------------------------------------

    def trial_program(self, steps: int, dt: float) -> TrialProgram:
        """The next ``steps`` caller steps of ``dt`` for a compiled loop
        (:class:`~plant_emulator.physics.trial.CompiledPlant`): the state, the kernel's parameters with this trial's
        settings, and the output noise of each step drawn now, as ``steps`` calls of :meth:`step` draw it."""
        params = np.concatenate([self._params, np.zeros(len(PmsmTrialParam))])
        params[PmsmTrialParam.U_MIN], params[PmsmTrialParam.U_MAX] = self._u_min, self._u_max
        params[PmsmTrialParam.STEP] = dt
        params[PmsmTrialParam.SUBSTEPS], params[PmsmTrialParam.SMOOTHING] = self._per_step_of(dt)
        params[PmsmTrialParam.VELOCITY_MODE] = 1.0 if self._velocity_mode else 0.0
        params[PmsmTrialParam.TRIAL] = self._trial
        state = np.concatenate([self._state, np.zeros(len(PmsmTrialState))])
        state[PmsmTrialState.REPORTED] = self._reported_rpm
        noise = np.zeros((steps, 1))
        if self.noise.active:  # the generator continues after the draw of the reset's measurement
            noise[:, :] = self.noise.following(steps)
        return TrialProgram(PlantKind.PMSM, state, params, noise)

    def end_trial_program(self, program: TrialProgram, commands: np.ndarray, output: float) -> None:
        """Take over the state ``program`` reached after ``len(commands)`` steps, measured as ``output`` (the noise
        stream stays where :meth:`trial_program` left it: at the program's end)."""
        steps = commands.shape[0]
        self._state[:] = program.state[:PMSM_STATE_SIZE]
        self._reported_rpm = float(program.state[PmsmTrialState.REPORTED])
        self._y = float(output)
        self.saturated = steps > 0 and bool(program.state[PmsmTrialState.SATURATED])

    # --- internals --------------------------------------------------------------------------------------------

    def _per_step_of(self, dt: float) -> tuple[int, float]:
        """Internal steps per caller step of ``dt`` and the reported velocity's low-pass weight over ``dt``
        (``kernels.pmsm_step``; NaN: no filter), computed once per step length and kept: both are fixed by ``dt``,
        and a step then pays one dict look-up for them instead of a division, a ceil and an exp."""
        settings = self._per_step.get(dt)
        if settings is None:  # a few step lengths in practice; bounded: measured periods must not grow it
            steps = max(1, math.ceil(check_step(dt) / self._config.internal_step - 1e-9))
            tau = self._config.velocity_filter
            settings = (steps, 1.0 - math.exp(-dt / tau) if tau > 0 else math.nan)
            if len(self._per_step) >= _SUBSTEP_CACHE:
                self._per_step.clear()
            self._per_step[dt] = settings
        return settings

    def _noise(self) -> float:
        return float(self.noise.sample()[0]) if self.noise.active else 0.0


def _draw_parameters(config: PmsmConfig, seed: int) -> dict[str, float]:
    """Nominal parameters scaled by factors drawn uniformly in ``[1 - spread, 1 + spread]`` (seeded per run)."""
    rng = trial_rng(seed, _RUN_TRIAL, _DRAW_STREAM)
    spread = config.spread
    # Always draw every factor, in a fixed order, so one spread does not shift the others' draws.
    factors = {
        name: 1.0 + getattr(spread, name) * float(rng.uniform(-1.0, 1.0))
        for name in ("inertia", "viscous", "coulomb", "torque_constant", "resistance", "inductance")
    }
    return {
        "inertia": config.inertia * factors["inertia"],
        "viscous": config.viscous * factors["viscous"],
        "coulomb": config.coulomb * factors["coulomb"],
        "torque_constant": config.torque_constant * factors["torque_constant"],
        "resistance": config.resistance * factors["resistance"],
        "inductance_d": config.inductance_d * factors["inductance"],
        "inductance_q": config.inductance_q * factors["inductance"],
    }


def _kernel_parameters(config: PmsmConfig, drawn: dict[str, float], count_angle: float) -> np.ndarray:
    """The parameter vector of :func:`~plant_emulator.physics.kernels.pmsm_advance`.

    The drive is tuned on the nominal (datasheet) parameters, not on the drawn ones: the current PI by pole-zero
    cancellation (``kp = L wc``, ``ki = R wc``) and the decoupling on the nominal ``L`` and flux linkage.
    """
    p = config.pole_pairs
    wc = config.current_bandwidth
    values = {
        PmsmParam.POLE_PAIRS: p,
        PmsmParam.SPEED_CAP: config.rated_speed * RAD_PER_S_PER_RPM,
        PmsmParam.VELOCITY_KP: config.velocity_kp,
        PmsmParam.VELOCITY_KI: config.velocity_ki,
        PmsmParam.SETPOINT_WEIGHT: config.velocity_setpoint_weight,
        PmsmParam.TORQUE_LIMIT: config.torque_limit,
        PmsmParam.TORQUE_CONSTANT: config.torque_constant,
        PmsmParam.INDUCTANCE_D_NOMINAL: config.inductance_d,
        PmsmParam.INDUCTANCE_Q_NOMINAL: config.inductance_q,
        PmsmParam.PSI_NOMINAL: config.torque_constant / (1.5 * p),
        PmsmParam.KP_D: config.inductance_d * wc,
        PmsmParam.KP_Q: config.inductance_q * wc,
        PmsmParam.KI_CURRENT: config.resistance * wc,
        PmsmParam.V_MAX: config.dc_bus_voltage / math.sqrt(3.0),
        PmsmParam.PSI: drawn["torque_constant"] / (1.5 * p),
        PmsmParam.RESISTANCE: drawn["resistance"],
        PmsmParam.INDUCTANCE_D: drawn["inductance_d"],
        PmsmParam.INDUCTANCE_Q: drawn["inductance_q"],
        PmsmParam.INERTIA: drawn["inertia"],
        PmsmParam.VISCOUS: drawn["viscous"],
        PmsmParam.COULOMB: drawn["coulomb"],
        PmsmParam.COULOMB_SCALE: config.coulomb_velocity_scale * RAD_PER_S_PER_RPM,
        PmsmParam.COGGING_AMPLITUDE: config.cogging_amplitude,
        PmsmParam.COGGING_PERIODS: config.cogging_periods,
        PmsmParam.DRIFT_AMPLITUDE: config.drift.amplitude,
        PmsmParam.DRIFT_FREQUENCY: config.drift.frequency,
        PmsmParam.DRIFT_PHASE_PER_TRIAL: config.drift.phase_per_trial,
        PmsmParam.DRIFT_PHASE: config.drift.phase,
        PmsmParam.COUNT_ANGLE: count_angle,
        PmsmParam.VELOCITY_LOOP_FILTER: config.velocity_loop_filter,
        PmsmParam.SPEED_LIMIT: config.speed_limit * RAD_PER_S_PER_RPM,
    }
    params = np.zeros(PMSM_PARAM_SIZE)
    for slot, value in values.items():
        params[slot] = value
    return params


def _set_disturbance_shape(params: np.ndarray, disturbance: DisturbanceConfig) -> None:
    """Write the load torque's amplitude, frequency, phase and start time (its code is set per trial by ``reset``)."""
    params[PmsmParam.DISTURBANCE_AMPLITUDE] = disturbance.amplitude
    params[PmsmParam.DISTURBANCE_FREQUENCY] = disturbance.frequency
    params[PmsmParam.DISTURBANCE_PHASE] = disturbance.phase
    params[PmsmParam.DISTURBANCE_START] = disturbance.start_time


def nominal_first_order(config: PmsmConfig, input_kind: InputKind | None = None) -> tuple[float, float]:
    """``(a, b)`` of the first-order approximation ``y' = a y + b u`` of the nominal axis, ``y`` in rpm.

    Velocity input (CSV): the closed velocity loop ``(beta kp s + ki) / (J s^2 + (kp + B) s + ki)`` matched in
    DC gain (1) and mean delay ``tau = (kp (1 - beta) + B) / ki``, floored at ``J / (kp + B)`` (the fast time
    constant) when the set-point weight makes the mean delay degenerate: ``a = -1/tau``, ``b = 1/tau``. With the
    defaults ``tau`` = 0.2004 s, ``a = -b`` = -4.99 1/s.
    Torque input (CST): ``a = -B / J``, ``b = (60 / 2 pi) / J`` (rpm/s per N m).
    Coulomb friction, cogging and the current-loop lag are neglected.

    Parameters
    ----------
    config
        The ``plant.pmsm`` section.
    input_kind
        ``"velocity"`` or ``"torque"``; default ``config.input_kind``.
    """
    kind = config.input_kind if input_kind is None else input_kind
    if kind == "torque":
        return -config.viscous / config.inertia, 1.0 / (config.inertia * RAD_PER_S_PER_RPM)
    if config.velocity_ki == 0:
        raise ConfigError(
            "the velocity loop has no integral action; give velocity_ki > 0", key="plant.pmsm.velocity_ki"
        )
    proportional = config.velocity_kp * (1.0 - config.velocity_setpoint_weight)
    mean_delay = (proportional + config.viscous) / config.velocity_ki
    tau = max(mean_delay, config.inertia / (config.velocity_kp + config.viscous))
    return -1.0 / tau, 1.0 / tau

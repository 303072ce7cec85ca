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

Limits: velocity commands are clamped to ``+-rated_speed``; ``torque_limited`` is set when the torque command
was clipped during the last step, ``over_speed`` when ``|w|`` exceeded ``speed_limit`` during it, so the
virtual drive can raise EMCY. ``plant.saturation`` clips the raw input first, in the input's unit.

The state is ``[theta (rad, unwrapped mechanical angle), w (rad/s), id (A), iq (A)]``; the output is the
measured velocity in rpm. ``plant.a``/``b``/``c``/``delay``/``uncertainty`` are the *design* model of a PMSM
plant and are not used by the physics.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from foilc_hil.errors import ConfigError
from plant_emulator.config import PlantConfig, PmsmConfig
from plant_emulator.physics.base import check_input, check_step, check_trial, trial_rng
from plant_emulator.physics.disturbance import Disturbance

__all__ = ["RAD_PER_S_PER_RPM", "InputKind", "PmsmPlant", "nominal_first_order"]

RAD_PER_S_PER_RPM = 2.0 * math.pi / 60.0
InputKind = Literal["velocity", "torque"]

_NOISE_STREAM = 3
_DRAW_STREAM = 10
_RUN_TRIAL = 0  # parameter draws belong to the run, not to a trial


class PmsmPlant:
    """A PMSM axis behind a CiA 402 drive; implements ``Plant`` with one input and one output (velocity, rpm).

    Parameters
    ----------
    plant
        The ``plant:`` section with ``model: pmsm``; the motor is ``plant.pmsm``.
    seed
        Seed of the parameter draws (per run) and of the output noise (per trial).
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
        self._seed = seed
        self._initial_speed = 0.0 if plant.x0 is None else plant.x0[0] * RAD_PER_S_PER_RPM
        self._u_min = -math.inf if plant.saturation.u_min is None else plant.saturation.u_min
        self._u_max = math.inf if plant.saturation.u_max is None else plant.saturation.u_max
        self._noise_std = plant.output_noise
        self._disturbance = Disturbance(plant.disturbance)
        self._input_kind: InputKind = config.input_kind
        self._drawn = _draw_parameters(config, seed)
        self._count_angle = 2.0 * math.pi / float(2**config.resolver_bits)
        # The drive is tuned on the nominal (datasheet) parameters, not on the drawn ones.
        p = config.pole_pairs
        self._psi_nominal = config.torque_constant / (1.5 * p)
        self._psi = self._drawn["torque_constant"] / (1.5 * p)
        wc = config.current_bandwidth
        self._kp_d, self._kp_q = config.inductance_d * wc, config.inductance_q * wc
        self._ki_current = config.resistance * wc
        self._v_max = config.dc_bus_voltage / math.sqrt(3.0)
        self._step_cache: dict[float, tuple[float, float, float, float]] = {}
        self._noise_rng = trial_rng(seed, 1, _NOISE_STREAM)
        self._trial = 1
        self.reset(1)

    # --- Plant protocol ---------------------------------------------------------------------------------------

    def reset(self, trial: int) -> None:
        """Start ``trial`` at rest (or at ``plant.x0`` rpm) at angle 0 with every controller state cleared."""
        self._trial = check_trial(trial)
        self._theta = 0.0
        self._omega = self._initial_speed
        self._id = 0.0
        self._iq = 0.0
        self._int_d = 0.0
        self._int_q = 0.0
        self._int_velocity = 0.0
        self._omega_estimate = self._omega
        self._count = math.floor(self._theta / self._count_angle)
        self._torque = 0.0
        self._torque_command = 0.0
        self._t = 0.0
        self._reported_rpm = self._omega / RAD_PER_S_PER_RPM
        self._disturbance.reset(self._trial)
        self._noise_rng = trial_rng(self._seed, self._trial, _NOISE_STREAM)
        self.torque_limited = False
        """Whether the torque command was clipped to ``torque_limit`` during the last step."""
        self.over_speed = False
        """Whether ``|w|`` exceeded ``speed_limit`` during the last step."""
        self.saturated = False
        """Whether the last input was clipped by ``plant.saturation``."""
        self._y = np.array([self._reported_rpm + self._noise()])

    def step(self, u: np.ndarray, dt: float) -> np.ndarray:
        """Hold ``u`` (rpm in velocity mode, N m in torque mode) over ``dt`` seconds; return the measured rpm."""
        command = float(check_input(u, 1)[0])
        dt = check_step(dt)
        applied = min(max(command, self._u_min), self._u_max)
        self.saturated = applied != command
        steps = max(1, math.ceil(dt / self._config.internal_step - 1e-9))
        h = dt / steps
        count_start = self._count
        self.torque_limited = False
        self.over_speed = False
        for _ in range(steps):
            self._substep(applied, h)
        measured = (self._count - count_start) * self._count_angle / dt / RAD_PER_S_PER_RPM
        tau = self._config.velocity_filter
        if tau > 0:
            self._reported_rpm += (1.0 - math.exp(-dt / tau)) * (measured - self._reported_rpm)
        else:
            self._reported_rpm = measured
        self._y = np.array([self._reported_rpm + self._noise()])
        return self._y.copy()

    def output(self) -> np.ndarray:
        """The measured velocity in rpm (quantisation, filter and noise included)."""
        return self._y.copy()

    def state(self) -> np.ndarray:
        """``[theta (rad), w (rad/s), id (A), iq (A)]``."""
        return np.array([self._theta, self._omega, self._id, self._iq])

    @property
    def time(self) -> float:
        """Seconds since :meth:`reset`."""
        return self._t

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
            self._int_velocity = self._torque_command + self._config.velocity_kp * self._omega_estimate
        self._input_kind = kind

    @property
    def torque(self) -> float:
        """The electromagnetic torque ``Te`` (N m) at the end of the last step."""
        return self._torque

    @property
    def torque_command(self) -> float:
        """The torque the drive commanded (N m) in the last internal step, after the torque limit."""
        return self._torque_command

    @property
    def position_counts(self) -> int:
        """The resolver position, multi-turn, in counts (``counts_per_revolution`` per revolution)."""
        return self._count

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

    # --- internals --------------------------------------------------------------------------------------------

    def _noise(self) -> float:
        return float(self._noise_std * self._noise_rng.standard_normal()) if self._noise_std > 0 else 0.0

    def _electrical_factors(self, h: float) -> tuple[float, float, float, float]:
        cached = self._step_cache.get(h)
        if cached is None:
            r = self._drawn["resistance"]
            decay_d = math.exp(-r * h / self._drawn["inductance_d"])
            decay_q = math.exp(-r * h / self._drawn["inductance_q"])
            cached = (decay_d, (1.0 - decay_d) / r, decay_q, (1.0 - decay_q) / r)
            if len(self._step_cache) > 64:
                self._step_cache.clear()
            self._step_cache[h] = cached
        return cached

    def _substep(self, command: float, h: float) -> None:
        c = self._config
        drawn = self._drawn
        p = c.pole_pairs
        # 1. The velocity estimate sensed at the end of the previous internal step.
        omega_est = self._omega_estimate
        # 2. Torque command: velocity loop (CSV) or direct (CST).
        limit = c.torque_limit
        if self._input_kind == "velocity":
            speed_cap = c.rated_speed * RAD_PER_S_PER_RPM
            reference = min(max(command * RAD_PER_S_PER_RPM, -speed_cap), speed_cap)
            error = reference - omega_est
            wanted = c.velocity_kp * (c.velocity_setpoint_weight * reference - omega_est) + self._int_velocity
            torque_command = min(max(wanted, -limit), limit)
            # Conditional integration: stop integrating into the limit (anti-windup).
            if torque_command == wanted or (error > 0) != (wanted > 0):
                self._int_velocity += c.velocity_ki * error * h
                self._int_velocity = min(
                    max(self._int_velocity, -limit - c.velocity_kp * abs(omega_est)),
                    limit + c.velocity_kp * abs(omega_est),
                )
        else:
            wanted = command
            torque_command = min(max(wanted, -limit), limit)
        if torque_command != wanted:
            self.torque_limited = True
        self._torque_command = torque_command
        # 3. Current loop: PI with decoupling on nominal parameters, voltage vector limit.
        iq_ref = torque_command / c.torque_constant
        we_est = p * omega_est
        error_d = -self._id
        error_q = iq_ref - self._iq
        vd = self._kp_d * error_d + self._int_d - we_est * c.inductance_q * self._iq
        vq = self._kp_q * error_q + self._int_q + we_est * (c.inductance_d * self._id + self._psi_nominal)
        magnitude = math.hypot(vd, vq)
        if magnitude > self._v_max:
            scale = self._v_max / magnitude
            vd *= scale
            vq *= scale
        else:
            self._int_d += self._ki_current * error_d * h
            self._int_q += self._ki_current * error_q * h
        # 4. Electrical plant: each axis exact over h with the cross-coupling held.
        we = p * self._omega
        ld, lq = drawn["inductance_d"], drawn["inductance_q"]
        decay_d, gain_d, decay_q, gain_q = self._electrical_factors(h)
        id_old, iq_old = self._id, self._iq
        self._id = decay_d * id_old + gain_d * (vd + we * lq * iq_old)
        self._iq = decay_q * iq_old + gain_q * (vq - we * (ld * id_old + self._psi))
        id_mean = 0.5 * (id_old + self._id)
        iq_mean = 0.5 * (iq_old + self._iq)
        torque = 1.5 * p * (self._psi * iq_mean + (ld - lq) * id_mean * iq_mean)
        # 5. Mechanics: Heun with Te and the load held over h.
        load = self._disturbance.over_step(self._t, h)
        drive = torque + load
        inertia = drawn["inertia"]
        if c.drift.amplitude > 0:
            phase = c.drift.frequency * (self._t + 0.5 * h) + c.drift.phase_per_trial * (self._trial - 1)
            inertia *= 1.0 + c.drift.amplitude * math.sin(phase)
        theta0, omega0 = self._theta, self._omega
        accel0 = (drive - self._losses(theta0, omega0)) / inertia
        omega_pred = omega0 + h * accel0
        theta_pred = theta0 + h * omega0
        accel1 = (drive - self._losses(theta_pred, omega_pred)) / inertia
        self._omega = omega0 + 0.5 * h * (accel0 + accel1)
        self._theta = theta0 + 0.5 * h * (omega0 + self._omega)
        self._torque = 1.5 * p * (self._psi * self._iq + (ld - lq) * self._id * self._iq)
        self._t += h
        # 6. Sensing at the end of the step (used by the next one): the quantised angle, differentiated over the
        # internal step and low-passed -- the drive's own velocity estimate.
        count = math.floor(self._theta / self._count_angle)
        raw = (count - self._count) * self._count_angle / h
        self._count = count
        if c.velocity_loop_filter > 0:
            self._omega_estimate += (1.0 - math.exp(-h / c.velocity_loop_filter)) * (raw - self._omega_estimate)
        else:
            self._omega_estimate = raw
        if abs(self._omega) > c.speed_limit * RAD_PER_S_PER_RPM:
            self.over_speed = True

    def _losses(self, theta: float, omega: float) -> float:
        """Friction and cogging torque (N m) opposing the motion at (theta, omega)."""
        c = self._config
        drawn = self._drawn
        losses = drawn["viscous"] * omega
        if drawn["coulomb"] > 0:
            losses += drawn["coulomb"] * math.tanh(omega / (c.coulomb_velocity_scale * RAD_PER_S_PER_RPM))
        if c.cogging_amplitude > 0:
            losses += c.cogging_amplitude * math.sin(c.cogging_periods * theta)
        return losses


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

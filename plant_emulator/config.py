"""Config sections owned by the plant side: physics models and the virtual drive.

The ``plant:`` section is shared by offline simulation, tuning, synthesis and the emulator (one physics code
path). The ``emulator:`` section configures only the virtual drive.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from drivers.schema import Section
from plant_emulator.matrix import Matrix


class VariationConfig(Section):
    """Time-varying parameter uncertainty ``Delta(t)`` added to a nominal parameter.

    ``sine`` is ``amplitude * sin(frequency * t + phase)``, the same in every trial; ``random_walk`` is a seeded
    Ornstein-Uhlenbeck process (``frequency`` its mean-reversion rate) and takes no phase.
    """

    kind: Literal["none", "sine", "random_walk"] = "none"
    amplitude: float = Field(default=0.0, ge=0)  # absolute bound on |Delta(t)|
    frequency: float = Field(default=1.0, gt=0)  # rad/s (sine) or correlation rate (random walk)
    phase: float = 0.0  # rad, the sine's phase at t = 0 (0: Delta(t) = amplitude sin(frequency t))

    @model_validator(mode="after")
    def _phase_needs_a_sine(self) -> VariationConfig:
        # a phase on a shape that has none would be silently ignored; say so instead
        if self.phase != 0 and self.kind != "sine":
            raise ValueError(f"phase applies to kind 'sine', not {self.kind!r}")
        return self


class ParameterVariation(Section):
    """Time variation of the first-order model's ``a`` and ``b``."""

    a: VariationConfig = VariationConfig()
    b: VariationConfig = VariationConfig()


class DisturbanceConfig(Section):
    """External disturbance ``d(t)`` entering the state equation, from ``start_trial`` on.

    ``constant`` is ``amplitude`` over the whole trial; ``step`` jumps from 0 to ``amplitude`` at ``start_time``;
    ``sine`` is ``amplitude * sin(frequency * (t - start_time) + phase)`` and ``square`` its sign, both from
    ``start_time`` on. For ``first_order`` plants ``d`` is added to every state equation; for ``pmsm`` it is a
    load torque in N m added to the motor torque.
    """

    kind: Literal["none", "constant", "step", "sine", "square"] = "none"
    amplitude: float = 0.0
    frequency: float = Field(default=1.0, gt=0)  # rad/s
    start_time: float = Field(default=0.0, ge=0)  # within a trial, seconds
    start_trial: int = Field(default=1, ge=1)
    phase: float = 0.0  # rad, of the sine (and the square wave) at start_time

    @model_validator(mode="after")
    def _phase_needs_a_wave(self) -> DisturbanceConfig:
        if self.phase != 0 and self.kind not in ("sine", "square"):
            raise ValueError(f"phase applies to kinds 'sine' and 'square', not {self.kind!r}")
        return self


class UncertaintyConfig(Section):
    """Norm-bounded uncertainty of the discrete model: ``dA = G1 Delta H1``, ``dB = G2 Delta H2``, ``||Delta|| <= 1``.

    Omitted matrices mean no uncertainty in that channel.
    """

    G1: Matrix | None = None
    H1: Matrix | None = None
    G2: Matrix | None = None
    H2: Matrix | None = None


class SaturationConfig(Section):
    """Actuator limits on the plant input ``u``."""

    u_min: float | None = None
    u_max: float | None = None

    @model_validator(mode="after")
    def _ordered(self) -> SaturationConfig:
        if self.u_min is not None and self.u_max is not None and self.u_min >= self.u_max:
            raise ValueError("u_min must be below u_max")
        return self


#: the largest ``internal_step (velocity_kp + viscous) / J`` a PMSM axis may have (see ``PmsmConfig._step_is_stable``)
MAX_STEP_GAIN = 0.25


class PmsmSpread(Section):
    """Relative bounds of the per-run random parameter draws: each parameter is scaled by a factor drawn
    uniformly from ``[1 - spread, 1 + spread]`` (seeded by ``plant.seed``, so runs reproduce)."""

    inertia: float = Field(default=0.0, ge=0, lt=1)
    viscous: float = Field(default=0.0, ge=0, lt=1)
    coulomb: float = Field(default=0.0, ge=0, lt=1)
    torque_constant: float = Field(default=0.0, ge=0, lt=1)
    resistance: float = Field(default=0.0, ge=0, lt=1)
    inductance: float = Field(default=0.0, ge=0, lt=1)


class PmsmDrift(Section):
    """Slow sinusoidal drift of the inertia within a trial:
    ``J(t) = J * (1 + amplitude * sin(frequency * t + phase + phase_per_trial * (trial - 1)))``."""

    amplitude: float = Field(default=0.0, ge=0, lt=1)  # relative
    frequency: float = Field(default=0.5, gt=0)  # rad/s
    phase: float = 0.0  # rad, the drift's phase at t = 0 of trial 1
    phase_per_trial: float = 0.0  # rad, so the drift differs from trial to trial


class PmsmConfig(Section):
    """A PMSM servo axis (default: a 400 W class SCARA joint) with its drive's current and velocity loops.

    Units: velocity in rpm (mechanical), torque in N m, angle in rad, resistance in ohm, inductance in H, inertia
    in kg m^2 (motor plus reflected load), viscous friction in N m s/rad. See :mod:`plant_emulator.physics.pmsm`.
    """

    # electrical
    pole_pairs: int = Field(default=4, ge=1)
    resistance: float = Field(default=1.2, gt=0)  # phase resistance Rs, ohm
    inductance_d: float = Field(default=4.0e-3, gt=0)  # Ld, H
    inductance_q: float = Field(default=4.0e-3, gt=0)  # Lq, H
    torque_constant: float = Field(default=0.3, gt=0)  # Kt = 1.5 * p * psi_f, N m/A (peak-current dq convention)
    dc_bus_voltage: float = Field(default=300.0, gt=0)  # V; the voltage vector is limited to Vdc / sqrt(3)
    current_bandwidth: float = Field(default=3000.0, gt=0)  # rad/s, closed current loop (PI tuned by pole-zero cancel)
    # mechanical
    inertia: float = Field(default=5.0e-4, gt=0)  # J, kg m^2
    viscous: float = Field(default=1.0e-4, ge=0)  # B, N m s/rad
    coulomb: float = Field(default=0.02, ge=0)  # N m
    coulomb_velocity_scale: float = Field(default=1.0, gt=0)  # rpm, tanh smoothing of the Coulomb term
    cogging_amplitude: float = Field(default=0.01, ge=0)  # N m
    cogging_periods: int = Field(default=24, ge=1)  # cogging periods per mechanical revolution
    # Without a brake an unpowered axis under a load (plant.disturbance) accelerates, and enabling its drive past
    # speed_limit trips over-speed; a real loaded joint has a brake the drive closes while its power stage is off.
    brake_torque: float = Field(default=0.0, ge=0)  # N m, holding brake (0: none): holds a load up to it, brakes motion
    # ratings and limits
    rated_torque: float = Field(default=1.27, gt=0)  # N m; 0x6071/0x6077 are per mille of this
    torque_limit: float = Field(default=3.8, gt=0)  # N m, peak torque the drive allows
    rated_speed: float = Field(default=3000.0, gt=0)  # rpm; velocity commands are clamped to +-rated_speed
    speed_limit: float = Field(default=3600.0, gt=0)  # rpm; above it ``over_speed`` is raised
    # sensing
    resolver_bits: int = Field(default=16, ge=4, le=32)  # counts per mechanical revolution = 2**bits
    velocity_filter: float = Field(default=0.0, ge=0)  # s, low-pass time constant of the reported velocity
    # drive's velocity loop (CSV), running every internal step
    input_kind: Literal["velocity", "torque"] = "velocity"
    velocity_kp: float = Field(default=0.05, ge=0)  # N m per rad/s
    velocity_ki: float = Field(default=0.25, ge=0)  # N m per rad
    velocity_setpoint_weight: float = Field(default=0.0, ge=0, le=1)  # 0: I-P (no overshoot), 1: plain PI
    velocity_loop_filter: float = Field(default=5.0e-4, ge=0)  # s, low-pass of the loop's own velocity estimate
    internal_step: float = Field(default=5.0e-5, gt=0, le=1.0e-3)  # s, fixed sub-step independent of the caller
    # uncertainty
    spread: PmsmSpread = PmsmSpread()
    drift: PmsmDrift = PmsmDrift()

    @model_validator(mode="after")
    def _limits_ordered(self) -> PmsmConfig:
        if self.torque_limit < self.rated_torque:
            raise ValueError("torque_limit must be at least rated_torque")
        if self.speed_limit < self.rated_speed:
            raise ValueError("speed_limit must be at least rated_speed")
        return self

    @model_validator(mode="after")
    def _step_is_stable(self) -> PmsmConfig:
        """The mechanics and the drive's velocity loop advance by explicit internal steps: with a step long against
        the axis's mechanical time constant they oscillate and then diverge (measured on the demo's axis: a limit
        cycle from ``internal_step (velocity_kp + viscous) / J`` of about 0.5, NaN from about 25). Refused above
        :data:`MAX_STEP_GAIN`, at the smallest inertia the spread and the drift reach."""
        smallest = self.inertia * (1.0 - self.spread.inertia) * (1.0 - self.drift.amplitude)
        gain = self.internal_step * (self.velocity_kp + self.viscous) / smallest
        if gain > MAX_STEP_GAIN:
            raise ValueError(
                f"inertia {self.inertia:g} kg m^2 (down to {smallest:g} with spread and drift) is too small for "
                f"internal_step {self.internal_step:g} s and velocity_kp + viscous {self.velocity_kp + self.viscous:g}"
                f": the emulated axis would diverge (internal_step (velocity_kp + viscous) / inertia = {gain:.3g}, at "
                f"most {MAX_STEP_GAIN}); raise inertia or lower internal_step"
            )
        return self


class PlantConfig(Section):
    """The plant. ``first_order`` is the paper's model (48) ``x' = (a + Da) x + (b + Db) u + d, y = c x`` (``a``,
    ``b``, ``c`` may be matrices for multi-input/multi-output plants); ``pmsm`` is a PMSM axis (``pmsm:``
    section) whose design model is still ``a``, ``b``, ``c`` (identified or given).
    ``num``/``den`` (highest power first) may be given instead of ``a``/``b``/``c`` for a single-input plant.
    """

    model: Literal["first_order", "pmsm"] = "first_order"
    a: Matrix | None = None
    b: Matrix | None = None
    c: Matrix | None = None
    num: list[float] | None = None
    den: list[float] | None = None
    delay: float = Field(default=0.0, ge=0)  # transport delay, seconds
    x0: list[float] | None = None
    uncertainty: UncertaintyConfig = UncertaintyConfig()
    variation: ParameterVariation = ParameterVariation()
    disturbance: DisturbanceConfig = DisturbanceConfig()
    saturation: SaturationConfig = SaturationConfig()
    output_noise: float = Field(default=0.0, ge=0)  # std of additive measurement noise
    seed: int = 0
    # why a second seed: a new plant.seed also redraws a pmsm's parameters (pmsm.spread); this one moves the noise alone
    noise_seed: int | None = None  # seed of the sensor noise (None: the physics seed, plant.seed or the node's)
    pmsm: PmsmConfig = PmsmConfig()  # used when ``model: pmsm``

"""Config sections owned by the plant side: physics models and the virtual drive.

The ``plant:`` section is shared by offline simulation, tuning, synthesis and the emulator (one physics code
path). The ``emulator:`` section configures only the virtual drive.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from foilc_hil.schema import Matrix, Section


class VariationConfig(Section):
    """Time-varying parameter uncertainty ``Delta(t)`` added to a nominal parameter."""

    kind: Literal["none", "sine", "random_walk"] = "none"
    amplitude: float = Field(default=0.0, ge=0)  # absolute bound on |Delta(t)|
    frequency: float = Field(default=1.0, gt=0)  # rad/s (sine) or correlation rate (random walk)


class ParameterVariation(Section):
    """Time variation of the first-order model's ``a`` and ``b``."""

    a: VariationConfig = VariationConfig()
    b: VariationConfig = VariationConfig()


class DisturbanceConfig(Section):
    """External disturbance ``d(t)`` entering the state equation, from ``start_trial`` on."""

    kind: Literal["none", "constant", "step", "sine", "square"] = "none"
    amplitude: float = 0.0
    frequency: float = Field(default=1.0, gt=0)  # rad/s
    start_time: float = Field(default=0.0, ge=0)  # within a trial, seconds
    start_trial: int = Field(default=1, ge=1)


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

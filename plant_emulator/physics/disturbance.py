"""The external disturbance ``d(t)`` of a trial (paper eq. 48; errata 6: added from a given trial on)."""

from __future__ import annotations

import numpy as np

from plant_emulator.config import DisturbanceConfig
from plant_emulator.physics.kernels import DisturbanceCode, disturbance_value, disturbance_values

__all__ = ["Disturbance"]


class Disturbance:
    """``d(t)`` within trial ``trial``: zero before ``start_trial``; see :class:`DisturbanceConfig` for shapes.

    The value is the compiled :func:`~plant_emulator.physics.kernels.disturbance_value`, the same function the PMSM
    kernel evaluates inside its sub-steps.
    """

    def __init__(self, config: DisturbanceConfig) -> None:
        self._config = config
        self._kind = DisturbanceCode[config.kind.upper()]
        self._code = DisturbanceCode.NONE

    @property
    def active(self) -> bool:
        """Whether the disturbance acts in the current trial."""
        return self._code is not DisturbanceCode.NONE

    @property
    def code(self) -> DisturbanceCode:
        """The shape acting in the current trial (``NONE`` while the disturbance is not armed)."""
        return self._code

    @property
    def config(self) -> DisturbanceConfig:
        """The ``plant.disturbance`` section."""
        return self._config

    def reset(self, trial: int) -> None:
        """Arm (or disarm) the disturbance for ``trial``."""
        armed = trial >= self._config.start_trial
        self._code = self._kind if armed else DisturbanceCode.NONE

    def value(self, t: float) -> float:
        """``d(t)``, ``t`` in seconds since the start of the trial."""
        config = self._config
        return float(
            disturbance_value(
                int(self._code), config.amplitude, config.frequency, config.phase, config.start_time, t
            )
        )

    def over_step(self, t0: float, dt: float) -> float:
        """The value held over ``[t0, t0 + dt]`` (sampled at the midpoint, like ``Delta``); 0.0 unarmed, as the
        kernel gives it, without its call (a plant asks every step)."""
        if not self.active:
            return 0.0
        return self.value(t0 + 0.5 * dt)

    def values(self, t0: float, dt: float, count: int) -> np.ndarray:
        """What :meth:`over_step` gives for ``count`` consecutive steps of ``dt`` from ``t0``, ``(count,)``."""
        out = np.zeros(count)
        if self.active:
            config = self._config
            disturbance_values(
                int(self._code), config.amplitude, config.frequency, config.phase, config.start_time, t0, dt, out
            )
        return out

"""The external disturbance ``d(t)`` of a trial (paper eq. 48; errata 6: added from a given trial on)."""

from __future__ import annotations

import math

from plant_emulator.config import DisturbanceConfig

__all__ = ["Disturbance"]


class Disturbance:
    """``d(t)`` within trial ``trial``: zero before ``start_trial``; see :class:`DisturbanceConfig` for shapes."""

    def __init__(self, config: DisturbanceConfig) -> None:
        self._config = config
        self._active = False

    @property
    def active(self) -> bool:
        """Whether the disturbance acts in the current trial."""
        return self._active

    def reset(self, trial: int) -> None:
        """Arm (or disarm) the disturbance for ``trial``."""
        config = self._config
        self._active = config.kind != "none" and trial >= config.start_trial

    def value(self, t: float) -> float:
        """``d(t)``, ``t`` in seconds since the start of the trial."""
        if not self._active:
            return 0.0
        config = self._config
        if config.kind == "constant":
            return config.amplitude
        elapsed = t - config.start_time
        if elapsed < 0:
            return 0.0
        if config.kind == "step":
            return config.amplitude
        phase = math.sin(config.frequency * elapsed)
        if config.kind == "sine":
            return config.amplitude * phase
        return config.amplitude if phase >= 0 else -config.amplitude  # square

    def over_step(self, t0: float, dt: float) -> float:
        """The value held over ``[t0, t0 + dt]`` (sampled at the midpoint, like ``Delta``)."""
        return self.value(t0 + 0.5 * dt)

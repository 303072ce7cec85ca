"""Time-varying parameter uncertainty ``Delta(t)`` (paper eq. 48) as a per-step signal.

The physics holds ``Delta`` constant over one integration step (piecewise constant), so each step stays an exact
zero-order-hold solution of a linear system. A ``sine`` is sampled at the step's midpoint (midpoint rule: the
state error of this approximation is second order in the step, see ``tests/test_physics_first_order.py``); a
``random_walk`` is a seeded Ornstein-Uhlenbeck process clipped to ``[-amplitude, amplitude]``, advanced once per
step and held over it.
"""

from __future__ import annotations

import math

import numpy as np

from plant_emulator.config import VariationConfig
from plant_emulator.physics.base import trial_rng

__all__ = ["VariationSignal"]


class VariationSignal:
    """``Delta(t)`` for one parameter; :meth:`reset` per trial, then :meth:`over_step` once per step.

    Parameters
    ----------
    config
        Kind, bound ``amplitude`` on ``|Delta|``, and ``frequency`` (rad/s for the sine; mean-reversion rate
        for the random walk).
    seed, stream
        Make the random walk reproducible: same (seed, trial, stream), same path.
    """

    def __init__(self, config: VariationConfig, seed: int, stream: int) -> None:
        self._config = config
        self._seed = seed
        self._stream = stream
        self._rng = trial_rng(seed, 1, stream)
        self._walk = 0.0

    @property
    def active(self) -> bool:
        """Whether ``Delta`` can be non-zero."""
        return self._config.kind != "none" and self._config.amplitude > 0

    def reset(self, trial: int) -> None:
        """Restart at ``Delta = 0`` (random walk) with the generator for ``trial``."""
        self._rng = trial_rng(self._seed, trial, self._stream)
        self._walk = 0.0

    def over_step(self, t0: float, dt: float) -> float:
        """The value of ``Delta`` held over the step ``[t0, t0 + dt]``."""
        config = self._config
        if not self.active:
            return 0.0
        if config.kind == "sine":
            return config.amplitude * math.sin(config.frequency * (t0 + 0.5 * dt))
        # Ornstein-Uhlenbeck with stationary standard deviation amplitude / 2, then clipped to the bound.
        rate = config.frequency
        decay = math.exp(-rate * dt)
        sigma = 0.5 * config.amplitude * math.sqrt(max(0.0, 1.0 - decay * decay))
        self._walk = decay * self._walk + sigma * float(self._rng.standard_normal())
        self._walk = float(np.clip(self._walk, -config.amplitude, config.amplitude))
        return self._walk

"""Time-varying parameter uncertainty ``Delta(t)`` (paper eq. 48) as a per-step signal.

The physics holds ``Delta`` constant over one integration step (piecewise constant), so each step stays an exact
zero-order-hold solution of a linear system. A ``sine`` is sampled at the step's midpoint (midpoint rule: the
state error of this approximation is second order in the step, see
``tests/plant_emulator/test_physics_first_order.py``); a ``random_walk`` is a seeded Ornstein-Uhlenbeck process clipped
to ``[-amplitude, amplitude]``, advanced once per step and held over it. The arithmetic is the compiled
:func:`~plant_emulator.physics.kernels.variation_values`: one step per :meth:`VariationSignal.over_step`, or a whole
trial's steps at once (:meth:`VariationSignal.values`, for the compiled trial loop), with the same numbers.
"""

from __future__ import annotations

import numpy as np

from plant_emulator.config import VariationConfig
from plant_emulator.physics.base import trial_rng
from plant_emulator.physics.kernels import VariationCode, variation_values

__all__ = ["VariationSignal"]


class VariationSignal:
    """``Delta(t)`` for one parameter; :meth:`reset` per trial, then :meth:`over_step` once per step.

    Parameters
    ----------
    config
        Kind, bound ``amplitude`` on ``|Delta|``, ``frequency`` (rad/s for the sine; mean-reversion rate
        for the random walk) and the sine's ``phase`` (rad).
    seed, stream
        Make the random walk reproducible: same (seed, trial, stream), same path.
    """

    def __init__(self, config: VariationConfig, seed: int, stream: int) -> None:
        self._config = config
        self._code = VariationCode[config.kind.upper()]
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
        if not self.active:
            return 0.0
        return float(self.values(t0, dt, 1)[0])

    def values(self, t0: float, dt: float, count: int) -> np.ndarray:
        """The values ``count`` calls of :meth:`over_step` would return for the consecutive steps of ``dt`` from
        ``t0`` (the random walk advances as they would), ``(count,)``: a trial's ``Delta`` drawn in advance."""
        out = np.zeros(count)
        if not self.active:
            return out
        config = self._config
        # one standard normal per step, from the trial's generator in order: the same numbers as step by step
        normals = self._rng.standard_normal(count) if self._code is VariationCode.RANDOM_WALK else out
        self._walk = variation_values(
            int(self._code), config.amplitude, config.frequency, config.phase, t0, dt, normals, self._walk, out
        )
        return out

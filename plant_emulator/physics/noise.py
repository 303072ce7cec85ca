"""Seeded sensor noise: white Gaussian noise of standard deviation ``plant.output_noise`` added to the measured output.

Both plants (:mod:`~plant_emulator.physics.first_order` and :mod:`~plant_emulator.physics.pmsm`, on top of the
resolver's quantisation) draw it here, so ``simulate`` and the virtual drive see the same noise for the same seed.
Trial ``k``'s noise comes from its own generator ``trial_rng(seed, k, stream)``: it does not depend on how many
trials ran before, and a reset replays it. The measurement at :meth:`SensorNoise.reset` takes draw 0 and the one
after step ``i`` draw ``i``, so :meth:`SensorNoise.trial_vector` is the whole trial's noise drawn in advance (the
same numbers, as a compiled trial kernel takes them: a vector argument, no generator inside the kernel).
"""

from __future__ import annotations

import numpy as np

from plant_emulator.config import PlantConfig
from plant_emulator.physics.base import trial_rng

__all__ = ["SensorNoise", "plant_noise"]


class SensorNoise:
    """The measurement noise of one plant: :meth:`reset` per trial, then :meth:`sample` once per measurement.

    Parameters
    ----------
    std
        Standard deviation (the output's unit); 0 disables the noise (no draws at all).
    seed, stream
        The generator of trial ``k`` is ``trial_rng(seed, k, stream)``.
    outputs
        Measured outputs (one draw each per measurement).
    """

    def __init__(self, std: float, seed: int, stream: int, outputs: int) -> None:
        self.std = float(std)
        self._seed = seed
        self._stream = stream
        self._outputs = outputs
        self._rng = trial_rng(seed, 1, stream)

    @property
    def active(self) -> bool:
        """Whether any noise is added."""
        return self.std > 0

    def reset(self, trial: int) -> None:
        """Start trial ``trial``'s sequence from its first draw."""
        self._rng = trial_rng(self._seed, trial, self._stream)

    def sample(self) -> np.ndarray:
        """The next measurement's noise, shape ``(outputs,)`` (zeros when inactive)."""
        if not self.active:
            return np.zeros(self._outputs)
        return self.std * self._rng.standard_normal(self._outputs)

    def following(self, measurements: int) -> np.ndarray:
        """The next ``measurements`` noise samples, ``(measurements, outputs)``, continuing the trial's sequence: what
        as many calls of :meth:`sample` would return (a compiled trial takes them as one array)."""
        if not self.active:
            return np.zeros((measurements, self._outputs))
        return self.std * self._rng.standard_normal((measurements, self._outputs))

    def trial_vector(self, trial: int, measurements: int) -> np.ndarray:
        """Trial ``trial``'s first ``measurements`` noise samples, ``(measurements, outputs)``, drawn at once: row 0
        is the measurement at reset, row ``i`` the one after step ``i`` (what :meth:`sample` returns in turn)."""
        if not self.active:
            return np.zeros((measurements, self._outputs))
        return self.std * trial_rng(self._seed, trial, self._stream).standard_normal((measurements, self._outputs))


def plant_noise(plant: PlantConfig, seed: int, stream: int, outputs: int) -> SensorNoise:
    """The sensor noise of a plant built with the physics seed ``seed``: ``plant.output_noise`` seeded by
    ``plant.noise_seed``, or by ``seed`` when that is not set (one rule for both plants)."""
    return SensorNoise(plant.output_noise, seed if plant.noise_seed is None else plant.noise_seed, stream, outputs)

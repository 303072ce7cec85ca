"""The plant's nominal linear model, extracted from the ``plant:`` config section.

Tuning (transfer function), synthesis (state space) and the physics all start from here, so they agree on
what the plant is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.errors import ConfigError
from plant_emulator.config import PlantConfig
from plant_emulator.matrix import as_array


@dataclass(frozen=True)
class ContinuousModel:
    """``x' = a x + b u``, ``y = c x``, with an optional input transport delay ``delay`` (seconds)."""

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    delay: float = 0.0

    @property
    def n_states(self) -> int:
        return int(self.a.shape[0])

    @property
    def n_inputs(self) -> int:
        return int(self.b.shape[1])

    @property
    def n_outputs(self) -> int:
        return int(self.c.shape[0])

    def transfer_function(self) -> tuple[list[float], list[float]]:
        """``num``, ``den`` (highest power first) of a single-input single-output model."""
        if self.n_inputs != 1 or self.n_outputs != 1:
            raise ConfigError(
                f"a transfer function needs a single-input single-output plant, this one is "
                f"{self.n_outputs}x{self.n_inputs}",
                key="plant",
            )
        # scipy.signal.ss2tf's own formula for D = 0, num = poly(A - B C) - poly(A), den = poly(A), without importing
        # scipy.signal (about 1 s of a process's start: it imports scipy.stats) for two characteristic polynomials
        den = np.poly(self.a)
        num = np.poly(self.a - self.b @ self.c) - den
        num_row = np.trim_zeros(np.asarray(num, dtype=float), "f")
        return [float(x) for x in (num_row if num_row.size else [0.0])], [float(x) for x in den]


def continuous_model(plant: PlantConfig) -> ContinuousModel:
    """The nominal continuous model of ``plant``, validated for shape; errors name the offending key.

    A ``pmsm`` plant given without ``a``/``b``/``num``/``den`` uses the first-order approximation of its nominal
    axis (:func:`plant_emulator.physics.pmsm.nominal_first_order`, in rpm), so a default PMSM config can be
    tuned and synthesised before it is identified.
    """
    if plant.model == "pmsm" and all(v is None for v in (plant.a, plant.b, plant.num, plant.den)):
        from plant_emulator.physics.pmsm import nominal_first_order

        pole, gain = nominal_first_order(plant.pmsm)
        return ContinuousModel(np.array([[pole]]), np.array([[gain]]), np.array([[1.0]]), plant.delay)
    if plant.a is not None or plant.b is not None:
        if plant.a is None or plant.b is None:
            raise ConfigError("give both 'a' and 'b' (or 'num' and 'den')", key="plant")
        a = as_array(plant.a, "plant.a")
        b = as_array(plant.b, "plant.b")
        n = a.shape[0]
        if a.shape != (n, n):
            raise ConfigError(f"must be square, got {a.shape[0]}x{a.shape[1]}", key="plant.a")
        if b.shape[0] != n:
            raise ConfigError(f"must have {n} rows (the states of 'a'), got {b.shape[0]}", key="plant.b")
        if not np.any(b):
            raise ConfigError("must be non-zero", key="plant.b")
        c = as_array(plant.c, "plant.c") if plant.c is not None else np.eye(n)
        if c.shape[1] != n:
            raise ConfigError(f"must have {n} columns (the states of 'a'), got {c.shape[1]}", key="plant.c")
        model = ContinuousModel(a, b, c, plant.delay)
        if plant.num is not None or plant.den is not None:
            _check_consistent(model, plant)
        return model
    if plant.num is None or plant.den is None:
        raise ConfigError("give 'a' and 'b' (state space) or 'num' and 'den' (transfer function)", key="plant")
    return _from_transfer_function(plant)


def _from_transfer_function(plant: PlantConfig) -> ContinuousModel:
    assert plant.num is not None and plant.den is not None
    den = np.trim_zeros(np.asarray(plant.den, dtype=float), "f")
    num = np.trim_zeros(np.asarray(plant.num, dtype=float), "f")
    if den.size < 2:
        raise ConfigError("must have degree 1 or more", key="plant.den")
    if num.size == 0:
        raise ConfigError("must be non-zero", key="plant.num")
    if num.size >= den.size:
        raise ConfigError("the plant must be strictly proper (deg num < deg den)", key="plant.num")
    from scipy import signal  # here: scipy.signal costs a process ~1 s to import (scipy.stats)

    a, b, c, _ = signal.tf2ss(num, den)
    return ContinuousModel(np.asarray(a, float), np.asarray(b, float), np.asarray(c, float), plant.delay)


def _check_consistent(model: ContinuousModel, plant: PlantConfig) -> None:
    other = _from_transfer_function(plant)
    for w in (0.1, 1.0, 10.0):
        g1 = _frequency_response(model, w)
        g2 = _frequency_response(other, w)
        if not np.allclose(g1, g2, rtol=1e-6, atol=1e-9):
            raise ConfigError("'num'/'den' disagree with 'a'/'b'/'c'; give one form", key="plant")


def _frequency_response(model: ContinuousModel, w: float) -> np.ndarray:
    n = model.n_states
    return np.asarray(model.c @ np.linalg.solve(1j * w * np.eye(n) - model.a, model.b))

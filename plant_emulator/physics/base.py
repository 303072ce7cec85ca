"""The ``Plant`` protocol: what every physics model offers to simulation, the virtual drive and identification.

A plant is advanced by :meth:`Plant.step` with the input held constant over the step (zero-order hold, as a
drive applies a setpoint received on SYNC). :meth:`Plant.reset` starts a trial (1-based) from the initial
condition; everything random (noise, random-walk variation, parameter draws) is a deterministic function of the
seed and the trial number, so runs reproduce bit for bit.
"""

from __future__ import annotations

import math
from typing import Protocol, runtime_checkable

import numpy as np

from drivers.errors import ConfigError, InputError

__all__ = ["Plant", "ScalarPlant", "check_input", "check_scalar_input", "check_step", "check_trial", "trial_rng"]


@runtime_checkable
class Plant(Protocol):
    """A physics model advanced step by step with a zero-order-held input."""

    n_inputs: int
    n_outputs: int

    def reset(self, trial: int) -> None:
        """Start trial ``trial`` (1-based) at the initial condition; the disturbance is active iff
        ``trial >= disturbance.start_trial``. Deterministic per (seed, trial)."""
        ...

    def step(self, u: np.ndarray, dt: float) -> np.ndarray:
        """Hold ``u`` over ``dt`` seconds (after actuator saturation); return the measured output at the end."""
        ...

    def output(self) -> np.ndarray:
        """The current measured output (quantisation and noise included)."""
        ...

    def state(self) -> np.ndarray:
        """The current true state."""
        ...

    @property
    def time(self) -> float:
        """Seconds since the last :meth:`reset`."""
        ...


class ScalarPlant(Protocol):
    """A single-input plant that also steps with floats: ``step_scalar(u, dt)`` is ``step(array([u]), dt)[0]``,
    without the two arrays. The virtual drive looks it up on the plant's class (``type(plant).step_scalar``), so a
    wrapper that delegates attributes (``plant_emulator.faults.InputGainDrift``) keeps its own ``step``."""

    def step_scalar(self, u: float, dt: float) -> float:
        """Hold ``u`` over ``dt`` seconds; return the measured output."""
        ...


def trial_rng(seed: int, trial: int, stream: int) -> np.random.Generator:
    """An independent random generator for (``seed``, ``trial``, ``stream``); same arguments, same numbers."""
    return np.random.default_rng([abs(int(seed)), int(seed < 0), int(trial), int(stream)])


def check_input(u: np.ndarray | float | list[float], n_inputs: int) -> np.ndarray:
    """``u`` as a float vector of length ``n_inputs``; a scalar is accepted for a single-input plant."""
    vector = np.asarray(u, dtype=float)
    if vector.shape != (n_inputs,):
        vector = np.atleast_1d(vector).reshape(-1)
        if vector.shape != (n_inputs,):
            raise InputError(f"u must have {n_inputs} entries, got {vector.size}")
    # math.isfinite over a short list: called every step, and ~10x cheaper than np.all(np.isfinite(.)) on tiny arrays
    if not all(map(math.isfinite, vector.tolist())):
        raise InputError("u must be finite")
    return vector


def check_scalar_input(u: np.ndarray | float | list[float]) -> float:
    """The one entry of a single-input plant's ``u`` as a finite float, by the rules of :func:`check_input`.

    The loop's own ``float64`` vector of one entry, and a plain float (:meth:`ScalarPlant.step_scalar`), are read
    directly (no conversion, no list): this runs every step of a plant, where :func:`check_input`'s general path
    costs about a fifth of a microsecond more.
    """
    if type(u) is float:
        if math.isfinite(u):
            return u
    elif type(u) is np.ndarray and u.shape == (1,) and u.dtype == np.float64:
        value = float(u[0])
        if math.isfinite(value):
            return value
    return float(check_input(u, 1)[0])  # anything else, and every error, by the general rules


def check_step(dt: float) -> float:
    """``dt`` as a positive finite float."""
    value = float(dt)
    if not math.isfinite(value) or value <= 0:  # math, not numpy: a plant checks every step
        raise InputError(f"dt must be positive and finite, got {dt!r}")
    return value


def check_trial(trial: int) -> int:
    """``trial`` as a 1-based trial number."""
    if int(trial) != trial or trial < 1:
        raise ConfigError(f"trial numbers start at 1, got {trial!r}", key="trial")
    return int(trial)

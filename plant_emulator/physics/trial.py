"""A plant's whole trial for a compiled loop: its state, parameters and per-step inputs as flat arrays.

A compiled trial loop (``foilc_hil.loop.trial_kernel``) steps the plant once per sample without returning to the
interpreter. It cannot call a plant object or draw from a numpy generator, so the plant hands it a
:class:`TrialProgram`: its state and parameters as ``float64`` vectors with named slots, and everything random or
time-varying of the trial drawn in advance from the plant's own seeded generators, one row per step (noise,
``Delta(t)``, ``d(t)``: the same numbers, in the same order, as stepping the plant one call at a time).
:func:`plant_trial_step` is one step of it: it calls the same compiled step the plant's own :meth:`step` calls
(:func:`~plant_emulator.physics.kernels.scalar_plant_step`, :func:`~plant_emulator.physics.kernels.pmsm_step`), so a
trial stepped here and one stepped call by call give the same outputs bit for bit.

Which plants have a program: the scalar first-order plant (one state, one input, one output) whose transport delay
is a whole number of steps (:attr:`TrialProgram.delay_steps`: the loop then hands it the command of that many steps
before) and the PMSM axis (:meth:`CompiledPlant.trial_program`; ``None`` for the others, which are then stepped call
by call). After the loop, :meth:`CompiledPlant.end_trial_program` puts the state it reached back into the plant.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numba import njit

from plant_emulator.physics.kernels import (
    PMSM_PARAM_SIZE,
    PMSM_STATE_SIZE,
    pmsm_step,
    scalar_plant_step,
)

__all__ = [
    "CompiledPlant",
    "PlantKind",
    "PmsmTrialParam",
    "PmsmTrialState",
    "ScalarInput",
    "ScalarParam",
    "ScalarState",
    "TrialProgram",
    "plant_trial_step",
    "warm_up",
]


@enum.unique
class PlantKind(enum.IntEnum):
    """Which compiled step a :class:`TrialProgram` runs."""

    SCALAR = 0  # the first-order plant with one state, one input, one output
    PMSM = 1


@enum.unique
class ScalarState(enum.IntEnum):
    """Slots of a scalar plant's program state."""

    X = 0
    TIME = 1  # seconds since the trial's reset, accumulated step by step as the plant's clock
    COMMAND = 2  # the saturated command of the last step (a slot: the step kernel takes a vector)
    SATURATED = 3  # 1.0: the last step's command was clipped by plant.saturation


@enum.unique
class ScalarParam(enum.IntEnum):
    """Slots of a scalar plant's program parameters."""

    A = 0
    B = 1
    B_PATTERN = 2  # 1.0 if Delta b acts on the input (b != 0), else 0.0
    C = 3
    U_MIN = 4  # plant.saturation (-inf / inf: none)
    U_MAX = 5
    STEP = 6  # seconds per step (the clock's increment)
    NOISY = 7  # 1.0: add the noise column to the output


@enum.unique
class ScalarInput(enum.IntEnum):
    """Columns of a scalar plant's per-step inputs: what holds over step ``k`` and the noise of the output after
    it."""

    DELTA_A = 0
    DELTA_B = 1
    DISTURBANCE = 2
    NOISE = 3
    STEP = 4  # the step's length as the plant integrates it: dt, or (t + dt) - t with a transport delay


@enum.unique
class PmsmTrialParam(enum.IntEnum):
    """Slots after the :class:`~plant_emulator.physics.kernels.PmsmParam` vector in a PMSM program's parameters."""

    U_MIN = PMSM_PARAM_SIZE  # plant.saturation (-inf / inf: none)
    U_MAX = PMSM_PARAM_SIZE + 1
    STEP = PMSM_PARAM_SIZE + 2  # seconds per caller step
    SUBSTEPS = PMSM_PARAM_SIZE + 3
    VELOCITY_MODE = PMSM_PARAM_SIZE + 4  # 1.0: velocity (CSV) input
    TRIAL = PMSM_PARAM_SIZE + 5
    SMOOTHING = PMSM_PARAM_SIZE + 6  # of the reported velocity's filter; NaN: no filter (kernels.pmsm_step)


@enum.unique
class PmsmTrialState(enum.IntEnum):
    """Slots after the :class:`~plant_emulator.physics.kernels.PmsmState` vector in a PMSM program's state."""

    REPORTED = PMSM_STATE_SIZE  # the reported velocity, rpm, before noise
    SATURATED = PMSM_STATE_SIZE + 1  # 1.0: the last step's command was clipped by plant.saturation


@dataclass(frozen=True)
class TrialProgram:
    """One trial of a plant as flat arrays (module docstring).

    Attributes
    ----------
    kind
        The compiled step that runs it.
    state
        The state it starts from, advanced in place by :func:`plant_trial_step`.
    params
        Parameters and per-trial settings (read only, but for the PMSM's derived slots, which its first step
        writes: :data:`~plant_emulator.physics.kernels.PmsmParam.DERIVED_STEP`).
    inputs
        ``(steps, k)``: row ``i`` holds over step ``i`` (and its noise is that of the output after step ``i``).
    delay_steps
        The plant's own transport delay in steps: step ``i`` must be given the command of step ``i - delay_steps``
        (zero before the trial's first).
    """

    kind: PlantKind
    state: np.ndarray
    params: np.ndarray
    inputs: np.ndarray
    delay_steps: int = 0

    @property
    def steps(self) -> int:
        """How many steps the program holds inputs for."""
        return int(self.inputs.shape[0])


@runtime_checkable
class CompiledPlant(Protocol):
    """A plant that can hand a trial to a compiled loop."""

    def trial_program(self, steps: int, dt: float) -> TrialProgram | None:
        """The next ``steps`` steps of ``dt`` seconds from the plant's current state (just after ``reset``), or
        ``None`` if this plant is only stepped call by call. Draws the trial's random inputs from the plant's
        generators, as ``steps`` calls of ``step`` would."""
        ...

    def end_trial_program(self, program: TrialProgram, commands: np.ndarray, output: float) -> None:
        """Take over the state ``program`` reached after ``len(commands)`` of its steps, given ``commands`` (before
        the transport delay and saturation), measured as ``output``: the plant is then where as many calls of
        ``step`` would have left it."""
        ...


# The cached machine code of plant_trial_step includes pmsm_step and the PmsmParam slots of kernels.py (up to the
# derived slots written by pmsm_advance itself), but numba invalidates it only when THIS file changes: a change of
# kernels.py needs one here.
@njit(cache=True)
def plant_trial_step(kind: int, state: np.ndarray, params: np.ndarray, row: np.ndarray, command: float) -> float:
    """Step ``k`` of a :class:`TrialProgram` (``row = inputs[k]``) with ``command`` held (before the plant's
    saturation); returns the measured output after it."""
    if kind == PlantKind.SCALAR:
        state[ScalarState.COMMAND] = min(max(command, params[ScalarParam.U_MIN]), params[ScalarParam.U_MAX])
        state[ScalarState.SATURATED] = 1.0 if state[ScalarState.COMMAND] != command else 0.0
        x = scalar_plant_step(
            state[ScalarState.X],
            params[ScalarParam.A],
            params[ScalarParam.B : ScalarParam.B + 1],
            params[ScalarParam.B_PATTERN : ScalarParam.B_PATTERN + 1],
            state[ScalarState.COMMAND : ScalarState.COMMAND + 1],
            (row[ScalarInput.DELTA_A], row[ScalarInput.DELTA_B]),
            row[ScalarInput.DISTURBANCE],
            row[ScalarInput.STEP],
        )
        state[ScalarState.X] = x
        state[ScalarState.TIME] = state[ScalarState.TIME] + params[ScalarParam.STEP]
        y = params[ScalarParam.C] * x
        return y + row[ScalarInput.NOISE] if params[ScalarParam.NOISY] > 0 else y
    applied = min(max(command, params[PmsmTrialParam.U_MIN]), params[PmsmTrialParam.U_MAX])
    state[PmsmTrialState.SATURATED] = 1.0 if applied != command else 0.0
    reported = pmsm_step(
        state[:PMSM_STATE_SIZE],
        params[:PMSM_PARAM_SIZE],
        applied,
        params[PmsmTrialParam.STEP],
        int(params[PmsmTrialParam.SUBSTEPS]),
        params[PmsmTrialParam.VELOCITY_MODE] > 0,
        int(params[PmsmTrialParam.TRIAL]),
        params[PmsmTrialParam.SMOOTHING],
        state[PmsmTrialState.REPORTED],
    )
    state[PmsmTrialState.REPORTED] = reported
    return reported + row[0]  # the PMSM's one input column: the noise (0.0 without)


def warm_up() -> None:
    """Run :func:`plant_trial_step` once for each kind (compiled, or loaded from numba's cache)."""
    scalar = np.zeros(len(ScalarParam))
    scalar[ScalarParam.U_MIN], scalar[ScalarParam.U_MAX], scalar[ScalarParam.STEP] = -math.inf, math.inf, 1e-3
    plant_trial_step(int(PlantKind.SCALAR), np.zeros(len(ScalarState)), scalar, np.zeros(len(ScalarInput)), 0.0)
    pmsm = np.ones(PMSM_PARAM_SIZE + len(PmsmTrialParam))
    plant_trial_step(int(PlantKind.PMSM), np.zeros(PMSM_STATE_SIZE + len(PmsmTrialState)), pmsm, np.zeros(1), 0.0)


warm_up()  # at import: never inside a control loop's first cycle

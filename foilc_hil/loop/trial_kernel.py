"""A whole lockstep trial of the simulated drive in one compiled call: the law's step and the plant's step per sample.

:func:`run_trial` runs the cycles ``0 .. N-1`` of :class:`~foilc_hil.loop.bench.TrialLoop`'s trial (the ``N``
samples; the trial's last cycle, which only reads ``y(N Ts)``, stays the loop's own) for a
:class:`~foilc_hil.loop.simulated_drive.SimulatedDrive`, with the loop's checks. Cycle ``i``: its SYNC steps the
plant (not at ``i = 0``: the trial starts at the SYNC that reset it) with the command of ``input_delay`` cycles
before (:func:`plant_emulator.physics.trial.plant_trial_step`, the function the plant's own ``step`` runs on); the
output ``y_i`` (not finite: stop) gives ``u_i`` by the law's compiled step (:func:`foilc_hil.laws.kernels.law_step`,
the function :meth:`~foilc_hil.laws.learning.LearningLaw.command` calls; not finite: stop). Nothing else is decided
here: the trial loop stays :class:`~foilc_hil.loop.bench.TrialLoop`, which asks the drive to run these cycles
(:meth:`~foilc_hil.loop.simulated_drive.SimulatedDrive.run_whole_trial`) and keeps the trial's last cycle, the
settle phases, the update between trials, the divergence rule and the log.

Compiled like the law's and the plant's kernels (``cache=True``, warmed at import, no ``fastmath``). The cached
machine code of :func:`run_trial` includes the kernels it calls and their constants (the slots of
:mod:`plant_emulator.physics.trial` and :mod:`~plant_emulator.physics.kernels`, as of the PMSM's derived slots), but
numba invalidates it only when THIS file changes: a change there needs a change here (this note is one).
"""

from __future__ import annotations

import enum
import math

import numpy as np
from numba import njit

from foilc_hil.laws.kernels import law_step
from plant_emulator.physics.trial import PlantKind, ScalarInput, ScalarParam, ScalarState, plant_trial_step

__all__ = ["TrialStatus", "run_trial", "warm_up"]


@enum.unique
class TrialStatus(enum.IntEnum):
    """How :func:`run_trial` ended."""

    COMPLETE = 0
    OUTPUT_NOT_FINITE = 1  # the feedback of cycle ``index`` was NaN or infinite
    COMMAND_NOT_FINITE = 2  # the command of cycle ``index`` was NaN or infinite


@njit(cache=True)
def run_trial(
    seen: np.ndarray,
    control: np.ndarray,
    input_delay: int,
    plant: tuple[int, np.ndarray, np.ndarray, np.ndarray],
    outputs: np.ndarray,
    base: np.ndarray,
    commands: np.ndarray,
    state: np.ndarray,
    previous_state: np.ndarray,
    c_pinv: np.ndarray,
    p1: np.ndarray,
    use_previous: bool,
    lower: float,
    upper: float,
) -> tuple[int, int]:
    """Run the trial's cycles ``0 .. N-1`` (``N = len(control)``); returns ``(status, index)``.

    Parameters
    ----------
    seen
        ``(N + 1,)``: ``seen[0]`` is the output at the trial's start; ``seen[i]``, ``1 <= i < N``, is written with
        the output after plant step ``i`` (``seen[N]`` is left to the trial's last cycle).
    control
        ``(N,)``: written with ``u_i``.
    input_delay
        ``d``: the step of cycle ``i`` applies ``u_{i - 1 - d}`` (zero before the trial's first command).
    plant
        ``(kind, state, params, inputs)`` of a :class:`~plant_emulator.physics.trial.TrialProgram` with (at least)
        ``N - 1`` rows of inputs, row ``i - 1`` for step ``i``; its state is advanced in place.
    outputs, base, commands, state, previous_state, c_pinv, p1, use_previous, lower, upper
        The law's step arguments (:class:`~foilc_hil.laws.learning.StepArguments`).

    Returns
    -------
    tuple
        ``(TrialStatus.COMPLETE, N)``, or the status that stopped the trial and the cycle it stopped in (whose
        plant step, if any, was made).
    """
    kind, plant_state, plant_params, plant_inputs = plant
    for i in range(control.shape[0]):
        if i > 0:
            issued = i - 1 - input_delay
            applied = control[issued] if issued >= 0 else 0.0
            seen[i] = plant_trial_step(kind, plant_state, plant_params, plant_inputs[i - 1], applied)
        if not math.isfinite(seen[i]):
            return TrialStatus.OUTPUT_NOT_FINITE, i
        outputs[i, 0] = seen[i]
        law_step(i, outputs, base, commands, state, previous_state, c_pinv, p1, use_previous, lower, upper)
        if not math.isfinite(commands[i, 0]):
            return TrialStatus.COMMAND_NOT_FINITE, i
        control[i] = commands[i, 0]
    return TrialStatus.COMPLETE, control.shape[0]


def warm_up() -> None:
    """Run :func:`run_trial` once with the argument types the simulated drive passes (compiled, or loaded from
    numba's cache)."""
    rows = np.zeros((1, 1))
    params = np.zeros(len(ScalarParam))
    program = (int(PlantKind.SCALAR), np.zeros(len(ScalarState)), params, np.zeros((1, len(ScalarInput))))
    run_trial(np.zeros(2), np.zeros(1), 1, program, rows, rows, np.zeros((1, 1)), np.zeros((1, 0)),
              np.zeros((1, 0)), np.zeros((0, 1)), np.zeros((1, 0)), False, -math.inf, math.inf)


warm_up()  # at import: never inside a trial

"""A simulated drive: the physics of ``plant_emulator.physics`` behind the bench's :class:`~drivers.drive.Drive`.

The offline simulator runs the bench's own :class:`~foilc_hil.loop.bench.TrialLoop` on this drive, in lockstep,
so there is one trial loop; only what answers the SYNC differs (a CiA 402 drive over CAN, or this object).

Cycle order at SYNC ``k`` (the virtual drive's lockstep order, :mod:`plant_emulator.device`, for ``input_delay = 1``):

1. advance the plant one period with the command received ``input_delay`` SYNCs ago (the oldest slot of a FIFO);
2. shift the FIFO: the command set since the last SYNC is now in flight (``input_delay = 0``: it is applied at
   the next SYNC's step, the ideal loop without transport delay);
3. answer with the output after that step.

So with the loop's ``SYNC -> feedback y_i -> u_i = law(y_i) -> set_target(u_i)``, ``y_{i+1}`` is the output of a
step driven by ``u_{i - input_delay}``: with ``input_delay = 1`` a command first moves the axis one cycle after it
is computed, exactly as over CAN.

A trial starts at the SYNC at which the plant is reset: :meth:`SimulatedDrive.begin_trial` (the loop's
``before_trial`` hook) resets the plant for that trial and empties the FIFO, and the next SYNC reports the initial
condition without stepping. (The virtual drive resets between two SYNCs and steps once, with a zero command,
before its first report; for a plant at rest at ``x0 = 0`` with no disturbance at ``t = 0`` both are the same.)

The plant is the one definition of the physics (``build_plant``, whose arithmetic is the compiled kernels of
:mod:`plant_emulator.physics.kernels`), stepped once per SYNC.

A whole trial in one call: :meth:`SimulatedDrive.run_whole_trial` runs a trial's ``N`` sample cycles (SYNC,
feedback, the law's command, the FIFO, the plant's step) in the compiled loop
:func:`foilc_hil.loop.trial_kernel.run_trial` when the trial loop asks for it (lockstep, no limiter) and the plant
can hand its trial over (:class:`~plant_emulator.physics.trial.CompiledPlant`). The law's step and the plant's
step are the same compiled functions the per-cycle path calls, the plant's random inputs are drawn in advance
from the same generators, and the drive ends where ``N`` cycles would have left it (plant, FIFO, cycle count): the
trial's last cycle, and everything after it, runs as usual. Both paths give the same trajectories
(``tests/loop/test_whole_trial.py``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import can
import numpy as np

from drivers.cia301 import NmtState
from drivers.cia402 import STATE_STATUSWORD, OperationMode, State402
from drivers.drive import DeviceInfo, Drive, Feedback, StopPath, StopReport
from foilc_hil.errors import ConfigError, FeedbackTimeoutError, InputError
from foilc_hil.laws.learning import LearningLaw, StepArguments
from foilc_hil.loop.interfaces import WholeTrial
from foilc_hil.loop.trial_kernel import TrialStatus, run_trial
from plant_emulator.physics import Plant
from plant_emulator.physics.trial import CompiledPlant, TrialProgram

__all__ = ["SimulatedDrive"]


class SimulatedDrive(Drive):
    """A single-axis drive whose SYNC advances ``plant`` by one period (see the module docstring).

    Parameters
    ----------
    plant
        A single-input single-output plant (``plant_emulator.physics.build_plant``).
    sample_time
        The period one SYNC advances the plant (seconds): the cycle period, given once.
    input_delay
        SYNCs between :meth:`set_target` and the step that applies the command, minus one: 1 is the CAN loop, 0 the
        ideal loop (the command acts over the very next period).
    whole_trials
        Offer :meth:`run_whole_trial` (the compiled trial); ``False``: the loop runs every cycle one by one (the
        per-cycle path, for comparisons).
    """

    def __init__(self, plant: Plant, *, sample_time: float, input_delay: int = 1, whole_trials: bool = True) -> None:
        if plant.n_inputs != 1 or plant.n_outputs != 1:
            raise ConfigError(
                f"the trial loop drives one axis; the plant is {plant.n_outputs}x{plant.n_inputs}", key="plant"
            )
        if input_delay < 0:
            raise InputError(f"input_delay: must be >= 0, got {input_delay}")
        if not (sample_time > 0 and math.isfinite(sample_time)):
            raise InputError(f"sample_time: must be positive, got {sample_time!r}")
        self.plant = plant
        # the plant's whole-trial capability, checked once (a protocol check costs more than a trial's Python)
        self._compiled: CompiledPlant | None = plant if whole_trials and isinstance(plant, CompiledPlant) else None
        self.sample_time = float(sample_time)
        self.input_delay = int(input_delay)
        self.mode = OperationMode.CYCLIC_SYNC_VELOCITY
        # slot 0 is applied at the next step, the last one is new; a list: shifting it is cheaper than an array's
        self._pending = [0.0] * (self.input_delay + 1)
        self._command = np.zeros(1)  # the plant's input vector, reused every SYNC
        self._at_trial_start = True  # the plant was just built or reset: the next SYNC reports it as it is
        self._cycle = 0
        self._state = State402.SWITCH_ON_DISABLED
        self._feedback: Feedback | None = None

    # -- trials --------------------------------------------------------------------------------------------------

    def begin_trial(self, trial: int) -> None:
        """Reset the plant for ``trial`` (its initial condition, disturbance and noise of that trial), nothing in
        flight; the next SYNC is the trial's first sample."""
        self.plant.reset(trial)
        self._pending = [0.0] * (self.input_delay + 1)
        self._at_trial_start = True

    # -- the cyclic path -----------------------------------------------------------------------------------------

    def set_target(self, value: float) -> float:
        """The command for the next SYNC (the newest FIFO slot); no limits or quantisation of its own."""
        self._pending[-1] = float(value)
        return value

    def sync(self) -> int:
        """Advance the plant one period with the oldest command in flight and prepare the answer."""
        self._cycle += 1
        pending = self._pending
        if self._at_trial_start:
            self._at_trial_start = False
            y = self.plant.output()
        else:
            self._command[0] = pending[0] if self._state is State402.OPERATION_ENABLED else 0.0
            y = self.plant.step(self._command, self.sample_time)
        if self.input_delay:
            del pending[0]
            pending.append(pending[-1])  # the newest slot keeps its value: a drive holds its last set-point
        self._answer(float(y[0]))
        return self._cycle

    def _answer(self, velocity: float) -> None:
        self._feedback = Feedback(
            cycle=self._cycle,
            statusword=STATE_STATUSWORD[self._state],
            state=self._state,
            velocity=velocity,
            torque=0.0,
            position=0,
            timestamp=0.0,
        )

    # -- a whole trial in one call ---------------------------------------------------------------------------------

    def run_whole_trial(self, law: object, seen: np.ndarray, control: np.ndarray) -> WholeTrial | None:
        """Run the trial's sample cycles ``0 .. N-1`` (``N = len(control)``) in one compiled call (module docstring).

        Parameters
        ----------
        law
            The trial's law, after its ``begin_trial``: a :class:`~foilc_hil.laws.learning.LearningLaw`.
        seen, control
            The trial loop's arrays, ``(N + 1,)`` and ``(N,)``: ``seen[0 .. N-1]`` and ``control`` are written.

        Returns
        -------
        WholeTrial or None
            What ran; ``None`` (nothing ran) unless the drive is enabled at a trial's start, the law is a
            ``LearningLaw`` and the plant has a trial program: the caller then runs the cycles one by one.
        """
        n = control.shape[0]
        ready = self._at_trial_start and self._state is State402.OPERATION_ENABLED and n > 0
        plant = self._compiled
        if not (ready and isinstance(law, LearningLaw) and plant is not None):
            return None
        program = plant.trial_program(n - 1, self.sample_time)
        if program is None:
            return None
        seen[0] = float(self.plant.output()[0])
        ended: list[tuple[int, int]] = []

        def run(arguments: StepArguments) -> int:
            delay = self.input_delay + program.delay_steps  # the drive's FIFO, then the plant's own delay
            status, index = run_trial(seen, control, delay, _kernel_program(program), *arguments)
            ended.append((int(status), int(index)))
            return index + 1 if status == TrialStatus.COMMAND_NOT_FINITE else index  # samples the law issued

        law.command_trial(run)
        status, cycles = ended[0]
        self._after_whole_trial(plant, program, (seen, control), cycles)
        if status == TrialStatus.OUTPUT_NOT_FINITE:
            return WholeTrial(cycles, "drive feedback", float(seen[cycles]))
        if status == TrialStatus.COMMAND_NOT_FINITE:
            return WholeTrial(cycles, "command", float(law.control[cycles, 0]))
        return WholeTrial(cycles)

    def _after_whole_trial(
        self, plant: CompiledPlant, program: TrialProgram, trial: tuple[np.ndarray, np.ndarray], cycles: int
    ) -> None:
        """Leave the drive where its SYNCs ``0 .. min(cycles, N - 1)`` and the commands ``u_0 .. u_{cycles-1}``
        would have left it (``trial``: the ``seen`` and ``control`` arrays; a trial that stopped early is stopped by
        the loop, which clears the FIFO)."""
        seen, control = trial
        steps = min(cycles, control.shape[0] - 1)  # SYNC i made plant step i, with the command u(i - 1 - d)
        given = np.zeros(steps)
        given[self.input_delay :] = control[: max(steps - self.input_delay, 0)]
        plant.end_trial_program(program, given, float(seen[steps]))
        self._cycle += steps + 1
        self._answer(float(seen[steps]))
        self._at_trial_start = False
        last = cycles - 1  # the newest command: the FIFO holds u(last - d) .. u(last), oldest first
        self._pending = [float(control[i]) if i >= 0 else 0.0 for i in range(last - self.input_delay, last + 1)]

    def wait_feedback(self, timeout: float) -> Feedback:
        """The answer to the last SYNC (there is no waiting: the plant answered in :meth:`sync`)."""
        if self._feedback is None:
            raise FeedbackTimeoutError("no SYNC was sent to the simulated drive")
        return self._feedback

    # -- state machine ---------------------------------------------------------------------------------------------

    def connect(self) -> DeviceInfo:
        """A simulated drive is always there: its identity is all zeros."""
        return DeviceInfo(0, 0, 0, 0, 0, 0, NmtState.PRE_OPERATIONAL, tuple(OperationMode))

    def configure(self, mode: OperationMode) -> None:
        """Record the mode (the plant's input is what its config says)."""
        self.mode = mode

    def enable(self) -> None:
        self._state = State402.OPERATION_ENABLED

    def disable(self) -> None:
        self._state = State402.SWITCH_ON_DISABLED

    def quick_stop(self) -> None:
        """Stop commanding the plant: from now on each SYNC steps it with a zero command."""
        self._state = State402.QUICK_STOP_ACTIVE
        self._pending = [0.0] * (self.input_delay + 1)

    def fault_reset(self) -> None:
        """A simulated drive never faults: nothing to clear."""

    def safe_stop(self) -> StopReport:
        """Disable; confirmed by construction (the simulated statusword is this object's own state)."""
        self.disable()
        return StopReport(
            commanded=True,
            confirmed=True,
            state=self._state,
            statusword=STATE_STATUSWORD[self._state],
            via=StopPath.PDO,
        )

    def close(self) -> None:
        """No bus resources to release."""

    def add_frame_listener(self, listener: Callable[[can.Message, str], None]) -> None:
        """No bus, no frames: the listener is never called."""


def _kernel_program(program: TrialProgram) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """A :class:`~plant_emulator.physics.trial.TrialProgram` as the trial kernel takes it."""
    return int(program.kind), program.state, program.params, program.inputs

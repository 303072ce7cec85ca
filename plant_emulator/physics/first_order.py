"""The paper's plant, eq. (48): ``x' = (a + Da(t)) x + (b + Db(t)) u(t - delay) + d(t)``, ``y = c x + noise``.

Integration is exact for a zero-order-held input (errata 1: no forward Euler): over each step the augmented
matrix ``[[A, B, E], [0, 0, 0]]`` is exponentiated, which gives ``x+ = Phi x + Gu u + Gd d``. ``Da``, ``Db`` and
``d`` are held constant over a step (sampled at its midpoint), so with time variation the step is the exact
solution of a piecewise-constant approximation; its error against a fine Runge-Kutta solution is second order
in the step and measured in ``tests/plant_emulator/test_physics_first_order.py``. With ``Da = Db = 0`` the matrices are
cached per step length. A scalar state (the paper's plant) takes the closed form
``x+ = e^(a h) x + h expm1(a h)/(a h) (b u + d)`` in the compiled kernel
:func:`~plant_emulator.physics.kernels.scalar_plant_step` instead of ``expm``; with one input and one output and a
transport delay of whole steps it also hands whole trials to a compiled loop (:meth:`FirstOrderPlant.trial_program`,
:mod:`plant_emulator.physics.trial`).

For matrix plants ``Da(t)`` is added to the diagonal of ``a`` (it shifts every mode by the same amount),
``Db(t)`` to every non-zero entry of ``b``, and ``d(t)`` to every state equation. A transport ``delay`` is
applied to the saturated command; the step is split where a delayed command change falls inside it.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.linalg import expm

from drivers.errors import ConfigError
from plant_emulator.config import PlantConfig
from plant_emulator.linear import continuous_model
from plant_emulator.physics.base import check_input, check_scalar_input, check_step, check_trial
from plant_emulator.physics.disturbance import Disturbance
from plant_emulator.physics.kernels import scalar_plant_step
from plant_emulator.physics.noise import plant_noise
from plant_emulator.physics.trial import PlantKind, ScalarInput, ScalarParam, ScalarState, TrialProgram
from plant_emulator.physics.variation import VariationSignal

__all__ = ["FirstOrderPlant"]

_NOISE_STREAM = 3
_CACHE_SIZE = 64


class FirstOrderPlant:
    """The linear (possibly multi-input/multi-output) plant of eq. (48); implements ``Plant``.

    Parameters
    ----------
    plant
        The ``plant:`` section (``model: first_order``).
    seed
        Seed of the random walk variation and of the output noise (unless ``plant.noise_seed`` is set).
    """

    def __init__(self, plant: PlantConfig, *, seed: int) -> None:
        model = continuous_model(plant)
        self._a = model.a
        self._b = model.b
        self._c = model.c
        self._delay = float(model.delay)
        n = model.n_states
        self.n_states = n
        self.n_inputs = model.n_inputs
        self.n_outputs = model.n_outputs
        if plant.x0 is None:
            self._x0 = np.zeros(n)
        else:
            if len(plant.x0) != n:
                raise ConfigError(f"must have {n} entries (the states of 'a'), got {len(plant.x0)}", key="plant.x0")
            self._x0 = np.asarray(plant.x0, dtype=float)
        self._b_pattern = (self._b != 0).astype(float)
        # The scalar plant's coefficients: its step is one compiled call.
        self._a_scalar = float(self._a[0, 0])
        self._b_row = np.ascontiguousarray(self._b[0])
        self._on_row = np.ascontiguousarray(self._b_pattern[0])
        # The paper's plant (one state, one input, one output, no transport delay) steps in floats (_step_floats)
        self._floats = (n, self.n_inputs, self.n_outputs) == (1, 1, 1) and self._delay == 0.0
        self._c_scalar = float(self._c[0, 0])
        self._applied = np.zeros(1)  # the compiled step's input vector, refilled every step
        self._delta_a = VariationSignal(plant.variation.a, seed, stream=1)
        self._delta_b = VariationSignal(plant.variation.b, seed, stream=2)
        self._disturbance = Disturbance(plant.disturbance)
        self.noise = plant_noise(plant, seed, _NOISE_STREAM, self.n_outputs)
        """The sensor noise (``plant.output_noise``): its :meth:`~SensorNoise.trial_vector` is a trial's draws."""
        self._u_min = -np.inf if plant.saturation.u_min is None else plant.saturation.u_min
        self._u_max = np.inf if plant.saturation.u_max is None else plant.saturation.u_max
        self._cache: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._x = self._x0.copy()
        self._t = 0.0
        self._y = self._c @ self._x
        self._commands: list[tuple[float, np.ndarray]] = []
        self.saturated = False
        """Whether the last step's input was clipped by ``plant.saturation``."""
        self.reset(1)

    # --- Plant protocol ---------------------------------------------------------------------------------------

    def reset(self, trial: int) -> None:
        """Start ``trial`` at ``x0`` with the input history cleared (the plant was at rest before)."""
        trial = check_trial(trial)
        self._x = self._x0.copy()
        self._t = 0.0
        self._commands = []
        self._delta_a.reset(trial)
        self._delta_b.reset(trial)
        self._disturbance.reset(trial)
        self.noise.reset(trial)
        self.saturated = False
        self._y = self._measure()

    def step(self, u: np.ndarray, dt: float) -> np.ndarray:
        """Hold ``u`` (saturated) over ``dt`` seconds and return the measured output."""
        if self._floats:
            return np.array([self._step_floats(check_scalar_input(u), check_step(dt))])
        command = check_input(u, self.n_inputs)
        dt = check_step(dt)
        # Clipped element by element in Python: for the few inputs of a plant this is ~10x cheaper than np.clip.
        values = command.tolist()
        clipped = [min(max(value, self._u_min), self._u_max) for value in values]
        self.saturated = clipped != values
        applied = np.array(clipped)
        t0 = self._t
        delta_a = self._delta_a.over_step(t0, dt)
        delta_b = self._delta_b.over_step(t0, dt)
        d = self._disturbance.over_step(t0, dt)
        x = self._x
        if self._delay == 0.0:
            x = self._advance(x, applied, d, dt, delta_a, delta_b)
        else:
            self._commands.append((t0, applied))
            for start, end, u_seg in self._delayed_segments(t0, t0 + dt):
                x = self._advance(x, u_seg, d, end - start, delta_a, delta_b)
        self._x = x
        self._t = t0 + dt
        self._y = self._measure()
        return self._y.copy()

    def step_scalar(self, u: float, dt: float) -> float:
        """:meth:`step` with the input and the output as floats: the virtual drive's call once a cycle (output 0;
        :class:`~plant_emulator.physics.base.ScalarPlant`)."""
        if self._floats:
            return self._step_floats(check_scalar_input(u), check_step(dt))
        return float(self.step(np.array([u]), dt)[0])

    def _step_floats(self, command: float, dt: float) -> float:
        """The step of the paper's plant, in floats: the draws, the compiled closed form and the measurement of the
        general path (:meth:`_advance`, :meth:`_measure`), without its arrays but the state's and the output's,
        updated in place.

        Why: the virtual drive steps its plant once a cycle, and the general path's arrays (the clipped input, the
        state, ``c @ x``, the output and its copy) would be most of the step.

        """
        applied = min(max(command, self._u_min), self._u_max)
        self.saturated = applied != command
        t0 = self._t
        variation = (self._delta_a.over_step(t0, dt), self._delta_b.over_step(t0, dt))
        d = self._disturbance.over_step(t0, dt)
        self._applied[0] = applied
        x = scalar_plant_step(float(self._x[0]), self._a_scalar, self._b_row, self._on_row, self._applied, variation,
                              d, dt)
        self._x[0] = x
        self._t = t0 + dt
        y = 0.0 + self._c_scalar * x  # as c @ x sums it: from +0.0, so a product of -0.0 measures +0.0
        if self.noise.active:
            y += float(self.noise.sample()[0])
        self._y[0] = y
        return y

    def output(self) -> np.ndarray:
        """The last measured output ``c x + noise``."""
        return self._y.copy()

    def state(self) -> np.ndarray:
        """The true state ``x``."""
        return self._x.copy()

    @property
    def time(self) -> float:
        """Seconds since :meth:`reset`."""
        return self._t

    # --- a whole trial in a compiled loop ----------------------------------------------------------------------

    def trial_program(self, steps: int, dt: float) -> TrialProgram | None:
        """The next ``steps`` steps for a compiled loop (:class:`~plant_emulator.physics.trial.CompiledPlant`):
        ``Delta a``, ``Delta b``, ``d`` and the output noise of each step drawn now, in the order ``steps`` calls of
        :meth:`step` draw them. ``None`` unless the plant is scalar, single-input, single-output, with a transport
        delay of a whole number of steps (then ``step`` never splits a step)."""
        dt = check_step(dt)
        delay_steps = round(self._delay / dt)
        if (self.n_states, self.n_inputs, self.n_outputs) != (1, 1, 1) or abs(self._delay - delay_steps * dt) > (
            1e-12 * dt
        ):
            return None
        t0 = self._t
        inputs = np.zeros((steps, len(ScalarInput)))
        # a delayed step integrates over [t, t + dt] as step() does: (t + dt) - t, which rounds unlike dt
        times = self._step_times(t0, dt, steps)
        inputs[:, ScalarInput.STEP] = (times + dt) - times if delay_steps else dt
        inputs[:, ScalarInput.DELTA_A] = self._delta_a.values(t0, dt, steps)
        inputs[:, ScalarInput.DELTA_B] = self._delta_b.values(t0, dt, steps)
        inputs[:, ScalarInput.DISTURBANCE] = self._disturbance.values(t0, dt, steps)
        if self.noise.active:  # the generator continues after the draw of the reset's measurement
            inputs[:, ScalarInput.NOISE] = self.noise.following(steps)[:, 0]
        params = np.zeros(len(ScalarParam))
        params[ScalarParam.A] = self._a_scalar
        params[ScalarParam.B] = self._b_row[0]
        params[ScalarParam.B_PATTERN] = self._on_row[0]
        params[ScalarParam.C] = self._c[0, 0]
        params[ScalarParam.U_MIN], params[ScalarParam.U_MAX] = self._u_min, self._u_max
        params[ScalarParam.STEP] = dt
        params[ScalarParam.NOISY] = 1.0 if self.noise.active else 0.0
        state = np.zeros(len(ScalarState))
        state[ScalarState.X], state[ScalarState.TIME] = self._x[0], t0
        return TrialProgram(PlantKind.SCALAR, state, params, inputs, delay_steps)

    def end_trial_program(self, program: TrialProgram, commands: np.ndarray, output: float) -> None:
        """Take over the state ``program`` reached after ``len(commands)`` steps given ``commands``, measured as
        ``output``; the delayed commands still to act are kept as :meth:`step` keeps them (the random streams stay
        where :meth:`trial_program` left them: at the program's end)."""
        steps = commands.shape[0]
        t0 = self._t
        self._x = np.array([program.state[ScalarState.X]])
        self._t = float(program.state[ScalarState.TIME])
        self._y = np.array([output])
        self.saturated = steps > 0 and bool(program.state[ScalarState.SATURATED])
        if program.delay_steps:  # the commands issued in the last delay + 1 steps, at their steps' start times
            first = max(0, steps - program.delay_steps - 1)
            times = self._step_times(t0, check_step(program.params[ScalarParam.STEP]), steps)
            self._commands = [
                (float(times[j]), np.array([min(max(float(commands[j]), self._u_min), self._u_max)]))
                for j in range(first, steps)
            ]

    @staticmethod
    def _step_times(t0: float, dt: float, steps: int) -> np.ndarray:
        """The start times of ``steps`` steps of ``dt`` from ``t0``, accumulated one step at a time as the plant's
        clock (``cumsum`` adds in order)."""
        return np.cumsum(np.concatenate([[t0], np.full(max(steps - 1, 0), dt)]))[:steps]

    # --- internals --------------------------------------------------------------------------------------------

    def _measure(self) -> np.ndarray:
        y = self._c @ self._x
        if self.noise.active:
            y = y + self.noise.sample()
        return np.asarray(y, dtype=float)

    def _advance(self, x: np.ndarray, u: np.ndarray, d: float, h: float, delta_a: float, delta_b: float) -> np.ndarray:
        if h <= 0:
            return x
        if self.n_states == 1:  # the compiled closed form (Delta may change every step: no expm, no cache)
            variation = (delta_a, delta_b)
            x_next = scalar_plant_step(float(x[0]), self._a_scalar, self._b_row, self._on_row, u, variation, d, h)
            return np.array([x_next])
        phi, gamma_u, gamma_d = self._discrete(h, delta_a, delta_b)
        return np.asarray(phi @ x + gamma_u @ u + gamma_d * d, dtype=float)

    def _discrete(self, h: float, delta_a: float, delta_b: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        nominal = delta_a == 0.0 and delta_b == 0.0
        if nominal and h in self._cache:
            return self._cache[h]
        n, m = self.n_states, self.n_inputs
        a = self._a + delta_a * np.eye(n)
        b = self._b + delta_b * self._b_pattern
        augmented = np.zeros((n + m + 1, n + m + 1))
        augmented[:n, :n] = a
        augmented[:n, n : n + m] = b
        augmented[:n, n + m] = 1.0  # d(t) enters every state equation
        exponential = expm(augmented * h)
        result = (exponential[:n, :n], exponential[:n, n : n + m], exponential[:n, n + m])
        if nominal:
            self._remember(h, result)
        return result

    def _remember(self, h: float, result: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        if len(self._cache) >= _CACHE_SIZE:
            self._cache.pop(next(iter(self._cache)))
        self._cache[h] = result

    def _delayed_segments(self, t0: float, t1: float) -> list[tuple[float, float, np.ndarray]]:
        """Split ``[t0, t1]`` where the delayed command changes; each piece with the input the plant sees."""
        delay = self._delay
        # Commands issued before t0 - delay are superseded by the last of them; drop the older ones.
        while len(self._commands) >= 2 and self._commands[1][0] + delay <= t0:
            self._commands.pop(0)
        zero = np.zeros(self.n_inputs)
        # Ignore change points within rounding of an edge: they would only create slivers of a step.
        slack = 1e-9 * (t1 - t0)
        inner = sorted({t + delay for t, _ in self._commands if t0 + slack < t + delay < t1 - slack})
        edges = [t0, *inner, t1]
        segments = []
        for start, end in itertools.pairwise(edges):
            # The command the plant sees in this piece: the last one issued before its delayed midpoint.
            seen = 0.5 * (start + end) - delay
            u_seg = zero
            for issued, value in self._commands:
                if issued <= seen:
                    u_seg = value
            segments.append((start, end, u_seg))
        return segments

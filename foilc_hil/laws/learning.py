"""Learning laws behind one sample-by-sample interface: FOILC (paper eq. 8, 19, 21), IOILC, P-type, NOILC and
gradient ILC.

Timing conventions (see also :mod:`foilc_hil.references`)
---------------------------------------------------------
Trial ``k`` has ``N`` samples. In sample ``t`` (``0 <= t < N``) the loop measures ``y_k(t Ts)`` and calls
:meth:`LearningLaw.command` with it; the returned ``u_k(t)`` is held over one sample (after ``d`` samples of
input delay, ``d = design.input_delay``, e.g. one cycle for a SYNC-driven CAN loop). After the trial the loop
calls :meth:`LearningLaw.end_trial` with the trial arrays ``reference[i] = y_r((i+1) Ts)`` and
``output[i] = y_k((i+1) Ts)``, ``i = 0 .. N-1`` -- so ``error[i]`` is the paper's ``e(t_d + 1)`` at ``t_d = i``.
A bench therefore takes one more measurement after the last command (the output at ``N Ts``).

The 2D law (FOILC; IOILC is the same with ``kp = 0``) is, with ``P = (p1 p2)`` from the design::

    u_k(t) = u_{k-1}(t) + p1 (x_k(t) - x_{k-1}(t)) + p2 E_{k-1}[t + d],     E = (I + kp D^r) e  (FractionalPD)

``E_{k-1}[t + d]`` is the paper's ``E(t + 1, k - 1)`` moved by the input delay: ``u(t)`` first reaches the output
at ``(t + 1 + d) Ts``. Entries past the end of the trial (``t + d >= N``) are zero -- those inputs cannot move
any output of the trial, so nothing is learned for them. The state is reconstructed from the measured output,
``x = pinv(C) y``, which requires ``C`` to have full column rank (else :class:`~foilc_hil.errors.ConfigError`
naming ``plant.c``) -- ``C`` here is the design's MEASURED output map ``design.measured_output``; with ``d > 0``
the design's augmented state is ``[x; u(t-d); ...; u(t-1)]`` (:func:`foilc_hil.design.models.augment_input_delay`,
oldest input first), whose extra entries are the law's own past commands of this trial (zero before the trial
starts, as the plant rests). The lead ``d`` is ``design.error_lead``.

Fractional memory (``law.fractional_memory``)
---------------------------------------------
The first ``d`` error samples ``error[0:d]`` cannot be moved by any input of the trial (``u(0)`` first reaches
the output at ``(1 + d) Ts``). By default (``"controllable"``) the fractional operator's memory starts at the
first controllable sample: ``E[d:] = (I + kp D^r) g`` with ``g = error[d:]`` and ``D^r`` the Grünwald–Letnikov
derivative with zero history before ``g`` (``FractionalPD(..., history="zero")``, a lower-triangular Toeplitz
operator with diagonal ``1 + kp h^-r``); ``E[0:d] = error[0:d]`` is only logged, never used. At the law's fixed
point ``E[d:] = 0`` and the operator is invertible, so the converged error is zero on the controllable samples.
``"trial"`` is the paper-literal operator: the Caputo derivative over the whole trial error, which subtracts
``e(0)``; with ``e(0) != 0`` its fixed point ``e + kp D^r e = 0`` is a Mittag-Leffler decay of ``e``, not zero
(kept for comparison). :mod:`foilc_hil.design.certificates` certifies the same operator (``fractional_memory``).

Saturation-aware learning
-------------------------
Given command ``limits`` (``make_law(..., limits=(lower, upper))``, the bench's drive and plant limits), the law
clamps each command before storing it, so the feedforward learned for the next trial is the input that was
applied, not a command the drive never executed (anti-windup: without it the stored feedforward can keep
growing while the drive saturates). The bench's limiter stays as the safety layer with the same limits.
For the same reason the bench hands :meth:`LearningLaw.end_trial` the input the drive latched at each SYNC
(``/ilc/sample.latched``: as sent, and the previous command where an RPDO missed its SYNC), and the law stores that
as ``u_{k-1}``: the law learns from the input that ran, never from a command the drive did not execute.

P-type (Arimoto): ``u_k(t) = u_{k-1}(t) + Gamma e_{k-1}[t + d]``, the 2D law with ``p1 = 0`` and ``E = e``; its
design (gain, model, certificates) comes from the same pipeline (:mod:`foilc_hil.design.pipeline`).

NOILC (norm-optimal, Amann–Owens): ``u_k = u_{k-1} + L e_{k-1}`` with the lifted gain
``L = (G^T Q G + R)^-1 G^T Q`` acting on the whole trial (:mod:`foilc_hil.design.noilc`), applied in its
state-space (Riccati) form between trials; ``L e[d:]`` updates ``u[:N-d]`` like every other law's learning term.
Gradient ILC (``u_k = u_{k-1} + beta G^T e_{k-1}``, :mod:`foilc_hil.design.gradient`) runs the same way with its
own update ``beta G^T`` (one adjoint pass).

First trial and restore
-----------------------
With no previous trial the law has no ``x_{k-1}`` and no ``E_{k-1}``: trial 1 runs the initial feedforward
(zeros) unchanged and only measures. :meth:`LearningLaw.restore` (the bench's divergence guard) sets the
feedforward and drops the previous-trial record the same way, so the next trial re-measures the plant under the
restored feedforward before learning resumes.

Optional Q-filter: after each trial the feedforward stored for the next trial is ``Q(u_k)`` (zero phase or
causal, ``law.q_filter.phase``; :mod:`foilc_hil.design.qfilter`). The law runs the design's filter
(:attr:`~foilc_hil.design.record.Design.q_filter`: the object the certificates were computed with), as it runs the
design's gains and ``kp``, ``r``: nothing the design computed is computed again here.

Determinism: every operation is a fixed sequence of numpy calls on fixed-shape float64 arrays (no threads, no
reductions whose order depends on data), so the same design, configuration and measured outputs give
bit-identical commands; ``replay --verify`` relies on this. :meth:`LearningLaw.command` writes into arrays
allocated once per law (no per-sample array allocation) and returns a read-only view into them.

One per-sample step: the arithmetic within a trial is the compiled :func:`foilc_hil.laws.kernels.law_step`, for
every law. :meth:`LearningLaw.command` calls it once per cycle; :meth:`LearningLaw.command_trial` hands the same
arrays to a compiled loop over a whole trial (the simulated drive's trial kernel), which calls the same step.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from foilc_hil.config import FractionalMemory, LawConfig, LawKind
from foilc_hil.design.fractional import FractionalPD, History
from foilc_hil.design.gradient import lifted_update
from foilc_hil.design.qfilter import QFilter
from foilc_hil.design.record import Design
from foilc_hil.errors import ConfigError, InputError, LearningDivergedError
from foilc_hil.laws.kernels import law_step, law_step_for
from foilc_hil.metrics import TrialMetrics, trial_metrics

__all__ = [
    "Foilc",
    "Gradient",
    "Ioilc",
    "LearningLaw",
    "Noilc",
    "PType",
    "StepArguments",
    "TrialUpdate",
    "make_law",
]


def _check_limits(limits: tuple[float, float] | None) -> tuple[float, float] | None:
    if limits is None:
        return None
    lower, upper = (float(value) for value in limits)
    if not (math.isfinite(lower) and math.isfinite(upper) and lower < upper):
        raise InputError(f"limits: must be finite with lower < upper, got {limits!r}")
    return lower, upper


@dataclass(frozen=True)
class TrialUpdate:
    """What :meth:`LearningLaw.end_trial` learned from a finished trial.

    Attributes
    ----------
    trial
        The finished trial's number (1-based).
    error
        ``e = y_r - y`` at ``t = (i+1) Ts``, shape ``(N, p)``.
    E
        The signal the law learns from: ``(I + kp D^r) e`` for the 2D laws, ``e`` for P-type; ``(N, p)``.
    metrics
        SSE, RMSE and peak of ``error``.
    """

    trial: int
    error: np.ndarray
    E: np.ndarray
    metrics: TrialMetrics


class StepArguments(NamedTuple):
    """The arguments of :func:`~foilc_hil.laws.kernels.law_step` after the sample, in its order: what a compiled
    trial loop passes to the law's step (``law_step(t, *arguments)``). The arrays are the law's own."""

    outputs: np.ndarray
    base: np.ndarray
    commands: np.ndarray
    state: np.ndarray
    previous_state: np.ndarray
    c_pinv: np.ndarray
    p1: np.ndarray
    use_previous: bool
    lower: float
    upper: float


def _as_trial_array(value: np.ndarray, n_samples: int, width: int, name: str) -> np.ndarray:
    """``value`` as a float ``(N, width)`` array; ``(N,)`` is broadcast to every column."""
    array = np.asarray(value, dtype=float)
    if array.ndim == 1 and array.shape[0] == n_samples:
        array = np.repeat(array[:, None], width, axis=1)
    if array.shape != (n_samples, width):
        raise InputError(f"{name}: must have shape ({n_samples}, {width}) or ({n_samples},), got {array.shape}")
    return array


class LearningLaw(ABC):
    """A learning law run sample by sample inside a trial and updated between trials.

    Attributes
    ----------
    n_samples, n_inputs, n_outputs
        ``N``, ``m``, ``p``.
    trial
        Number of completed trials.
    input_delay
        ``d``: samples between issuing ``u(t)`` and the plant applying it.
    """

    kind: LawKind

    def __init__(
        self,
        *,
        n_samples: int,
        n_inputs: int,
        n_outputs: int,
        input_delay: int,
        error_gain: np.ndarray,
        q_filter: QFilter | None,
        limits: tuple[float, float] | None = None,
    ) -> None:
        if n_samples < 1:
            raise InputError(f"n_samples: must be >= 1, got {n_samples}")
        if input_delay < 0:
            raise InputError(f"input_delay: must be >= 0, got {input_delay}")
        self.n_samples = int(n_samples)
        self.n_inputs = int(n_inputs)
        self.n_outputs = int(n_outputs)
        self.input_delay = int(input_delay)
        self.trial = 0
        self.q_filter = q_filter
        #: ``(lower, upper)`` every command is clamped to before it is stored and returned; ``None``: no clamp.
        self.limits = _check_limits(limits)
        self._error_gain = np.array(error_gain, dtype=float, copy=True)  # m x p: p2 or Gamma
        if self._error_gain.shape != (self.n_inputs, self.n_outputs):
            raise InputError(
                f"error gain must be {self.n_inputs}x{self.n_outputs}, got "
                f"{self._error_gain.shape[0]}x{self._error_gain.shape[1]}"
            )
        n, m, p = self.n_samples, self.n_inputs, self.n_outputs
        self._feedforward = np.zeros((n, m))  # u_{k-1}
        self._learned = np.zeros((n, p))  # E_{k-1} (or e_{k-1} for P-type)
        self._has_record = False  # whether _learned and the state record belong to a previous trial
        self._base = np.zeros((n, m))  # u_{k-1}(t) + gain * E_{k-1}[t + d], computed once per trial
        self._u = np.zeros((n, m))  # u_k, written sample by sample
        self._u_readonly = self._u.view()
        self._u_readonly.flags.writeable = False
        self._y = np.zeros((n, p))  # outputs measured at the start of each sample
        # The state term of law_step, zero-width for a law without one (P-type, NOILC); a 2D law sets its own.
        self._x = np.zeros((n, 0))  # x_k(t), augmented
        self._x_prev = np.zeros((n, 0))  # x_{k-1}(t)
        self._c_pinv = np.zeros((0, p))
        self._p1 = np.zeros((m, 0))
        self._arguments = self._step_arguments()  # law_step's arguments, rebuilt by begin_trial for each trial
        self._step: Callable[..., None] = law_step  # command's law_step: its machine code once begin_trial ran
        self._next_sample = 0
        self._in_trial = False

    # --- between trials -------------------------------------------------------------------------------------

    @property
    def feedforward(self) -> np.ndarray:
        """``u_{k-1}``, the feedforward the next trial starts from, ``(N, m)`` (a read-only view)."""
        view = self._feedforward.view()
        view.flags.writeable = False
        return view

    def begin_trial(self) -> None:
        """Prepare trial ``trial + 1``: precompute everything that does not depend on its measurements."""
        d, n = self.input_delay, self.n_samples
        np.copyto(self._base, self._feedforward)
        if self._has_record and d < n:
            # base[t] += gain @ E_{k-1}[t + d] for t + d < N; later samples learn nothing (module docstring).
            self._base[: n - d] += self._learning_update(self._learned[d:])
        self._u.fill(0.0)
        self._y.fill(0.0)
        self._x.fill(0.0)
        self.compile_step()  # the arguments fixed for the trial (built once, not per sample) and their machine code
        self._next_sample = 0
        self._in_trial = True

    def end_trial(self, reference: np.ndarray, output: np.ndarray, applied: np.ndarray | None = None) -> TrialUpdate:
        """Learn from the finished trial: ``e = y_r - y``, ``E``, optional Q-filter; the input that ran becomes
        ``u_{k-1}``.

        Parameters
        ----------
        reference, output
            ``y_r`` and ``y`` at ``t = (i+1) Ts``, ``i = 0 .. N-1``; ``(N,)`` or ``(N, p)``.
        applied
            ``(N,)`` or ``(N, m)``: the input the plant ran in each sample, when it is known and may differ from the
            law's commands (the bench's ``latched``: a command whose RPDO missed its SYNC never ran, and the drive
            held the previous one; the commands as sent are quantised). ``None``: the law's own commands ran.

        Raises
        ------
        foilc_hil.errors.LearningDivergedError
            If the error or the learned signal is not finite.
        foilc_hil.errors.InputError
            If the trial is incomplete or the arrays have the wrong shape.
        """
        if not self._in_trial or self._next_sample != self.n_samples:
            raise InputError(
                f"end_trial: trial {self.trial + 1} issued {self._next_sample} of {self.n_samples} commands"
            )
        ref = _as_trial_array(reference, self.n_samples, self.n_outputs, "reference")
        out = _as_trial_array(output, self.n_samples, self.n_outputs, "output")
        error = ref - out
        if not np.all(np.isfinite(error)):
            raise LearningDivergedError(f"trial {self.trial + 1}: the tracking error is not finite")
        learned = self._learning_signal(error)
        if not np.all(np.isfinite(learned)):
            raise LearningDivergedError(f"trial {self.trial + 1}: the learning signal E is not finite")
        ran = self._u if applied is None else _as_trial_array(applied, self.n_samples, self.n_inputs, "applied")
        if not np.all(np.isfinite(ran)):
            raise InputError("applied: must be finite")
        np.copyto(self._learned, learned)
        # u_{k-1} is what ran (module notes): the law's commands, or the input the bench knows the drive latched
        if self.q_filter is not None:
            np.copyto(self._feedforward, self.q_filter.apply(ran))
        else:
            np.copyto(self._feedforward, ran)
        np.copyto(self._x_prev, self._x)  # this trial's state becomes the previous trial's
        self._has_record = True
        self._in_trial = False
        self.trial += 1
        metrics = trial_metrics(self.trial, error, first_learnable=min(self.input_delay, self.n_samples - 1))
        return TrialUpdate(self.trial, error, learned.copy(), metrics)

    def restore(self, feedforward: np.ndarray) -> None:
        """Divergence guard: continue from ``feedforward`` (e.g. the best trial's); the next trial re-measures."""
        u = np.asarray(feedforward, dtype=float)
        if u.ndim == 1 and self.n_inputs == 1:
            u = u[:, None]
        if u.shape != (self.n_samples, self.n_inputs):
            raise InputError(f"feedforward: must have shape ({self.n_samples}, {self.n_inputs}), got {u.shape}")
        if not np.all(np.isfinite(u)):
            raise InputError("feedforward: must be finite")
        np.copyto(self._feedforward, u)
        self._has_record = False
        self._in_trial = False

    def state_dict(self) -> dict[str, Any]:
        """The law's learning state, for logging (JSON-friendly lists)."""
        return {
            "kind": str(self.kind),
            "trial": self.trial,
            "input_delay": self.input_delay,
            "has_record": self._has_record,
            "limits": None if self.limits is None else list(self.limits),
            "feedforward": self._feedforward.tolist(),
            "learned": self._learned.tolist(),
        }

    # --- within a trial -------------------------------------------------------------------------------------

    def command(self, t: int, output: np.ndarray) -> np.ndarray:
        """``u_k(t)`` given the output ``y_k(t Ts)`` measured at the start of sample ``t``; ``(m,)`` read-only.

        Samples must come in order ``0, 1, ..., N-1`` after :meth:`begin_trial`.
        """
        if not self._in_trial:
            raise InputError("command: call begin_trial() first")
        if t != self._next_sample:
            raise InputError(f"command: sample {t} out of order, expected {self._next_sample}")
        y = self._y[t]
        y[:] = output  # raises if the shape does not fit (p,)
        if not all(map(math.isfinite, y.tolist())):  # no temporary array, no numpy reduction: a few outputs a cycle
            raise LearningDivergedError(f"trial {self.trial + 1}, sample {t}: the measured output is not finite")
        self._step(t, *self._arguments)  # law_step; clamps to the limits: learn from what is applied (module notes)
        self._next_sample = t + 1
        return self._u_readonly[t]

    def command_trial(self, run: Callable[[StepArguments], int]) -> int:
        """Issue the trial's commands from a compiled loop instead of :meth:`command`, sample by sample.

        ``run`` gets the law's step arguments and calls ``law_step(t, *arguments)`` for ``t = 0, 1, ...`` in order,
        each after writing ``y_k(t Ts)`` into ``arguments.outputs[t]``; it returns how many samples it issued (fewer
        than ``N`` when it stopped early, e.g. at a non-finite value). Afterwards the law is where :meth:`command`
        would have left it after those samples.

        Raises
        ------
        foilc_hil.errors.InputError
            Outside a trial, after :meth:`command` has issued samples of this trial, or for a count out of range.
        """
        if not self._in_trial or self._next_sample != 0:
            raise InputError("command_trial: call begin_trial() first, and issue no sample before it")
        issued = int(run(self._arguments))
        if not 0 <= issued <= self.n_samples:
            raise InputError(f"command_trial: issued {issued} of {self.n_samples} samples")
        self._next_sample = issued
        return issued

    def _step_arguments(self) -> StepArguments:
        lower, upper = self.limits if self.limits is not None else (-math.inf, math.inf)
        return StepArguments(
            self._y, self._base, self._u, self._x, self._x_prev, self._c_pinv, self._p1, self._has_record, lower, upper
        )

    def compile_step(self) -> None:
        """Compile (or load from numba's cache) :func:`~foilc_hil.laws.kernels.law_step` for this law's argument
        types, now. Why: :func:`~foilc_hil.laws.kernels.warm_up` covers the types of its own arguments at import, and
        a law whose arguments differ (a design's read-only gain did, before the 2D law copied it) had that overload
        compiled by the first :meth:`begin_trial`: 0.6 s on a fresh install, inside the first trial of a realtime run
        (the drive's SYNC-loss EMCY).
        :meth:`begin_trial` calls it again for the trial's arguments (the same types: found, not compiled)."""
        self._arguments = self._step_arguments()
        self._step = law_step_for(self._arguments)

    @property
    def control(self) -> np.ndarray:
        """The commands issued so far in the current (or last) trial, ``(N, m)``, read-only."""
        return self._u_readonly

    # --- subclass hooks -------------------------------------------------------------------------------------

    @abstractmethod
    def _learning_signal(self, error: np.ndarray) -> np.ndarray:
        """``E`` from ``e`` (both ``(N, p)``)."""

    def _learning_update(self, learned: np.ndarray) -> np.ndarray:
        """The learning update of ``u[0..N-d-1]`` from ``E[d..N-1]`` (``(N-d, p)`` -> ``(N-d, m)``): the gain per
        sample; a lifted law (NOILC) acts on the whole trial."""
        return np.asarray(learned @ self._error_gain.T)


class Foilc(LearningLaw):
    """The 2D fractional-order law (paper eq. 21) with the gain ``P = (p1 p2)`` of ``design``.

    Parameters
    ----------
    design
        The synthesized design (``A, B, C`` possibly augmented by ``input_delay``; ``P``; ``kp``, ``r``).
    n_samples
        ``N``, samples per trial. The Q-filter, if any, is the design's (:attr:`Design.q_filter`).
    fractional_memory
        ``"controllable"`` (default) or ``"trial"``: where the fractional operator's memory starts (module
        notes). Must match the memory the design was certified with, when the design records it.
    limits
        Optional ``(lower, upper)`` command limits (module notes: saturation-aware learning).
    """

    kind = LawKind.FOILC

    def __init__(
        self,
        design: Design,
        n_samples: int,
        *,
        fractional_memory: FractionalMemory | str = FractionalMemory.CONTROLLABLE,
        limits: tuple[float, float] | None = None,
    ) -> None:
        n, m, p, d = design.n_states, design.n_inputs, design.n_outputs, design.error_lead
        super().__init__(
            n_samples=n_samples,
            n_inputs=m,
            n_outputs=p,
            input_delay=d,
            error_gain=design.p2,
            q_filter=design.q_filter,
            limits=limits,
        )
        try:
            memory = FractionalMemory(fractional_memory)
        except ValueError:
            raise ConfigError(
                f"must be 'controllable' or 'trial', got {fractional_memory!r}", key="law.fractional_memory"
            ) from None
        self.design = design
        self.kp = float(design.kp)
        self.r = design.r
        self.fractional_memory = memory
        certified = design.certificates.fractional_memory if design.certificates and self.kp > 0 else None
        if certified is not None and certified is not memory:
            raise ConfigError(
                f"is {fractional_memory!r} but the design was certified with {certified!r}: the certificate would "
                "not be of the law that runs; re-synthesize or set the same memory",
                key="law.fractional_memory",
            )
        self._fractional: FractionalPD | None = None
        if self.kp > 0:
            # "controllable": zero history before e[d] (applied to e[d:]); "trial": Caputo over the whole trial
            history: History = "zero" if memory is FractionalMemory.CONTROLLABLE else "caputo"
            self._fractional = FractionalPD(self.kp, design.r, design.sample_time, history=history)
        n_plant = n - d * m
        if n_plant < 1:
            raise InputError(f"design: {n} states cannot hold {d} delayed copies of {m} inputs")
        measured = np.asarray(design.measured_output, dtype=float)
        c_plant = measured[:, :n_plant]
        if np.any(measured[:, n_plant:] != 0):
            raise InputError("design.C_measured: the input-delay augmentation states must not be measured")
        rank = int(np.linalg.matrix_rank(c_plant))
        if rank < n_plant:
            raise ConfigError(
                f"has rank {rank} < {n_plant} states: the 2D law needs the state, reconstructed as pinv(C) y",
                key="plant.c",
            )
        self.n_plant_states = n_plant
        self._c_pinv = np.ascontiguousarray(np.linalg.pinv(c_plant))
        # a writable copy: a design's gains are read-only arrays, and law_step's machine code for a read-only p1 is
        # a second overload to compile (seconds on a fresh install, in each process) for the same arithmetic
        self._p1 = np.array(design.p1, dtype=float, order="C")
        self._x = np.zeros((n_samples, n))
        self._x_prev = np.zeros((n_samples, n))

    def _learning_signal(self, error: np.ndarray) -> np.ndarray:
        if self._fractional is None:
            return error.copy()
        if self.fractional_memory is FractionalMemory.TRIAL:
            return self._fractional_pd(error)
        # Memory from the first controllable sample, zero history before it; E[:d] = e[:d] is never used.
        d = self.input_delay
        learned = error.copy()
        if d < error.shape[0]:
            learned[d:] = self._fractional_pd(error[d:])
        return learned

    def _fractional_pd(self, error: np.ndarray) -> np.ndarray:
        """``(I + kp D^r)`` of the error, ``(N, p)``, as one 2-D call: ``replay --verify`` of existing logs needs
        the rounding of scipy's 2-D direct sum bit for bit, which the compiled near field keeps (a 1-D
        ``np.convolve`` per column rounds differently)."""
        assert self._fractional is not None
        return np.asarray(self._fractional.apply(error), dtype=float).reshape(error.shape)

    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        state.update(
            {
                "kp": self.kp,
                "r": self.r,
                "fractional_memory": str(self.fractional_memory),
                "previous_state": self._x_prev.tolist(),
            }
        )
        return state


class Ioilc(Foilc):
    """The integer-order 2D law: :class:`Foilc` with ``kp = 0`` (``E = e``), run with its own design's gain; the
    design's ``kp`` must be 0 (an IOILC design's is), the law does not set it aside."""

    kind = LawKind.IOILC

    def __init__(
        self,
        design: Design,
        n_samples: int,
        *,
        fractional_memory: FractionalMemory | str = FractionalMemory.CONTROLLABLE,
        limits: tuple[float, float] | None = None,
    ) -> None:
        if design.kp != 0.0:
            raise InputError(f"design.kp: IOILC runs kp = 0 (E = e), the design has {design.kp!r}")
        super().__init__(design, n_samples, fractional_memory=fractional_memory, limits=limits)


class PType(LearningLaw):
    """Arimoto P-type ILC, ``u_k(t) = u_{k-1}(t) + Gamma e_{k-1}[t + d]``, with the gain of a P-type design.

    Parameters
    ----------
    design
        A design with ``P = (0 Gamma)`` (:func:`foilc_hil.design.pipeline.build_design`'s P-type design, whose
        ``Gamma`` is ``law.p_type_gain`` or :func:`foilc_hil.design.ptype.p_type_default_gain`, certified): the law
        runs its ``Gamma``, input delay and Q-filter.
    n_samples
        ``N``.
    limits
        Optional ``(lower, upper)`` command limits (saturation-aware learning, module notes).
    """

    kind = LawKind.P_TYPE

    def __init__(self, design: Design, n_samples: int, *, limits: tuple[float, float] | None = None) -> None:
        if np.any(design.p1 != 0.0):
            raise InputError("design.p1: a P-type law has no state term, P = (0 Gamma)")
        super().__init__(
            n_samples=n_samples,
            n_inputs=design.n_inputs,
            n_outputs=design.n_outputs,
            input_delay=design.input_delay,
            error_gain=design.p2,
            q_filter=design.q_filter,
            limits=limits,
        )
        self.gain = self._error_gain.copy()

    def _learning_signal(self, error: np.ndarray) -> np.ndarray:
        return error.copy()


class Noilc(LearningLaw):
    """Norm-optimal ILC (Amann–Owens): ``u_k = u_{k-1} + L e_{k-1}`` (:mod:`foilc_hil.design.noilc`).

    ``L`` is applied in its state-space form (a backward costate pass, then a forward pass with the Riccati
    feedback: ``O(N)`` per trial, no lifted matrix), rebuilt from the design's model and the weights (and scale) its
    certificates record (``certificates.noilc``), for ``n_samples``, with the same compiled recursions as the
    design: a logged design replays bit for bit.

    Parameters
    ----------
    design
        A ``noilc`` design (:func:`foilc_hil.design.noilc.certify_noilc`).
    n_samples
        ``N``, samples per trial.
    limits
        As for every law (module notes); the Q-filter, if any, is the design's.
    """

    kind = LawKind.NOILC

    def __init__(self, design: Design, n_samples: int, *, limits: tuple[float, float] | None = None) -> None:
        if design.law is not self.kind:
            raise InputError(f"design.law: {type(self).__name__} runs a {self.kind} design, got {design.law}")
        super().__init__(
            n_samples=n_samples,
            n_inputs=design.n_inputs,
            n_outputs=design.n_outputs,
            input_delay=design.input_delay,
            error_gain=design.p2,
            q_filter=design.q_filter,
            limits=limits,
        )
        self._update = lifted_update(design, self.n_samples) if self.input_delay < n_samples else None

    def _learning_signal(self, error: np.ndarray) -> np.ndarray:
        return error.copy()

    def _learning_update(self, learned: np.ndarray) -> np.ndarray:
        assert self._update is not None  # begin_trial only asks when d < N
        return self._update.apply(learned)


class Gradient(Noilc):
    """Gradient ILC: ``u_k = u_{k-1} + beta G^T e_{k-1}`` (:mod:`foilc_hil.design.gradient`); ``beta G^T e`` is one
    backward pass of the adjoint plant, rebuilt from the design's model and the step its certificates record
    (``certificates.gradient``). Runs like :class:`Noilc`: feedforward only, the update applied between trials."""

    kind = LawKind.GRADIENT


# --- factory ----------------------------------------------------------------------------------------------------


def make_law(
    design: Design,
    law_cfg: LawConfig,
    n_samples: int,
    *,
    limits: tuple[float, float] | None = None,
) -> LearningLaw:
    """Build the law ``design.law`` (``foilc``, ``ioilc``, ``p-type``, ``noilc``, ``gradient``) for ``n_samples``
    samples per trial.

    ``design`` gives everything the law runs that the design computed: the gain (``P``; ``p2 = Gamma`` for P-type),
    ``kp``, ``r``, the model, the input delay and the Q-filter (:attr:`~foilc_hil.design.record.Design.q_filter`, the
    object its certificates were computed with); ``law_cfg.q_filter`` must be that filter's section (else
    :class:`~foilc_hil.errors.ConfigError`: the certificates would not be of the law that runs), and
    ``law_cfg.fractional_memory`` picks the fractional operator's memory (FOILC). ``limits``: the command limits the
    law clamps to and learns from (module notes; the bench passes its limiter's).

    The law's compiled step is ready when this returns (:meth:`LearningLaw.compile_step`): never compiled in a
    control loop's first cycle.
    """
    _check_q_filter(design, law_cfg)
    law = _new_law(design, law_cfg, n_samples, limits)
    law.compile_step()
    return law


def _check_q_filter(design: Design, law_cfg: LawConfig) -> None:
    """The law runs the design's Q-filter: refuse a ``law.q_filter`` section it is not, and a design whose
    certificates were computed with a filter it does not hold (or without the one it holds)."""
    held, section = design.q_filter, law_cfg.q_filter
    if not (held.is_of(section) if held is not None else section is None):
        asked = "none" if section is None else f"cutoff={section.cutoff}, order={section.order}, phase={section.phase}"
        raise ConfigError(
            f"is {asked} but the design was certified with {held!r}: the certificates would not be of the law that "
            "runs; build the design from this config",
            key="law.q_filter",
        )
    certified = None if design.certificates is None else design.certificates.q_filter
    if certified is not None and certified != (held is not None):
        raise InputError(
            f"design.q_filter: the certificates were computed {'with' if certified else 'without'} a Q-filter, the "
            f"design holds {held!r}"
        )


def _new_law(design: Design, law_cfg: LawConfig, n_samples: int, limits: tuple[float, float] | None) -> LearningLaw:
    memory = law_cfg.fractional_memory
    if design.law is LawKind.NOILC:
        return Noilc(design, n_samples, limits=limits)
    if design.law is LawKind.GRADIENT:
        return Gradient(design, n_samples, limits=limits)
    if design.law is LawKind.FOILC:
        return Foilc(design, n_samples, fractional_memory=memory, limits=limits)
    if design.law is LawKind.IOILC:
        return Ioilc(design, n_samples, fractional_memory=memory, limits=limits)
    return PType(design, n_samples, limits=limits)

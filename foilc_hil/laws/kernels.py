"""The learning laws' per-sample step, compiled: the one definition of the arithmetic inside a trial.

:func:`law_step` computes ``u_k(t)`` for every law of :mod:`foilc_hil.laws.learning` (FOILC, IOILC, P-type, NOILC).
Everything a law learns between trials is folded into ``base[t] = u_{k-1}(t) + gain E_{k-1}[t + d]`` before the
trial (:meth:`~foilc_hil.laws.learning.LearningLaw.begin_trial`); within the trial a 2D law (FOILC, IOILC) adds
``p1 (x_k(t) - x_{k-1}(t))`` with the state reconstructed from the measured output, ``x = [pinv(C) y; u(t-d) ...
u(t-1)]``, and every law clamps to its command limits. A law without a state term (P-type, NOILC) passes
zero-width state arrays and gets ``u_k(t) = base[t]`` clamped.

Two callers, one kernel: :meth:`~foilc_hil.laws.learning.LearningLaw.command` calls it once per cycle (the bench
over CAN, the per-cycle path of ``simulate``), and the compiled trial kernel of the simulated drive
(:mod:`foilc_hil.loop.trial_kernel`) calls it inside its loop over a whole trial's samples. Both therefore issue
the same commands bit for bit for the same outputs.

Compilation as for the physics kernels (:mod:`plant_emulator.physics.kernels`): ``cache=True``, no ``fastmath``
(IEEE-exact, reproducible), run once at import by :func:`warm_up` so no control loop pays the compilation or the
cache load. The state term is written as plain loops in a fixed order (no BLAS), so its rounding does not depend
on the machine's BLAS build.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numba import njit

__all__ = ["law_step", "law_step_for", "warm_up"]


@njit(cache=True)
def law_step(
    t: int,
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
) -> None:
    """Write ``u_k(t)`` into ``commands[t]`` (and ``x_k(t)`` into ``state[t]``) from the output ``outputs[t]``.

    Parameters
    ----------
    t
        The sample, ``0 <= t < N``.
    outputs
        ``(N, p)``: ``y_k(i Ts)`` measured at the start of each sample; row ``t`` is read.
    base
        ``(N, m)``: ``u_{k-1}(t) + gain E_{k-1}[t + d]``, computed once per trial.
    commands
        ``(N, m)``: the trial's commands; rows before ``t`` are the commands already issued (the input-delay
        states), row ``t`` is written.
    state, previous_state
        ``(N, n)``: ``x_k`` (row ``t`` is written) and ``x_{k-1}``; ``n = 0`` for a law without a state term.
        ``n = n_plant + d m`` with ``n_plant = c_pinv.shape[0]``: the plant's state then ``d`` delayed inputs,
        oldest first (:func:`foilc_hil.design.models.augment_input_delay`).
    c_pinv
        ``(n_plant, p)``: ``pinv(C)`` of the measured output map.
    p1
        ``(m, n)``: the state gain.
    use_previous
        Whether ``previous_state`` is the previous trial's (else the state term is left out: the first trial and
        the trial after a restore only measure).
    lower, upper
        The command limits (``-inf``, ``inf``: none). A NaN command stays NaN (as :func:`numpy.clip` leaves it), so
        the caller's finiteness check sees it.
    """
    m = commands.shape[1]
    n = state.shape[1]
    n_plant = c_pinv.shape[0]
    y = outputs[t]
    x = state[t]
    for row in range(n_plant):
        total = 0.0
        for column in range(y.shape[0]):
            total += c_pinv[row, column] * y[column]
        x[row] = total
    delay = (n - n_plant) // m
    for slot in range(delay):  # slot j holds u(t - d + j), oldest first
        issued = t - delay + slot
        for j in range(m):
            x[n_plant + slot * m + j] = commands[issued, j] if issued >= 0 else 0.0
    u = commands[t]
    x_previous = previous_state[t]
    for i in range(m):
        value = base[t, i]
        if use_previous and n > 0:
            correction = 0.0
            for k in range(n):
                correction += p1[i, k] * (x[k] - x_previous[k])
            value = value + correction
        # np.clip's semantics: a NaN passes through (neither comparison holds)
        if value < lower:
            value = lower
        elif value > upper:
            value = upper
        u[i] = value


def law_step_for(arguments: Sequence[object]) -> Callable[..., None]:
    """:func:`law_step`'s machine code for the types of ``(t, *arguments)`` (``t`` a Python ``int``), to be called
    without numba's dispatcher, which works out the types of all eleven arguments on every call to pick the overload
    (about two microseconds: a few per cent of a lockstep cycle over CAN). Look it up whenever the arguments change:
    the call does not check them against the overload's types."""
    signature = tuple(law_step.typeof_pyval(value) for value in (0, *arguments))
    overload = law_step.overloads.get(signature)
    if overload is None:  # types no call has had yet: compiled (or loaded from the cache) now
        law_step.compile(signature)
        overload = law_step.overloads[signature]
    # (numba's CompileResult declares its fields at run time, so mypy does not see entry_point)
    entry: Callable[..., None] = overload.entry_point  # type: ignore[attr-defined]
    return entry


def warm_up() -> None:
    """Run :func:`law_step` once with the argument types the laws pass (compiled, or loaded from numba's cache)."""
    rows = np.zeros((2, 1))
    law_step(1, rows, rows, np.zeros((2, 1)), np.zeros((2, 2)), np.zeros((2, 2)), np.ones((1, 1)), np.ones((1, 2)),
             True, -np.inf, np.inf)


warm_up()  # at import: never inside a control loop's first cycle
